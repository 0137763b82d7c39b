"""Timing harness of ``fsswarp bench``: repeated calls, size sweeps under a budget, records and
the physical limit of every figure (docs/benchmarks.md).

A participant (``Backend`` or ``Peer``) has ``name``, ``device`` and ``is_gpu``; its limit
profile is keyed ``"name:device"`` (``profile_key``). Times are in seconds, bandwidths in B/s,
peak rates in operations per second.

- ``measure(fn, repeat)``: median, min and max seconds of the timed calls after a warm-up.
- ``sweep(points, run_point, skipped, budget=)``: run sizes in order, skipping those whose
  projected time passes the budget, and every later one.
- ``timed_record``, ``skipped_record``, ``physical_limit``: the JSON records of bench.json.
- ``probe_machine(participants)``: the CPU, the versions and a limit profile per participant
  (memory bandwidth, peak rate, host link), from data sheets or measured copies.
"""

from __future__ import annotations

import math
import os
import platform
import statistics
import time
from collections.abc import Callable, Sequence

import numpy as np

#: (name fragment, memory B/s, FP32 op/s, source); the first fragment found in the name wins.
GPU_PEAKS = (
    ("H200", 4.8e12, 67e12, "NVIDIA H200 Tensor Core GPU data sheet"),
    ("H100 PCIe", 2.0e12, 51e12, "NVIDIA H100 Tensor Core GPU data sheet (PCIe)"),
    ("H100 NVL", 3.9e12, 60e12, "NVIDIA H100 Tensor Core GPU data sheet (NVL)"),
    ("H100", 3.35e12, 67e12, "NVIDIA H100 Tensor Core GPU data sheet (SXM)"),
)
#: Host link of every GPU in GPU_PEAKS: PCIe 5.0 x16, 64 GB/s per direction (the same data sheets).
PCIE5_X16 = 64e9

Progress = Callable[[str], None]


# --- timing ----------------------------------------------------------------------------------
def measure(fn: Callable[[], object], repeat: int, *, warmup: int = 1, budget: float | None = None,
            clock: Callable[[], float] = time.perf_counter) -> dict:
    """Time ``fn``: ``warmup`` untimed calls, then up to ``repeat`` timed ones (stopping before
    one that would take the calls past ``budget`` seconds, keeping at least one). Returns
    {median_s, min_s, max_s, repeat (calls timed), timed_s (all calls, warm-up included)}."""
    start = clock()
    for _ in range(warmup):
        fn()
    times: list[float] = []
    while len(times) < repeat:
        if times and budget is not None and clock() - start + times[-1] > budget:
            break
        begin = clock()
        fn()
        times.append(clock() - begin)
    return {"median_s": statistics.median(times), "min_s": min(times), "max_s": max(times), "repeat": len(times),
            "timed_s": clock() - start}


def sweep(points: Sequence[tuple], run_point: Callable[[object], list[dict]],
          skipped: Callable[[object, float], list[dict]], *, budget: float,
          clock: Callable[[], float] = time.perf_counter) -> list[dict]:
    """Run ``run_point(x)`` for each point ``(x, size, work)`` in order, skipping a point, and
    every later one, whose projected time exceeds ``budget`` s (``skipped(x, projected)`` makes
    its records). Projection from the last point run: its setup time × size growth + its timed
    calls (``timed_s`` of its records) × work growth."""
    records: list[dict] = []
    last = None  # (size, work, setup_s, timed_s)
    stop = False
    for x, size, work in points:
        projected = 0.0 if last is None else (last[2] * size / last[0] + last[3] * work / last[1])
        if stop or projected > budget:
            stop = True
            records += skipped(x, projected)
            continue
        begin = clock()
        got = run_point(x)
        total = clock() - begin
        timed = sum(r.get("timed_s", 0.0) for r in got)
        last = (size, work, max(total - timed, 0.0), timed)
        records += got
    return records


# --- records and limits ----------------------------------------------------------------------
class Peer:
    """A non-fsswarp implementation timed beside the backends (Embree, NumPy); ``cores``: the
    CPU cores it uses (the peak rate of its profile)."""

    def __init__(self, name: str, device: str, is_gpu: bool = False, cores: int = 1):
        self.name, self.device, self.is_gpu, self.cores = name, device, is_gpu, cores


