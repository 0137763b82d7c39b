"""The two runtimes as fsswarp meets them: Warp started quietly (``import_warp``) and an
OpenCL device as found on this machine (``OpenCLDevice``). Importing this module imports
neither ``warp`` nor ``pyopencl``. select.py chooses among them; each backend starts from them.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from dataclasses import dataclass
from typing import Any

_WARP_STATE: dict[str, Any] = {}


def import_warp():
    """(warp module, None) initialized quietly, or (None, why it is unavailable)."""
    try:
        import warp as wp
    except ImportError as err:
        return None, f"warp-lang is not installed ({err})"
    if "init" not in _WARP_STATE:
        _WARP_STATE["init"] = _init_warp(wp)
    return wp, None


def _init_warp(wp) -> str:
    """wp.init() without its banner; returns what the native library printed to stderr
    (on a machine without a CUDA driver: "Could not find or load the NVIDIA CUDA driver")."""
    if hasattr(wp, "LOG_WARNING"):  # the banner and "Module ... loaded" lines are LOG_INFO
        wp.config.log_level = max(getattr(wp.config, "log_level", 0), wp.LOG_WARNING)
    else:  # older Warp
        wp.config.quiet = True
    with _captured_stderr_fd() as captured:
        wp.init()
    return " ".join(line.strip() for line in "".join(captured).splitlines() if line.strip())


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
