"""Timing shared by the benchmark scripts (run as ``python bench/<script>.py``, so this folder
is on the import path)."""

from __future__ import annotations

import statistics
import time


def time_call(fn, repeat: int) -> tuple[float, float, float]:
    """(median, min, max) seconds of ``repeat`` calls of ``fn`` after one warm-up call (which
    compiles kernels and uploads)."""
    fn()
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), min(times), max(times)
