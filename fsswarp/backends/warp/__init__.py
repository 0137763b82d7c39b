"""The NVIDIA Warp backend: kernels grouped per family as kernels/*.cl are, and ``WarpBackend``.

Importing this package imports ``warp``; ``fsswarp.backends.select`` imports it only when a
Warp backend is first asked for.
"""

from .backend import WarpBackend, WarpLayers, WarpMesh

__all__ = ["WarpBackend", "WarpLayers", "WarpMesh"]
