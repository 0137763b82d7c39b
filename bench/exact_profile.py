"""Where one E_mu evaluation (``ViewComparison.exact``, paper eq. 6) spends its time, one command:

    python bench/exact_profile.py [--scene NAME] [--backend B] [--device D] [--calls N]
                                  [--seed S] [--replay] [--out FILE.json]

Simulates the scene (noisy, ``--seed``), takes its true model (``Dataset.truth_mesh``), puts it
in a ``ViewComparison`` at the measured (D0, β0) and evaluates ``exact`` ``--calls`` times,
cycling through the poses of ``POSES`` near the start (as the BOBYQA polish does: never the
located estimate itself), after one untimed round to fill the kernel caches. Each call's stages
are timed inclusively by wrappers: ``synthetic_contours`` (render + contour kernels),
``align`` (ICP set-up, iterations, results), ``frontal_motions`` (the frontal-patch search),
``patch_motions`` (the 3-D least squares), and the rest (bookkeeping, μ_m), plus the backend
calls inside them (device time as the host waits for it, with the backend's own host work) and
``host``, the call less those backend calls. Prints one Markdown table of the
medians per stage (ms) and writes ``--out``: the machine, the command, the medians, every
call's times, and each pose's E_mu and μ_m (to compare results before and after a change).
With ``--replay`` the backend's calls answer from a recording of the untimed round (the same
results, no device work): ``total`` is then the host's work alone, free of the device's noise.
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import json
import math
import sys
import time
from pathlib import Path

#: (ΔD m, Δβ deg) of the timed poses about the measured start.
POSES = ((0.004, 0.0), (-0.004, 0.25), (0.0, -0.25), (0.002, 0.1), (-0.002, -0.1))
#: ViewComparison methods and compare-module functions timed as stages, in call order.
STAGES = ("synthetic_contours", "align", "frontal_motions", "patch_motions")
BACKEND_CALLS = ("render_planned", "contour_cost", "icp_runs", "frontal_faces")

_spec = importlib.util.spec_from_file_location("bench_profiling", Path(__file__).resolve().parent / "profiling.py")
profiling = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(profiling)


class Tape(profiling.Patches):
    """The backend's ``BACKEND_CALLS`` recorded (``record``: their results, call after call) and
    then answered from the recording in the same order (``replay``), with no device work."""

    def __init__(self, backend):
        super().__init__()
        self.results: dict[str, list] = {name: [] for name in BACKEND_CALLS if hasattr(type(backend), name)}
        self.played = dict.fromkeys(self.results, 0)
        self.replaying = False
        for name in self.results:
            self.wrap(type(backend), name)

    def wrap(self, owner, name: str) -> None:
        original = getattr(owner, name)

        @functools.wraps(original)
        def taped(*args, **kwargs):
            if self.replaying:
                tape = self.results[name]
                self.played[name] += 1
                return tape[(self.played[name] - 1) % len(tape)]
            result = original(*args, **kwargs)
            self.results[name].append(result)
            return result

        self.replace(owner, name, taped)


def profile(dataset, backend, calls: int, *, replay: bool = False):
    """(per-call stage times [{label: s}], {pose index: (E_mu, μ_m list)}, poses) of ``calls``
    exact evaluations of ``dataset``'s true model about its measured start, after one untimed
    round; with ``replay`` the backend's calls answer from that round's recording (``Tape``)."""
    import fsswarp.compare as compare

    surface = dataset.manifest.surface
    comparison = compare.ViewComparison(dataset, backend=backend).use(dataset.truth_mesh(), surface.depth,
                                                                       surface.tilt)
    poses = [(surface.depth + dd, surface.tilt + math.radians(db)) for dd, db in POSES]
    results = {}
    tape = Tape(backend) if replay else None
    try:
        for k, pose in enumerate(poses):  # warm-up: kernel caches, first-use copies
            found = comparison.exact(*pose)
            results[k] = (found.value, [float(v) for v in found.per_view])
        if tape is not None:
            tape.replaying = True
        rows = timed_calls(comparison, backend, poses, results, calls)
    finally:
        if tape is not None:
            tape.restore()
    return rows, results, poses


def timed_calls(comparison, backend, poses, results, calls: int) -> list[dict[str, float]]:
    """Per-call stage times (s) of ``calls`` exact evaluations cycling through ``poses``;
    RuntimeError where one's E_mu is not ``results``' (the warm-up's) for its pose."""
    import fsswarp.compare as compare

    times = profiling.StageTimes()
    for name in STAGES:
        owner = compare if name == "patch_motions" else compare.ViewComparison
        times.wrap(owner, name, name)
    times.wrap_backend(backend, BACKEND_CALLS)
    rows = []
    try:
        for call in range(calls):
            k = call % len(poses)
            times.current = {}
            start = time.perf_counter()
            found = comparison.exact(*poses[k])
            total = time.perf_counter() - start
            if found.value != results[k][0] and not (math.isnan(found.value) and math.isnan(results[k][0])):
                raise RuntimeError(f"pose {k}: E_mu {found.value} differs from its first evaluation {results[k][0]}")
            row = dict(times.current, total=total)
            row["rest"] = total - sum(row.get(name, 0.0) for name in STAGES)
            row["host"] = total - sum(row.get(f"backend.{name}", 0.0) for name in BACKEND_CALLS)
            rows.append(row)
    finally:
        times.restore()
    return rows


def table(med: dict[str, float]) -> str:
    order = ["total", *STAGES, "rest", *[f"backend.{n}" for n in BACKEND_CALLS], "host"]
    return profiling.stage_table(med, order)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    profiling.add_scene_options(parser)
    parser.add_argument("--calls", type=int, default=25, help="timed exact calls (>= 1)")
    parser.add_argument("--replay", action="store_true",
                        help="the backend's calls answer from a recording of the untimed round: the host's work alone")
    parser.add_argument("--out", default=None, help="JSON record to write")
    args = parser.parse_args(argv)
    from fsswarp.atomic import json_number, write_text
    from fsswarp.errors import check_integer

    backend = profiling.scene_backend(args, "exact_profile", lambda: check_integer("--calls", args.calls, 1))
    if backend is None:
        return 2
    with profiling.simulated(args, backend) as dataset:
        rows, results, poses = profile(dataset, backend, args.calls, replay=args.replay)
    med = profiling.medians(rows)
    print(f"{args.scene} exact on {backend.name} {backend.device} ({profiling.cpu_model()}), median of {args.calls} calls"
          f"{', backend calls replayed' if args.replay else ''}:\n")
    print(table(med))
    if args.out:
        record = dict(scene=args.scene, backend=backend.name, device=str(backend.device), cpu=profiling.cpu_model(),
                      command=" ".join(sys.argv), date=time.strftime("%Y-%m-%d %H:%M:%S"), calls=args.calls,
                      replay=args.replay,
                      seed=args.seed, median_ms={k: 1e3 * v for k, v in med.items()},
                      rows_ms=[{k: 1e3 * v for k, v in row.items()} for row in rows],
                      poses=[dict(depth=d, tilt=t, E_mu=json_number(results[k][0]),
                                  per_view=[json_number(v) for v in results[k][1]])
                             for k, (d, t) in enumerate(poses)])
        write_text(args.out, json.dumps(record, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
