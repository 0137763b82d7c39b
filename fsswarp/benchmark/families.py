"""The five benchmark families of ``fsswarp bench``: what each one launches, at which sizes,
and its minimal operations and bytes (the physical limit; docs/benchmarks.md).

- ``raycast``: ``Backend.cast_rays`` of a fixed ray set on icospheres (sweep: triangles);
  peer ``embree_raycast``.
- ``synthesis``: ``Backend.render`` / ``render_device`` of coral-one views (sweep: views), views
  streamed in batches (``render_batches`` beside ``render`` per batch) and the first call of a
  new process with a cold and a warm kernel cache.
- ``carving``: one carve launch over an N³ grid × 16 views (sweep: voxels); peers
  ``numpy_carving`` (``carve_reference``) and ``array_carving`` (CuPy point projection).
- ``pose_grid``: the (D, β) grid surrogate of coral-one (sweep: cells).
- ``reconstruction``: ``fsswarp.reconstruction.reconstruct`` of simulated coral-one.

Each takes a backend, the swept sizes, the limit profiles of ``probe_machine`` and returns
records (``timed_record`` / ``skipped_record``). ``run_suite`` runs the families and peers
on every backend. Lengths in metres, times in seconds; poses ``P_ref = R @ P_view + t`` with
rotations (N, 3, 3) and translations (N, 3) float.
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from collections.abc import Sequence

import numpy as np

from ..errors import InputError
from .harness import (CupyPeer, Peer, Progress, format_value, measure, physical_limit, probe_machine, profile_key,
                      record_base, say, skipped_record, sweep, timed_record, unavailable_record)

FAMILIES = ("raycast", "synthesis", "carving", "pose", "reconstruction")
#: Swept values per family: icosphere subdivisions, views, voxels per side, cells per side,
#: (iterations, carving resolution).
FULL_SIZES = {"raycast": (3, 4, 5, 6, 7, 8), "synthesis": (1, 4, 16, 64, 256), "carving": (64, 128, 256, 512),
              "pose": (8, 16, 32, 64, 128), "reconstruction": ((1, 128),)}
QUICK_SIZES = {"raycast": (2, 3), "synthesis": (1, 2), "carving": (16, 24), "pose": (2, 3),
               "reconstruction": ((0, 24),)}
#: Synthesis streamed to the host in batches (``Backend.render_batches``): views in all, and
#: the views of a batch (full sizes; --quick: (4,) in batches of 2).
STREAM_SIZES, STREAM_BATCH = (1024, 4096), 256

NODE_OPS = 44
TRIANGLE_OPS = 40
RAY_SETUP_OPS = 60
HIT_OPS = 140
CARVE_OPS = 100
CONTOUR_OPS = 2
LEAF_TRIANGLES = 4
RAY_IN_BYTES, RAY_OUT_BYTES, TRIANGLE_BYTES = 24, 8, 36

#: The peers: Embree on every logical CPU, the NumPy reference and CuPy on one thread or GPU.
EMBREE = Peer("embree", "cpu", cores=os.cpu_count() or 1)
NUMPY = Peer("numpy", "cpu")
CUPY = CupyPeer()
PEERS = (EMBREE, NUMPY, CUPY)


def _tree_depth(triangles: int) -> int:
    return max(0, math.ceil(math.log2(max(1.0, triangles / LEAF_TRIANGLES))))


def _cast_ops(hits: int, misses: int, triangles: int) -> float:
    return hits * (_tree_depth(triangles) * NODE_OPS + TRIANGLE_OPS) + misses * NODE_OPS


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


def _ray_count(who) -> int:
    return 1 << (22 if who.is_gpu else 18)


def _triangle_points(levels: Sequence[int], rays: int) -> list[tuple]:
    faces = [20 * 4**level for level in levels]
    return [(level, f, rays * math.log2(f)) for level, f in zip(levels, faces)]


def raycast(backend, levels: Sequence[int], *, profiles: dict, repeat: int = 3, budget: float = 20.0,
            rays: int | None = None, progress: Progress | None = None) -> list[dict]:
    """Ray casting on icospheres of 20·4^level triangles (``levels``), the same ray set at
    every size: "end to end" (``Backend.cast_rays``) and "resident" (``Backend.prepared_cast``:
    the kernel alone on rays already on the device)."""
    rays = rays or _ray_count(backend)
    origins, dirs = sphere_rays(rays)
    profile = profiles[profile_key(backend)]
    link = profile.get("link_up_Bps") is not None
    bases = {mode: record_base("raycast", "cast_rays", mode, backend, "triangles")
             for mode in ("end to end", "resident")}

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
                           ("resident", backend.prepared_cast(handle, origins, dirs))):
            timing = measure(call, repeat, budget=budget)
            up, down = (rays * RAY_IN_BYTES, rays * RAY_OUT_BYTES) if link and mode == "end to end" else (0, 0)
            out.append(timed_record(bases[mode], faces, timing, rays, "rays", size=size,
                                    limit=physical_limit(profile, bytes_moved=moved, ops=ops, up=up, down=down)))
            say(progress, out[-1])
        return out

    def skipped(level, projected):
        return [skipped_record(b, 20 * 4**level, projected, budget) for b in bases.values()]

    return sweep(_triangle_points(levels, rays), run_point, skipped, budget=budget)


def embree_raycast(levels: Sequence[int], *, profiles: dict, repeat: int = 3, budget: float = 20.0,
                   rays: int | None = None, progress: Progress | None = None) -> list[dict]:
    """Embree (trimesh + embreex) on the ray sets of ``raycast`` on a CPU; one record per
    level, or one "unavailable" record when embreex is missing."""
    peer = EMBREE
    base = record_base("raycast", "intersects_first (trimesh + embreex)", "end to end", peer, "triangles")
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector
    except ImportError as err:
        return [unavailable_record(base, str(err))]
    rays = rays or _ray_count(peer)
    origins, dirs = sphere_rays(rays)
    profile = profiles[profile_key(peer)]

    def run_point(level):
        mesh = icosphere(level)
        faces = len(mesh.faces)
        intersector = RayMeshIntersector(mesh)
        hits = int((intersector.intersects_first(origins, dirs) >= 0).sum())
        timing = measure(lambda: intersector.intersects_first(origins, dirs), repeat, budget=budget)
        record = timed_record(base, faces, timing, rays, "rays", size={"triangles": faces, "rays": rays, "hits": hits},
                              limit=physical_limit(profile, bytes_moved=rays * (RAY_IN_BYTES + RAY_OUT_BYTES)
                                                   + faces * TRIANGLE_BYTES, ops=_cast_ops(hits, rays - hits, faces)))
        say(progress, record)
        return [record]

    return sweep(_triangle_points(levels, rays), run_point,
                 lambda level, p: [skipped_record(base, 20 * 4**level, p, budget)], budget=budget)


# --- image synthesis ---------------------------------------------------------------------------
def coral_batch(n_views: int):
    """coral-one at its true depth and tilt, ``n_views`` views (its 16 poses repeated with
    0.01 rad more roll per round): (sonar, mesh in the reference frame, rotations (N, 3, 3),
    translations (N, 3), plane normals (N, 3), plane offsets (N,))."""
    from ..rig import Rig, View, world_to_reference
    from ..scenes import builtin_scene, target_world_mesh
    from ..surface import view_planes

    scene = builtin_scene("coral-one")
    truth, base = scene.truth, scene.rig.views
    views = tuple(View(f"v{k}", base[k % len(base)].position, base[k % len(base)].heading,
                       base[k % len(base)].roll + 0.01 * (k // len(base))) for k in range(n_views))
    rig = Rig(views)
    mesh = target_world_mesh(scene.target)
    mesh.vertices = world_to_reference(mesh.vertices, scene.rig, truth.depth, truth.tilt)
    return (scene.sonar, mesh, *view_planes(rig, truth.depth, truth.tilt))


def render_ops(backend, sonar, mesh, rot, t, n, d, samples) -> np.ndarray:
    """(N,) minimal operations of rendering each view (docs/benchmarks.md), from the measured
    hits of its primary sub-rays."""
    kt, kp = samples
    widths = sonar.beam_widths.astype(np.float64)
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
              samples: tuple[int, int] = (2, 64), streamed: Sequence[int] = (), batch: int = STREAM_BATCH,
              first_run: bool = False, progress: Progress | None = None) -> list[dict]:
    """Image synthesis of coral-one views: N views in one launch (``view_counts``), "resident"
    (``render_device``) and "end to end" (``render``, with the read-back of the layers); N views
    in batches of ``batch`` (``streamed``), "end to end" both ways side by side: ``render`` per
    batch (pageable copies, one after the other: the path before ``render_batches``) and
    ``render_batches`` (page-locked staging, copies overlapped with the next batch); with
    ``first_run``, the first call in a fresh process with a cold and a warm kernel cache
    (``first_run_records``)."""
    sonar, mesh, rot, t, n, d = coral_batch(max([*view_counts, *streamed]))
    base_ops = render_ops(backend, sonar, mesh, rot[:16], t[:16], n[:16], d[:16], samples)
    handle = backend.load_mesh(mesh.vertices, mesh.faces)
    profile = profiles[profile_key(backend)]
    link = profile.get("link_up_Bps") is not None
    layer_bytes = 4 * sonar.bins * sonar.beams * 4
    rays_per_view = sonar.beams * samples[0] * samples[1]
    kernels = {"resident": ("render_device", backend.render_device), "end to end": ("render", backend.render)}
    bases = {m: record_base("synthesis", k, m, backend, "views") for m, (k, _) in kernels.items()}
    size = {"triangles": len(mesh.faces), "samples": list(samples), "bins": sonar.bins, "beams": sonar.beams}

    def limit(views, end_to_end):
        ops = float(sum(base_ops[k % len(base_ops)] for k in range(views)))
        return physical_limit(profile, bytes_moved=views * layer_bytes + len(mesh.faces) * TRIANGLE_BYTES, ops=ops,
                              down=views * layer_bytes if link and end_to_end else 0)

    def run_point(views):
        args = (handle, sonar, rot[:views], t[:views], n[:views], d[:views], samples)
        out = []
        for mode, (_, method) in kernels.items():
            timing = measure(lambda: method(*args, gamma=1.0, surface_reflection=0.9), repeat,  # noqa: B023
                             budget=budget)
            out.append(timed_record(bases[mode], views, timing, views, "views", size=dict(size, views=views),
                                    rates={"primary rays": views * rays_per_view},
                                    limit=limit(views, mode == "end to end")))
            say(progress, out[-1])
        return out

    records = sweep([(v, v, v) for v in view_counts], run_point,
                    lambda v, p: [skipped_record(b, v, p, budget) for b in bases.values()], budget=budget)

    paths = {"pageable": (f"render per batch of {batch} (pageable, in turn)", _batched_render),
             "pinned": (f"render_batches of {batch} (pinned, overlapped)", _streamed_render)}
    stream_bases = {k: record_base("synthesis", name, "end to end", backend, "views") for k, (name, _) in paths.items()}

    def run_stream(views):
        args = (handle, sonar, rot[:views], t[:views], n[:views], d[:views], samples)
        out = {}
        for key, (_, call) in paths.items():
            timing = measure(lambda: call(backend, args, batch), repeat, budget=budget)  # noqa: B023
            out[key] = timed_record(stream_bases[key], views, timing, views, "views",
                                    size=dict(size, views=views, batch=batch),
                                    rates={"primary rays": views * rays_per_view, "bytes to the host":
                                           views * layer_bytes}, limit=limit(views, True))
            say(progress, out[key])
        if progress is not None:
            before, after = out["pageable"]["throughput"], out["pinned"]["throughput"]
            progress(f"  synthesis {backend.name} {backend.device[:40]}, {views} views in batches of {batch}, all "
                     f"layers to the host: {format_value(before)} views/s before (pageable), {format_value(after)} "
                     f"views/s after (pinned, overlapped): x{after / before:.3g}")
        return list(out.values())

    records += sweep([(v, v, v) for v in streamed], run_stream,
                     lambda v, p: [skipped_record(b, v, p, budget) for b in stream_bases.values()], budget=budget)
    if first_run:
        records += first_run_records(backend, profiles=profiles, samples=samples, progress=progress)
    return records


def _batched_render(backend, args, batch: int) -> None:
    """``render`` of the views of ``args`` batch after batch, each read back before the next
    (pageable host arrays)."""
    handle, sonar, rot, t, n, d, samples = args
    for start in range(0, len(rot), batch):
        views = slice(start, start + batch)
        backend.render(handle, sonar, rot[views], t[views], n[views], d[views], samples, gamma=1.0,
                       surface_reflection=0.9)


def _streamed_render(backend, args, batch: int) -> None:
    """``render_batches`` of the views of ``args``, every batch's layers handed to the host."""
    for _ in backend.render_batches(*args, gamma=1.0, surface_reflection=0.9, batch=batch):
        pass


