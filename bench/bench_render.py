"""Benchmark of image synthesis: rays/s and views/s per backend, Embree on the same rays.

    python bench/bench_render.py [--views N] [--repeat K] [--json FILE]

Renders coral-one (5120 triangles) with the default 96-beam × 512-bin sonar, samples (2, 64)
(12,288 primary sub-rays per view), all four layers, N views in one launch (the scene's 16
poses repeated with extra rolls). Times are medians of K runs after a warm-up, two ways:
"synthesis" through ``Backend.render_device`` (pose upload, zeroing, the render kernel and
the fixed-point conversion, synchronized; the layers stay on the device, as the grid search
uses them) and "end to end" through ``Backend.render`` (the same plus the read-back of the
(N, 4, 512, 96) float32 images, 786 KB per view). Embree (trimesh + embreex, CPU) casts the
same primary rays for comparison.
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np

from timing import time_call


def scene_batch(n_views: int):
    from fsswarp.rig import Rig, View, world_to_reference
    from fsswarp.scenes import builtin_scene, target_world_mesh
    from fsswarp.surface import surface_in_views

    scene = builtin_scene("coral-one")
    truth = scene.truth
    base = scene.rig.views
    views = tuple(View(f"v{k}", base[k % len(base)].position, base[k % len(base)].heading,
                       base[k % len(base)].roll + 0.01 * (k // len(base))) for k in range(n_views))
    rig = Rig(views)
    mesh = target_world_mesh(scene.target)
    mesh.vertices = world_to_reference(mesh.vertices, scene.rig, truth.depth, truth.tilt)
    rot, t = rig.relative_poses(truth.depth, truth.tilt)
    n, d = surface_in_views(rig, truth.depth, truth.tilt)
    return scene.sonar, mesh, rot, t, n, d


def bench_backend(backend, sonar, mesh, rot, t, n, d, samples, repeat):
    handle = backend.load_mesh(mesh.vertices, mesh.faces)
    args = (handle, sonar, rot, t, n, d, samples)
    rows = []
    for mode, method in (("synthesis", backend.render_device), ("end to end", backend.render)):
        med, lo, hi = time_call(lambda: method(*args, gamma=1.0, surface_reflection=0.9), repeat)  # noqa: B023
        rays = len(rot) * sonar.beams * samples[0] * samples[1]
        rows.append({"backend": backend.name, "device": backend.device, "mode": mode, "views": len(rot),
                     "median_s": med, "min_s": lo, "max_s": hi, "views_per_s": len(rot) / med,
                     "primary_rays_per_s": rays / med})
    return rows


def primary_rays(sonar, rot, t, samples, limit):
    """The direct sub-rays of the first views (reference frame), at most ``limit``."""
    from fsswarp.backends import _beam_widths

    kt, kp = samples
    widths = _beam_widths(sonar).astype(np.float64)
    i = (np.arange(kt) + 0.5) / kt - 0.5
    j = (np.arange(kp) + 0.5) / kp
    theta = (sonar.beam_centres[:, None] + i[None, :] * widths[:, None]).reshape(-1, 1)
    phi = (-sonar.half_elevation + j * sonar.elevation_fov)[None, :]
    theta, phi = np.broadcast_arrays(theta, phi)
    u = np.stack([np.cos(phi) * np.sin(theta), np.cos(phi) * np.cos(theta), np.sin(phi)], -1).reshape(-1, 3)
    per_view = len(u)
    count = max(1, min(len(rot), limit // per_view))
    dirs = np.concatenate([u @ rot[m].T for m in range(count)])
    origins = np.repeat(t[:count], per_view, axis=0)
    return origins, dirs


def bench_embree(mesh, origins, dirs, repeat):
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector
    except ImportError:
        return None
    intersector = RayMeshIntersector(mesh)
    med, lo, hi = time_call(lambda: intersector.intersects_first(origins, dirs), repeat)
    return {"backend": "embree (trimesh+embreex)", "device": "cpu", "rays": len(origins), "median_s": med,
            "min_s": lo, "max_s": hi, "rays_per_s": len(origins) / med}


def bench_cast(backend, mesh, origins, dirs, repeat):
    handle = backend.load_mesh(mesh.vertices, mesh.faces)
    med, lo, hi = time_call(lambda: backend.cast_rays(handle, origins, dirs), repeat)
    return {"backend": backend.name, "device": backend.device, "rays": len(origins), "median_s": med,
            "min_s": lo, "max_s": hi, "rays_per_s": len(origins) / med}


def main() -> None:
    from fsswarp.backends import describe_backends, get_backend

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=64)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--rays", type=int, default=1_000_000, help="rays for the cast comparison")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    samples = (2, 64)
    sonar, mesh, rot, t, n, d = scene_batch(args.views)
    devices = [("warp", r["device"]) for r in describe_backends() if r["backend"] == "warp" and r["available"]]
    devices += [("opencl", str(r["index"])) for r in describe_backends() if r["backend"] == "opencl" and r["available"]]
    origins, dirs = primary_rays(sonar, rot, t, samples, args.rays)
    results = {"machine": platform.node(), "python": platform.python_version(), "date": time.strftime("%Y-%m-%d"),
               "render": [], "cast": []}
    for name, device in devices:
        backend = get_backend(name, device)
        views = args.views if backend.is_gpu or backend.name == "opencl" else min(args.views, 16)
        results["render"].extend(bench_backend(backend, sonar, mesh, rot[:views], t[:views], n[:views], d[:views],
                                               samples, args.repeat))
        results["cast"].append(bench_cast(backend, mesh, origins, dirs, args.repeat))
    embree = bench_embree(mesh, origins, dirs, args.repeat)
    if embree:
        results["cast"].append(embree)
    for row in results["render"]:
        print(f"render {row['mode']:10s} {row['backend']:7s} {row['device'][:40]:40s} {row['views']:6d} views  "
              f"median {row['median_s'] * 1e3:9.2f} ms  {row['views_per_s']:10.1f} views/s  "
              f"{row['primary_rays_per_s'] / 1e6:8.2f} Mrays/s")
    for row in results["cast"]:
        print(f"cast   {row['backend']:24s} {row['device'][:30]:30s} {row['rays']:8d} rays  "
              f"median {row['median_s'] * 1e3:9.2f} ms  {row['rays_per_s'] / 1e6:8.2f} Mrays/s")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(results, handle, indent=2)


if __name__ == "__main__":
    main()
