"""Kernel benchmarks: throughput, cost curves and the physical limit of every figure (issue 8).

``fsswarp bench`` (``run_suite``) times five families on every backend present, with peers
in the same run, and writes ``bench.json``, ``bench.md`` and one log-log plot per family;
``python bench/report.py`` turns the recorded runs under ``bench/records/`` into
``bench/RESULTS.md``.

Families and their cost curves (full sizes; ``--quick`` runs tiny ones):

========================  ==================================================  =====================
family                    what is timed                                       swept
========================  ==================================================  =====================
raycast                   first hit of a fixed ray set (2^18 rays on a CPU,   icosphere triangles
                          2^22 on a GPU, from one point at a sphere of        1,280 → 1,310,720
                          radius 0.5 m, 70% hit) with ``Backend.cast_rays``   (subdivisions 3 → 8)
synthesis                 coral-one (5,120 triangles), 96 beams × 512 bins,   views 1 → 256
                          samples (2, 64), all four layers
carving                   one carve launch over an N³ grid of a 0.3 m cube    voxels 64³ → 512³
                          around coral-one × its 16 views (feasible masks     (× 16 views)
                          from the noise-free object layer)
pose                      the (D, β) grid surrogate of coral-one (true        cells 8² → 128²
                          model, 16 views): every cell × view rendered and    (× 16 views)
                          reduced on the device, only the costs read back
reconstruction            ``fsswarp.reconstruction.reconstruct`` of simulated    iterations (1)
                          coral-one (seed 0): carve, mesh, pose and shape
                          steps, metrics against the truth
========================  ==================================================  =====================

Modes. "end to end" goes through the public method: host arrays in, uploads, the kernels,
read-back of the results. "resident" keeps inputs and outputs on the device and synchronizes
inside the timed region (Warp ``wp.synchronize_device``, OpenCL ``queue.finish()``): for ray
casting and carving the kernel is launched directly on arrays uploaded beforehand; for
synthesis it is ``Backend.render_device`` (pose upload, zeroing, render and fixed-point
kernels; the layers stay); for the pose grid it is ``Backend.contour_cost`` on layers already
rendered (only the small contours and sums come back). Every figure is the median of
``repeat`` calls after one warm-up call (which compiles and caches kernels), with the min and
max; the reconstruction has no warm-up. Repeats stop early, keeping at least one, when the
next would pass the per-point budget.

Peers in the same run: Embree (trimesh + embreex, all CPU threads) casts the ray sets on the
CPU; ``fsswarp.carving.carve_reference`` (NumPy, float64) carves the smaller grids; on a CUDA
GPU, CuPy carves by projecting every voxel centre into every view and looking the mask up
(``carve_array_module``: the obvious array-library method, a point test instead of the
kernels' bounding-sphere box test). A peer that is not installed is recorded as unavailable.

Budget. A point whose projected time exceeds the budget (``--budget`` seconds) is recorded as
skipped with its projection, and so are the larger ones: projected = setup time of the
previous point × the growth of the size + its timed calls × the growth of the work (work:
rays × log2(triangles) for the triangle sweep, else the swept count). With the default 20 s
the CPU suite ends in minutes while a GPU covers the full ranges.

Physical limit of a figure: a lower bound on its time, the largest of
  memory  = bytes that must move / memory bandwidth: inputs read once, outputs written once,
            nothing else (ray sets 24 B in and 8 B out per ray; triangles 36 B; layers
            4 B per pixel and layer; voxel results 2 B; summed-area tables 4 B per entry);
  compute = minimal operations / peak rate;
  link    = for "end to end" on a GPU: bytes that cross the host link / its rate (PCIe 5.0 x16,
            64 GB/s per direction, for the GPUs of the table below; the measured pageable-copy
            rates, 1–8 GB/s on the H100 machine, are recorded beside it).
The fraction printed beside every figure is limit / median: 1 means at the limit.

Minimal operations (floating-point operations, compares and min/max counted alike; special
functions at a typical polynomial cost). Estimated from the work's structure, not measured by
instrumenting the kernels:
  BVH node (slab tests of its two child boxes)                         ``NODE_OPS``     = 44
  watertight ray–triangle test (Woop, Benthin and Wald 2013)            ``TRIANGLE_OPS`` = 40
  a ray that hits descends at least one root-to-leaf path of the shallowest binary tree over
  leaves of 4 triangles: ceil(log2(triangles / 4)) nodes + 1 triangle test; a ray that misses
  at least tests the root. Hits come from the measured results.
  synthesis sub-ray: direction (two sin/cos, rotation, surface distance) ``RAY_SETUP_OPS`` = 60,
  the direct leg's traversal as above; a hit adds its deposits, mirror and reflection points
  and their polar angles (``HIT_OPS`` = 140) and the two clearance legs (each ≥ the root, 2 ×
  44); a sub-ray that meets the surface first adds the reflected leg (≥ 44). Hit and surface
  fractions are measured by casting the primary sub-rays of the 16 views.
  carving: one voxel × view test ``CARVE_OPS`` = 100 (transform 18, range 6, azimuth and
  elevation 40, the sphere's angular radius 20, beam/bin bounds 12, four table reads and three
  adds 4). A voxel's loop ends at the first rejecting view: the limit counts the views
  actually tested, measured on a 4,096-voxel sample (view by view); the throughput counts
  every voxel × view, as the issue asks.
  pose grid: per cell × view the synthesis of one view plus ``CONTOUR_OPS`` = 2 per layer
  pixel (read once, one compare); contour cost alone: the same 2 per pixel.
  reconstruction: one synthesis of every view plus one test per voxel of the first carving
  pass (96³): a loose bound; the figure is host-bound (segmentation, ICP, meshing, metrics).

Peak rates. NVIDIA GPUs from their vendor data sheets (FP32 non-tensor, an FMA counted as
2; memory bandwidth): H100 SXM 67 TFLOP/s and 3.35 TB/s, H100 PCIe 51 TFLOP/s and 2.0 TB/s,
H100 NVL 60 TFLOP/s and 3.9 TB/s, H200 67 TFLOP/s and 4.8 TB/s (NVIDIA H100 and H200 Tensor
Core GPU data sheets); a GPU missing from this table uses its measured device-to-device copy
bandwidth and no compute bound. The measured copy bandwidth is recorded beside the data sheet.
CPU: peak = cores used × clock × SIMD float32 lanes (16 with AVX-512, 8 with AVX2, else 4) ×
2 (FMA) × 2 FMA units per core (an assumption: server cores since Skylake-SP have two), from
the "cpu MHz" and "flags" lines of /proc/cpuinfo (a virtual machine reports its nominal
clock); cores used: 1 for Warp on the CPU and NumPy, the OpenCL device's compute units for
PoCL, every logical CPU for Embree. CPU memory bandwidth: a measured 256 MB NumPy copy
(2 bytes moved per byte copied), single-threaded; for PoCL the faster of that and an OpenCL
buffer-to-buffer copy on the device (all cores).
"""