FIRST_CALL = """
import json, sys, time
from fsswarp.backends import get_backend
from fsswarp.benchmark.families import coral_batch
sonar, mesh, rot, t, n, d = coral_batch(1)
args = (sonar, rot, t, n, d, tuple(json.loads(sys.argv[3])))
begin = time.perf_counter()
backend = get_backend(sys.argv[1], sys.argv[2])
made = time.perf_counter()
handle = backend.load_mesh(mesh.vertices, mesh.faces)
backend.render(handle, *args, gamma=1.0, surface_reflection=0.9)
first = time.perf_counter()
backend.render(handle, *args, gamma=1.0, surface_reflection=0.9)
print(json.dumps({"backend_s": made - begin, "first_s": first - begin, "again_s": time.perf_counter() - first}))
"""


def first_run_records(backend, *, profiles: dict, samples: tuple[int, int] = (2, 64), timeout: float = 900.0,
                      progress: Progress | None = None) -> list[dict]:
    """The first synthesis of one coral-one view in a new process (``FIRST_CALL``): creating the
    backend, loading the mesh and the first ``render``, which compiles the kernels or loads
    them from the kernel cache. Twice, in child processes whose kernel caches live in one
    temporary folder (``cache_environment``): first empty ("first run (cold cache)": kernel
    compilation), then as the first left it ("first run (warm cache)": cache load). Each
    record's size holds the backend's creation (``backend_s``) and a second render in the same
    process (``again_s``, warm); the limit is that of rendering one view."""
    import json
    import subprocess
    import sys

    profile = profiles[profile_key(backend)]
    sonar, mesh, rot, t, n, d = coral_batch(1)
    ops = float(render_ops(backend, sonar, mesh, rot, t, n, d, samples).sum())
    layer_bytes = 4 * sonar.bins * sonar.beams * 4
    out = []
    with tempfile.TemporaryDirectory(prefix="fsswarp-cache-") as folder:
        env = dict(os.environ, **cache_environment(folder))
        for mode in ("first run (cold cache)", "first run (warm cache)"):
            done = subprocess.run([sys.executable, "-c", FIRST_CALL, backend.name, backend.device,
                                   json.dumps(list(samples))], env=env, capture_output=True, text=True,
                                  timeout=timeout, check=False)
            base = record_base("synthesis", "render, first call of a new process", mode, backend, "views")
            if done.returncode != 0:
                out.append(unavailable_record(base, " ".join((done.stderr or done.stdout).split()[-30:])))
                continue
            times = json.loads(done.stdout.strip().splitlines()[-1])
            timing = {"median_s": times["first_s"], "min_s": times["first_s"], "max_s": times["first_s"],
                      "repeat": 1, "timed_s": times["first_s"]}
            out.append(timed_record(base, 1, timing, 1, "views",
                                    size={"views": 1, "samples": list(samples), "backend_s": times["backend_s"],
                                          "again_s": times["again_s"]},
                                    limit=physical_limit(profile, bytes_moved=layer_bytes + len(mesh.faces)
                                                         * TRIANGLE_BYTES, ops=ops)))
            say(progress, out[-1])
    return out


