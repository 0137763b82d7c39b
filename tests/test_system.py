"""fsswarp.system: importing fsswarp lets glibc keep the memory of freed NumPy temporaries
(``keep_freed_memory``), unless the environment tunes glibc's allocator itself; work mapped on
threads (``map_on_threads``)."""

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


def test_work_mapped_on_threads_comes_back_in_order_on_at_most_the_cpus_and_the_cap(monkeypatch):
    """One thread per item, at most the usable CPUs and ``most``; the results in the items' order;
    one item, one CPU or a cap of one: no threads at all."""
    import threading
    import time

    import fsswarp.system as system

    def work(k):
        time.sleep(0.01 * (5 - k))  # the first items end last
        return k * k, threading.current_thread().name

    monkeypatch.setattr(system, "usable_cpus", lambda: 3)
    results = system.map_on_threads(work, range(5), name="fsswarp-test")
    assert [value for value, _ in results] == [0, 1, 4, 9, 16]
    names = {name for _, name in results}
    assert len(names) == 3 and all(name.startswith("fsswarp-test") for name in names)
    assert len({name for _, name in system.map_on_threads(work, range(5), most=2)}) == 2
    here = threading.current_thread().name
    assert {name for _, name in system.map_on_threads(work, range(5), most=1)} == {here}
    assert system.map_on_threads(work, [2]) == [(4, here)]
    monkeypatch.setattr(system, "usable_cpus", lambda: 1)
    assert {name for _, name in system.map_on_threads(work, range(5))} == {here}