from __future__ import annotations

import math
import os
import platform
import statistics
import tempfile
import time
from collections.abc import Callable, Sequence

import numpy as np

from .errors import InputError

__all__ = ["FAMILIES", "FULL_SIZES", "QUICK_SIZES", "measure", "sweep", "raycast", "synthesis", "carving",
           "pose_grid", "reconstruction", "check_options", "embree_raycast", "numpy_carving", "array_carving", "probe_machine",
           "run_suite", "markdown", "plot_family"]

FAMILIES = ("raycast", "synthesis", "carving", "pose", "reconstruction")
#: Swept values per family: icosphere subdivisions, views, voxels per side, cells per side,
#: (iterations, carving resolution).
FULL_SIZES = {"raycast": (3, 4, 5, 6, 7, 8), "synthesis": (1, 4, 16, 64, 256), "carving": (64, 128, 256, 512),
              "pose": (8, 16, 32, 64, 128), "reconstruction": ((1, 128),)}
QUICK_SIZES = {"raycast": (2, 3), "synthesis": (1, 2), "carving": (16, 24), "pose": (2, 3),
               "reconstruction": ((0, 24),)}

NODE_OPS = 44
TRIANGLE_OPS = 40
RAY_SETUP_OPS = 60
HIT_OPS = 140
CARVE_OPS = 100
CONTOUR_OPS = 2
LEAF_TRIANGLES = 4
RAY_IN_BYTES, RAY_OUT_BYTES, TRIANGLE_BYTES = 24, 8, 36

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
def _record(base: dict, x, timing: dict, work: float, unit: str, *, size: dict, rates: dict | None = None,
            limit: dict | None = None) -> dict:
    """A timed record: ``base`` (family, kernel, mode, backend, device, sweep) plus the point."""
    record = dict(base, x=x, size=size, work=float(work), work_unit=unit, **timing,
                  throughput=work / timing["median_s"], throughput_unit=f"{unit}/s",
                  rates={k: v / timing["median_s"] for k, v in (rates or {}).items()}, skipped=None)
    if limit is not None:
        record["limit"] = dict(limit, fraction=limit["limit_s"] / timing["median_s"])
    return record


def _skip(base: dict, x, projected: float, budget: float, reason: str | None = None) -> dict:
    return dict(base, x=x, skipped={"projected_s": projected, "budget_s": budget,
                                   "reason": reason or f"projected {projected:.3g} s > budget {budget:g} s"})


def _limit(profile: dict, *, bytes_moved: float, ops: float, up: float = 0.0, down: float = 0.0) -> dict:
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


def _tree_depth(triangles: int) -> int:
    return max(0, math.ceil(math.log2(max(1.0, triangles / LEAF_TRIANGLES))))


def _cast_ops(hits: int, misses: int, triangles: int) -> float:
    return hits * (_tree_depth(triangles) * NODE_OPS + TRIANGLE_OPS) + misses * NODE_OPS


def _base(family: str, kernel: str, mode: str, who, sweep_name: str) -> dict:
    return {"family": family, "kernel": kernel, "mode": mode, "backend": who.name, "device": who.device,
            "sweep": sweep_name}


class Peer:
    """A non-fsswarp implementation timed beside the backends (Embree, NumPy, CuPy)."""

    def __init__(self, name: str, device: str, is_gpu: bool = False):
        self.name, self.device, self.is_gpu = name, device, is_gpu


def _key(who) -> str:
    return f"{who.name}:{who.device}"


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


def _host_bandwidth(nbytes: int, repeat: int = 5) -> float:
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