def cache_environment(folder) -> dict[str, str]:
    """Environment variables that put every kernel cache fsswarp's backends use under
    ``folder``: Warp's (``WARP_CACHE_PATH``), PoCL's and pyopencl's and fsswarp's own records
    (``XDG_CACHE_HOME``; PoCL also ``POCL_CACHE_DIR``) and NVIDIA's JIT cache
    (``CUDA_CACHE_PATH``, which its OpenCL driver uses too)."""
    return {"WARP_CACHE_PATH": f"{folder}/warp", "XDG_CACHE_HOME": f"{folder}/xdg",
            "POCL_CACHE_DIR": f"{folder}/pocl", "CUDA_CACHE_PATH": f"{folder}/nv"}


# --- carving -----------------------------------------------------------------------------------
def carve_scene(backend):
    """coral-one's 16 views at the true depth and tilt: (sonar, feasible masks (16, bins, beams)
    bool from the noise-free object layer, rotations, translations, the target's centre (3,))."""
    from ..rendering import RenderSettings, render
    from ..rig import world_to_reference
    from ..scenes import builtin_scene, target_world_mesh
    from ..segment import from_highlight

    manifest = builtin_scene("coral-one")
    truth = manifest.truth
    mesh = target_world_mesh(manifest.target)
    mesh.vertices = world_to_reference(mesh.vertices, manifest.rig, truth.depth, truth.tilt)
    views = render(mesh, manifest.sonar, manifest.rig, truth.depth, truth.tilt, settings=RenderSettings(),
                   backend=backend)
    masks = np.stack([from_highlight(stack[0] > 0).feasible for stack in views.values()])
    rot, t = manifest.rig.relative_poses(truth.depth, truth.tilt)
    return manifest.sonar, masks, rot, t, mesh.bounds.mean(axis=0)


