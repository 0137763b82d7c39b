"""Facts about the host machine: the CPUs this process may use and the memory installed.

Part of the model layer: imports nothing from the pipeline or the backends.
"""

from __future__ import annotations

import os


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
