"""Benchmark of the (D, β) grid evaluation: grid cells × views per second per backend.

    python bench/bench_pose.py [--grid N] [--repeat K] [--backends warp,opencl] [--json FILE]

coral-one is simulated (seed 1) into a temporary folder and all 16 of its views take part
(the held-out rolls too), with the true model (5120 triangles). One grid evaluation is what
``fsswarp.pose.PoseProblem.surrogate`` runs per level of the search: an N × N grid of (D, β)
cells, every cell × view pair rendered in one ``Backend.render_device`` launch (samples
(2, 64), all four layers) and reduced on the device by one ``Backend.contour_cost`` launch;
only the costs come back. "contour cost" times that kernel alone on layers already on the
device. Times are medians of K runs after a warm-up. The layers take 2 × 786 KB per pair
(512 bins × 96 beams × 4 layers, accumulator and floats), so a 64 × 64 × 16 grid (65,536
pairs, 103 GB) needs ``PoseSettings.launch_bytes`` chunks on any device; the default N = 16
(4,096 pairs, 6.4 GB) runs in one launch.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import tempfile

import numpy as np

from timing import time_call


def problem_for(backend, folder):
    import trimesh

    from fsswarp.dataset import Dataset
    from fsswarp.pose import PoseProblem, PoseSettings
    from fsswarp.rig import Rig
    from fsswarp.simulate import simulate

    dataset = simulate("coral-one", folder, seed=1, backend=backend)
    rig = dataset.rig
    every = Rig(tuple(dataclasses.replace(v, optimize=True) for v in rig.views), rig.reference)
    dataset = Dataset(dataclasses.replace(dataset.manifest, rig=every), dataset.images, dataset.root)
    model = trimesh.load(dataset.truth_model_path, process=False)
    truth = dataset.manifest.truth
    return PoseProblem(model, dataset, truth.depth, truth.tilt, settings=PoseSettings(launch_bytes=8 << 30),
                       backend=backend), truth


def bench_backend(backend, n: int, repeat: int):
    with tempfile.TemporaryDirectory() as folder:
        problem, truth = problem_for(backend, f"{folder}/coral-one")
        depths, tilts = np.meshgrid(truth.depth + np.linspace(-0.05, 0.05, n),
                                    truth.tilt + np.radians(np.linspace(-2.0, 2.0, n)), indexing="ij")
        data = problem.data
        views = len(data.views)
        pairs = n * n * views
        rows = []
        med, lo, hi = time_call(lambda: problem.surrogate(depths, tilts), repeat)
        rows.append(dict(mode="grid evaluation", median_s=med, min_s=lo, max_s=hi))
        layers = problem.render_pairs(data.views, depths.ravel(), tilts.ravel(), problem.settings.samples)
        index = np.tile(np.arange(views), n * n)
        capped = np.minimum(data.distances, np.float32(problem.settings.cap))
        shift = [problem.shift]
        med, lo, hi = time_call(lambda: backend.contour_cost(layers, index, data.threshold, data.windows, data.masks,
                                                             capped, shift, problem.smoothing), repeat)
        rows.append(dict(mode="contour cost", median_s=med, min_s=lo, max_s=hi))
        for row in rows:
            row.update(backend=backend.name, device=backend.device, grid=f"{n} x {n}", views=views, pairs=pairs,
                       pairs_per_s=pairs / row["median_s"])
        return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid", type=int, default=16, help="N: an N x N grid of (D, beta) cells")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--backends", default="warp,opencl")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    from fsswarp.backends import get_backend

    rows = []
    for name in args.backends.split(","):
        rows += bench_backend(get_backend(name), args.grid, args.repeat)
    print(f"machine: {platform.processor() or platform.machine()}, {platform.system()}; "
          f"{rows[0]['grid']} cells x {rows[0]['views']} views = {rows[0]['pairs']} pairs\n")
    print("| backend | device | step | median s | min s | max s | cells x views / s |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['backend']} | {r['device']} | {r['mode']} | {r['median_s']:.3f} | {r['min_s']:.3f} | "
              f"{r['max_s']:.3f} | {r['pairs_per_s']:,.0f} |")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as out:
            json.dump(rows, out, indent=1)


if __name__ == "__main__":
    main()