def carving_grid(centre, side: int) -> tuple[float, np.ndarray]:
    """(voxel size h, origin (3,) float32) of the side³ grid of a 0.3 m cube centred at ``centre``."""
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


def _carve_limit(profile, sonar, views, side, tests, *, end_to_end: bool) -> dict:
    tables = views * (sonar.bins + 1) * (sonar.beams + 1) * 4
    link = profile.get("link_up_Bps") is not None and end_to_end
    return physical_limit(profile, bytes_moved=2 * side**3 + tables, ops=side**3 * tests * CARVE_OPS,
                          up=tables if link else 0, down=2 * side**3 if link else 0)


def carving(backend, sides: Sequence[int], *, profiles: dict, repeat: int = 3, budget: float = 20.0,
            scene=None, progress: Progress | None = None) -> list[dict]:
    """One carve launch over side³ voxels × 16 views (``sides``): "end to end"
    (``Backend.carve``) and "resident" (``Backend.prepared_carve``: the kernel alone on
    tables already on the device)."""
    sonar, masks, rot, t, centre = scene or carve_scene(backend)
    views = len(rot)
    profile = profiles[profile_key(backend)]
    bases = {m: record_base("carving", "carve", m, backend, "voxels") for m in ("end to end", "resident")}

    def run_point(side):
        h, origin = carving_grid(centre, side)
        tests = _tests_per_voxel(backend, masks, rot, t, sonar, h, origin, side)
        calls = {"end to end": lambda: backend.carve(masks, rot, t, sonar, h, origin=origin, shape=(side,) * 3),
                 "resident": backend.prepared_carve(masks, rot, t, sonar, h, origin, side)}
        out = []
        for mode, call in calls.items():
            timing = measure(call, repeat, budget=budget)
            out.append(timed_record(bases[mode], side**3, timing, side**3 * views, "voxel-views",
                                    size={"voxels": side**3, "side": side, "views": views, "tests_per_voxel": tests},
                                    limit=_carve_limit(profile, sonar, views, side, tests,
                                                       end_to_end=mode == "end to end")))
            say(progress, out[-1])
        return out

    return sweep([(s, s**3, s**3) for s in sides], run_point,
                 lambda s, p: [skipped_record(b, s**3, p, budget) for b in bases.values()], budget=budget)


