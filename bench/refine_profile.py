"""Where one shape step (``fsswarp.refine.refine_shape``) spends its time, one command:

    python bench/refine_profile.py [--scene NAME] [--backend B] [--device D] [--calls N]
                                   [--iterations T] [--seed S] [--out FILE.json]

Simulates the scene (noisy, ``--seed``), carves it at its measured (D0, β0) (resolution 128)
and refines the carving there ``--calls`` times with ``RefineSettings(iterations=T)`` (the
reconstruction's shape step: T = 3) through one ``ViewComparison``, as the reconstruction does,
after one untimed call to fill the kernel caches. Every call starts from the same carving, so
every call must give the same mesh (checked, bit for bit). Each call's stages are timed
inclusively by wrappers: locating the model (``use``), the synthetic contours, the ICP
(``align``), the frontal patches and their 3-D least squares (``contour_motions``), the
overshoot term, the vertex displacements (of which ``membrane``, the sparse solve), the step
checks (``apply``), the closing CE (``contour_errors``) and the rest; plus the backend calls
inside them (device time as the host waits for it, with the backend's own host work) and
``host``, the call less those backend calls. Prints one Markdown table of the medians per stage
(ms) and writes ``--out``: the machine, the command, the medians, every call's times, and the
refined mesh's digest, ACE and steps (to compare results before and after a change).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
from pathlib import Path

#: (module, class name or None, function name, label) of the stages, in call order; a name that
#: a version of the code lacks is skipped.
STAGES = (
    ("fsswarp.compare", "ViewComparison", "use", "use"),
    ("fsswarp.compare", "ViewComparison", "synthetic_contours", "synthetic_contours"),
    ("fsswarp.compare", "ViewComparison", "align", "align"),
    ("fsswarp.refine", "_Update", "_contour_motions", "contour_motions"),
    ("fsswarp.refine", "_Update", "_overshoot", "overshoot"),
    ("fsswarp.refine", "_Update", "displacement", "displacement"),
    ("fsswarp.refine", None, "_apply", "apply"),
    ("fsswarp.compare", "ViewComparison", "contour_errors", "contour_errors"),
)
#: Stages timed within others (not summed into ``rest``).
INNER = (
    ("fsswarp.compare", "ViewComparison", "frontal_motions", "contour_motions.frontal_motions"),
    ("fsswarp.refine", "_Membrane", "solve", "displacement.membrane"),
)
BACKEND_CALLS = ("load_mesh", "device_distances", "render_planned", "contour_cost", "view_costs", "icp_runs",
                 "frontal_faces", "cast_rays")
#: Stages whose time holds other stages' (``contour_errors`` calls ``synthetic_contours`` and ``align``).
NESTED = {"synthetic_contours", "align"}

_spec = importlib.util.spec_from_file_location("bench_profiling", Path(__file__).resolve().parent / "profiling.py")
profiling = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(profiling)


def profile(dataset, backend, calls: int, iterations: int):
    """(per-call stage times [{label: s}], the refined mesh, the RefineResult, the carving) of
    ``calls`` shape steps on the carving of ``dataset`` at its measured pose, after one untimed
    call; RuntimeError where a call's mesh differs from the untimed one's."""
    import importlib

    from fsswarp.carving import carve
    from fsswarp.compare import ViewComparison
    from fsswarp.refine import RefineSettings, refine_shape

    surface = dataset.manifest.surface
    depth, tilt = surface.depth, surface.tilt
    carved = carve(dataset, depth, tilt, resolution=128, backend=backend).mesh
    settings = RefineSettings(iterations=iterations)
    comparison = ViewComparison(dataset, settings=settings.pose, backend=backend)
    first = refine_shape(carved, dataset, depth, tilt, settings=settings, comparison=comparison)
    want = profiling.mesh_digest(first.mesh)
    times = profiling.StageTimes("contour_errors", NESTED)
    for module, owner, name, label in STAGES + INNER:
        target = importlib.import_module(module)
        target = getattr(target, owner) if owner else target
        if hasattr(target, name):
            times.wrap(target, name, label)
    times.wrap_backend(backend, BACKEND_CALLS)
    rows = []
    try:
        for _ in range(calls):
            times.current = {}
            start = time.perf_counter()
            result = refine_shape(carved, dataset, depth, tilt, settings=settings, comparison=comparison)
            total = time.perf_counter() - start
            if profiling.mesh_digest(result.mesh) != want:
                raise RuntimeError("a timed call's mesh differs from the untimed call's")
            row = dict(times.current, total=total)
            row["rest"] = total - sum(row.get(label, 0.0) for *_, label in STAGES)
            row["host"] = total - sum(row.get(f"backend.{name}", 0.0) for name in BACKEND_CALLS)
            rows.append(row)
    finally:
        times.restore()
    return rows, first, carved


def table(med: dict[str, float]) -> str:
    order = ["total", *[label for *_, label in STAGES], "rest", *[label for *_, label in INNER],
             *[f"backend.{n}" for n in BACKEND_CALLS], "host"]
    return profiling.stage_table(med, order)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    profiling.add_scene_options(parser)
    parser.add_argument("--calls", type=int, default=5, help="timed refine_shape calls (>= 1)")
    parser.add_argument("--iterations", type=int, default=3, help="shape updates per call (>= 1)")
    parser.add_argument("--out", default=None, help="JSON record to write")
    args = parser.parse_args(argv)
    from fsswarp.atomic import json_number, write_text
    from fsswarp.errors import check_integer

    def check() -> None:
        check_integer("--calls", args.calls, 1)
        check_integer("--iterations", args.iterations, 1)

    backend = profiling.scene_backend(args, "refine_profile", check)
    if backend is None:
        return 2
    with profiling.simulated(args, backend) as dataset:
        rows, result, carved = profile(dataset, backend, args.calls, args.iterations)
    med = profiling.medians(rows)
    print(f"{args.scene} refine_shape (iterations={args.iterations}, {len(carved.vertices)} vertices) on "
          f"{backend.name} {backend.device} ({profiling.cpu_model()}), median of {args.calls} calls:\n")
    print(table(med))
    print(f"\nmesh {profiling.mesh_digest(result.mesh)[:16]}, ACE {result.ace_before:.6g} -> {result.ace_after:.6g} m")
    if args.out:
        record = dict(scene=args.scene, backend=backend.name, device=str(backend.device), cpu=profiling.cpu_model(),
                      command=" ".join(sys.argv), date=time.strftime("%Y-%m-%d %H:%M:%S"), calls=args.calls,
                      iterations=args.iterations, seed=args.seed, vertices=len(carved.vertices),
                      faces=len(carved.faces), median_ms={k: 1e3 * v for k, v in med.items()},
                      rows_ms=[{k: 1e3 * v for k, v in row.items()} for row in rows],
                      mesh_sha256=profiling.mesh_digest(result.mesh), carving_sha256=profiling.mesh_digest(carved),
                      ace_before=json_number(result.ace_before), ace_after=json_number(result.ace_after),
                      steps=[dict(contour_patches=s.contour_patches, shrink_patches=s.shrink_patches,
                                  mean_displacement=s.mean_displacement, step=s.step, ace=json_number(s.ace))
                             for s in result.steps])
        write_text(args.out, json.dumps(record, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
