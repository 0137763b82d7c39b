"""Benchmark of voxel space carving: voxel × view tests per second per backend, the NumPy
reference beside them, and the whole coarse-to-fine carving.

    python bench/bench_carve.py [--size N] [--repeat K] [--json FILE]

Scene: coral-one's 16 views at the true depth and tilt, feasible masks from the noise-free
object layer (rendered once). Kernel: one ``Backend.carve`` launch over an N³ grid of a
0.3 m cube around the target (N³ × 16 tests), end to end (mask tables, upload, kernel,
read-back); Warp on the CPU runs single-threaded and gets (N/2)³. NumPy: ``carve_reference``
on a 64³ grid. Coarse-to-fine: ``fsswarp.carve.carve_masks`` at resolution N (domain, pass 1,
levels), the way ``fsswarp carve`` runs. Times are medians of K runs after a warm-up.
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np

from timing import time_call


def scene():
    """(sonar, masks (16, bins, beams), rotations, translations, plane, centre of the target)."""
    from fsswarp.backends import get_backend
    from fsswarp.render import RenderSettings, render
    from fsswarp.rig import world_to_reference
    from fsswarp.scenes import builtin_scene, target_world_mesh
    from fsswarp.segment import from_highlight
    from fsswarp.surface import surface_in_reference

    manifest = builtin_scene("coral-one")
    truth = manifest.truth
    mesh = target_world_mesh(manifest.target)
    mesh.vertices = world_to_reference(mesh.vertices, manifest.rig, truth.depth, truth.tilt)
    views = render(mesh, manifest.sonar, manifest.rig, truth.depth, truth.tilt, settings=RenderSettings(),
                   backend=get_backend())
    masks = np.stack([from_highlight(stack[0] > 0).feasible for stack in views.values()])
    rot, t = manifest.rig.relative_poses(truth.depth, truth.tilt)
    normal, offset = surface_in_reference(manifest.rig, truth.depth, truth.tilt)
    return manifest.sonar, masks, rot, t, (normal, float(offset)), mesh.bounds.mean(axis=0)


def bench_grid(backend, sonar, masks, rot, t, centre, size, repeat):
    h = 0.3 / size
    origin = centre - 0.15 + 0.5 * h
    call = lambda: backend.carve(masks, rot, t, sonar, h, origin=origin, shape=(size,) * 3)  # noqa: E731
    med, lo, hi = time_call(call, repeat)
    tests = size**3 * len(rot)
    return {"kernel": "carve grid", "backend": backend.name, "device": backend.device, "voxels": size**3,
            "views": len(rot), "median_s": med, "min_s": lo, "max_s": hi, "tests_per_s": tests / med}


def bench_reference(sonar, masks, rot, t, centre, size, repeat):
    from fsswarp.carve import carve_reference

    h = 0.3 / size
    origin = centre - 0.15 + 0.5 * h
    call = lambda: carve_reference(masks, rot, t, sonar, h, origin=origin, shape=(size,) * 3)  # noqa: E731
    med, lo, hi = time_call(call, repeat)
    return {"kernel": "carve grid", "backend": "numpy (float64 reference)", "device": "cpu", "voxels": size**3,
            "views": len(rot), "median_s": med, "min_s": lo, "max_s": hi, "tests_per_s": size**3 * len(rot) / med}


def bench_coarse_to_fine(backend, sonar, masks, rot, t, plane, resolution, repeat):
    from fsswarp.carve import carve_masks

    result = {}

    def call():
        result["carving"] = carve_masks(masks, rot, t, sonar, resolution=resolution, plane=plane, backend=backend)

    med, lo, hi = time_call(call, repeat)
    carving = result["carving"]
    return {"kernel": "carve coarse-to-fine", "backend": backend.name, "device": backend.device,
            "resolution": resolution, "shape": list(carving.occupancy.shape), "kept": carving.kept,
            "tested": carving.tested, "views": len(rot), "median_s": med, "min_s": lo, "max_s": hi,
            "tests_per_s": carving.tested * len(rot) / med}


def main() -> None:
    from fsswarp.backends import describe_backends, get_backend

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=256, help="grid voxels per side (and carving resolution)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    sonar, masks, rot, t, plane, centre = scene()
    rows = describe_backends()
    devices = [("warp", r["device"]) for r in rows if r["backend"] == "warp" and r["available"]]
    devices += [("opencl", str(r["index"])) for r in rows if r["backend"] == "opencl" and r["available"]]
    results = {"machine": platform.node(), "python": platform.python_version(), "date": time.strftime("%Y-%m-%d"),
               "rows": []}
    for name, device in devices:
        backend = get_backend(name, device)
        size = args.size if backend.is_gpu or backend.name == "opencl" else args.size // 2
        results["rows"].append(bench_grid(backend, sonar, masks, rot, t, centre, size, args.repeat))
        results["rows"].append(bench_coarse_to_fine(backend, sonar, masks, rot, t, plane, args.size, args.repeat))
    results["rows"].append(bench_reference(sonar, masks, rot, t, centre, 64, args.repeat))
    print("| kernel | backend / device | work | median | throughput |")
    print("|---|---|---|---|---|")
    for row in results["rows"]:
        if row["kernel"] == "carve grid":
            work = f"{round(row['voxels'] ** (1 / 3))}³ voxels × {row['views']} views"
        else:
            work = (f"resolution {row['resolution']} ({'×'.join(map(str, row['shape']))}), "
                    f"{row['tested']:,} voxels tested, {row['kept']:,} kept")
        print(f"| {row['kernel']} | {row['backend']} {row['device'][:40]} | {work} | "
              f"{row['median_s'] * 1e3:.1f} ms | {row['tests_per_s'] / 1e6:.1f} M voxel-views/s |")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(results, handle, indent=2)


if __name__ == "__main__":
    main()