def numpy_carving(sides: Sequence[int], *, profiles: dict, scene, repeat: int = 3, budget: float = 20.0,
                  progress: Progress | None = None) -> list[dict]:
    """``fsswarp.carving.carve_reference`` (NumPy, float64) on the grids of ``carving``."""
    from ..carving import carve_reference

    peer = NUMPY
    sonar, masks, rot, t, centre = scene
    views = len(rot)
    base = record_base("carving", "carve_reference (float64)", "end to end", peer, "voxels")
    profile = profiles[profile_key(peer)]

    def run_point(side):
        h, origin = carving_grid(centre, side)
        seen, rejected = carve_reference(masks, rot, t, sonar, h, origin=origin, shape=(side,) * 3)
        timing = measure(lambda: carve_reference(masks, rot, t, sonar, h, origin=origin, shape=(side,) * 3), repeat,
                         budget=budget)
        # the reference also stops at the first rejection: its tests per voxel come from its own result
        tests = float(np.where(rejected > 0, np.minimum(seen, views), views).mean())
        record = timed_record(base, side**3, timing, side**3 * views, "voxel-views",
                              size={"voxels": side**3, "side": side, "views": views, "tests_per_voxel": tests},
                              limit=_carve_limit(profile, sonar, views, side, tests, end_to_end=False))
        say(progress, record)
        return [record]

    return sweep([(s, s**3, s**3) for s in sides], run_point,
                 lambda s, p: [skipped_record(base, s**3, p, budget)], budget=budget)


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
    peer = CUPY
    base = record_base("carving", "point projection (CuPy)", "resident", peer, "voxels")
    try:
        import cupy

        cupy.cuda.runtime.getDeviceCount()
    except Exception as err:  # noqa: BLE001 - ImportError or no CUDA device
        return [unavailable_record(base, " ".join(str(err).split()))]
    sonar, masks, rot, t, centre = scene
    views = len(rot)
    profile = profiles[profile_key(peer)]

    def run_point(side):
        h, origin = carving_grid(centre, side)

        def call():
            carve_array_module(cupy, masks, rot, t, sonar, h, origin, side)
            cupy.cuda.runtime.deviceSynchronize()

        timing = measure(call, repeat, budget=budget)
        record = timed_record(base, side**3, timing, side**3 * views, "voxel-views",
                              size={"voxels": side**3, "side": side, "views": views, "tests_per_voxel": views},
                              limit=_carve_limit(profile, sonar, views, side, views, end_to_end=False))
        say(progress, record)
        return [record]

    return sweep([(s, s**3, s**3) for s in sides], run_point,
                 lambda s, p: [skipped_record(base, s**3, p, budget)], budget=budget)