class CupyPeer(Peer):
    """CuPy on CUDA device 0, with the name and copies its GPU profile needs."""

    def __init__(self):
        super().__init__("cupy", "cuda:0", is_gpu=True)

    @property
    def device_name(self) -> str:
        import cupy

        name = cupy.cuda.runtime.getDeviceProperties(0)["name"]
        return name.decode() if isinstance(name, bytes) else str(name)

    def transfer_calls(self, nbytes: int) -> tuple[Callable[[], None], Callable[[], None], Callable[[], None]]:
        """Blocking (device-to-device, host-to-device, device-to-host) copies of ``nbytes``."""
        import cupy

        host = np.ones(nbytes // 4, np.float32)
        src = cupy.asarray(host)
        dst = cupy.empty_like(src)
        sync = cupy.cuda.runtime.deviceSynchronize

        def d2d():
            dst[...] = src
            sync()

        def h2d():
            src.set(host)
            sync()

        def d2h():
            src.get()

        return d2d, h2d, d2h


def profile_key(who) -> str:
    """The key of ``who``'s limit profile: "name:device"."""
    return f"{who.name}:{who.device}"


def record_base(family: str, kernel: str, mode: str, who, sweep_name: str) -> dict:
    """The fields shared by every record of one series."""
    return {"family": family, "kernel": kernel, "mode": mode, "backend": who.name, "device": who.device,
            "sweep": sweep_name}


def timed_record(base: dict, x, timing: dict, work: float, unit: str, *, size: dict, rates: dict | None = None,
                 limit: dict | None = None) -> dict:
    """A timed record: ``base`` (family, kernel, mode, backend, device, sweep) plus the point."""
    record = dict(base, x=x, size=size, work=float(work), work_unit=unit, **timing,
                  throughput=work / timing["median_s"], throughput_unit=f"{unit}/s",
                  rates={k: v / timing["median_s"] for k, v in (rates or {}).items()}, skipped=None)
    if limit is not None:
        record["limit"] = dict(limit, fraction=limit["limit_s"] / timing["median_s"])
    return record


def skipped_record(base: dict, x, projected: float, budget: float, reason: str | None = None) -> dict:
    """A point not run: its projected seconds, the budget and why."""
    return dict(base, x=x, skipped={"projected_s": projected, "budget_s": budget,
                                   "reason": reason or f"projected {projected:.3g} s > budget {budget:g} s"})


def unavailable_record(base: dict, reason: str) -> dict:
    """The one record of a peer that cannot run here."""
    return dict(base, x=None, skipped={"reason": f"unavailable: {reason}"})


def physical_limit(profile: dict, *, bytes_moved: float, ops: float, up: float = 0.0, down: float = 0.0) -> dict:
    """Lower bound on time: max of bytes / bandwidth, ops / peak and (``up``, ``down`` bytes over
    the host link, GPUs only)."""
    parts = {"memory": bytes_moved / profile["bandwidth_Bps"]}
    if profile.get("peak_ops"):
        parts["compute"] = ops / profile["peak_ops"]
    if profile.get("link_up_Bps") and (up or down):
        parts["link"] = up / profile["link_up_Bps"] + down / profile["link_down_Bps"]
    bound = max(parts, key=parts.get)
    return {"bytes": float(bytes_moved), "ops": float(ops), "link_bytes": float(up + down),
            **{f"{k}_s": v for k, v in parts.items()}, "limit_s": parts[bound], "bound": bound,
            "profile": profile["key"]}


# --- progress lines ----------------------------------------------------------------------------
def say(progress: Progress | None, record: dict) -> None:
    """Pass ``record``'s one-line summary to ``progress``, if any."""
    if progress is not None:
        progress("  " + record_line(record))


def record_line(r: dict) -> str:
    """One line: who, the size, the median (min-max), the throughput and the fraction of the limit."""
    who = f"{r['family']} {r['kernel']} ({r['mode']}) {r['backend']} {r['device'][:40]}"
    if r.get("skipped"):
        return f"{who} {r['sweep']} {format_value(r['x'])}: skipped ({r['skipped']['reason']})"
    limit = r.get("limit")
    return (f"{who} {r['sweep']} {format_value(r['x'])}: {format_seconds(r['median_s'])} "
            f"({format_seconds(r['min_s'])}-{format_seconds(r['max_s'])}), "
            f"{format_value(r['throughput'])} {r['throughput_unit']}"
            + (f", {limit['fraction']:.3g} of the {limit['bound']} limit" if limit else ""))


def format_value(value) -> str:
    """Four significant digits, with an SI prefix outside [0.01, 10⁴); "-" for None."""
    if value is None:
        return "-"
    value = float(value)
    if value == 0 or 1e-2 <= abs(value) < 1e4:
        return f"{value:.4g}"
    exponent = int(math.floor(math.log10(abs(value)) / 3) * 3)
    suffix = {3: "k", 6: "M", 9: "G", 12: "T", 15: "P", -3: "m", -6: "u", -9: "n"}.get(exponent)
    return f"{value / 10**exponent:.3g} {suffix}" if suffix else f"{value:.3g}"


def format_seconds(seconds: float) -> str:
    """Milliseconds below one second, else seconds, three significant digits."""
    return f"{seconds * 1e3:.3g} ms" if seconds < 1 else f"{seconds:.3g} s"


# --- machine ---------------------------------------------------------------------------------
def cpu_info() -> dict:
    """Model, logical CPUs, clock and SIMD width from /proc/cpuinfo, and the per-core peak."""
    model, mhz, flags = platform.processor() or platform.machine(), None, set()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as handle:
            for line in handle:
                key, _, value = line.partition(":")
                key = key.strip()
                if key == "model name":
                    model = value.strip()
                elif key == "cpu MHz" and mhz is None:
                    mhz = float(value)
                elif key == "flags" and not flags:
                    flags = set(value.split())
    except OSError:
        pass
    lanes = 16 if "avx512f" in flags else 8 if "avx2" in flags else 4
    fma = 2 if "fma" in flags or "avx512f" in flags else 1
    per_core = None if mhz is None else mhz * 1e6 * lanes * fma * 2
    how = (None if mhz is None else
           f"{mhz:.0f} MHz x {lanes} float32 lanes x {fma} (FMA) x 2 FMA units per core (assumed)")
    return {"model": model, "logical_cpus": os.cpu_count(), "clock_mhz": mhz, "simd_lanes": lanes,
            "peak_ops_per_core": per_core, "peak_derivation": how}


def host_bandwidth(nbytes: int, repeat: int = 5) -> float:
    """Measured host memory bandwidth (B/s): 2 × bytes / time of the fastest NumPy copy."""
    src = np.ones(nbytes // 4, np.float32)
    dst = np.empty_like(src)
    np.copyto(dst, src)
    best = min(_once(lambda: np.copyto(dst, src)) for _ in range(repeat))
    return 2 * src.nbytes / best


def _once(fn) -> float:
    begin = time.perf_counter()
    fn()
    return time.perf_counter() - begin


def copy_rates(who, nbytes: int) -> tuple[float, float, float]:
    """(device-to-device B/s counting read + write, host-to-device B/s, device-to-host B/s) of
    ``who.transfer_calls(nbytes)``: the fastest of 5 copies after one untimed."""
    rates = []
    for fn, factor in zip(who.transfer_calls(nbytes), (2, 1, 1)):
        fn()
        rates.append(factor * nbytes / min(_once(fn) for _ in range(5)))
    return rates[0], rates[1], rates[2]


def limit_profile(who, cpu: dict, host_bw: float, *, quick: bool) -> dict:
    """Bandwidth, peak and host link of one backend or peer (docs/benchmarks.md)."""
    if not who.is_gpu:
        opencl = getattr(who, "cl_device", None)  # an OpenCL CPU device runs on its compute units
        cores = who.cores if isinstance(who, Peer) else 1 if opencl is None else int(opencl.max_compute_units)
        peak = None if cpu["peak_ops_per_core"] is None else cores * cpu["peak_ops_per_core"]
        bandwidth, source = host_bw, "measured NumPy copy (1 thread)"
        if opencl is not None:  # all cores: the faster of that and a buffer copy on the device
            copy = copy_rates(who, (64 if quick else 256) << 20)[0]
            bandwidth, source = max((host_bw, source), (copy, "measured OpenCL buffer copy"))
        return {"key": profile_key(who), "name": cpu["model"], "kind": "cpu", "cores_used": cores,
                "bandwidth_Bps": bandwidth, "bandwidth_source": source,
                "peak_ops": peak, "peak_source": None if peak is None else
                f"{cores} core(s) x {cpu['peak_derivation']}"}
    name = who.device_name
    size = (64 if quick else 512) << 20
    copy, up, down = copy_rates(who, size)
    sheet = next((p for p in GPU_PEAKS if p[0].lower() in name.lower()), None)
    return {"key": profile_key(who), "name": name, "kind": "gpu", "measured_copy_Bps": copy,
            "bandwidth_Bps": sheet[1] if sheet else copy,
            "bandwidth_source": sheet[3] if sheet else "measured device-to-device copy",
            "peak_ops": sheet[2] if sheet else None, "peak_source": sheet[3] if sheet else None,
            "link_up_Bps": PCIE5_X16 if sheet else up, "link_down_Bps": PCIE5_X16 if sheet else down,
            "link_source": ("PCIe 5.0 x16 (data sheet)" if sheet else "measured")
            + f"; measured pageable copies of {size >> 20} MB: {up / 1e9:.3g} GB/s up, {down / 1e9:.3g} GB/s down"}


def probe_machine(participants: Sequence, *, quick: bool = False) -> dict:
    """The machine and a limit profile (``limit_profile``) per backend or peer, keyed "name:device"."""
    cpu = cpu_info()
    host_bw = host_bandwidth((32 if quick else 256) << 20)
    versions = {"python": platform.python_version(), "numpy": np.__version__}
    for module in ("warp", "pyopencl", "trimesh", "embreex", "cupy"):
        try:
            versions[module] = __import__(module).__version__
        except Exception:  # noqa: BLE001 - absent or broken: not recorded
            continue
    return {"host": platform.node(), "system": f"{platform.system()} {platform.release()}", "cpu": cpu,
            "host_bandwidth_Bps": host_bw, "versions": versions,
            "profiles": {profile_key(p): limit_profile(p, cpu, host_bw, quick=quick) for p in participants}}

