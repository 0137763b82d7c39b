"""How far the pose step's answer follows the shape it is given (sensor fusion, docs/experiments.md):

    python bench/interval_study.py --out DIR [--backend B] [--device D] [--scenes ...]
                                   [--seeds S ...] [--sensors realistic|poor] [--iterations T]

For every scene, seed and start of ``bench/paper_table.py`` (the measured start and a tilt
sensor 2° off): run ``fsswarp.reconstruction.reconstruct``, then, around its answer c0 =
(D, β), take the answer's model (``fsswarp.reconstruction.sighting``: carved and refined once)
at c0, at c0 ± one prior σ in tilt and in depth, and at the truth; for each run the pose step from the carving's own pose (its answer f(c)) and
evaluate the per-view surrogate costs on two 11 × 11 grids around c0 (the answer's posterior
± 4 σ, and the prior's ± 3 σ). Writes DIR/SCENE-SEED-START.npz (the carvings' poses, answers,
posteriors, grids and per-view costs) and DIR/summary.json: the raw material from which the
intervals' shape error is studied offline (the answer's slope df/dc along each axis, the
spread of the answers, the per-view scatter of the gradients).
"""

from __future__ import annotations

import argparse
import importlib.util
import itertools
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
_spec = importlib.util.spec_from_file_location("bench_paper_table", HERE / "paper_table.py")
paper_table = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(paper_table)


def carvings(result, prior, truth) -> dict:
    """name -> (depth m, tilt rad) of the study's carving poses around ``result``'s answer."""
    d, t = result.depth, result.tilt
    return {"answer": (d, t), "tilt+": (d, t + prior.tilt_sigma), "tilt-": (d, t - prior.tilt_sigma),
            "depth+": (d + prior.depth_sigma, t), "depth-": (d - prior.depth_sigma, t),
            "truth": (truth.depth, truth.tilt)}


def study_run(data, backend, iterations: int, progress) -> dict:
    """The arrays of one reconstruction and its carvings (module docstring)."""
    from fsswarp.compare import ViewComparison
    from fsswarp.pose import POSTERIOR_CELLS, Prior, estimate_pose
    from fsswarp.reconstruction import ReconstructSettings, reconstruct, sighting

    settings = ReconstructSettings(iterations=iterations)
    result = reconstruct(data, settings=settings, backend=backend)
    prior, truth = Prior.of(data), data.manifest.truth
    comparison = ViewComparison(data, settings=settings.pose, backend=backend)
    shaping = ViewComparison(data, settings=settings.refine.pose, backend=backend)
    c0 = np.array([result.depth, result.tilt])
    u = np.linspace(-1.0, 1.0, POSTERIOR_CELLS)
    unit = np.stack(np.meshgrid(u, u, indexing="ij"), axis=-1)
    boxes = {"narrow": result.posterior.axes(4.0),
             "wide": np.diag([3 * prior.depth_sigma, 3 * prior.tilt_sigma])}
    out = {"answer": c0, "start": np.array(result.start), "truth": np.array([truth.depth, truth.tilt]),
           "prior": np.array([prior.depth, prior.tilt, prior.depth_sigma, prior.tilt_sigma]),
           "covariance": result.posterior.covariance, "seconds": result.seconds}
    for name, at in carvings(result, prior, truth).items():
        model = sighting(data, *at, settings, shaping)
        pose = estimate_pose(model, data, depth0=at[0], tilt0=at[1], comparison=comparison, prior=prior)
        out[f"{name}/at"] = np.array(at)
        out[f"{name}/pose"] = np.array([pose.depth, pose.tilt])
        out[f"{name}/candidate"] = np.array(pose.candidate)
        out[f"{name}/covariance"] = pose.posterior.covariance
        comparison.use(model, *c0)
        for box, axes in boxes.items():
            grid = c0 + np.einsum("ij,abj->abi", axes, unit)
            per_view = comparison.surrogate_views(grid[..., 0], grid[..., 1], cap=settings.pose.min_cap,
                                                  samples=settings.pose.samples)
            out[f"{name}/{box}/grid"], out[f"{name}/{box}/per_view"] = grid, per_view
        progress(f"  carved at {name} (D {at[0]:.4f} m, tilt {math.degrees(at[1]):.3f} deg): pose step D "
                 f"{pose.depth:.4f} m, tilt {math.degrees(pose.tilt):.3f} deg")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--backend", default=None)
    parser.add_argument("--device", default=None)
    parser.add_argument("--scenes", nargs="+", choices=paper_table.SCENES, default=list(paper_table.SCENES))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--sensors", choices=("realistic", "poor"), default="realistic")
    parser.add_argument("--iterations", type=int, default=6)
    parser.add_argument("--tilt-offset", type=float, default=2.0)
    args = parser.parse_args(argv)
    from fsswarp.backends import get_backend
    from fsswarp.scenes import builtin_scene
    from fsswarp.simulation import simulate

    backend = get_backend(args.backend or "auto", args.device)
    args.out.mkdir(parents=True, exist_ok=True)
    summary = []
    with tempfile.TemporaryDirectory() as folder:
        for scene, seed in itertools.product(args.scenes, args.seeds):
            dataset = simulate(builtin_scene(scene, None, args.sensors), Path(folder) / f"{scene}-{seed}", seed=seed,
                               backend=backend)
            for index, (label, data) in enumerate(paper_table.starts(dataset, args.tilt_offset)):
                print(f"{scene}, seed {seed}, {args.sensors} sensors, start {label}", flush=True)
                begin = time.perf_counter()
                arrays = study_run(data, backend, args.iterations, lambda line: print(line, flush=True))
                name = f"{scene}-{seed}-{args.sensors}-{index}"
                np.savez(args.out / f"{name}.npz", **arrays)
                summary.append({"name": name, "scene": scene, "seed": seed, "sensors": args.sensors, "start": label,
                                "seconds": time.perf_counter() - begin})
    (args.out / f"summary-{args.sensors}-{'-'.join(args.scenes)}.json").write_text(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
