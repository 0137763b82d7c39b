"""The two runtimes as fsswarp meets them: Warp started quietly (``import_warp``) and an
OpenCL device as found on this machine (``OpenCLDevice``). Importing this module imports
neither ``warp`` nor ``pyopencl``. select.py chooses among them; each backend starts from them.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import sys
import tempfile
import threading
from dataclasses import dataclass
from typing import Any

_WARP_STATE: dict[str, Any] = {}
_WARP_LOCK = threading.Lock()  # one init, whichever thread asks first (cli.State.start_backend)


def import_warp():
    """(warp module, None) initialized quietly, or (None, why it is unavailable)."""
    try:
        import warp as wp
    except ImportError as err:
        return None, f"warp-lang is not installed ({err})"
    with _WARP_LOCK:
        if "init" not in _WARP_STATE:
            _WARP_STATE["init"] = _init_warp(wp)
    return wp, None


def _init_warp(wp) -> str:
    """wp.init() without its banner; returns what the native library printed to stderr where
    no CUDA driver loads ("Could not find or load the NVIDIA CUDA driver", hidden). Where one
    loads, that warning cannot come and stderr is left alone: a thread may then start Warp
    while the command's own thread writes to stderr (``cuda_driver_loads``)."""
    if hasattr(wp, "LOG_WARNING"):  # the banner and "Module ... loaded" lines are LOG_INFO
        wp.config.log_level = max(getattr(wp.config, "log_level", 0), wp.LOG_WARNING)
    else:  # older Warp
        wp.config.quiet = True
    if cuda_driver_loads():
        wp.init()
        return ""
    with _captured_stderr_fd() as captured:
        wp.init()
    return " ".join(line.strip() for line in "".join(captured).splitlines() if line.strip())


@functools.cache
def cuda_driver_loads() -> bool:
    """Whether the NVIDIA CUDA driver library loads here, by the names Warp's native code tries
    (libcuda.so, then libcuda.so.1; nvcuda.dll on Windows)."""
    for name in ("nvcuda.dll",) if sys.platform == "win32" else ("libcuda.so", "libcuda.so.1"):
        try:
            ctypes.CDLL(name)
        except OSError:
            continue
        return True
    return False


@contextlib.contextmanager
def _captured_stderr_fd():
    """Redirect file descriptor 2 (where native libraries print) into a temporary file; the
    yielded list holds the text once the block ends."""
    captured: list[str] = []
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        yield captured
        return
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield captured
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            captured.append(tmp.read().decode("utf-8", "replace"))


def warp_note() -> str:
    """Why Warp sees no CUDA device, from what its init printed."""
    text = _WARP_STATE.get("init", "")
    if "Could not find or load the NVIDIA CUDA driver" in text:
        return "no CUDA GPU found (no NVIDIA CUDA driver)"
    text = text.replace("Warp CUDA warning: ", "").strip()
    return f"no CUDA GPU found ({text})" if text else "no CUDA GPU found"



@dataclass(frozen=True)
class OpenCLDevice:
    """One OpenCL device as found here: its index for ``--device``, label, pyopencl handles and kind."""

    index: int
    label: str  # "<platform>: <device name>"
    platform: Any  # pyopencl.Platform
    device: Any  # pyopencl.Device
    is_gpu: bool
    is_cpu: bool
    is_pocl: bool