# --- pose grid ---------------------------------------------------------------------------------
def every_view_scene(backend, folder, scene: str = "coral-one", seed: int = 1):
    """(the built-in ``scene`` simulated on ``backend`` into ``folder`` (noise ``seed``) with every
    view to optimize, its true model as a trimesh): the pose grid's problem of 16 views."""
    import dataclasses

    import trimesh

    from ..dataset import Dataset
    from ..rig import Rig
    from ..simulation import simulate

    dataset = simulate(scene, f"{folder}/{scene}", seed=seed, backend=backend)
    rig = dataset.rig
    every = Rig(tuple(dataclasses.replace(v, optimize=True) for v in rig.views), rig.reference)
    dataset = Dataset(dataclasses.replace(dataset.manifest, rig=every), dataset.images, dataset.root)
    return dataset, trimesh.load(dataset.truth_model_path, process=False)


def grid_cells(truth, side: int) -> tuple[np.ndarray, np.ndarray]:
    """(side, side) depths (m) and tilts (rad) of the pose grid's benchmark: ± 5 cm and ± 2°
    around ``truth`` (its ``depth`` m and ``tilt`` rad)."""
    return np.meshgrid(truth.depth + np.linspace(-0.05, 0.05, side),
                       truth.tilt + np.radians(np.linspace(-2.0, 2.0, side)), indexing="ij")


