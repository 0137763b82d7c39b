"""Kernel backends: one interface (``base``), two implementations, and their selection.

``Backend`` (``base.py``) is the interface every kernel family goes through; ``WarpBackend``
(NVIDIA Warp on "cpu" or "cuda:N") and ``OpenCLBackend`` (OpenCL C from the top-level
``kernels/`` on any OpenCL device) implement it. Pick one with :func:`get_backend`; list what
this machine offers with :func:`describe_backends` (``fsswarp info``), both in ``select.py``.

Importing this package imports neither ``warp`` nor ``pyopencl``; a backend imports its
package when it is first asked for.
"""

from .base import (Backend, DeviceDistances, DeviceLayers, HostLayers, ICPRuns, PreparedLaunch, SonarConstants,
                   beams_read, most_launch_views, most_layer_views, rows_read)
from .constants import FRONTAL_VISIBLE, MAX_DISTANCE, RAY_EPSILON
from .select import BACKEND_NAMES, INSTALL_OPENCL, INSTALL_WARP, describe_backends, get_backend

__all__ = ["Backend", "DeviceLayers", "HostLayers", "DeviceDistances", "ICPRuns", "PreparedLaunch", "SonarConstants",
           "get_backend", "describe_backends", "beams_read", "most_launch_views", "most_layer_views", "rows_read",
           "BACKEND_NAMES", "INSTALL_WARP", "INSTALL_OPENCL", "RAY_EPSILON", "FRONTAL_VISIBLE", "MAX_DISTANCE"]
