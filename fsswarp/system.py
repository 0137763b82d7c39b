"""Facts about the host machine (the CPUs this process may use, the memory installed), work
spread over those CPUs in threads (``map_on_threads``), and how the process's memory allocator
keeps what NumPy frees (``keep_freed_memory``).

Part of the model layer: imports nothing from the pipeline or the backends.
"""

from __future__ import annotations

import ctypes
import os

#: glibc's ``mallopt`` parameters (malloc.h) and the values ``keep_freed_memory`` sets: blocks up
#: to 32 MiB (glibc's largest) come from the heap, which keeps up to 128 MiB free at its top.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD = 32 << 20
TRIM_THRESHOLD = 128 << 20


def host_memory() -> int | None:
    """Physical memory of the host (bytes), or None where the system does not tell."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def usable_cpus() -> int:
    """CPUs this process may use: its affinity where the system tells it (a container given
    some of a host's CPUs), else every CPU."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def map_on_threads(function, items, *, most: int | None = None, name: str = "fsswarp-thread") -> list:
    """``[function(item) for item in items]``, worked out on threads (one per item, at most the CPUs
    this process may use and ``most``), for work that releases the interpreter's lock (zlib,
    NumPy, SciPy and scikit-image filters); in this thread where one would do."""
    from concurrent.futures import ThreadPoolExecutor

    items = list(items)
    threads = min(len(items), usable_cpus(), len(items) if most is None else most)
    if threads < 2:
        return [function(item) for item in items]
    with ThreadPoolExecutor(threads, thread_name_prefix=name) as pool:
        return list(pool.map(function, items))


def keep_freed_memory() -> bool:
    """Let glibc's allocator keep and reuse the memory of freed NumPy temporaries of up to 32 MiB
    instead of mapping fresh pages for each (whose first touch faults): the pose grid's host
    plans took half their time in such faults (docs/decisions.md, "The allocator keeps freed
    memory"). Returns whether it applied: not on other C libraries, and not where the
    environment tunes glibc's allocator itself (``GLIBC_TUNABLES`` or a ``MALLOC_*`` variable)."""
    if "GLIBC_TUNABLES" in os.environ or any(k.startswith("MALLOC_") for k in os.environ):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError, TypeError):  # no such C library call (macOS, musl; Windows)
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
