"""The allocator setting of fsswarp.system: importing fsswarp lets glibc keep the memory of freed
NumPy temporaries (``keep_freed_memory``), unless the environment tunes glibc's allocator itself."""

import os
import platform
import subprocess
import sys

import pytest

#: Prints how many more bytes glibc holds mapped apart from its heap while a 16 MiB temporary lives,
#: how much its heap grew and kept once the temporary is freed (mallinfo2: hblkhd, arena), and
#: whether ``keep_freed_memory`` applied.
FREED_TEMPORARY = """
import ctypes
import numpy as np
import fsswarp
from fsswarp.system import keep_freed_memory

class Info(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                      "fsmblks", "uordblks", "fordblks", "keepcost")]
mallinfo2 = ctypes.CDLL(None).mallinfo2
mallinfo2.restype = Info
start = mallinfo2()
a = np.ones(1 << 21)  # 16 MiB
mapped = mallinfo2().hblkhd - start.hblkhd
del a
print(mapped, mallinfo2().arena - start.arena, keep_freed_memory())
"""


def _run(env: dict) -> tuple[int, int, str]:
    out = subprocess.run([sys.executable, "-c", FREED_TEMPORARY], env=env, capture_output=True, text=True,
                         check=True).stdout.split()
    return int(out[0]), int(out[1]), out[2]


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc" or platform.libc_ver()[1] < "2.33",
                    reason="glibc's allocator (mallinfo2: glibc 2.33)")
def test_importing_fsswarp_keeps_freed_memory_unless_the_environment_tunes_the_allocator():
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"}
    mapped, kept, applied = _run(env)
    assert applied == "True"
    assert mapped == 0 and kept > (8 << 20)  # from the heap, and kept there once freed
    mapped, kept, applied = _run({**env, "GLIBC_TUNABLES": "glibc.malloc.tcache_count=7"})
    assert applied == "False" and mapped >= (16 << 20) and kept < (8 << 20)  # mapped apart, then unmapped
    assert _run({**env, "MALLOC_ARENA_MAX": "4"})[2] == "False"
