"""The OpenCL backend: program sources and builds (``programs``) and ``OpenCLBackend``.

Importing this package imports ``pyopencl``; ``fsswarp.backends.select`` imports it only
when an OpenCL backend is first asked for.
"""

from .backend import OpenCLBackend, OpenCLLayers, OpenCLMesh
from .programs import GROUP, KernelBuildError, build, kernel_dir, kernel_source, program

__all__ = ["OpenCLBackend", "OpenCLLayers", "OpenCLMesh", "GROUP", "KernelBuildError", "build", "kernel_dir",
           "kernel_source", "program"]