def _gpu_copy_rates(backend, nbytes: int) -> tuple[float, float, float]:
    """(device-to-device B/s counting read + write, host-to-device B/s, device-to-host B/s),
    fastest of 5 copies of ``nbytes`` (pageable host memory)."""
    host = np.ones(nbytes // 4, np.float32)
    back = np.empty_like(host)
    if backend.name == "warp":
        import warp as wp

        device = wp.get_device(backend.device)
        src = wp.array(host, device=device)
        dst = wp.empty_like(src)

        def d2d():
            wp.copy(dst, src)
            wp.synchronize_device(device)

        staging = wp.array(host, device="cpu")

        def h2d():
            wp.copy(src, staging)
            wp.synchronize_device(device)

        def d2h():
            back[:] = src.numpy()
    else:
        import pyopencl as cl

        queue, flags = backend.queue, cl.mem_flags.READ_WRITE
        src = cl.Buffer(backend.context, flags, size=host.nbytes)
        dst = cl.Buffer(backend.context, flags, size=host.nbytes)

        def d2d():
            cl.enqueue_copy(queue, dst, src, byte_count=host.nbytes)
            queue.finish()

        def h2d():
            cl.enqueue_copy(queue, src, host, is_blocking=True)

        def d2h():
            cl.enqueue_copy(queue, back, src, is_blocking=True)
    rates = []
    for fn, factor in ((d2d, 2), (h2d, 1), (d2h, 1)):
        fn()
        rates.append(factor * host.nbytes / min(_once(fn) for _ in range(5)))
    return rates[0], rates[1], rates[2]


def device_name(backend) -> str:
    """The device's own name (GPU model, OpenCL device, or Warp's "cpu")."""
    if backend.name == "warp":
        import warp as wp

        return wp.get_device(backend.device).name
    if backend.name == "cupy":
        import cupy

        name = cupy.cuda.runtime.getDeviceProperties(0)["name"]
        return name.decode() if isinstance(name, bytes) else str(name)
    return backend.cl_device.name.strip()


def _profile(who, cpu: dict, host_bw: float, *, quick: bool) -> dict:
    """Bandwidth, peak and host link of one backend or peer (see the module docstring)."""
    if not who.is_gpu:
        if who.name == "opencl":
            cores = int(who.cl_device.max_compute_units)
        else:
            cores = (os.cpu_count() or 1) if who.name == "embree" else 1
        peak = None if cpu["peak_ops_per_core"] is None else cores * cpu["peak_ops_per_core"]
        bandwidth, source = host_bw, "measured NumPy copy (1 thread)"
        if who.name == "opencl":  # all cores: the faster of that and a buffer copy on the device
            copy = _gpu_copy_rates(who, (64 if quick else 256) << 20)[0]
            bandwidth, source = max((host_bw, source), (copy, "measured OpenCL buffer copy"))
        return {"key": _key(who), "name": cpu["model"], "kind": "cpu", "cores_used": cores,
                "bandwidth_Bps": bandwidth, "bandwidth_source": source,
                "peak_ops": peak, "peak_source": None if peak is None else
                f"{cores} core(s) x {cpu['peak_derivation']}"}
    name = device_name(who)
    size = (64 if quick else 512) << 20
    copy, up, down = _gpu_copy_rates(who, size) if who.name != "cupy" else _cupy_copy_rates(size)
    sheet = next((p for p in GPU_PEAKS if p[0].lower() in name.lower()), None)
    return {"key": _key(who), "name": name, "kind": "gpu", "measured_copy_Bps": copy,
            "bandwidth_Bps": sheet[1] if sheet else copy,
            "bandwidth_source": sheet[3] if sheet else "measured device-to-device copy",
            "peak_ops": sheet[2] if sheet else None, "peak_source": sheet[3] if sheet else None,
            "link_up_Bps": PCIE5_X16 if sheet else up, "link_down_Bps": PCIE5_X16 if sheet else down,
            "link_source": ("PCIe 5.0 x16 (data sheet)" if sheet else "measured")
            + f"; measured pageable copies of {size >> 20} MB: {up / 1e9:.3g} GB/s up, {down / 1e9:.3g} GB/s down"}


def _cupy_copy_rates(nbytes: int) -> tuple[float, float, float]:
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

    rates = []
    for fn, factor in ((d2d, 2), (h2d, 1), (d2h, 1)):
        fn()
        rates.append(factor * host.nbytes / min(_once(fn) for _ in range(5)))
    return rates[0], rates[1], rates[2]


def probe_machine(participants: Sequence, *, quick: bool = False) -> dict:
    """The machine and a limit profile (``_profile``) per backend or peer, keyed "name:device"."""
    cpu = cpu_info()
    host_bw = _host_bandwidth((32 if quick else 256) << 20)
    versions = {"python": platform.python_version(), "numpy": np.__version__}
    for module in ("warp", "pyopencl", "trimesh", "embreex", "cupy"):
        try:
            versions[module] = __import__(module).__version__
        except Exception:  # noqa: BLE001 - absent or broken: not recorded
            continue
    return {"host": platform.node(), "system": f"{platform.system()} {platform.release()}", "cpu": cpu,
            "host_bandwidth_Bps": host_bw, "versions": versions,
            "profiles": {_key(p): _profile(p, cpu, host_bw, quick=quick) for p in participants}}


# --- ray casting -------------------------------------------------------------------------------
def icosphere(level: int):
    """trimesh icosphere of radius 0.5 m at the origin (20·4^level faces)."""
    import trimesh

    return trimesh.creation.icosphere(subdivisions=level, radius=0.5)


def sphere_rays(count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(origins, directions) (count, 3) float32: rays from (0, −2, 0) through uniform points of
    the disc of radius 0.6 m in the plane y = 0 (25/36 of them hit a sphere of radius 0.5)."""
    rng = np.random.default_rng(seed)
    radius = 0.6 * np.sqrt(rng.random(count))
    angle = 2 * np.pi * rng.random(count)
    target = np.stack([radius * np.cos(angle), np.zeros(count), radius * np.sin(angle)], -1)
    origins = np.tile(np.array([0.0, -2.0, 0.0]), (count, 1))
    dirs = target - origins
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return origins.astype(np.float32), dirs.astype(np.float32)


def _resident_cast(backend, handle, origins: np.ndarray, dirs: np.ndarray):
    """A call that launches the cast kernel on rays already on the device and waits."""
    n = origins.shape[0]
    if backend.name == "warp":
        import warp as wp

        from .backends.warp_backend import cast_rays_kernel

        device = wp.get_device(backend.device)
        org, dir_ = (wp.array(a, dtype=wp.vec3, device=device) for a in (origins, dirs))
        distance, face = wp.empty(n, dtype=float, device=device), wp.empty(n, dtype=wp.int32, device=device)

        def call():
            wp.launch(cast_rays_kernel, dim=n, inputs=[handle.id, handle.points, handle.indices, org, dir_, 1.0e6],
                      outputs=[distance, face], device=device)
            wp.synchronize_device(device)
        return call
    import pyopencl as cl

    from .backends.opencl_backend import GROUP

    org, dir_ = backend._input(origins), backend._input(dirs)
    distance = cl.Buffer(backend.context, cl.mem_flags.WRITE_ONLY, size=4 * n)
    face = cl.Buffer(backend.context, cl.mem_flags.WRITE_ONLY, size=4 * n)

    def call():
        with backend._lock:
            backend._cast_kernel(backend.queue, (-(-n // GROUP) * GROUP,), None, handle.nodes, handle.children,
                                 handle.triangles, handle.face_index, org, dir_, np.int32(n), np.float32(1.0e6),
                                 distance, face)
            backend.queue.finish()
    return call


def _ray_count(who) -> int:
    return 1 << (22 if who.is_gpu else 18)


def _triangle_points(levels: Sequence[int], rays: int) -> list[tuple]:
    faces = [20 * 4**level for level in levels]
    return [(level, f, rays * math.log2(f)) for level, f in zip(levels, faces)]


def raycast(backend, levels: Sequence[int], *, profiles: dict, repeat: int = 3, budget: float = 20.0,
            rays: int | None = None, progress: Progress | None = None) -> list[dict]:
    """Ray casting on icospheres of 20·4^level triangles (``levels``), the same ray set at
    every size: "end to end" (``Backend.cast_rays``) and "resident" (the kernel alone)."""
    rays = rays or _ray_count(backend)
    origins, dirs = sphere_rays(rays)
    profile = profiles[_key(backend)]
    link = profile.get("link_up_Bps") is not None
    bases = {mode: _base("raycast", "cast_rays", mode, backend, "triangles") for mode in ("end to end", "resident")}

    def run_point(level):
        mesh = icosphere(level)
        faces = len(mesh.faces)
        handle = backend.load_mesh(mesh.vertices, mesh.faces)
        distance, _ = backend.cast_rays(handle, origins, dirs)
        hits = int(np.isfinite(distance).sum())
        ops = _cast_ops(hits, rays - hits, faces)
        moved = rays * (RAY_IN_BYTES + RAY_OUT_BYTES) + faces * TRIANGLE_BYTES
        size = {"triangles": faces, "rays": rays, "hits": hits}
        out = []
        for mode, call in (("end to end", lambda: backend.cast_rays(handle, origins, dirs)),
                           ("resident", _resident_cast(backend, handle, origins, dirs))):
            timing = measure(call, repeat, budget=budget)
            up, down = (rays * RAY_IN_BYTES, rays * RAY_OUT_BYTES) if link and mode == "end to end" else (0, 0)
            out.append(_record(bases[mode], faces, timing, rays, "rays", size=size,
                               limit=_limit(profile, bytes_moved=moved, ops=ops, up=up, down=down)))
            _say(progress, out[-1])
        return out

    def skipped(level, projected):
        return [_skip(b, 20 * 4**level, projected, budget) for b in bases.values()]

    return sweep(_triangle_points(levels, rays), run_point, skipped, budget=budget)


def embree_raycast(levels: Sequence[int], *, profiles: dict, repeat: int = 3, budget: float = 20.0,
                   rays: int | None = None, progress: Progress | None = None) -> list[dict]:
    """Embree (trimesh + embreex) on the ray sets of ``raycast`` on a CPU; one record per
    level, or one "unavailable" record when embreex is missing."""
    peer = Peer("embree", "cpu")
    base = _base("raycast", "intersects_first (trimesh + embreex)", "end to end", peer, "triangles")
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector
    except ImportError as err:
        return [dict(base, x=None, skipped={"reason": f"unavailable: {err}"})]
    rays = rays or _ray_count(peer)
    origins, dirs = sphere_rays(rays)
    profile = profiles[_key(peer)]

    def run_point(level):
        mesh = icosphere(level)
        faces = len(mesh.faces)
        intersector = RayMeshIntersector(mesh)
        hits = int((intersector.intersects_first(origins, dirs) >= 0).sum())
        timing = measure(lambda: intersector.intersects_first(origins, dirs), repeat, budget=budget)
        record = _record(base, faces, timing, rays, "rays", size={"triangles": faces, "rays": rays, "hits": hits},
                         limit=_limit(profile, bytes_moved=rays * (RAY_IN_BYTES + RAY_OUT_BYTES)
                                      + faces * TRIANGLE_BYTES, ops=_cast_ops(hits, rays - hits, faces)))
        _say(progress, record)
        return [record]

    return sweep(_triangle_points(levels, rays), run_point,
                 lambda level, p: [_skip(base, 20 * 4**level, p, budget)], budget=budget)


# --- image synthesis ---------------------------------------------------------------------------
def coral_batch(n_views: int):
    """coral-one at its true depth and tilt, ``n_views`` views (its 16 poses repeated with
    0.01 rad more roll per round): (sonar, mesh in the reference frame, rotations (N, 3, 3),
    translations (N, 3), plane normals (N, 3), plane offsets (N,))."""
    from .rig import Rig, View, world_to_reference
    from .scenes import builtin_scene, target_world_mesh
    from .surface import surface_in_views

    scene = builtin_scene("coral-one")
    truth, base = scene.truth, scene.rig.views
    views = tuple(View(f"v{k}", base[k % len(base)].position, base[k % len(base)].heading,
                       base[k % len(base)].roll + 0.01 * (k // len(base))) for k in range(n_views))
    rig = Rig(views)
    mesh = target_world_mesh(scene.target)
    mesh.vertices = world_to_reference(mesh.vertices, scene.rig, truth.depth, truth.tilt)
    rot, t = rig.relative_poses(truth.depth, truth.tilt)
    n, d = surface_in_views(rig, truth.depth, truth.tilt)
    return scene.sonar, mesh, rot, t, n, d


def render_ops(backend, sonar, mesh, rot, t, n, d, samples) -> np.ndarray:
    """(N,) minimal operations of rendering each view (module docstring), from the measured
    hits of its primary sub-rays."""
    from .backends import _beam_widths

    kt, kp = samples
    widths = _beam_widths(sonar).astype(np.float64)
    i = (np.arange(kt) + 0.5) / kt - 0.5
    j = (np.arange(kp) + 0.5) / kp
    theta = (sonar.beam_centres[:, None] + i[None, :] * widths[:, None]).reshape(-1, 1)
    phi = (-sonar.half_elevation + j * sonar.elevation_fov)[None, :]
    theta, phi = np.broadcast_arrays(theta, phi)
    u = np.stack([np.cos(phi) * np.sin(theta), np.cos(phi) * np.cos(theta), np.sin(phi)], -1).reshape(-1, 3)
    handle = backend.load_mesh(mesh.vertices, mesh.faces)
    per_ray = len(u)
    depth = _tree_depth(len(mesh.faces))
    ops = np.empty(len(rot))
    for v in range(len(rot)):
        r, _ = backend.cast_rays(handle, np.repeat(t[v:v + 1], per_ray, axis=0), u @ rot[v].T.astype(np.float64))
        towards = u @ n[v]
        s = np.where(towards > 0, d[v] / np.where(towards > 0, towards, 1.0), np.inf)
        hit = r < s
        surface_first = np.isfinite(s) & (s < r)
        ops[v] = (per_ray * RAY_SETUP_OPS + hit.sum() * (depth * NODE_OPS + TRIANGLE_OPS + HIT_OPS + 2 * NODE_OPS)
                  + (~hit).sum() * NODE_OPS + surface_first.sum() * NODE_OPS)
    return ops


def synthesis(backend, view_counts: Sequence[int], *, profiles: dict, repeat: int = 3, budget: float = 20.0,
              samples: tuple[int, int] = (2, 64), progress: Progress | None = None) -> list[dict]:
    """Image synthesis of N views in one launch (``view_counts``): "resident"
    (``render_device``) and "end to end" (``render``, with the read-back of the layers)."""
    sonar, mesh, rot, t, n, d = coral_batch(max(view_counts))
    base_ops = render_ops(backend, sonar, mesh, rot[:16], t[:16], n[:16], d[:16], samples)
    handle = backend.load_mesh(mesh.vertices, mesh.faces)
    profile = profiles[_key(backend)]
    link = profile.get("link_up_Bps") is not None
    layer_bytes = 4 * sonar.bins * sonar.beams * 4
    rays_per_view = sonar.beams * samples[0] * samples[1]
    kernels = {"resident": ("render_device", backend.render_device), "end to end": ("render", backend.render)}
    bases = {m: _base("synthesis", k, m, backend, "views") for m, (k, _) in kernels.items()}

    def run_point(views):
        args = (handle, sonar, rot[:views], t[:views], n[:views], d[:views], samples)
        ops = float(sum(base_ops[k % len(base_ops)] for k in range(views)))
        out = []
        for mode, (_, method) in kernels.items():
            timing = measure(lambda: method(*args, gamma=1.0, surface_reflection=0.9), repeat,  # noqa: B023
                             budget=budget)
            down = views * layer_bytes if link and mode == "end to end" else 0
            out.append(_record(bases[mode], views, timing, views, "views",
                               size={"views": views, "triangles": len(mesh.faces), "samples": list(samples),
                                     "bins": sonar.bins, "beams": sonar.beams},
                               rates={"primary rays": views * rays_per_view},
                               limit=_limit(profile, bytes_moved=views * layer_bytes + len(mesh.faces) * TRIANGLE_BYTES,
                                            ops=ops, down=down)))
            _say(progress, out[-1])
        return out

    return sweep([(v, v, v) for v in view_counts], run_point,
                 lambda v, p: [_skip(b, v, p, budget) for b in bases.values()], budget=budget)


# --- carving -----------------------------------------------------------------------------------
def carve_scene(backend):
    """coral-one's 16 views at the true depth and tilt: (sonar, feasible masks (16, bins, beams)
    bool from the noise-free object layer, rotations, translations, the target's centre (3,))."""
    from .rendering import RenderSettings, render
    from .rig import world_to_reference
    from .scenes import builtin_scene, target_world_mesh
    from .segment import from_highlight

    manifest = builtin_scene("coral-one")
    truth = manifest.truth
    mesh = target_world_mesh(manifest.target)
    mesh.vertices = world_to_reference(mesh.vertices, manifest.rig, truth.depth, truth.tilt)
    views = render(mesh, manifest.sonar, manifest.rig, truth.depth, truth.tilt, settings=RenderSettings(),
                   backend=backend)
    masks = np.stack([from_highlight(stack[0] > 0).feasible for stack in views.values()])
    rot, t = manifest.rig.relative_poses(truth.depth, truth.tilt)
    return manifest.sonar, masks, rot, t, mesh.bounds.mean(axis=0)


def _grid(centre, side: int) -> tuple[float, np.ndarray]:
    h = 0.3 / side
    return h, (np.asarray(centre) - 0.15 + 0.5 * h).astype(np.float32)


def _tests_per_voxel(backend, masks, rot, t, sonar, h, origin, side, sample=4096, seed=0) -> float:
    """Mean number of views a voxel's loop tests (it ends at the first rejection), measured on
    ``sample`` seeded voxels of the grid, one view at a time."""
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, side, size=(min(sample, side**3), 3))
    centres = origin + np.float32(h) * idx.astype(np.float32)
    rejected = np.stack([backend.carve(masks[v:v + 1], rot[v:v + 1], t[v:v + 1], sonar, h, centres=centres)[1]
                         for v in range(len(rot))])
    first = np.where(rejected.any(axis=0), rejected.argmax(axis=0) + 1, len(rot))
    return float(first.mean())


def _resident_carve(backend, masks, rot, t, sonar, h, origin, side):
    """A call that launches the carve-grid kernel on tables already on the device and waits."""
    from .backends import SonarConstants

    consts = SonarConstants.of(sonar)
    integral = np.zeros((len(rot), sonar.bins + 1, sonar.beams + 1), np.int32)
    np.cumsum(np.cumsum(masks != 0, axis=1, dtype=np.int32), axis=2, out=integral[:, 1:, 1:])
    rot32, t32 = np.ascontiguousarray(rot, np.float32), np.ascontiguousarray(t, np.float32)
    radius = float(np.float32(h * np.sqrt(3.0) / 2.0))
    h32 = float(np.float32(h))
    n = side**3
    scalars = (consts.use_table, consts.beams, consts.bins, consts.half_azimuth, consts.beam_scale,
               consts.range_min, consts.inv_range_step, consts.half_elevation, radius)
    if backend.name == "warp":
        import warp as wp

        from .backends.warp_backend import carve_grid

        device = wp.get_device(backend.device)
        arrays = [wp.array(rot32, dtype=wp.mat33, device=device), wp.array(t32, dtype=wp.vec3, device=device),
                  wp.array(integral, dtype=wp.int32, device=device),
                  wp.array(consts.beam_table, dtype=float, device=device)]
        seen, rejected = (wp.empty(n, dtype=wp.uint8, device=device) for _ in range(2))

        def call():
            wp.launch(carve_grid, dim=n, inputs=[wp.vec3(*(float(x) for x in origin)), h32, side, side, *arrays,
                                                 *scalars], outputs=[seen, rejected], device=device)
            wp.synchronize_device(device)
        return call
    import pyopencl as cl

    from .backends.opencl_backend import GROUP

    inputs = [backend._input(a) for a in (np.ascontiguousarray(origin, np.float32), rot32, t32, integral,
                                          consts.beam_table)]
    seen, rejected = (cl.Buffer(backend.context, cl.mem_flags.WRITE_ONLY, size=n) for _ in range(2))
    types = (np.int32, np.int32, np.int32, np.float32, np.float32, np.float32, np.float32, np.float32, np.float32)

    def call():
        with backend._lock:
            backend._carve_grid_kernel(backend.queue, (-(-n // GROUP) * GROUP,), None, inputs[0], np.float32(h32),
                                       *(np.int32(side) for _ in range(3)), np.int32(n), inputs[1], inputs[2],
                                       inputs[3], np.int32(len(rot)), inputs[4],
                                       *(ty(v) for ty, v in zip(types, scalars)), seen, rejected)
            backend.queue.finish()
    return call


def _carve_limit(profile, sonar, views, side, tests, *, end_to_end: bool) -> dict:
    tables = views * (sonar.bins + 1) * (sonar.beams + 1) * 4
    link = profile.get("link_up_Bps") is not None and end_to_end
    return _limit(profile, bytes_moved=2 * side**3 + tables, ops=side**3 * tests * CARVE_OPS,
                  up=tables if link else 0, down=2 * side**3 if link else 0)


def carving(backend, sides: Sequence[int], *, profiles: dict, repeat: int = 3, budget: float = 20.0,
            scene=None, progress: Progress | None = None) -> list[dict]:
    """One carve launch over side³ voxels × 16 views (``sides``): "end to end"
    (``Backend.carve``) and "resident" (the kernel alone)."""
    sonar, masks, rot, t, centre = scene or carve_scene(backend)
    views = len(rot)
    profile = profiles[_key(backend)]
    bases = {m: _base("carving", "carve", m, backend, "voxels") for m in ("end to end", "resident")}

    def run_point(side):
        h, origin = _grid(centre, side)
        tests = _tests_per_voxel(backend, masks, rot, t, sonar, h, origin, side)
        calls = {"end to end": lambda: backend.carve(masks, rot, t, sonar, h, origin=origin, shape=(side,) * 3),
                 "resident": _resident_carve(backend, masks, rot, t, sonar, h, origin, side)}
        out = []
        for mode, call in calls.items():
            timing = measure(call, repeat, budget=budget)
            out.append(_record(bases[mode], side**3, timing, side**3 * views, "voxel-views",
                               size={"voxels": side**3, "side": side, "views": views, "tests_per_voxel": tests},
                               limit=_carve_limit(profile, sonar, views, side, tests,
                                                  end_to_end=mode == "end to end")))
            _say(progress, out[-1])
        return out

    return sweep([(s, s**3, s**3) for s in sides], run_point,
                 lambda s, p: [_skip(b, s**3, p, budget) for b in bases.values()], budget=budget)


def numpy_carving(sides: Sequence[int], *, profiles: dict, scene, repeat: int = 3, budget: float = 20.0,
                  progress: Progress | None = None) -> list[dict]:
    """``fsswarp.carving.carve_reference`` (NumPy, float64) on the grids of ``carving``."""
    from .carving import carve_reference

    peer = Peer("numpy", "cpu")
    sonar, masks, rot, t, centre = scene
    views = len(rot)
    base = _base("carving", "carve_reference (float64)", "end to end", peer, "voxels")
    profile = profiles[_key(peer)]

    def run_point(side):
        h, origin = _grid(centre, side)
        seen, rejected = carve_reference(masks, rot, t, sonar, h, origin=origin, shape=(side,) * 3)
        timing = measure(lambda: carve_reference(masks, rot, t, sonar, h, origin=origin, shape=(side,) * 3), repeat,
                         budget=budget)
        # the reference also stops at the first rejection: its tests per voxel come from its own result
        tests = float(np.where(rejected > 0, np.minimum(seen, views), views).mean())
        record = _record(base, side**3, timing, side**3 * views, "voxel-views",
                         size={"voxels": side**3, "side": side, "views": views, "tests_per_voxel": tests},
                         limit=_carve_limit(profile, sonar, views, side, tests, end_to_end=False))
        _say(progress, record)
        return [record]

    return sweep([(s, s**3, s**3) for s in sides], run_point, lambda s, p: [_skip(base, s**3, p, budget)],
                 budget=budget)


def carve_array_module(xp, masks, rot, t, sonar, h: float, origin, side: int, chunk: int = 1 << 22):
    """Point carving with an array module (NumPy or CuPy): every voxel centre projected into
    every view, its nearest pixel looked up in the mask. Returns (side³,) bool, kept by every
    view that sees the centre. A plain-array baseline, not the kernels' bounding-sphere rule."""
    masks = xp.asarray(masks)
    rot, t = xp.asarray(rot, dtype=xp.float32), xp.asarray(t, dtype=xp.float32)
    ox, oy, oz = (float(v) for v in origin)
    centres_axis = xp.arange(side, dtype=xp.float32) * xp.float32(h)
    keep = xp.ones(side**3, dtype=bool)
    scale = xp.float32((sonar.beams - 1) / sonar.azimuth_fov)
    for start in range(0, side**3, chunk):
        p = xp.arange(start, min(start + chunk, side**3))
        pts = xp.stack([ox + centres_axis[p // (side * side)], oy + centres_axis[(p // side) % side],
                        oz + centres_axis[p % side]], -1)
        for v in range(rot.shape[0]):
            q = (pts - t[v]) @ rot[v]
            r = xp.sqrt((q * q).sum(axis=1))
            beam = xp.floor((xp.arctan2(q[:, 0], q[:, 1]) + xp.float32(sonar.half_azimuth)) * scale + 0.5)
            row = xp.floor((r - xp.float32(sonar.range_min)) / xp.float32(sonar.range_step) + 0.5)
            inside = ((beam >= 0) & (beam < sonar.beams) & (row >= 0) & (row < sonar.bins)
                      & (xp.abs(xp.arcsin(q[:, 2] / xp.maximum(r, 1e-12))) <= sonar.half_elevation))
            hit = masks[v, xp.clip(row, 0, sonar.bins - 1).astype(xp.int32),
                        xp.clip(beam, 0, sonar.beams - 1).astype(xp.int32)]
            keep[start:start + len(p)] &= ~inside | hit
    return keep


def array_carving(sides: Sequence[int], *, profiles: dict, scene, repeat: int = 3, budget: float = 20.0,
                  progress: Progress | None = None) -> list[dict]:
    """CuPy point carving (``carve_array_module``) on the grids of ``carving``, on the current
    CUDA device; one "unavailable" record without CuPy or a GPU."""
    peer = Peer("cupy", "cuda:0", is_gpu=True)
    base = _base("carving", "point projection (CuPy)", "resident", peer, "voxels")
    try:
        import cupy

        cupy.cuda.runtime.getDeviceCount()
    except Exception as err:  # noqa: BLE001 - ImportError or no CUDA device
        return [dict(base, x=None, skipped={"reason": f"unavailable: {' '.join(str(err).split())}"})]
    sonar, masks, rot, t, centre = scene
    views = len(rot)
    profile = profiles[_key(peer)]

    def run_point(side):
        h, origin = _grid(centre, side)

        def call():
            carve_array_module(cupy, masks, rot, t, sonar, h, origin, side)
            cupy.cuda.runtime.deviceSynchronize()

        timing = measure(call, repeat, budget=budget)
        record = _record(base, side**3, timing, side**3 * views, "voxel-views",
                         size={"voxels": side**3, "side": side, "views": views, "tests_per_voxel": views},
                         limit=_carve_limit(profile, sonar, views, side, views, end_to_end=False))
        _say(progress, record)
        return [record]

    return sweep([(s, s**3, s**3) for s in sides], run_point, lambda s, p: [_skip(base, s**3, p, budget)],
                 budget=budget)


# --- pose grid ---------------------------------------------------------------------------------
def pose_grid(backend, sides: Sequence[int], *, profiles: dict, repeat: int = 3, budget: float = 20.0,
              launch_bytes: int | None = None, progress: Progress | None = None) -> list[dict]:
    """The (D, β) grid surrogate over side² cells × 16 views (``sides``): "end to end"
    (``PoseProblem.surrogate``: render + contour cost per launch, costs read back) and
    "resident" (``Backend.contour_cost`` alone on layers already rendered, where they fit in
    one launch of ``launch_bytes``: default 16 GiB on a GPU, 2 GiB on a CPU)."""
    import dataclasses

    import trimesh

    from .dataset import Dataset
    from .pose import PoseProblem, PoseSettings
    from .rig import Rig
    from .simulation import simulate

    launch_bytes = launch_bytes or (16 << 30 if backend.is_gpu else 2 << 30)
    profile = profiles[_key(backend)]
    link = profile.get("link_up_Bps") is not None
    bases = {"end to end": _base("pose", "surrogate (render + contour cost)", "end to end", backend, "cells"),
             "resident": _base("pose", "contour_cost", "resident", backend, "cells")}
    with tempfile.TemporaryDirectory() as folder:
        dataset = simulate("coral-one", f"{folder}/coral-one", seed=1, backend=backend)
        rig = dataset.rig
        every = Rig(tuple(dataclasses.replace(v, optimize=True) for v in rig.views), rig.reference)
        dataset = Dataset(dataclasses.replace(dataset.manifest, rig=every), dataset.images, dataset.root)
        model = trimesh.load(dataset.truth_model_path, process=False)
        truth = dataset.manifest.truth
        problem = PoseProblem(model, dataset, truth.depth, truth.tilt,
                              settings=PoseSettings(launch_bytes=launch_bytes), backend=backend)
    data, sonar, settings = problem.data, problem.sonar, problem.settings
    views = len(data.views)
    rot, t, n, d = problem.view_poses(data.views, np.array([truth.depth]), np.array([truth.tilt]))
    per_pair = render_ops(backend, sonar, model, rot.reshape(-1, 3, 3), t.reshape(-1, 3), n.reshape(-1, 3),
                          d.reshape(-1), settings.samples)
    pixels = 4 * sonar.bins * sonar.beams
    distance_bytes = data.distances.nbytes
    mesh_bytes = len(model.faces) * TRIANGLE_BYTES

    def cells(side):
        return np.meshgrid(truth.depth + np.linspace(-0.05, 0.05, side),
                           truth.tilt + np.radians(np.linspace(-2.0, 2.0, side)), indexing="ij")

    def run_point(side):
        depths, tilts = cells(side)
        pairs = side * side * views
        shifts = [problem.shift] if problem.shift is not None else problem.shifts
        cost_bytes = pairs * 2 * len(shifts) * 4
        size = {"cells": side * side, "side": side, "views": views, "pairs": pairs}
        timing = measure(lambda: problem.surrogate(depths, tilts), repeat, budget=budget)
        out = [_record(bases["end to end"], side * side, timing, pairs, "cell-views", size=size,
                       limit=_limit(profile, bytes_moved=distance_bytes + mesh_bytes + cost_bytes,
                                    ops=side * side * float(per_pair.sum()) + pairs * pixels * CONTOUR_OPS,
                                    up=distance_bytes if link else 0, down=cost_bytes if link else 0))]
        _say(progress, out[-1])
        if pairs * 8 * pixels > launch_bytes:
            out.append(_skip(bases["resident"], side * side, 0.0, budget,
                             reason=f"layers of {pairs} pairs exceed one launch ({launch_bytes >> 20} MB)"))
            return out
        layers = problem.render_pairs(data.views, depths.ravel(), tilts.ravel(), settings.samples)
        index = np.tile(np.arange(views), side * side)
        capped = np.minimum(data.distances, np.float32(settings.cap))
        timing = measure(lambda: backend.contour_cost(layers, index, data.threshold, data.windows, data.masks,
                                                      capped, shifts, problem.smoothing), repeat, budget=budget)
        out.append(_record(bases["resident"], side * side, timing, pairs, "cell-views", size=size,
                           limit=_limit(profile, bytes_moved=pairs * pixels * 4 + distance_bytes + cost_bytes,
                                        ops=pairs * pixels * CONTOUR_OPS)))
        _say(progress, out[-1])
        return out

    return sweep([(s, s * s, s * s) for s in sides], run_point,
                 lambda s, p: [_skip(b, s * s, p, budget) for b in bases.values()], budget=budget)


# --- end-to-end reconstruction -----------------------------------------------------------------
def reconstruction(backend, settings: Sequence[tuple[int, int]], *, profiles: dict, repeat: int = 3,
                   budget: float = 20.0, progress: Progress | None = None) -> list[dict]:
    """``reconstruct`` of simulated coral-one for each (iterations, resolution) in ``settings``,
    no warm-up; repeats stop at the budget (at least one run)."""
    from .reconstruction import ReconstructSettings
    from .reconstruction import reconstruct as run
    from .simulation import simulate

    profile = profiles[_key(backend)]
    base = _base("reconstruction", "reconstruct", "end to end", backend, "iterations")
    out = []
    with tempfile.TemporaryDirectory() as folder:
        dataset = simulate("coral-one", f"{folder}/coral-one", seed=0, backend=backend)
        sonar = dataset.sonar
        views = len(dataset.images)
        scene = coral_batch(views)
        ops = float(render_ops(backend, *scene, (2, 64)).sum()) + 96**3 * CARVE_OPS
        image_bytes = views * sonar.bins * sonar.beams * 4
        for iterations, resolution in settings:
            chosen = ReconstructSettings(iterations=iterations, resolution=resolution)
            timing = measure(lambda: run(dataset, settings=chosen, backend=backend), repeat,  # noqa: B023
                             warmup=0, budget=budget)
            out.append(_record(base, iterations, timing, views, "views",
                               size={"iterations": iterations, "resolution": resolution, "views": views},
                               limit=_limit(profile, bytes_moved=image_bytes, ops=ops)))
            _say(progress, out[-1])
    return out


# --- the suite ---------------------------------------------------------------------------------
def _say(progress: Progress | None, record: dict) -> None:
    if progress is not None:
        progress("  " + _line(record))


def _line(r: dict) -> str:
    who = f"{r['family']} {r['kernel']} ({r['mode']}) {r['backend']} {r['device'][:40]}"
    if r.get("skipped"):
        return f"{who} {r['sweep']} {_fmt(r['x'])}: skipped ({r['skipped']['reason']})"
    limit = r.get("limit")
    return (f"{who} {r['sweep']} {_fmt(r['x'])}: {_ms(r['median_s'])} ({_ms(r['min_s'])}-{_ms(r['max_s'])}), "
            f"{_fmt(r['throughput'])} {r['throughput_unit']}"
            + (f", {limit['fraction']:.3g} of the {limit['bound']} limit" if limit else ""))


def _fmt(value) -> str:
    if value is None:
        return "-"
    value = float(value)
    if value == 0 or 1e-2 <= abs(value) < 1e4:
        return f"{value:.4g}"
    exponent = int(math.floor(math.log10(abs(value)) / 3) * 3)
    suffix = {3: "k", 6: "M", 9: "G", 12: "T", 15: "P", -3: "m", -6: "u", -9: "n"}.get(exponent)
    return f"{value / 10**exponent:.3g} {suffix}" if suffix else f"{value:.3g}"


def _ms(seconds: float) -> str:
    return f"{seconds * 1e3:.3g} ms" if seconds < 1 else f"{seconds:.3g} s"


def check_options(families: Sequence[str], budget: float) -> None:
    """InputError naming ``--families`` or ``--budget`` when one is bad."""
    unknown = [f for f in families if f not in FAMILIES]
    if unknown or not families:
        raise InputError(f"unknown family; choose from {', '.join(FAMILIES)}", field="--families",
                         value=",".join(unknown))
    if not (math.isfinite(budget) and budget > 0):
        raise InputError("must be a number of seconds > 0", field="--budget", value=budget)


def run_suite(backends: Sequence, families: Sequence[str] = FAMILIES, *, quick: bool = False, budget: float = 20.0,
              repeat: int = 3, peers: bool = True, command: str = "", progress: Progress | None = None) -> dict:
    """Run ``families`` on ``backends`` (and the peers) and return the run:
    {schema, date, command, quick, budget_s, repeat, machine, records}."""
    check_options(families, budget)
    sizes = QUICK_SIZES if quick else FULL_SIZES
    say = progress or (lambda line: None)
    embree = Peer("embree", "cpu")
    numpy_peer = Peer("numpy", "cpu")
    cupy_peer = Peer("cupy", "cuda:0", is_gpu=True)
    want_cupy = peers and "carving" in families and any(b.is_gpu for b in backends) and _has_cupy()
    participants = list(backends) + ([embree, numpy_peer] if peers else []) + ([cupy_peer] if want_cupy else [])
    say("measuring memory bandwidths")
    machine = probe_machine(participants, quick=quick)
    profiles = machine["profiles"]
    records: list[dict] = []
    common = dict(profiles=profiles, repeat=repeat, budget=budget, progress=say)
    for family in families:
        say(f"{family}:")
        scene = None
        for backend in backends:
            if family == "raycast":
                records += raycast(backend, sizes["raycast"], **common)
            elif family == "synthesis":
                records += synthesis(backend, sizes["synthesis"], **common)
            elif family == "carving":
                scene = scene or carve_scene(backend)
                records += carving(backend, sizes["carving"], scene=scene, **common)
            elif family == "pose":
                records += pose_grid(backend, sizes["pose"], **common)
            else:
                records += reconstruction(backend, sizes["reconstruction"], **common)
        if peers and family == "raycast":
            records += embree_raycast(sizes["raycast"], **common)
        if peers and family == "carving":
            scene = scene or carve_scene(backends[0])
            records += numpy_carving(sizes["carving"][:2], scene=scene, **common)
            if any(b.is_gpu for b in backends):  # an "unavailable" record when CuPy is missing
                records += array_carving(sizes["carving"], scene=scene, **common)
    return {"schema": 1, "date": time.strftime("%Y-%m-%d %H:%M:%S %z"), "command": command, "quick": quick,
            "budget_s": budget, "repeat": repeat, "machine": machine, "records": records}


def _has_cupy() -> bool:
    try:
        import cupy

        return cupy.cuda.runtime.getDeviceCount() > 0
    except Exception:  # noqa: BLE001 - ImportError or no CUDA device
        return False


# --- tables and plots --------------------------------------------------------------------------
FAMILY_TITLES = {"raycast": "Ray casting (rays/s; fixed ray set, icosphere triangles swept)",
                 "synthesis": "Image synthesis (views/s; coral-one, 96 × 512, samples (2, 64))",
                 "carving": "Space carving (voxel × views/s; 16 views)",
                 "pose": "Depth and tilt grid evaluation (cell × views/s; 16 views)",
                 "reconstruction": "End-to-end reconstruction (coral-one, 16 views)"}


def markdown(run: dict, *, heading: str = "##") -> str:
    """Tables of a run: one per family, every record with its median (min–max), throughput,
    limit and the fraction of it reached."""
    lines = []
    for family in FAMILIES:
        rows = [r for r in run["records"] if r["family"] == family]
        if not rows:
            continue
        lines += ["", f"{heading} {FAMILY_TITLES[family]}", "",
                  "| kernel | mode | backend / device | size | median (min–max), runs | throughput | "
                  "limit (bound) | fraction of limit |", "|---|---|---|---|---|---|---|---|"]
        for r in rows:
            who = f"{r['backend']} {r['device'][:48]}"
            size = f"{r['sweep']} {_fmt(r['x'])}" if r.get("x") is not None else "—"
            if r.get("skipped"):
                lines.append(f"| {r['kernel']} | {r['mode']} | {who} | {size} | skipped: {r['skipped']['reason']} "
                             "| — | — | — |")
                continue
            extra = "".join(f"; {_fmt(v)} {k}/s" for k, v in r.get("rates", {}).items())
            limit = r["limit"]
            lines.append(f"| {r['kernel']} | {r['mode']} | {who} | {size} | {_ms(r['median_s'])} "
                         f"({_ms(r['min_s'])}–{_ms(r['max_s'])}), {r['repeat']} | "
                         f"{_fmt(r['throughput'])} {r['throughput_unit']}{extra} | {_ms(limit['limit_s'])} "
                         f"({limit['bound']}) | {limit['fraction']:.3g} |")
    return "\n".join(lines).lstrip("\n") + "\n"


def machine_markdown(run: dict) -> str:
    """The machine, the command, the date and every limit profile of a run, as Markdown."""
    m = run["machine"]
    cpu = m["cpu"]
    lines = [f"- machine: {m['host']} ({m['system']}), CPU {cpu['model']}, {cpu['logical_cpus']} logical CPUs",
             f"- command: `{run['command']}`", f"- date: {run['date']}",
             f"- budget {run['budget_s']:g} s per point, {run['repeat']} timed runs per figure after a warm-up"
             + (" (quick sizes)" if run["quick"] else ""),
             "- versions: " + ", ".join(f"{k} {v}" for k, v in m["versions"].items()),
             "", "| profile | device | memory bandwidth | peak | host link up / down |", "|---|---|---|---|---|"]
    for key, p in m["profiles"].items():
        bw = f"{p['bandwidth_Bps'] / 1e9:.3g} GB/s ({p['bandwidth_source']}"
        bw += f"; measured copy {p['measured_copy_Bps'] / 1e9:.3g} GB/s)" if "measured_copy_Bps" in p else ")"
        peak = f"{p['peak_ops'] / 1e9:.4g} Gop/s ({p['peak_source']})" if p.get("peak_ops") else "—"
        link = (f"{p['link_up_Bps'] / 1e9:.3g} / {p['link_down_Bps'] / 1e9:.3g} GB/s ({p['link_source']})"
                if p.get("link_up_Bps") else "—")
        lines.append(f"| {key} | {p['name']} | {bw} | {peak} | {link} |")
    return "\n".join(lines) + "\n"


def slowest(records: Sequence[dict], count: int = 3) -> list[dict]:
    """The ``count`` fsswarp kernel families furthest from their limits: per (family, backend,
    device), the lowest fraction of its modes at the largest size measured, lowest first."""
    largest: dict[tuple, dict] = {}
    for r in records:
        if r.get("skipped") or r["backend"] in ("embree", "numpy", "cupy") or r["family"] == "reconstruction":
            continue
        key = (r["family"], r["backend"], r["device"])
        best = largest.get(key)
        if best is None or r["x"] > best["x"] or (r["x"] == best["x"]
                                                  and r["limit"]["fraction"] < best["limit"]["fraction"]):
            largest[key] = r
    return sorted(largest.values(), key=lambda r: r["limit"]["fraction"])[:count]


def plot_family(records: Sequence[dict], family: str, path, *, title: str = ""):
    """Log-log time against work size of one family: one line per kernel, mode, backend and
    device (label), its limit dashed in the same colour. Returns the path, or None without
    measured records."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .figures import _save

    series: dict[str, list[dict]] = {}
    for r in records:
        if r["family"] == family and not r.get("skipped"):
            device = "PoCL" if "Portable Computing Language" in r["device"] else r["device"][:28]
            series.setdefault(f"{r['backend']} {device}, {r['kernel']} ({r['mode']})", []).append(r)
    if not series:
        return None
    fig, ax = plt.subplots(figsize=(8.5, 5.5))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    styles = ["o", "s", "^", "v", "D", "x", "P", "*"]
    for k, (label, rows) in enumerate(sorted(series.items())):
        rows = sorted(rows, key=lambda r: r["x"])
        x = [r["x"] for r in rows]
        colour = colours[k % len(colours)]
        ax.plot(x, [r["median_s"] for r in rows], marker=styles[k // len(colours) % len(styles)], color=colour,
                label=label)
        ax.plot(x, [r["limit"]["limit_s"] for r in rows], linestyle="--", color=colour, linewidth=0.8)
    sweep_name = next(iter(series.values()))[0]["sweep"]
    if all(r["x"] > 0 for rows in series.values() for r in rows):
        ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(sweep_name)
    ax.set_ylabel("median time (s); dashed: physical limit")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=6, loc="best")
    return _save(fig, path, title or FAMILY_TITLES[family])
