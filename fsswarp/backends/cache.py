"""Whether a backend's kernels are in its kernel cache, told without compiling (``fsswarp info``),
and the warm-up that fills it (``fsswarp info --warm-up``, :func:`warm_up`).

- Warp compiles each kernel module, at the first launch of one of its kernels, once per module
  hash, device kind (a CPU target or a CUDA architecture) and Warp version into
  ``wp.config.kernel_cache_dir`` (``WARP_CACHE_PATH``, default ~/.cache/warp/<version>).
  ``warp_cache`` hashes fsswarp's Warp modules as Warp would for the device (the hash covers the
  kernels' code and options; no code is generated for a compiler) and looks for each module's
  binary and metadata there: exact, as long as Warp keeps its cache layout (private names;
  anything unexpected gives "unknown").
- OpenCL: PoCL and NVIDIA's driver cache program binaries themselves (pyopencl then keeps
  none), under keys of their own that only a build can look up. fsswarp records each program
  it builds (``builds.record_build``: a file named by pyopencl's key of device, driver, options
  and source, under ``$XDG_CACHE_HOME/fsswarp/opencl``); ``opencl_cache`` says warm when every
  program of the backend is recorded with the driver's cache folder as it is now (its path and
  the token of a marker file fsswarp keeps in it, ``builds.MARKER``: PoCL's ``POCL_CACHE_DIR``,
  default ``$XDG_CACHE_HOME/pocl/kcache``; NVIDIA's ``CUDA_CACHE_PATH``, default
  ~/.nv/ComputeCache), cold when one is missing, the folder was removed or moved since, or the
  driver's cache is switched off (``POCL_KERNEL_CACHE=0``, ``CUDA_CACHE_DISABLE=1``). Entries
  removed from inside the folder, or evicted by size, still read warm: the driver alone knows.
  Other drivers use pyopencl's binary cache, whose entry for each program is looked up exactly.
"""

from __future__ import annotations

import sys
from pathlib import Path

from .builds import build_key, driver_cache, driver_identity, records
from .runtimes import import_warp

#: OpenCL programs that ``OpenCLBackend`` builds, and those it builds only with float64.
OPENCL_PROGRAMS = ("project.cl", "carve.cl", "raycast.cl", "render.cl", "pose.cl")
FLOAT64_PROGRAMS = ("icp.cl", "closest.cl")
#: Warp modules holding fsswarp's kernels (fsswarp/backends/warp/).
WARP_MODULES = ("project", "carve", "raycast", "closest", "render", "pose", "icp")
#: Threads that compile Warp's modules side by side in :func:`warm_up`.
WARM_UP_THREADS = 4


# --- Warp ------------------------------------------------------------------------------------
def warp_cache(device: str) -> tuple[str, str]:
    """("warm" | "partly warm" | "cold" | "unknown", a one-line reason) for fsswarp's Warp
    kernel modules on ``device`` ("cpu", "cuda:N"); partly: some modules compiled (Warp compiles
    a module at the first launch of one of its kernels: a synthesis compiles ``render``)."""
    wp, why = import_warp()
    if wp is None:
        return "unknown", why
    try:
        missing, folder = _warp_missing(wp, device)
    except Exception as err:  # noqa: BLE001 - Warp's private cache layout changed: say so
        return "unknown", f"cannot read Warp's cache layout ({' '.join(str(err).split())})"
    compiled = [name for name in WARP_MODULES if name not in missing]
    where = f"for {device} in {folder}"
    if not compiled:
        return "cold", f"no module compiled {where}"
    if missing:  # Warp compiles a module when one of its kernels is first launched
        return "partly warm", f"{', '.join(compiled)} compiled, {', '.join(missing)} not, {where}"
    return "warm", f"all {len(WARP_MODULES)} modules compiled {where}"


def _warp_modules(wp) -> dict:
    """{name: Warp Module} of ``WARP_MODULES`` (their Python modules imported)."""
    import importlib

    return {name: wp.get_module(importlib.import_module(f"fsswarp.backends.warp.{name}").__name__)
            for name in WARP_MODULES}


