"""Where the carving's mesh extraction (``fsswarp.carving.voxel_mesh``) spends its time, one command:

    python bench/mesh_profile.py [--scene NAME] [--backend B] [--device D] [--seed S]
                                 [--resolution N] [--repeats K] [--out FILE]

Simulates the scene (noisy, ``--seed``), carves it at its measured pose (``fsswarp.carving.carve``
at ``--resolution``, default ``ReconstructSettings().resolution``, and the default CarveSettings),
then meshes the carving's voxels ``--repeats`` times (after one uncounted call that imports the
libraries) with ``voxel_mesh``'s ``timings``. Prints one Markdown table: per stage the median,
minimum and maximum milliseconds, and the mesh (faces, vertices, SHA-256 of its float64 vertices
and int64 faces: equal hashes, the same mesh bit for bit). ``--out`` writes the same as JSON
(atomically).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import statistics
import sys
import time
from pathlib import Path

#: voxel_mesh's stages, in order (its docstring).
STAGES = ("fill_s", "components_s", "marching_cubes_s", "orient_s", "smooth_s", "smooth_check_s", "decimate_s",
          "decimate_check_s", "trimesh_s")

_spec = importlib.util.spec_from_file_location("bench_profiling", Path(__file__).resolve().parent / "profiling.py")
profiling = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(profiling)


def profile(voxels, repeats: int) -> tuple[dict[str, list[float]], object]:
    """(stage -> seconds of each counted call, with "total_s"; the last mesh) of ``repeats``
    calls of ``voxel_mesh`` after one uncounted call."""
    from fsswarp.carving import voxel_mesh

    voxel_mesh(voxels)
    runs: dict[str, list[float]] = {stage: [] for stage in (*STAGES, "total_s")}
    for _ in range(repeats):
        timings: dict[str, float] = {}
        start = time.perf_counter()
        mesh = voxel_mesh(voxels, timings=timings)
        runs["total_s"].append(time.perf_counter() - start)
        for stage in STAGES:
            runs[stage].append(timings.get(stage, 0.0))
    return runs, mesh


def table_markdown(runs: dict[str, list[float]]) -> str:
    """Markdown: one row per stage (median, min, max ms) and the total."""
    lines = ["| stage | median ms | min ms | max ms |", "|---|---|---|---|"]
    for stage, seconds in runs.items():
        lines.append(f"| {stage.removesuffix('_s')} | {1e3 * statistics.median(seconds):.1f} | "
                     f"{1e3 * min(seconds):.1f} | {1e3 * max(seconds):.1f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    profiling.add_scene_options(parser)
    parser.add_argument("--resolution", type=int, default=None,
                        help="carving resolution (default: ReconstructSettings().resolution)")
    parser.add_argument("--repeats", type=int, default=7, help="counted voxel_mesh calls (at least 5)")
    parser.add_argument("--out", type=Path, default=None, help="also write the record as JSON here")
    args = parser.parse_args(argv)
    from fsswarp.atomic import write_text
    from fsswarp.carving import carve
    from fsswarp.errors import InputError, check_integer
    from fsswarp.reconstruction import ReconstructSettings

    resolution = ReconstructSettings().resolution if args.resolution is None else args.resolution

    def check() -> None:
        check_integer("--repeats", args.repeats, 5)
        check_integer("--resolution", resolution, 8)
        if args.out is not None and args.out.is_dir():
            raise InputError("is a folder; name a file", file=args.out)

    backend = profiling.scene_backend(args, "mesh_profile", check)
    if backend is None:
        return 2
    with profiling.simulated(args, backend) as dataset:
        carved = carve(dataset, resolution=resolution, backend=backend)
    voxels = carved.voxels
    runs, mesh = profile(voxels, args.repeats)
    record = {"scene": args.scene, "seed": args.seed, "resolution": resolution, "backend": backend.name,
              "device": backend.device, "cpu": profiling.cpu_model(), "date": time.strftime("%Y-%m-%d"),
              "grid": list(voxels.occupancy.shape), "kept_voxels": voxels.kept, "repeats": args.repeats,
              "median_ms": {stage: 1e3 * statistics.median(s) for stage, s in runs.items()},
              "runs_ms": {stage: [1e3 * v for v in s] for stage, s in runs.items()},
              "faces": len(mesh.faces), "vertices": len(mesh.vertices), "mesh_sha256": profiling.mesh_digest(mesh)}
    print(f"{args.scene} (seed {args.seed}) carved at resolution {resolution}: grid {voxels.occupancy.shape}, "
          f"{voxels.kept} voxels kept; voxel_mesh on {record['cpu']}, {args.repeats} calls\n")
    print(table_markdown(runs))
    print(f"\nmesh: {record['faces']} faces, {record['vertices']} vertices, sha256 {record['mesh_sha256']}")
    if args.out is not None:
        try:
            write_text(args.out, json.dumps(record, indent=1))
        except InputError as err:
            print(f"mesh_profile: error: {err}", file=sys.stderr)
            return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