def pose_grid(backend, sides: Sequence[int], *, profiles: dict, repeat: int = 3, budget: float = 20.0,
              launch_bytes: int | None = None, progress: Progress | None = None) -> list[dict]:
    """The (D, β) grid surrogate over side² cells × 16 views (``sides``): "end to end"
    (``ViewComparison.surrogate``: render + view costs per launch, costs read back), its
    "render alone" (``render_pairs`` of the same bands of rows, beams and components' sums in
    the same launches, layers dropped) and "resident" (``Backend.view_costs`` alone on the
    components' sums already rendered, where they fit in one launch of ``launch_bytes``: default
    16 GiB on a GPU, 2 GiB on a CPU)."""
    from ..compare import PoseSettings, ViewComparison, grid_render_options

    launch_bytes = launch_bytes or (16 << 30 if backend.is_gpu else 2 << 30)
    profile = profiles[profile_key(backend)]
    link = profile.get("link_up_Bps") is not None
    bases = {"end to end": record_base("pose", "surrogate (render + contour cost)", "end to end", backend, "cells"),
             "render alone": record_base("pose", "render_pairs (window bands, beams read)", "render alone", backend,
                                         "cells"),
             "resident": record_base("pose", "view_costs", "resident", backend, "cells")}
    with tempfile.TemporaryDirectory() as folder:
        dataset, model = every_view_scene(backend, folder)
        truth = dataset.manifest.truth
        problem = ViewComparison(dataset, settings=PoseSettings(launch_bytes=launch_bytes),
                                 backend=backend).use(model, truth.depth, truth.tilt)
    data, sonar, settings = problem.data, problem.sonar, problem.settings
    views = len(data.views)
    rot, t, n, d = problem.view_poses(data.views, np.array([truth.depth]), np.array([truth.tilt]))
    per_pair = render_ops(backend, sonar, model, rot.reshape(-1, 3, 3), t.reshape(-1, 3), n.reshape(-1, 3),
                          d.reshape(-1), settings.samples)
    pixels = 4 * sonar.bins * sonar.beams  # of the four layers, whose contour work CONTOUR_OPS counts
    summed = 2 * sonar.bins * sonar.beams  # of the components' sums the grid renders
    distance_bytes = data.distances.nbytes
    mesh_bytes = len(model.faces) * TRIANGLE_BYTES
    layout = problem.grid_launches(settings.samples)  # view_costs' bands, beams and launches
    _, rows, _, per = layout

    def render_alone(depths, tilts):
        for start in range(0, len(depths), per):
            cell_d, cell_t = depths[start:start + per], tilts[start:start + per]
            problem.render_pairs(data.views, cell_d, cell_t, settings.samples,
                                 **grid_render_options(layout, len(cell_d)))

    def run_point(side):
        depths, tilts = grid_cells(truth, side)
        pairs = side * side * views
        shifts = [problem.shift] if problem.shift is not None else problem.shifts
        cost_bytes = pairs * 2 * len(shifts) * 4
        size = {"cells": side * side, "side": side, "views": views, "pairs": pairs}
        timing = measure(lambda: problem.surrogate(depths, tilts), repeat, budget=budget)
        out = [timed_record(bases["end to end"], side * side, timing, pairs, "cell-views", size=size,
                            limit=physical_limit(profile, bytes_moved=distance_bytes + mesh_bytes + cost_bytes,
                                                 ops=side * side * float(per_pair.sum()) + pairs * pixels * CONTOUR_OPS,
                                                 up=distance_bytes if link else 0, down=cost_bytes if link else 0))]
        say(progress, out[-1])
        timing = measure(lambda: render_alone(depths.ravel(), tilts.ravel()), repeat, budget=budget)
        out.append(timed_record(bases["render alone"], side * side, timing, pairs, "cell-views", size=size,
                                limit=physical_limit(profile, bytes_moved=mesh_bytes + pairs * 8 * rows * sonar.beams,
                                                     ops=side * side * float(per_pair.sum()))))
        say(progress, out[-1])
        if pairs * 4 * summed > launch_bytes or pairs * summed >= 2**31:  # int32 sums
            out.append(skipped_record(bases["resident"], side * side, 0.0, budget,
                                      reason=f"layers of {pairs} pairs exceed one launch ({launch_bytes >> 20} MB "
                                             "or 2^31 values)"))
            return out
        layers = problem.render_pairs(data.views, depths.ravel(), tilts.ravel(), settings.samples, components=True)
        index = np.tile(np.arange(views), side * side)
        uploaded = backend.device_distances(data.distances)
        timing = measure(lambda: backend.view_costs(layers, index, data.threshold, data.windows, data.masks, uploaded,
                                                    shifts, problem.smoothing, data.counts, settings.cap),
                         repeat, budget=budget)
        out.append(timed_record(bases["resident"], side * side, timing, pairs, "cell-views", size=size,
                                limit=physical_limit(profile, bytes_moved=pairs * summed * 4 + distance_bytes
                                                     + cost_bytes, ops=pairs * pixels * CONTOUR_OPS)))
        say(progress, out[-1])
        return out

    return sweep([(s, s * s, s * s) for s in sides], run_point,
                 lambda s, p: [skipped_record(b, s * s, p, budget) for b in bases.values()], budget=budget)


