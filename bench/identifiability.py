"""Where the images pin the sonar's tilt: models refined along the D–β valley, one command:

    python bench/identifiability.py [--name NAME] [--backend B] [--device D] [--scenes ...]
                                    [--positions LETTERS] [--tilts DEG ...] [--rounds R] [--seed S]

For every scene: simulate it (noisy, ``--seed``; at ``--positions``, default its own), then
for every tilt error δ of ``--tilts`` put the sonar at β = β_true + δ and at the depth D(β)
that keeps the true object's centroid at its true depth below the surface
(:func:`valley_depth`: the valley along which the ghost and mirror stay put, ΔD ≈ 3.5 cm per
degree at 2 m). There, three starting shapes are
refined for ``--rounds`` rounds of the loop's shape step (3 updates each,
``ReconstructSettings().refine``):

- ``carved``: the model carved at that (D, β), as the loop starts;
- ``true shape``: the truth mesh, with the loop's refinement (contour, mirror-contour and
  overshoot terms);
- ``true shape, contours only``: the truth mesh, refined by the object contours alone
  (no mirror, no overshoot term), which leave the true shape nearly in place at the truth.

After every round it records AIE, ACE, E_mu and E_V (``fsswarp.reconstruction.image_errors``,
``fsswarp.pose.pose_objective``, ``fsswarp.metrics.compare``). A shape free to move that
matches the images equally well at every δ means the images cannot tell the tilt; the tilt
of the lowest value says which β the images prefer for that family of shapes, and the
parabola fitted through a row (:func:`parabola_fit`) how sharply: its minimum ± the half-width
at which it rises by its own residual noise (the tilt resolution). Writes
``bench/records/identifiability/NAME.json`` (the machine, the command, the date, every value)
and regenerates ``bench/RESULTS.md`` with ``bench/report.py``, which renders every such
record with :func:`table_markdown` and draws it with :func:`plot_record`.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import sys
import tempfile
import time
import warnings
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _load_module(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


#: bench/paper_table.py (bench/ is not a package): its run options, record header and saving.
paper_table = _load_module("bench_paper_table", HERE / "paper_table.py")
SCENES = ("coral-one", "coral-two", "table")
#: The starting shapes (module docstring): name -> (starts from the truth, RefineSettings overrides).
STARTS = {"carved": (False, {}), "true shape": (True, {}),
          "true shape, contours only": (True, {"shrink": 0.0, "mirror": False})}
#: The recorded values: name -> (factor to the printed unit, label with the unit, table format).
METRICS = {"AIE": (1.0, "AIE", "{:.3f}"), "ACE": (1e3, "ACE (mm)", "{:.2f}"), "E_mu": (1e3, "E_mu (mm)", "{:.2f}"),
           "E_V": (1.0, "E_V", "{:.3f}")}


def valley_depth(rig, centroid, depth_true: float, tilt_true: float, tilt: float) -> float:
    """The depth D (m) at which the surface lies as far above ``centroid`` (3,) (reference
    frame, m) at tilt ``tilt`` (rad) as it does at the true (depth_true m, tilt_true rad)."""
    import numpy as np

    from fsswarp.surface import surface_in_reference

    normal, offset = surface_in_reference(rig, depth_true, tilt_true)
    below = float(offset) - float(np.dot(normal, centroid))  # the centroid's depth below the surface
    normal, offset = surface_in_reference(rig, depth_true, tilt)
    return depth_true + below - (float(offset) - float(np.dot(normal, centroid)))  # the offset is D + δD_ref


def state(model, dataset, depth: float, tilt: float, truth, backend) -> dict:
    """AIE, ACE (m), E_mu (m) and E_V of ``model`` at (depth m, tilt rad)."""
    from fsswarp.compare import PoseWarning
    from fsswarp.metrics import compare
    from fsswarp.pose import pose_objective
    from fsswarp.reconstruction import image_errors

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoseWarning)  # a view that does not see the model gets no CE
        images = image_errors(model, dataset, depth, tilt, backend=backend)
        e_mu = pose_objective(model, dataset, depth, tilt, backend=backend)
    return {"AIE": images["AIE"], "ACE": images["ACE"], "E_mu": e_mu, "E_V": compare(model, truth)["E_V"]}


def run_scene(dataset, backend, *, tilts_deg, rounds: int, progress=print) -> dict:
    """{"valley": [(δ deg, D m), ...], "starts": {start: [[state per round] per δ]}} of one
    simulated dataset (module docstring)."""
    import dataclasses

    from fsswarp.carving import carve
    from fsswarp.reconstruction import ReconstructSettings
    from fsswarp.refine import refine_shape

    truth_info = dataset.manifest.truth
    truth = dataset.truth_mesh()
    base = ReconstructSettings()
    valley = [(delta, valley_depth(dataset.rig, truth.center_mass, truth_info.depth, truth_info.tilt,
                                   truth_info.tilt + math.radians(delta))) for delta in tilts_deg]
    out = {"valley": valley, "starts": {}}
    for start, (from_truth, overrides) in STARTS.items():
        settings = dataclasses.replace(base.refine, **overrides)
        series = []
        for delta, depth in valley:
            tilt = truth_info.tilt + math.radians(delta)
            model = truth if from_truth else carve(dataset, depth, tilt, resolution=base.resolution,
                                                   settings=base.carve, backend=backend).mesh
            states = [state(model, dataset, depth, tilt, truth, backend)]
            for _ in range(rounds):
                model = refine_shape(model, dataset, depth, tilt, settings=settings, backend=backend).mesh
                states.append(state(model, dataset, depth, tilt, truth, backend))
            series.append(states)
            first, last = states[0], states[-1]
            progress(f"  {start}, tilt {delta:+g} deg, D {depth:.4f} m: AIE {first['AIE']:.3f} -> {last['AIE']:.3f}, "
                     f"E_mu {first['E_mu'] * 1e3:.2f} -> {last['E_mu'] * 1e3:.2f} mm, "
                     f"E_V {first['E_V']:.3f} -> {last['E_V']:.3f}")
        out["starts"][start] = series
    return out


def lowest_at(values, tilts_deg) -> str:
    """The tilt error (deg) of the lowest finite value, as the table prints it; "all equal"
    where the finite values differ by rounding alone (the truth's E_V of 0 at every tilt)."""
    finite = [(v, t) for v, t in zip(values, tilts_deg) if math.isfinite(v)]
    if not finite:
        return "—"
    low, high = min(v for v, _ in finite), max(v for v, _ in finite)
    if len(finite) > 1 and high - low <= 1e-9 * max(1.0, abs(low)):
        return "all equal"
    return f"{min(finite)[1]:+g}°"


def parabola_fit(tilts_deg, values) -> dict:
    """The least-squares parabola v ≈ a (δ − δ_min)² + c through the finite ``values`` (N,)
    at tilt errors ``tilts_deg`` (N,) (deg): {"minimum_deg": δ_min, "curvature": a (per deg²),
    "noise": the residuals' RMS with N − 3 degrees of freedom, "resolution_deg": √(noise / a),
    the half-width at which the parabola rises by its noise}. A parabola flat to rounding or
    opening downwards has no minimum: δ_min NaN, the resolution ∞ (the values do not tell the
    tilt); fewer than three distinct tilts leave every value NaN, fewer than four finite points
    the noise and the resolution."""
    import numpy as np

    x, y = np.asarray(tilts_deg, np.float64), np.asarray(values, np.float64)
    keep = np.isfinite(x) & np.isfinite(y)
    x, y = x[keep], y[keep]
    nan = {"minimum_deg": math.nan, "curvature": math.nan, "noise": math.nan, "resolution_deg": math.nan}
    if x.size < 3 or np.unique(x).size < 3:
        return nan
    a, b, c = np.polyfit(x, y, 2)
    noise = float(np.sqrt(np.sum((np.polyval((a, b, c), x) - y) ** 2) / (x.size - 3))) if x.size > 3 else math.nan
    if a <= 1e-12 * max(1.0, float(np.max(np.abs(y)))):  # flat to rounding, or opening downwards
        return {**nan, "curvature": float(a), "noise": noise, "resolution_deg": math.inf}
    return {"minimum_deg": float(-b / (2.0 * a)), "curvature": float(a), "noise": noise,
            "resolution_deg": math.sqrt(noise / a) if math.isfinite(noise) else math.nan}


def parabola_cell(values, tilts_deg) -> str:
    """The table's cell of :func:`parabola_fit`: "+0.12° ± 0.30°" (the minimum ± the
    resolution), "none" for no minimum, "—" for fewer than three points."""
    fit = parabola_fit(tilts_deg, values)
    if math.isnan(fit["curvature"]):
        return "—"
    if math.isnan(fit["minimum_deg"]):
        return "none"
    spread = "" if math.isnan(fit["resolution_deg"]) else f" ± {fit['resolution_deg']:.2f}°"
    return f"{fit['minimum_deg']:+.2f}°{spread}"


def table_markdown(record: dict, name: str) -> str:
    """The Markdown of one record: the machine line and, per scene, one table with a row per
    (start, metric) at the start (round 0) and after the last round, with the tilt error of
    the lowest value and of the fitted parabola's minimum (:func:`parabola_cell`)."""
    tilts, rounds = record["tilts_deg"], record["rounds"]
    lines = paper_table.record_header(record, name) + [
        f"- noisy images, seed {record['seed']}{paper_table.rig_note(record)}; {rounds} rounds of the loop's "
        f"shape step (3 updates each) at every point; whole command {record['seconds']:.0f} s", ""]
    header = ("| start | value | round | " + " | ".join(f"{t:+g}°" for t in tilts)
              + " | lowest at | parabola's minimum ± resolution |")
    rule = "|---|---|---|" + "---|" * len(tilts) + "---|---|"
    for scene, result in record["scenes"].items():
        depths = ", ".join(f"{d:.4f}" for _, d in result["valley"])
        lines += [f"#### {scene}", "", f"Depths along the valley (m): {depths}.", "", header, rule]
        for start, series in result["starts"].items():
            for metric, (factor, label, form) in METRICS.items():
                for k in sorted({0, rounds}):
                    values = [states[k][metric] * factor for states in series]
                    cells = " | ".join(form.format(v) if math.isfinite(v) else "—" for v in values)
                    lines.append(f"| {start} | {label} | {k} | {cells} | {lowest_at(values, tilts)} | "
                                 f"{parabola_cell(values, tilts)} |")
        lines.append("")
    return "\n".join(lines)


def plot_record(record: dict, path: Path, *, title: str = "") -> Path:
    """One panel per (scene, metric): the metric against the tilt error along the valley, a
    line per start after the last round, dotted at round 0 (the two true-shape starts share
    it); the truth's tilt marked. Returns the PNG's path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fsswarp.figures import save_figure

    tilts, rounds, scenes = record["tilts_deg"], record["rounds"], record["scenes"]
    fig, axes = plt.subplots(len(scenes), len(METRICS), figsize=(3.2 * len(METRICS), 2.6 * len(scenes)),
                             squeeze=False)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for row, (scene, result) in enumerate(scenes.items()):
        for col, (metric, (factor, label, _)) in enumerate(METRICS.items()):
            ax = axes[row][col]
            for k, (start, series) in enumerate(result["starts"].items()):
                for when, style in ((0, ":"), (rounds, "-")):
                    ax.plot(tilts, [states[when][metric] * factor for states in series], style, marker="o",
                            markersize=3, color=colours[k % len(colours)],
                            label=f"{start}, round {when}" if row == col == 0 else None)
            ax.axvline(0.0, color="0.6", linewidth=0.8)
            ax.set_xticks(tilts)
            ax.set_title(f"{scene}: {label}", fontsize=9)
            ax.set_xlabel("tilt error along the valley (°)", fontsize=8)
            ax.tick_params(labelsize=7)
    fig.legend(loc="lower center", ncol=3, fontsize=7, frameon=False)
    return save_figure(fig, path, title, rect=(0, 0.06, 1, 1))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    paper_table.add_run_options(parser, HERE / "records" / "identifiability")
    parser.add_argument("--tilts", nargs="+", type=float, default=[-1.0, -0.5, 0.0, 0.5, 1.0],
                        help="tilt errors (degrees) along the valley")
    parser.add_argument("--rounds", type=int, default=3, help="shape steps (3 updates each) per point")
    args = parser.parse_args(argv)
    from fsswarp.backends import get_backend
    from fsswarp.errors import InputError, check_integer
    from fsswarp.scenes import builtin_scene, check_positions
    from fsswarp.simulation import simulate

    try:
        backend = get_backend(args.backend or "auto", args.device)
        check_integer("--seed", args.seed, 0)
        positions = check_positions(args.positions)
        check_integer("--rounds", args.rounds, 0)
        bad = [t for t in args.tilts if not (math.isfinite(t) and abs(t) <= 5)]
        if bad:
            raise InputError("must be in [-5, 5] degrees", field="--tilts", value=bad[0])
    except InputError as err:
        print(f"identifiability: error: {err}", file=sys.stderr)
        return 2
    name, command = paper_table.run_identity("identifiability.py", args.name, backend, argv)
    begin = time.perf_counter()
    scenes = {}
    with tempfile.TemporaryDirectory() as folder:
        for scene in args.scenes:
            print(scene, flush=True)
            dataset = simulate(builtin_scene(scene, positions), Path(folder) / scene, seed=args.seed,
                               backend=backend)
            scenes[scene] = run_scene(dataset, backend, tilts_deg=args.tilts, rounds=args.rounds,
                                      progress=lambda line: print(line, flush=True))
    record = {"schema": 1, "date": time.strftime("%Y-%m-%d %H:%M:%S %z"), "command": command.strip(),
              "seed": args.seed, "positions": positions, "rounds": args.rounds, "tilts_deg": args.tilts,
              "machine": paper_table.machine(backend), "seconds": time.perf_counter() - begin, "scenes": scenes}
    return paper_table.save_record(record, name, args.records, HERE / "records" / "identifiability",
                                   table_markdown)


if __name__ == "__main__":
    sys.exit(main())
