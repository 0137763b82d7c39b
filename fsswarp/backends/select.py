"""Backend selection and discovery: ``get_backend``, ``describe_backends`` (``fsswarp info``).

Warp is initialized quietly on first use; OpenCL devices are listed over every platform and
resolved from ``--device`` (an index or a substring of "<platform>: <device name>"). Importing
this module imports neither ``warp`` nor ``pyopencl``; a backend imports its package when it
is first asked for.
"""

from __future__ import annotations

import os
import re
import threading
import warnings
from typing import Any

from ..errors import InputError
from ..system import host_memory
from .base import Backend
from .runtimes import OpenCLDevice, import_warp, warp_note

#: Values of ``--backend``.
BACKEND_NAMES = ("auto", "warp", "opencl")
#: How to install what is missing.
INSTALL_WARP = "pip install warp-lang"
INSTALL_OPENCL = 'pip install "fsswarp[pocl]"'  # pyopencl with PoCL, a CPU OpenCL runtime

_WARP_DEVICE = re.compile(r"^(cpu|cuda(:\d+)?)$")


_CACHE: dict[tuple, Backend] = {}
_LOCK = threading.RLock()


def get_backend(name: str = "auto", device: str | int | None = None) -> Backend:
    """The backend ``name`` on ``device``, created once per (backend, device) and cached.

    name : "auto", "warp" or "opencl" (``--backend``)
        auto: Warp on CUDA when a CUDA GPU is present, else OpenCL on a usable CPU device
        (PoCL first), else Warp on the CPU. With a ``device``, auto sends "cpu", "cuda" and "cuda:N"
        to Warp and anything else to OpenCL.
    device : (``--device``)
        warp: "cpu", "cuda" (the current CUDA device) or "cuda:N"; default "cuda:0" when a
        GPU is present, else "cpu".
        opencl: a case-insensitive substring of "<platform>: <device name>" (the first
        match wins), or an index into the list of ``describe_backends()`` (``index``);
        default the first usable CPU device (PoCL first), else the first usable device.
        A device whose runtime cannot build a trivial kernel (``build_failure``) is never
        picked by auto or by default; naming it still selects it.

    Raises ``InputError`` (field "--backend" or "--device") naming the value, what is
    available and how to install what is missing.
    """
    if not isinstance(name, str) or name.strip().lower() not in BACKEND_NAMES:
        raise InputError("unknown backend; choose one of " + ", ".join(BACKEND_NAMES),
                         field="--backend", value=name)
    name = name.strip().lower()
    if isinstance(device, bool) or not (device is None or isinstance(device, (str, int))):
        raise InputError("must be a device name or index", field="--device", value=device)
    if isinstance(device, str):
        device = device.strip() or None
    with _LOCK:
        if name == "auto":
            name, device = _auto_choice(device)
        if name == "warp":
            key = ("warp", _resolve_warp_device(device))
        else:
            key = ("opencl", _resolve_opencl_device(device).index)
        backend = _CACHE.get(key)
        if backend is None:
            backend = _CACHE[key] = _create(key)
        return backend


def _create(key: tuple) -> Backend:
    if key[0] == "warp":
        from .warp import WarpBackend

        return WarpBackend(key[1])
    from .opencl import OpenCLBackend

    return OpenCLBackend(_opencl_devices()[0][key[1]])


def _auto_choice(device) -> tuple[str, Any]:
    """(backend name, device) that ``auto`` picks; ``device`` only decides the backend."""
    if device is not None:
        if isinstance(device, str) and _WARP_DEVICE.match(device.lower()):
            return "warp", device
        return "opencl", device
    wp, _ = import_warp()
    if wp is not None and wp.is_cuda_available():
        return "warp", "cuda:0"
    found, _ = _opencl_devices()
    cpu = _default_opencl(found, cpu_only=True)
    if cpu is not None:
        return "opencl", cpu.index
    if wp is not None:
        return "warp", "cpu"
    raise InputError(f"no backend is available: install Warp ({INSTALL_WARP}) or an OpenCL "
                     f"runtime ({INSTALL_OPENCL})", field="--backend", value="auto")