def _warp_missing(wp, device: str) -> tuple[list[str], Path]:
    """(the ``WARP_MODULES`` without a compiled binary and metadata for ``device`` in Warp's
    kernel cache, the cache folder), each module's variant as its launches use it (the block
    size that its options name)."""
    from warp._src.context import _resolve_launch_block_dim

    target = wp.get_device(device)
    folder = Path(wp.config.kernel_cache_dir)
    missing = []
    for name, module in _warp_modules(wp).items():
        block_dim = _resolve_launch_block_dim(target, module.options.get("block_dim"))  # as its launches
        ident = module.get_module_identifier(block_dim)
        binary = module._get_compile_output_name(target, block_dim=block_dim)
        meta = module._get_meta_name(block_dim)
        if not ((folder / ident / binary).is_file() and (folder / ident / meta).is_file()):
            missing.append(name)
    return missing, folder


def warm_up(backend) -> tuple[list[str], float]:
    """Make ``backend``'s kernels ready now rather than at their first launches: Warp compiles
    the modules that its cache lacks (and loads the rest) in parallel threads, ``WARM_UP_THREADS``
    at most, each as its launches use it; an OpenCL backend built its programs when it was made
    (``OpenCLBackend``), so nothing is left. Returns (the modules that were compiled, seconds)."""
    import time

    if backend.name != "warp":
        return [], 0.0
    wp, _ = import_warp()
    start = time.perf_counter()
    try:
        missing, _ = _warp_missing(wp, backend.device)
    except Exception:  # noqa: BLE001 - Warp's private cache layout changed: it cannot say what compiles
        missing = []
    modules = _warp_modules(wp)
    for block_dim in sorted({m.options["block_dim"] for m in modules.values()}):  # one variant per module
        alike = [module for module in modules.values() if module.options["block_dim"] == block_dim]
        wp.force_load(device=backend.device, modules=alike, block_dim=block_dim, max_workers=WARM_UP_THREADS)
    return missing, time.perf_counter() - start


# --- OpenCL ----------------------------------------------------------------------------------
def opencl_cache(found) -> tuple[str, str]:
    """("warm" | "cold" | "unknown", a one-line reason) for fsswarp's OpenCL programs on
    ``found`` (an ``OpenCLDevice``)."""
    from .opencl.programs import BUILD_OPTIONS, kernel_source

    try:
        names = OPENCL_PROGRAMS + (FLOAT64_PROGRAMS if "cl_khr_fp64" in found.device.extensions.split() else ())
        keys = {name: build_key(found.device, BUILD_OPTIONS, kernel_source(name)) for name in names}
        folder, off = driver_cache(found.device)
        if off:
            return "cold", off
        if folder is None:  # pyopencl's own binary cache: the exact entry
            import pyopencl as cl
            import platformdirs
            from pyopencl.cache import get_cache_key

            base = Path(platformdirs.user_cache_dir("pyopencl", "pyopencl"))
            where = base / f"pyopencl-compiler-cache-v2-py{'.'.join(str(i) for i in sys.version_info)}"
            options = cl.Program._process_build_options(cl.Context([found.device]), list(BUILD_OPTIONS))[0]
            missing = [n for n in names if not (where / get_cache_key(found.device, options, kernel_source(n))).is_dir()]
            what = f"pyopencl's binary cache {where}"
        else:
            now = driver_identity(found.device)
            missing = [n for n, key in keys.items()
                       if not (records() / key).is_file() or (records() / key).read_text() != now]
            what = f"the driver's cache {folder} (fsswarp's build records in {records()})"
    except Exception as err:  # noqa: BLE001 - pyopencl's cache layout changed: say so
        return "unknown", f"cannot check the program cache ({' '.join(str(err).split())})"
    if missing:
        return "cold", f"{', '.join(missing)} not built for this device and driver in {what}"
    return "warm", f"{len(names)} programs built for this device and driver in {what}"


def kernel_cache(row: dict) -> tuple[str, str]:
    """``warp_cache`` or ``opencl_cache`` of one available ``describe_backends()`` row."""
    if row["backend"] == "warp":
        return warp_cache(row["device"])
    from .select import _opencl_devices

    return opencl_cache(_opencl_devices()[0][row["index"]])