# --- end-to-end reconstruction -----------------------------------------------------------------
def reconstruction(backend, settings: Sequence[tuple[int, int]], *, profiles: dict, repeat: int = 3,
                   budget: float = 20.0, progress: Progress | None = None) -> list[dict]:
    """``reconstruct`` of simulated coral-one for each (iterations, resolution) in ``settings``,
    no warm-up; repeats stop at the budget (at least one run)."""
    from ..reconstruction import ReconstructSettings
    from ..reconstruction import reconstruct as run
    from ..simulation import simulate

    profile = profiles[profile_key(backend)]
    base = record_base("reconstruction", "reconstruct", "end to end", backend, "iterations")
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
            out.append(timed_record(base, iterations, timing, views, "views",
                                    size={"iterations": iterations, "resolution": resolution, "views": views},
                                    limit=physical_limit(profile, bytes_moved=image_bytes, ops=ops)))
            say(progress, out[-1])
    return out


# --- the suite ---------------------------------------------------------------------------------
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
    echo = progress or (lambda line: None)
    want_cupy = peers and "carving" in families and any(b.is_gpu for b in backends) and _has_cupy()
    participants = list(backends) + ([EMBREE, NUMPY] if peers else []) + ([CUPY] if want_cupy else [])
    echo("measuring memory bandwidths")
    machine = probe_machine(participants, quick=quick)
    profiles = machine["profiles"]
    records: list[dict] = []
    common = dict(profiles=profiles, repeat=repeat, budget=budget, progress=echo)
    for family in families:
        echo(f"{family}:")
        scene = None
        for backend in backends:
            if family == "raycast":
                records += raycast(backend, sizes["raycast"], **common)
            elif family == "synthesis":
                records += synthesis(backend, sizes["synthesis"], streamed=(4,) if quick else STREAM_SIZES,
                                     batch=2 if quick else STREAM_BATCH, first_run=not quick, **common)
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