# --- Warp devices ------------------------------------------------------------------------------
def _resolve_warp_device(device) -> str:
    """Canonical Warp device alias ("cpu", "cuda:N") for ``device``, or InputError."""
    wp, why = import_warp()
    if wp is None:
        raise InputError(f"{why}; install it with {INSTALL_WARP}", field="--backend", value="warp")
    aliases = [str(d.alias) for d in wp.get_devices()]
    if device is None:
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    text = str(device).lower()
    if not _WARP_DEVICE.match(text):
        raise InputError(f"not a Warp device (cpu, cuda or cuda:N); available: {', '.join(aliases)}",
                         field="--device", value=device)
    if text == "cuda":
        if not wp.is_cuda_available():
            raise InputError(f"{warp_note()}; available: {', '.join(aliases)}",
                             field="--device", value=device)
        return str(wp.get_device("cuda").alias)
    if text not in aliases:
        note = "" if wp.is_cuda_available() else f"; {warp_note()}"
        raise InputError(f"no such Warp device{note}; available: {', '.join(aliases)}",
                         field="--device", value=device)
    return text


# --- OpenCL devices ---------------------------------------------------------------------------
def _opencl_devices() -> tuple[list[OpenCLDevice], str | None]:
    """Every OpenCL device of every platform, and why there are none (else None). Never raises."""
    try:
        import pyopencl as cl
    except ImportError as err:
        return [], f"pyopencl is not installed ({err})"
    try:
        platforms = cl.get_platforms()
    except cl.Error as err:
        return [], f"no OpenCL platform found ({_one_line(err)})"
    found = []
    for platform in platforms:
        try:
            devices = platform.get_devices()
        except cl.Error:
            continue
        for device in devices:
            found.append((platform, device))
    if not found:
        return [], "no OpenCL device found" if platforms else "no OpenCL platform found"
    labels = [f"{p.name.strip()}: {d.name.strip()}" for p, d in found]
    result = []
    for i, ((platform, device), label) in enumerate(zip(found, labels)):
        if labels.count(label) > 1:
            label = f"{label} #{labels[:i].count(label)}"
        pocl = "portable computing language" in platform.name.lower() or "pocl" in platform.name.lower()
        result.append(OpenCLDevice(i, label, platform, device, bool(device.type & cl.device_type.GPU),
                                    bool(device.type & cl.device_type.CPU), pocl))
    return result, None


def _default_opencl(found: list[OpenCLDevice], *, cpu_only: bool) -> OpenCLDevice | None:
    """First usable PoCL CPU device, else the first usable CPU device, else (unless cpu_only)
    the first usable device (``build_failure``)."""
    for want in (lambda d: d.is_cpu and d.is_pocl, lambda d: d.is_cpu, lambda d: not cpu_only):
        for d in found:
            if want(d) and build_failure(d) is None:
                return d
    return None


_PROBES: dict[tuple[int, str], str | None] = {}
_PROBE_SOURCE = "__kernel void probe(__global float *x) { x[0] = 1.0f; }\n"


def build_failure(found: OpenCLDevice) -> str | None:
    """Why the device's runtime cannot build a trivial kernel (one line), else None: a device
    that fails this is never picked by default. Probed once per process and device."""
    key = (found.index, found.label)
    if key not in _PROBES:
        _PROBES[key] = _probe(found)
    return _PROBES[key]


def _probe(found: OpenCLDevice) -> str | None:
    """Build the trivial kernel on the device; the first error line of a failure, else None."""
    import pyopencl as cl

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", cl.CompilerWarning)
            cl.Program(cl.Context([found.device]), _PROBE_SOURCE).build()
    except Exception as err:  # noqa: BLE001 - whatever fails, the device cannot run our kernels
        lines = [line.strip() for line in str(err).splitlines() if line.strip().startswith("error:")]
        return "cannot build an OpenCL kernel: " + (lines[0] if lines else _one_line(err))
    return None


def _resolve_opencl_device(device) -> OpenCLDevice:
    found, why = _opencl_devices()
    if not found:
        missing = why.startswith("pyopencl")
        raise InputError(f"{why}; install {'pyopencl with ' if missing else ''}a CPU OpenCL "
                         f"runtime with {INSTALL_OPENCL}, or a GPU vendor's OpenCL driver",
                         field="--backend", value="opencl")
    available = "available: " + ", ".join(f"{d.index} = {d.label!r}" for d in found)
    if device is None:
        usable = _default_opencl(found, cpu_only=False)
        if usable is None:
            reasons = "; ".join(f"{d.label!r}: {build_failure(d)}" for d in found)
            raise InputError(f"no usable OpenCL device ({reasons})", field="--backend", value="opencl")
        return usable
    if isinstance(device, int) or (isinstance(device, str) and device.isdigit()):
        index = int(device)
        if 0 <= index < len(found):
            return found[index]
        raise InputError(f"no OpenCL device of that index; {available}", field="--device",
                         value=device)
    for d in found:
        if device.lower() in d.label.lower() or (d.is_pocl and device.lower() == "pocl"):
            return d
    raise InputError(f"no OpenCL device matches; {available}", field="--device", value=device)


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split())


# --- fsswarp info ----------------------------------------------------------------------------
def describe_backends() -> list[dict]:
    """Every device of every backend found here, for ``fsswarp info``. Never raises.

    One dict per device, and one per thing that is missing, all with the same keys:
    backend ("warp" | "opencl"), device (the ``--device`` value naming it, None for a missing
    thing), index (OpenCL: its index for ``--device``, else None), name, platform, kind
    ("cpu" | "gpu" | None), version, driver, compute_units, memory_bytes, available (bool),
    auto (whether ``--backend auto`` picks it) and note (why something is missing or unusable
    and how to install it, else ""). An OpenCL device that cannot build a kernel is listed
    with available False and the reason.
    """
    rows: list[dict] = []

    def row(**fields) -> None:
        base = dict(backend=None, device=None, index=None, name=None, platform=None, kind=None,
                    version=None, driver=None, compute_units=None, memory_bytes=None,
                    available=True, auto=False, note="")
        base.update(fields)
        rows.append(base)

    try:
        wp, why = import_warp()
    except Exception as err:  # noqa: BLE001 - a broken install is reported, not raised
        wp, why = None, f"warp failed to initialize ({_one_line(err)})"
    if wp is None:
        row(backend="warp", available=False, note=f"{why}; install it with {INSTALL_WARP}")
    else:
        for d in wp.get_devices():
            if d.is_cuda:
                driver = getattr(wp, "get_cuda_driver_version", lambda: None)()
                row(backend="warp", device=str(d.alias), name=d.name, platform=f"Warp {wp.__version__}",
                    kind="gpu", version=f"sm_{d.arch}", driver=_cuda_version(driver),
                    compute_units=int(d.sm_count), memory_bytes=int(d.total_memory))
            else:
                row(backend="warp", device=str(d.alias), name=d.name, platform=f"Warp {wp.__version__}",
                    kind="cpu", compute_units=os.cpu_count(), memory_bytes=host_memory())
        if not wp.is_cuda_available():
            row(backend="warp", device="cuda", kind="gpu", available=False, note=warp_note())

    found, why = _opencl_devices()
    for d in found:
        try:
            failure = build_failure(d)
            row(backend="opencl", device=d.label, index=d.index, name=d.device.name.strip(),
                platform=d.platform.name.strip(), kind="gpu" if d.is_gpu else "cpu" if d.is_cpu else None,
                version=d.device.version.strip(), driver=d.device.driver_version.strip(),
                compute_units=int(d.device.max_compute_units), memory_bytes=int(d.device.global_mem_size),
                available=failure is None, note=failure or "")
        except Exception as err:  # noqa: BLE001 - a broken driver is reported, not raised
            row(backend="opencl", device=d.label, index=d.index, available=False, note=_one_line(err))
    if why is not None:
        row(backend="opencl", available=False,
            note=f"{why}; for a CPU OpenCL runtime: {INSTALL_OPENCL}")
    elif not any(d.is_cpu for d in found):
        row(backend="opencl", kind="cpu", available=False,
            note=f"no CPU OpenCL device; for one: {INSTALL_OPENCL}")

    try:
        pick = _auto_choice(None)
    except Exception:  # noqa: BLE001 - nothing available: no row is marked
        pick = None
    if pick is not None:
        for r in rows:
            if r["available"] and r["backend"] == pick[0] and (
                    r["device"] == pick[1] if pick[0] == "warp" else r["index"] == pick[1]):
                r["auto"] = True
                break
    return rows


def _cuda_version(version) -> str | None:
    if isinstance(version, tuple):
        return "CUDA " + ".".join(str(v) for v in version)
    if isinstance(version, int) and version > 0:  # e.g. 12040
        return f"CUDA {version // 1000}.{version % 1000 // 10}"
    return None
