"""The unified optimization loop, ``fsswarp reconstruct`` and ``fsswarp demo`` as a user runs them."""

import dataclasses
import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
import trimesh

import fsswarp.reconstruction as reconstruct_module
from fsswarp.carving import carve
from fsswarp.errors import InputError
from fsswarp.metrics import compare
from fsswarp.reconstruction import ReconstructSettings, image_errors, reconstruct
from fsswarp.refine import RefineSettings, refine_shape

HISTORY_KEYS = {"iteration", "depth_m", "tilt_deg", "E_mu", "AIE", "ACE", "E_I", "E_V", "chamfer_m", "fscore"}
RESULT_KEYS = {"depth_m", "tilt_deg", "depth_interval_m", "tilt_interval_deg", "valley", "identified", "start",
               "error_vs_truth", "best_iteration", "iterations", "converged", "backend", "device",
               "seconds", "history"}
FAST = ReconstructSettings(iterations=1, resolution=64)


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "fsswarp", "--backend", "opencl", *args],
                          capture_output=True, text=True)


@pytest.fixture(scope="module")
def one_iteration(coral_one):
    """A reconstruction of FAST settings on PoCL, every mesh made in this process, and its lines."""
    from fsswarp.backends import get_backend

    lines = []
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("FSSWARP_MESH_WORKERS", "0")
        return reconstruct(coral_one, settings=FAST, backend=get_backend("opencl"), progress=lines.append), lines


def test_history_follows_the_contract(one_iteration, coral_one):
    result, _ = one_iteration
    assert set(result.summary()) == RESULT_KEYS
    assert [h["iteration"] for h in result.history] == list(range(len(result.history)))
    answer = result.history[-1]  # the kept model refined at the self-consistent answer
    assert answer["answer"] and len(result.history) == result.iterations + 2
    assert result.best_iteration == answer["iteration"]
    assert (answer["depth_m"], answer["tilt_deg"]) == (result.depth, math.degrees(result.tilt))
    first = result.history[0]
    assert set(first) == HISTORY_KEYS
    surface = coral_one.manifest.surface
    assert first["depth_m"] == surface.depth and first["tilt_deg"] == pytest.approx(math.degrees(surface.tilt))
    assert first["E_I"] == 1.0
    assert all(np.isfinite(h[k]) for h in result.history for k in HISTORY_KEYS)
    assert result.model.is_watertight and result.carved.is_watertight
    assert len(result.pose_steps) == 1 and result.pose_steps[0].levels  # the figure's grid
    json.dumps(result.summary())  # JSON-ready


def test_the_answer_carries_its_intervals_start_and_error(one_iteration, coral_one):
    result, lines = one_iteration
    summary, truth = result.summary(), coral_one.manifest.truth
    (d0, d1), (t0, t1) = summary["depth_interval_m"], summary["tilt_interval_deg"]
    assert d0 < summary["depth_m"] < d1 and t0 < summary["tilt_deg"] < t1
    assert summary["start"] == {"depth_m": coral_one.manifest.surface.depth,
                                "tilt_deg": math.degrees(coral_one.manifest.surface.tilt)}
    assert summary["error_vs_truth"] == {"depth_m": result.depth - truth.depth,
                                         "tilt_deg": math.degrees(result.tilt) - math.degrees(truth.tilt)}
    assert set(summary["valley"]) == {"slope_m_per_deg", "depth_m_at_estimated_tilt"}
    assert 0.01 < summary["valley"]["slope_m_per_deg"] < 0.08  # D − L·β: about 3.5 cm per degree at 2 m
    assert summary["converged"] == (result.stopped and all(summary["identified"].values()))
    for entry in result.history[1:]:  # each pose step's intervals, and whether the model was carved again
        assert len(entry["depth_interval_m"]) == 2 and len(entry["tilt_interval_deg"]) == 2
        assert isinstance(entry["recarved"], bool)
    assert any(line.startswith("the answer: D ") and "(95%: " in line for line in lines)


def test_truth_metrics_of_every_recorded_iteration_are_reported(one_iteration, coral_one):
    """Each recorded iteration gets its truth metrics, with one progress line each, in order,
    and they are compare()'s values for that iteration's model (the distances from the
    backend's search, the volumes from a worker process)."""
    from fsswarp.metrics import compare

    result, lines = one_iteration
    reported = [line for line in lines if "against the truth" in line]
    assert [line.split()[1] for line in reported] == [str(h["iteration"]) for h in result.history]
    want = compare(result.model, trimesh.load_mesh(coral_one.truth_model_path, process=True))
    kept = result.history[result.best_iteration]
    assert_compare_s(kept, want)
    assert f"E_V {kept['E_V']:.3f}" in reported[result.best_iteration]


def test_truth_metrics_reach_their_entries_in_order():
    """Concentric icospheres, one mesh scaled: the smaller lies inside the larger, so E_V is
    1 − (r_small / r_large)³ (closed form); each entry gets its own model's values, with one
    line each, in order."""
    truth = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    radii = (0.11, 0.095)
    entries = [{"iteration": i} for i in range(len(radii))]
    lines = []
    with reconstruct_module._TruthMetrics(truth, lines.append) as metrics:
        for entry, radius in zip(entries, radii):
            metrics.submit(entry, trimesh.creation.icosphere(subdivisions=3, radius=radius))
        metrics.collect(wait=True)
    assert entries[0]["E_V"] == pytest.approx(1 - (0.1 / 0.11) ** 3, rel=1e-3)
    assert entries[1]["E_V"] == pytest.approx(1 - (0.095 / 0.1) ** 3, rel=1e-3)
    assert entries[0]["chamfer_m"] == pytest.approx(0.01, rel=0.05)
    assert [line.split()[1] for line in lines] == ["0", "1"] and not metrics.pending
    alone = {"iteration": 0}
    with reconstruct_module._TruthMetrics(None, lines.append) as metrics:
        metrics.submit(alone, truth)
        metrics.collect(wait=True)
    assert alone == {"iteration": 0} and len(lines) == 2  # no truth model: nothing to add
    assert metrics.processes is None


def test_truth_metrics_in_the_child_process_are_compares_and_raise_its_errors():
    """The metrics come from a worker process (one worker: one process, on any machine): the
    same values as ``compare`` here, bit for bit; its errors reach ``collect``; the process ends
    with the context. Where processes cannot start, one line says so and the values are made
    here, the same."""
    truth = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    model = trimesh.creation.icosphere(subdivisions=2, radius=0.105)
    entry = {"iteration": 0}
    with reconstruct_module._TruthMetrics(truth, [].append, workers=1) as metrics:
        metrics.submit(entry, model)
        metrics.collect(wait=True)
        children = processes_of(metrics)
    want = compare(model, truth)
    assert (entry["E_V"], entry["chamfer_m"], entry["fscore"]) == (want["E_V"], want["chamfer_m"], want["fscore"])
    assert len(children) == 1 and os.getpid() not in {child.pid for child in children}
    assert [child.exitcode for child in children] == [0]
    with pytest.raises(InputError, match="holds no triangles"):
        with reconstruct_module._TruthMetrics(truth, [].append, workers=1) as metrics:
            children = processes_of(metrics)
            metrics.submit({"iteration": 1}, trimesh.Trimesh())
            metrics.collect(wait=True)
    assert [child.exitcode for child in children] == [0]

    def cannot_start(*args, **kwargs):
        raise OSError("no /dev/shm")

    here, lines = {"iteration": 2}, []
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("fsswarp.processes.WorkerProcesses", cannot_start)
        with reconstruct_module._TruthMetrics(truth, lines.append, workers=1) as metrics:
            metrics.submit(here, model)
            metrics.collect(wait=True)
    assert metrics.processes is None and "could not start (no /dev/shm)" in lines[0]
    assert (here["E_V"], here["chamfer_m"], here["fscore"]) == (want["E_V"], want["chamfer_m"], want["fscore"])


@pytest.mark.parametrize("killed", ["before the submit", "after the submit"])
def test_truth_metrics_of_a_dead_process_are_made_here(killed):
    """A worker process killed (out of memory, say), whether the pool knows it at the submit or
    only at the collect: one line, the same values made in this process, and no process from
    then on."""
    import signal

    truth = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    models = [trimesh.creation.icosphere(subdivisions=2, radius=r) for r in (0.105, 0.11)]
    entries, lines = [{"iteration": 0}, {"iteration": 1}], []
    with reconstruct_module._TruthMetrics(truth, lines.append, workers=2) as metrics:
        children = processes_of(metrics)
        if killed == "after the submit":
            metrics.submit(entries[0], models[0])
        for child in children:
            os.kill(child.pid, signal.SIGKILL)
        for child in children:
            child.join()
        if killed == "before the submit":
            metrics.submit(entries[0], models[0])
        metrics.submit(entries[1], models[1])
        metrics.collect(wait=True)
        assert metrics.processes is None
    for entry, model in zip(entries, models):
        want = compare(model, truth)
        assert (entry["E_V"], entry["chamfer_m"], entry["fscore"]) == (want["E_V"], want["chamfer_m"], want["fscore"])
    assert [line for line in lines if "ended unexpectedly" in line] == [
        "truth metrics: a worker process ended unexpectedly; computing them in this process"]


def assert_compare_s(entry: dict, want: dict) -> None:
    """The entry's truth metrics are ``want``'s (compare()'s): E_V bit for bit, the distances'
    means and shares within the backends' agreement with NumPy's search (1e-9 relative)."""
    assert entry["E_V"] == want["E_V"]
    assert entry["chamfer_m"] == pytest.approx(want["chamfer_m"], rel=1e-9)
    assert entry["fscore"] == pytest.approx(want["fscore"], rel=1e-9)


def test_truth_metrics_take_their_distances_from_the_backend(backend, monkeypatch):
    """With a backend the distances come from its exact search, in a thread of their own, and
    the worker's job is the volumes alone: compare()'s values. A model without triangles is
    refused at once."""
    truth = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    models = [trimesh.creation.icosphere(subdivisions=2, radius=r) for r in (0.105, 0.09)]
    entries, jobs = [{"iteration": i} for i in range(len(models))], []
    where = _thread_names(monkeypatch, backend, "surface_distances")
    with reconstruct_module._TruthMetrics(truth, [].append, backend, workers=1) as metrics:
        submit = metrics.processes.submit
        metrics.processes.submit = lambda function, *args, **kwargs: jobs.append(kwargs) or submit(function, *args,
                                                                                                     **kwargs)
        for entry, model in zip(entries, models):
            metrics.submit(entry, model)
        assert all(distances is not None for _, _, distances, _, _ in metrics.pending)
        metrics.collect(wait=True)
        with pytest.raises(InputError, match="holds no triangles"):
            metrics.submit({"iteration": 2}, trimesh.Trimesh())
    assert jobs == [{"distances": False}] * 2
    assert len(where) == 4 and all(name.startswith("fsswarp-truth") for name in where)
    for entry, model in zip(entries, models):
        assert_compare_s(entry, compare(model, truth))


def processes_of(metrics) -> list:
    """The processes of a _TruthMetrics (started with it)."""
    return list(metrics.processes.pool._processes.values())


def test_truth_metrics_share_out_among_at_most_their_workers_in_order():
    """Five models on three workers: each entry gets its own model's compare, bit for bit and
    in order, from three worker processes, which end with the context."""
    truth = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    models = [trimesh.creation.icosphere(subdivisions=2, radius=r) for r in (0.09, 0.1, 0.105, 0.11, 0.12)]
    entries = [{"iteration": i} for i in range(len(models))]
    lines = []
    with reconstruct_module._TruthMetrics(truth, lines.append, workers=3) as metrics:
        for entry, model in zip(entries, models):
            metrics.submit(entry, model)
        metrics.collect(wait=True)
        children = processes_of(metrics)
    for entry, model in zip(entries, models):
        want = compare(model, truth)
        assert (entry["E_V"], entry["chamfer_m"], entry["fscore"]) == (want["E_V"], want["chamfer_m"], want["fscore"])
    assert [line.split()[1] for line in lines] == ["0", "1", "2", "3", "4"]
    assert len(children) == 3 and all(child.exitcode == 0 for child in children)


@pytest.mark.parametrize("field, change", [("surface.depth_sigma_m", dict(depth_sigma=0.0)),
                                           ("surface.depth_sigma_m", dict(depth_sigma=1.0)),
                                           ("surface.tilt_sigma_deg", dict(tilt_sigma=0.0)),
                                           ("surface.tilt_sigma_deg", dict(tilt_sigma=math.radians(40.0)))])
def test_uncertainties_that_span_no_search_name_their_field_before_the_carving(coral_one, monkeypatch, field,
                                                                               change):
    """The pose steps' grids span ``BOUNDS_FACTOR`` × the manifest's uncertainties: one that
    gives no grid (zero, or wider than the depth or 45°) is refused naming the manifest's
    field, before the carving runs."""
    import dataclasses

    manifest = coral_one.manifest
    spoilt = dataclasses.replace(coral_one, manifest=dataclasses.replace(
        manifest, surface=dataclasses.replace(manifest.surface, **change)))
    monkeypatch.setattr(reconstruct_module, "carve", lambda *a, **k: pytest.fail("carved before the check"))
    with pytest.raises(InputError, match=f"dataset.toml: {field} = .*: must be > 0") as info:
        reconstruct(spoilt, settings=FAST)
    assert "\n" not in str(info.value)


def test_image_errors_vanish_for_the_truth_and_grow_with_a_bad_model(coral_one):
    """The true model at the true (D, β) explains the images better than a sphere there."""
    truth = trimesh.load_mesh(coral_one.truth_model_path)
    true = coral_one.manifest.truth
    good = image_errors(truth, coral_one, true.depth, true.tilt)
    blob = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    blob.apply_translation(truth.centroid)
    bad = image_errors(blob, coral_one, true.depth, true.tilt)
    assert good["ACE"] < 0.5 * bad["ACE"] and good["AIE"] < bad["AIE"]
    assert good["ACE"] < 0.004  # within about one 3.9 mm range bin



def test_the_contour_error_follows_refinement(coral_one):
    """E_I's CE finds the synthetic contour with the data's detector, so it falls as
    refinement improves the model at the true (D, β). With the synthetic contour taken as the
    first row above 1% of the object's peak, ACE went 1.66 mm after 2 updates, 1.41 after 6
    and 1.61 after 12 on this dataset while E_V fell from 0.287 to 0.262."""
    truth = trimesh.load_mesh(coral_one.truth_model_path)
    true = coral_one.manifest.truth
    model = carve(coral_one, true.depth, true.tilt).mesh
    contour_error, volume_error = [], []
    for updates in (2, 10):
        model = refine_shape(model, coral_one, true.depth, true.tilt, settings=RefineSettings(iterations=updates)).mesh
        contour_error.append(image_errors(model, coral_one, true.depth, true.tilt)["ACE"])
        volume_error.append(compare(model, truth, samples=2000)["E_V"])
    assert volume_error[1] < volume_error[0]
    assert contour_error[1] < 0.9 * contour_error[0]


def _script_the_loop(monkeypatch, pose_step, errors, completed=None, axes=None):
    """Replace the loop's pose step with ``pose_step``, its shape step with a copy of the model,
    and its record with the next of ``errors`` as E_I; the E_I of every entry completed for the
    history (E_mu, truth metrics) goes to ``completed``, the first posterior grid's axes that
    each pose step is given to ``axes``. Returns the shape steps' (depth, tilt, mesh), in order."""
    from types import SimpleNamespace

    from fsswarp.pose import Posterior

    errors, refined = iter(errors), []
    completed = [] if completed is None else completed
    axes = [] if axes is None else axes

    def wide(depth, tilt, prior):  # a posterior that identifies nothing and holds every pose tried
        return Posterior(depth, tilt, np.diag([1.0, 1.0]), prior, 0.0, depth, 1e-3)

    def posed(model, dataset, *, depth0, tilt0, comparison, prior, posterior_axes):
        axes.append(posterior_axes)
        step = pose_step(model, dataset, depth0=depth0, tilt0=tilt0, comparison=comparison)
        return SimpleNamespace(**vars(step), posterior=wide(step.depth, step.tilt, prior))

    def refine(model, dataset, depth, tilt, *, settings, comparison):
        moved = model.copy()
        moved.apply_translation((1e-6, 0.0, 0.0))  # a shape step that moves the model
        refined.append((depth, tilt, moved))
        comparison.model = moved  # as ViewComparison.use leaves it
        return SimpleNamespace(mesh=moved)

    def record(iteration, model, dataset, depth, tilt, settings, comparison, first):
        return {"iteration": iteration, "depth_m": depth, "E_I": next(errors)}

    def complete(entry, comparison, model, depth, tilt, truth):
        completed.append(entry["E_I"])
        return entry

    for name, fake in (("estimate_pose", posed), ("refine_shape", refine), ("_record", record),
                       ("_complete", complete), ("_line", str),
                       ("_valley_answer", lambda dataset, comparison, shaping, pose, prior, settings, say, heights,
                        carvings: wide(*pose, prior)),
                       ("carving_descent", lambda dataset, comparison, depth, tilt, settings, say, carvings: tilt)):
        monkeypatch.setattr(reconstruct_module, name, fake)
    return refined


def test_a_refused_pose_step_keeps_the_estimate_and_the_shape_step_runs(coral_one, monkeypatch):
    """Greedy acceptance: when E_mu does not fall, D and β stay, the shape is refined at them,
    and the loop goes on until E_I has not reached a new lowest for ``patience`` iterations
    (paper §2.3). The next pose steps would see the same model from the same start: the first
    step stands for them, not run again."""
    from types import SimpleNamespace

    calls = []

    def refused(model, dataset, *, depth0, tilt0, comparison):
        calls.append((depth0, tilt0))
        return SimpleNamespace(accepted=False, depth=depth0 + 0.01, tilt=tilt0 + 0.01)

    axes = []
    refined = _script_the_loop(monkeypatch, refused, [1.0, 0.9, 0.8, 0.85, 0.82], axes=axes)
    result = reconstruct(coral_one, settings=dataclasses.replace(FAST, iterations=6))
    start = coral_one.manifest.surface.depth, coral_one.manifest.surface.tilt
    assert calls == [start] and [r[:2] for r in refined] == [start] * 5  # 1 before the loop, 4 in it
    assert axes == [None]  # the first posterior grid: the level's frame
    assert len(result.pose_steps) == 4 and all(step is result.pose_steps[0] for step in result.pose_steps)
    assert [h["E_I"] for h in result.history] == [1.0, 0.9, 0.8, 0.85, 0.82] and result.stopped
    assert not result.converged  # nothing identified
    assert (result.depth, result.tilt) == start and result.best_iteration == 2
    assert result.model is refined[2][2]


def test_a_pose_that_raises_the_image_error_is_not_adopted(coral_one, monkeypatch):
    """The objective only diminishes: a proposed (D, β) whose shape step does not lower E_I
    below its lowest is dropped and the shape step is tried again at the previous (D, β).
    When that does not lower E_I either, the iteration is recorded and the next goes on from
    its model; after ``patience`` such iterations in a row the loop stops, and the result is
    the iteration with the lowest E_I. A pose step from the last one's model and start is that
    step (it is not run again, so it proposes the same pose)."""
    from types import SimpleNamespace

    moves, starts = iter([0.01, 0.02, 0.03, 0.04, 0.05, 0.06]), []

    def accepted(model, dataset, *, depth0, tilt0, comparison):
        starts.append((depth0, model))
        return SimpleNamespace(accepted=True, depth=depth0 + next(moves), tilt=tilt0)

    completed = []
    errors = [1.0, 0.9, 0.95, 0.85, 0.99, 0.99, 0.8, 0.9, 0.88, 0.9, 0.9]
    refined = _script_the_loop(monkeypatch, accepted, errors, completed)
    result = reconstruct(coral_one, settings=dataclasses.replace(FAST, iterations=10))
    s = coral_one.manifest.surface.depth
    # before the loop; it. 1 at the proposal (kept); it. 2 at the proposal, then at the old
    # depth (kept); it. 3 (it. 2's step again) neither (a miss); it. 4 (it. 2's step again) at the
    # proposal (kept); it. 5 and 6 (it. 5's step again) neither (two misses in a row: stop)
    assert [r[0] for r in refined] == pytest.approx(
        [s, s + 0.01, s + 0.03, s + 0.01, s + 0.03, s + 0.01, s + 0.03, s + 0.06, s + 0.03, s + 0.06, s + 0.03])
    assert [d for d, _ in starts] == pytest.approx([s, s + 0.01, s + 0.03])
    # every pose step sees the carving (never re-carved here: the scripted posteriors hold every pose), no
    # refined model: a shape refined at one (D, β) absorbs the tilt signal
    assert all(model is starts[0][1] for _, model in starts)
    assert not any(model is r[2] for _, model in starts for r in refined)
    assert [h["E_I"] for h in result.history] == [1.0, 0.9, 0.85, 0.99, 0.8, 0.88, 0.9]
    assert [h["depth_m"] for h in result.history] == pytest.approx([s, s + 0.01, s + 0.01, s + 0.01, s + 0.03,
                                                                     s + 0.03, s + 0.03])
    assert result.iterations == 6 and result.best_iteration == 4 and result.stopped
    assert result.depth == pytest.approx(s + 0.03) and result.model is refined[6][2]
    assert completed == [1.0, 0.9, 0.85, 0.99, 0.8, 0.88, 0.9]  # E_mu and truth metrics: recorded trials only


def test_patience_one_stops_at_the_first_iteration_that_does_not_lower_the_image_error(coral_one, monkeypatch):
    from types import SimpleNamespace

    def refused(model, dataset, *, depth0, tilt0, comparison):
        return SimpleNamespace(accepted=False, depth=depth0, tilt=tilt0)

    _script_the_loop(monkeypatch, refused, [1.0, 0.9, 0.95, 0.5])
    result = reconstruct(coral_one, settings=dataclasses.replace(FAST, iterations=6, patience=1))
    assert [h["E_I"] for h in result.history] == [1.0, 0.9, 0.95] and result.best_iteration == 1


def test_a_shape_step_that_leaves_the_model_unchanged_stops_the_loop(coral_one, monkeypatch):
    """Every update refused at the same (D, β): the next iterations would repeat this one, so
    the loop stops at once without recording it, keeping the best iteration."""
    from types import SimpleNamespace

    def refused(model, dataset, *, depth0, tilt0, comparison):
        return SimpleNamespace(accepted=False, depth=depth0, tilt=tilt0)

    refined = _script_the_loop(monkeypatch, refused, [1.0, 0.9, 0.95, 0.95])
    unchanged = iter([False, False, True])
    real = reconstruct_module.refine_shape

    def refine(model, dataset, depth, tilt, *, settings, comparison):
        result = real(model, dataset, depth, tilt, settings=settings, comparison=comparison)
        return SimpleNamespace(mesh=model) if next(unchanged) else result

    monkeypatch.setattr(reconstruct_module, "refine_shape", refine)
    result = reconstruct(coral_one, settings=dataclasses.replace(FAST, iterations=6, patience=3))
    assert len(refined) == 3  # none after the third, which returned its input
    assert [h["E_I"] for h in result.history] == [1.0, 0.9] and result.stopped and result.best_iteration == 1


def test_the_loop_hands_one_comparison_to_every_step(coral_one, monkeypatch):
    """The loop builds one ViewComparison and hands that one to the pose steps, the shape
    steps, the records and E_mu (two only when the shape steps' contour settings differ)."""
    from types import SimpleNamespace

    from fsswarp.compare import PoseSettings, ViewComparison

    built, seen = [], []

    class Counted(ViewComparison):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            built.append(self)

    def accepted(model, dataset, *, depth0, tilt0, comparison):
        seen.append(("pose", comparison))
        return SimpleNamespace(accepted=True, depth=depth0 + 0.01, tilt=tilt0)

    monkeypatch.setattr(reconstruct_module, "ViewComparison", Counted)
    _script_the_loop(monkeypatch, accepted, [1.0, 0.9, 0.8, 1.0])
    fakes = {name: getattr(reconstruct_module, name) for name in ("refine_shape", "_record", "_complete")}

    def spy(name):
        def call(*args, **kwargs):
            seen.append((name, kwargs["comparison"] if "comparison" in kwargs else args[6 if name == "_record" else 1]))
            return fakes[name](*args, **kwargs)
        return call

    for name in fakes:
        monkeypatch.setattr(reconstruct_module, name, spy(name))
    reconstruct(coral_one, settings=dataclasses.replace(FAST, iterations=2))
    assert len(built) == 1 and all(comparison is built[0] for _, comparison in seen)
    assert {name for name, _ in seen} == {"pose", "refine_shape", "_record", "_complete"}
    built.clear()
    other = dataclasses.replace(FAST.refine, pose=PoseSettings(window=0.2))
    reconstruct(coral_one, settings=dataclasses.replace(FAST, iterations=0, refine=other))
    assert len(built) == 2


def test_settings_are_validated():
    from fsswarp.errors import InputError

    with pytest.raises(InputError, match="iterations"):
        ReconstructSettings(iterations=-1)
    with pytest.raises(InputError, match="resolution"):
        ReconstructSettings(resolution=4)
    with pytest.raises(InputError, match="patience"):
        ReconstructSettings(patience=0)
    for bad in (-0.5, math.nan, "2"):
        with pytest.raises(InputError, match="answer_top_level"):
            ReconstructSettings(answer_top_level=bad)
    for bad in ("yes", 1, None):
        for name in ("answer_ahead", "answer_threads"):
            with pytest.raises(InputError, match=name):
                ReconstructSettings(**{name: bad})


def test_reconstruct_command_writes_model_result_and_figures(coral_south, tmp_path):
    done = run_cli("reconstruct", str(coral_south.root), "--out", str(tmp_path / "r"), "--iterations", "0",
                   "--resolution", "48")
    assert done.returncode == 0, done.stderr
    names = sorted(p.relative_to(tmp_path / "r").as_posix() for p in (tmp_path / "r").rglob("*") if p.is_file())
    assert names == ["carved.ply", "figures/carved.png", "figures/contours.png", "figures/history.png",
                     "figures/model.png", "model.ply", "report.html", "result.json"]
    result = json.loads((tmp_path / "r" / "result.json").read_text())
    assert set(result) == RESULT_KEYS and result["iterations"] == 0
    assert trimesh.load_mesh(tmp_path / "r" / "model.ply").is_watertight


def test_reconstruct_starts_from_a_given_depth_and_tilt(coral_south, tmp_path):
    """--depth/--tilt replace the measured D0/β0 as the start (the paper table's 2° runs)."""
    done = run_cli("reconstruct", str(coral_south.root), "--out", str(tmp_path / "r"), "--iterations", "0",
                   "--resolution", "32", "--depth", "0.435", "--tilt", "11.9")
    assert done.returncode == 0, done.stderr
    result = json.loads((tmp_path / "r" / "result.json").read_text())
    first = result["history"][0]
    assert (first["depth_m"], first["tilt_deg"]) == (0.435, pytest.approx(11.9))
    assert result["start"] == {"depth_m": 0.435, "tilt_deg": pytest.approx(11.9)}
    assert "given D0 = 0.4350 m" in done.stdout and "started from depth 0.4350 m, tilt 11.90 deg" in done.stdout
    assert "error against the truth: depth +5.0 mm" in done.stdout  # no iterations: the start is the answer


@pytest.mark.parametrize("args, field", [
    (["reconstruct", "nowhere", "--out", "OUT"], "nowhere"),
    (["reconstruct", "DATA", "--out", "OUT", "--depth", "-0.2"], "depth"),
    (["reconstruct", "DATA", "--out", "OUT", "--tilt", "nan"], "tilt"),
    (["reconstruct", "DATA", "--out", "OUT", "--patience", "0"], "patience"),
    (["reconstruct", "DATA", "--out", "OUT", "--depth", "47"], "--depth = 47.0: is "),  # cm typed as m
    (["reconstruct", "DATA", "--out", "OUT", "--tilt", "0.19"], "--tilt = 0.19: is "),  # rad typed as deg
    (["demo", "no-such-scene", "--out", "OUT"], "no-such-scene"),
])
def test_bad_input_exits_2_and_writes_nothing(coral_one, tmp_path, args, field):
    named = {"OUT": str(tmp_path / "out"), "nowhere": str(tmp_path / "nowhere"), "DATA": str(coral_one.root)}
    args = [named.get(a, a) for a in args]
    done = run_cli(*args)
    assert done.returncode == 2, done.stderr
    assert field in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("command", [["reconstruct", "DATA"], ["carve", "DATA"],
                                     ["enhance", "DATA", "--model", "TRUTH"], ["pose", "DATA", "--model", "TRUTH"],
                                     ["render", "TRUTH", "--dataset", "DATA"],
                                     ["simulate", "coral-one"]])
@pytest.mark.parametrize("where, message", [("mine", "not an fsswarp output"), ("file/out", "file is not a folder")])
def test_a_wrong_out_fails_before_the_work(coral_one, tmp_path, command, where, message):
    """--out in a folder of the user's, or under a file, is refused before anything runs
    (nothing printed), and the user's files stay."""
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    (tmp_path / "file").write_text("a file")
    named = {"DATA": str(coral_one.root), "TRUTH": str(coral_one.truth_model_path)}
    done = run_cli(*[named.get(a, a) for a in command], "--out", str(tmp_path / where))
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "--out" in lines[0] and message in lines[0], lines
    assert done.stdout == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "mine"]
    assert [p.name for p in (tmp_path / "mine").iterdir()] == ["notes.txt"]


@pytest.mark.parametrize("command", ["check", "reconstruct", "carve"])
def test_an_unreadable_truth_model_is_named_before_the_work(coral_one, tmp_path, command):
    import shutil

    data = tmp_path / "data"
    shutil.copytree(coral_one.root, data)
    (data / "truth" / "model.ply").write_text("not a mesh")
    done = run_cli(command, str(data), *(["--out", str(tmp_path / "out")] if command != "check" else []))
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "dataset.toml: truth.model" in lines[0] and "cannot read mesh" in lines[0]
    assert not (tmp_path / "out").exists() and "iteration" not in done.stdout and "carving" not in done.stdout


def test_the_demo_simulates_reconstructs_and_draws_its_figures_while_it_goes_on(tmp_path, monkeypatch, capsys):
    """The command writes its three folders (the dataset passes ``check``). Run again over its own
    output, in this process, it replaces it silently; the reconstruction's figures and report
    are finished when the demo ends, not before the enhancement starts (their figures are drawn
    meanwhile); the enhancement's figures, the slowest, are queued before the report's views,
    whose rows show the enhancement's views (the views are enhanced once); an error after them
    leaves no output and no temporary folder. (Three demos in one test: each takes ~10 s on
    CI's machine.)"""
    out = tmp_path / "demo"
    done = run_cli("demo", "coral-one", "--out", str(out), "--iterations", "0")
    assert done.returncode == 0, done.stderr
    assert "reconstruction" in done.stdout and ".tmp" not in done.stdout
    for name in ("demo.json", "dataset/dataset.toml", "dataset/figures/layers.png", "reconstruction/model.ply",
                 "reconstruction/result.json", "reconstruction/figures/history.png", "enhance/enhance.json",
                 "enhance/enhance.png", "enhance/S0_enhanced.tiff", "enhance/S0_ghost.tiff"):
        assert (out / name).is_file(), name
    assert run_cli("check", str(out / "dataset")).returncode == 0
    assert json.loads((out / "enhance" / "enhance.json").read_text())["dataset"] == str(out / "dataset")
    first_model = (out / "reconstruction" / "model.ply").stat().st_mtime_ns

    import fsswarp.cli as cli
    import fsswarp.enhancement
    from fsswarp.processes import WorkerProcesses

    monkeypatch.setenv("FSSWARP_FIGURE_WORKERS", "2")
    enhance = cli.run_enhancement
    seen, queued = [], []
    submit = WorkerProcesses.submit

    def recorded(self, function, *args, **kwargs):
        queued.append(function.__name__)
        return submit(self, function, *args, **kwargs)

    monkeypatch.setattr(WorkerProcesses, "submit", recorded)

    def watched(state, dataset, mesh, model_name, depth, tilt, out, *args, **kwargs):
        reconstruction = list(out.parent.glob(".reconstruction.*.tmp"))
        seen.append([(folder / "result.json").is_file() for folder in reconstruction]
                    + [(folder / "report.html").exists() for folder in reconstruction])
        enhanced = enhance(state, dataset, mesh, model_name, depth, tilt, out, *args, **kwargs)
        if fail:
            raise InputError("stopped here", field="test")
        return enhanced

    monkeypatch.setattr(cli, "run_enhancement", watched)
    enhancements, enhance_views = [], fsswarp.enhancement.enhance

    def counted(*args, **kwargs):
        enhancements.append(args[2:4])  # (depth, tilt)
        return enhance_views(*args, **kwargs)

    monkeypatch.setattr(fsswarp.enhancement, "enhance", counted)
    fail = False
    capsys.readouterr()
    assert cli.main(["-q", "--backend", "opencl", "demo", "coral-one", "--out", str(out), "--iterations", "0"]) == 0
    assert capsys.readouterr().out == ""  # replaced its own earlier output, silently
    assert (out / "reconstruction" / "model.ply").stat().st_mtime_ns != first_model
    assert seen == [[True, False]]  # written, its page not yet
    assert len(enhancements) == 1  # by the enhancement; the report's rows show its views
    last_enhancement = max(i for i, name in enumerate(queued) if name in ("enhance_figure", "comparison_figure"))
    assert queued.index("carve_figure") < last_enhancement < queued.index("views_figure")
    for name in ("reconstruction/report.html", "reconstruction/figures/history.png", "enhance/enhance.png",
                 "enhance/views_optimized.png", "dataset/figures/layers.png"):
        assert (out / name).is_file(), name
    fail = True
    again = tmp_path / "again"
    assert cli.main(["-q", "--backend", "opencl", "demo", "coral-one", "--out", str(again), "--iterations", "0"]) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["demo"]


def test_the_image_errors_read_the_located_comparison_s_layers(coral_one, monkeypatch):
    """AIE's synthetic views are the layers that the comparison located at that (D, β)
    rendered, to the bit those of ``render``; only the views it does not hold are rendered, and
    everything is when the render settings differ from the comparison's or it is located elsewhere."""
    from fsswarp.backends import get_backend
    from fsswarp.compare import ViewComparison
    from fsswarp.rendering import RenderSettings, render

    truth = coral_one.manifest.truth
    model = trimesh.load(coral_one.truth_model_path, process=False)
    backend = get_backend("opencl")
    comparison = ViewComparison(coral_one, backend=backend).use(model, truth.depth, truth.tilt)
    held_out = next(v.name for v in coral_one.rig.views if not v.optimize)
    names = list(comparison.data.names) + [held_out]
    want = render(model, coral_one.sonar, coral_one.rig, truth.depth, truth.tilt, views=names, backend=backend)
    rendered = []

    def spy(*args, **kwargs):
        rendered.append(list(kwargs["views"]))
        return render(*args, **kwargs)

    monkeypatch.setattr(reconstruct_module, "render", spy)
    settings = ReconstructSettings()
    got = reconstruct_module._synthetic_views(model, coral_one, truth.depth, truth.tilt, names, settings, comparison)
    assert rendered == [[held_out]]
    for name in names:
        np.testing.assert_array_equal(got[name], want[name])
    coarse = dataclasses.replace(settings, render=RenderSettings(samples=(1, 32)))
    reconstruct_module._synthetic_views(model, coral_one, truth.depth, truth.tilt, names, coarse, comparison)
    reconstruct_module._synthetic_views(model, coral_one, truth.depth + 0.01, truth.tilt, names, settings, comparison)
    assert rendered[1:] == [names, names]


@pytest.mark.parametrize("earlier", [[], [0.004]])
def test_the_answer_keeps_the_height_and_is_made_again_where_it_moves(coral_one, monkeypatch, earlier):
    """The answer's orchestration with a scripted pose step: a model made at c fixes the height
    h = D − L·β at g(c) = g + k (aᵀc − g), a = (1, −L) (a shape partly follows its making),
    with variance v, and the pose step's posterior is the prior × N(aᵀθ; g(c), v). The answer
    is made again at its own mean while that moves (at most FIXED_POINT_STEPS times), from the
    pose step's proposal even where greedy acceptance refused it; its posterior is the prior ×
    N(aᵀθ; g(c), v + aᵀ CARVING_ERROR a + s²), s² the sample variance of the heights of every
    model made for the answer (``earlier``: offsets from g of heights made before this call),
    written out here."""
    from types import SimpleNamespace

    from fsswarp.pose import CARVING_ERROR, Posterior, Prior

    prior = Prior.of(coral_one)
    lever, follows, v = 2.0, 0.3, 0.001 ** 2
    a = np.array([1.0, -lever])
    g = coral_one.manifest.truth.depth - lever * coral_one.manifest.truth.tilt
    precision0 = np.diag([prior.depth_sigma ** -2, prior.tilt_sigma ** -2])
    mu0 = np.array([prior.depth, prior.tilt])
    made = []

    def posterior_of(height, variance):
        covariance = np.linalg.inv(precision0 + np.outer(a, a) / variance)
        return covariance @ (precision0 @ mu0 + a * height / variance), covariance

    def sighting(dataset, depth, tilt, settings, shaping, carvings=None):
        made.append(np.array([depth, tilt]))
        return made[-1]  # the "model" remembers where it was made

    def pose_step(model, dataset, *, depth0, tilt0, comparison, prior):
        mean, covariance = posterior_of(g + follows * (a @ model - g), v)
        # greedy acceptance refused the proposal: the posterior is centred at the start
        return SimpleNamespace(candidate=tuple(mean),
                               posterior=Posterior(depth0, tilt0, covariance, prior, math.nan, math.nan, 1e-3))

    monkeypatch.setattr(reconstruct_module, "sighting", sighting)
    monkeypatch.setattr(reconstruct_module, "estimate_pose", pose_step)
    monkeypatch.setattr(reconstruct_module, "model_lever", lambda model, rig, depth, tilt: lever)
    start = (prior.depth + 0.002, prior.tilt + math.radians(1.5))
    heights_seen = [g + h for h in earlier]
    posterior = reconstruct_module._valley_answer(coral_one, None, None, start, prior, FAST, lambda line: None,
                                                  heights_seen)
    assert 2 <= len(made) <= reconstruct_module.FIXED_POINT_STEPS + 1 and np.allclose(made[0], start)
    widened = v + a @ CARVING_ERROR @ a
    for before, after in zip(made, made[1:]):  # each model made at the previous answer's mean
        assert np.allclose(after, posterior_of(g + follows * (a @ before - g), widened)[0], atol=1e-12)
    heights = [g + h for h in earlier] + [g + follows * (a @ c - g) for c in made]
    assert np.allclose(heights_seen, heights, atol=1e-15)
    mean = np.mean(heights)
    spread = sum((h - mean) ** 2 for h in heights) / (len(heights) - 1)
    mean, covariance = posterior_of(heights[-1], widened + spread)
    assert np.allclose([posterior.depth, posterior.tilt], mean, atol=1e-12)
    assert np.allclose(posterior.covariance, covariance, rtol=1e-8)
    assert posterior.valley_slope == lever


@pytest.mark.parametrize("vertex_steps, wall, expected_steps",
                         [(0.2, None, 0), (-2.3, None, -2), (3.6, -0.5, 4), (20.0, None, 8), (-2.3, -1.5, -1)])
def test_the_carving_descent_walks_to_the_least_self_disagreement(coral_one, monkeypatch, vertex_steps, wall,
                                                                   expected_steps):
    """A scripted carving whose E_mu at its own pose is a parabola in tilt with its vertex
    ``vertex_steps`` DESCENT_STEPs from the start: the descent carves at the answer's depth and
    stops at the step nearest the vertex, or after DESCENT_STEPS; a carving that loses every voxel
    (beyond ``wall`` steps) counts as worse."""
    from types import SimpleNamespace

    from fsswarp.errors import InputError

    step, start, depth = reconstruct_module.DESCENT_STEP, math.radians(11.0), 0.4321
    vertex = start + vertex_steps * step
    carved_at = []

    def carve(dataset, at_depth, tilt, *, resolution, settings, backend):
        carved_at.append((at_depth, tilt))
        if wall is not None and tilt < start + wall * step:  # beyond the wall: nothing left
            raise InputError("every voxel was carved away", field="views", value=16)
        return SimpleNamespace(mesh=tilt)

    class Comparison:
        backend = None

        def use(self, model, at_depth, tilt):
            self.model = model

        def exact(self, at_depth, tilt):
            return SimpleNamespace(value=0.004 + 30.0 * (self.model - vertex) ** 2)

    monkeypatch.setattr(reconstruct_module, "carve", carve)
    found = reconstruct_module.carving_descent(coral_one, Comparison(), depth, start, FAST, lambda line: None)
    assert found == pytest.approx(start + expected_steps * step, abs=1e-12)
    assert all(d == depth for d, _ in carved_at)
    assert len(carved_at) == 3 + abs(expected_steps)  # start, both neighbours, then one ahead per step


@pytest.mark.parametrize("errors, overlap", [({"moved": 0.7, "held": 0.75, "fresh": 0.8}, 5),
                                             ({"moved": 0.7, "held": 0.65, "fresh": 0.8}, 5),
                                             ({"moved": 0.9, "held": 0.7, "fresh": 0.6}, 5),
                                             ({"moved": 0.7, "held": 0.5, "fresh": 0.8}, 0)])
def test_the_answer_model_is_the_lowest_image_error_of_the_kept_held_and_fresh_models(coral_one, monkeypatch,
                                                                                      errors, overlap):
    """At the answer the views are carved; the kept model, the kept model held to that carving
    (``fsswarp.carving.held`` with the carving's views at the answer, meshed) and the carving (meshed
    while the others are refined) are each refined there, and the lowest E_I is the result (greedy, as in the loop): ``recarved``
    says whether the carving won, and the comparison is left on the result. Where no carved voxel
    lies inside the kept model (``overlap`` 0) there is no held model."""
    from types import SimpleNamespace

    answer, made, levels = (0.4321, math.radians(10.4)), [], []
    voxels = SimpleNamespace(name="voxels")
    refined = {"kept": "moved", "held mesh": "held", "carved": "fresh"}

    def refine(model, dataset, depth, tilt, *, settings, comparison):
        made.append(("refined", model, (depth, tilt)))
        levels.append(settings.top_level)
        return SimpleNamespace(mesh=refined[model])

    views = coral_one.rig.names[1::2]
    rotations, translations = (a[1::2] for a in coral_one.rig.relative_poses(*answer))

    def carve(dataset, depth, tilt, *, resolution, settings, backend, mesh=True):
        assert not mesh  # the answer's carving is meshed while the other models are refined
        made.append(("carved", None, (depth, tilt)))
        return SimpleNamespace(voxels=voxels, views=tuple(views))

    def held(carving, model, view_rotations, view_translations, sonar, backend):
        assert np.array_equal(view_rotations, rotations) and np.array_equal(view_translations, translations)
        assert sonar is coral_one.sonar and backend is Comparison.backend
        made.append(("held", model, carving.name))
        return SimpleNamespace(kept=overlap, name="held")

    class MeshJob:  # the carving's and the held model's meshes, made while the kept model is refined
        def __init__(self, voxels, *, smooth, faces):
            assert (smooth, faces) == (FAST.carve.smooth, FAST.carve.faces)
            made.append(("meshed", voxels.name, None))
            self.mesh = {"held": "held mesh", "voxels": "carved"}[voxels.name]

        def result(self):
            return self.mesh

    def record(iteration, model, dataset, depth, tilt, settings, comparison, first):
        comparison.on = model
        return {"iteration": iteration, "E_I": errors[model]}

    class Comparison:
        backend = SimpleNamespace(is_gpu=False)  # the three refined in turn (_threads_pay)

        def use(self, model, depth, tilt):
            self.on = model

    for name, stand_in in (("refine_shape", refine), ("carve", carve), ("held", held),
                           ("MeshJob", MeshJob), ("_record", record)):
        monkeypatch.setattr(reconstruct_module, name, stand_in)
    comparison = Comparison()
    model, entry = reconstruct_module._answer_model("kept", coral_one, answer, 7, FAST, comparison, comparison, {},
                                                    lambda line: None, carvings={})
    candidates = ["moved", "held", "fresh"] if overlap else ["moved", "fresh"]
    winner = min(candidates, key=errors.get)
    meshed = [("meshed", "held", None)] if overlap else []
    assert made == ([("carved", None, answer), ("meshed", "voxels", None), ("held", "kept", "voxels")] + meshed
                    + [("refined", "kept", answer)]
                    + ([("refined", "held mesh", answer)] if overlap else []) + [("refined", "carved", answer)])
    assert model == winner and comparison.on == winner
    assert entry == {"iteration": 7, "E_I": errors[winner], "recarved": winner == "fresh"}
    # the answer's shape steps take the double-bounce votes, the loop's do not
    assert FAST.refine.top_level == 0 < FAST.answer_top_level and levels == [FAST.answer_top_level] * len(candidates)


def test_a_reconstruction_carves_each_pose_once(coral_one, monkeypatch):
    """With a reconstruction's ``carvings`` a pose carved already comes back as it was (the same
    object, no second carving); another pose is carved; without ``carvings`` every call carves.
    A carving started ahead is carved without its mesh, whose job is made at once, and finished
    by the ``_carve`` that asks for it; its InputError is raised there. The answer's tilt check
    starts its three carvings ahead, in order, and passes the memo on to the answer's model."""
    from types import SimpleNamespace

    from fsswarp.errors import InputError

    carved, jobs = [], []

    def carve(dataset, depth, tilt, *, resolution, settings, backend, mesh=True):
        if tilt < 0:
            raise InputError("every voxel was carved away", field="views", value=16)
        carved.append((depth, tilt, resolution, mesh))
        return SimpleNamespace(mesh=f"mesh {len(carved)}" if mesh else None, voxels=f"voxels {len(carved)}")

    class MeshJob:
        def __init__(self, voxels, *, smooth, faces):
            jobs.append(voxels)
            self.voxels = voxels

        def result(self):
            return f"mesh of {self.voxels}"

    monkeypatch.setattr(reconstruct_module, "carve", carve)
    monkeypatch.setattr(reconstruct_module, "MeshJob", MeshJob)
    memo = {}
    first = reconstruct_module._carve(coral_one, 0.43, 0.18, FAST, None, memo)
    assert reconstruct_module._carving(coral_one, 0.43, np.float64(0.18), FAST, None, memo) is first.mesh
    assert reconstruct_module._carve(coral_one, 0.43, 0.19, FAST, None, memo) is not first
    assert carved == [(0.43, 0.18, FAST.resolution, True), (0.43, 0.19, FAST.resolution, True)]
    reconstruct_module._carve(coral_one, 0.43, 0.18, FAST, None)
    reconstruct_module._carve(coral_one, 0.43, 0.18, FAST, None)
    assert len(carved) == 4 and not jobs

    carved.clear()
    for tilt in (0.18, 0.2, -0.1):  # 0.18 is carved already: nothing to start
        reconstruct_module._carve_ahead(coral_one, 0.43, tilt, FAST, None, memo)
    reconstruct_module._carve_ahead(coral_one, 0.43, 0.21, FAST, None, None)  # no memo: nothing to start
    assert carved == [(0.43, 0.2, FAST.resolution, False)] and jobs == ["voxels 1"]
    ahead = reconstruct_module._carve(coral_one, 0.43, 0.2, FAST, None, memo)
    assert ahead.mesh == "mesh of voxels 1"
    assert reconstruct_module._carve(coral_one, 0.43, 0.2, FAST, None, memo) is ahead
    for _ in range(2):
        with pytest.raises(InputError, match="every voxel was carved away"):
            reconstruct_module._carve(coral_one, 0.43, -0.1, FAST, None, memo)
    assert len(carved) == 1

    class Comparison:
        backend = None
        used = []

        def use(self, model, depth, tilt):
            self.model = model

        def exact(self, depth, tilt):
            self.used.append(self.model)
            return SimpleNamespace(value=0.01)

    carved.clear()
    jobs.clear()
    comparison = Comparison()
    found = reconstruct_module.carving_descent(coral_one, comparison, 0.43, 0.18, FAST, lambda line: None, memo)
    assert found == 0.18  # no neighbour agrees better
    step = reconstruct_module.DESCENT_STEP
    assert [t for _, t, _, _ in carved] == pytest.approx([0.18 - step, 0.18 + step])
    assert not any(mesh for _, _, _, mesh in carved) and jobs == ["voxels 1", "voxels 2"]
    assert comparison.used == [first.mesh, "mesh of voxels 1", "mesh of voxels 2"]


def test_a_resting_pose_step_has_the_best_pose_carved_ahead(coral_one, monkeypatch):
    """Where mesh processes run and the pose step finds nothing better, the loop starts the best
    pose's carving (its mesh in a process), which the answer's first model is made from; with
    no mesh processes it carves nothing ahead."""
    from fsswarp.backends import get_backend

    class Reached(Exception):
        pass

    refused = reconstruct_module.estimate_pose

    def estimate_pose(*args, **kwargs):
        return dataclasses.replace(refused(*args, **kwargs), accepted=False)

    def valley_answer(dataset, comparison, shaping, pose, *rest):
        raise Reached(pose)

    ahead = []
    monkeypatch.setattr(reconstruct_module, "estimate_pose", estimate_pose)
    monkeypatch.setattr(reconstruct_module, "_valley_answer", valley_answer)
    monkeypatch.setattr(reconstruct_module, "_carve_ahead",
                        lambda dataset, depth, tilt, *rest: ahead.append((depth, tilt)))
    for workers, expected in ((object(), 1), (None, 0)):
        ahead.clear()
        monkeypatch.setattr(reconstruct_module, "start_mesh_workers", lambda: workers)
        with pytest.raises(Reached) as reached:
            reconstruct(coral_one, settings=FAST, backend=get_backend("opencl"))
        assert ahead == [reached.value.args[0]] * expected


def _thread_names(monkeypatch, owner, name: str) -> list[str]:
    """Wrap ``owner.name`` so that each call records the name of the thread it runs in; returns
    the list it records into."""
    import threading

    original, where = getattr(owner, name), []

    def recorded(*args, **kwargs):
        where.append(threading.current_thread().name)
        return original(*args, **kwargs)

    monkeypatch.setattr(owner, name, recorded)
    return where


def _refusing_pose_steps(monkeypatch):
    """Make every pose step of the loop find nothing better (its real result, not accepted), so
    that the answer is worked out ahead from the first iteration on."""
    found = reconstruct_module.estimate_pose
    monkeypatch.setattr(reconstruct_module, "estimate_pose", lambda *args, **kwargs: dataclasses.replace(
        found(*args, **kwargs), accepted=False) if "posterior_axes" in kwargs else found(*args, **kwargs))


def test_the_answer_worked_out_ahead_and_its_models_refined_in_threads_give_the_answer_found_in_turn(
        coral_one, monkeypatch):
    """Two ReconstructSettings and the mesh processes, all off and all on (two loops, not eight):
    - ``answer_ahead``: once a pose step finds nothing better, the answer's pose is worked out in
      a thread of its own while the loop's shape steps go on, not at the loop's end;
    - ``answer_threads``: the answer's three models (kept, held, carving) are refined side by
      side, two of them in threads with comparisons of their own. Threads are taken on GPUs alone
      (``_threads_pay``), here said to pay on any backend;
    - two mesh processes (FSSWARP_MESH_WORKERS): the carvings that the loop and the answer know
      ahead are meshed there.
    Either way the same reconstruction, bit for bit (result, history, model, and the answer's
    lines in the same place; the truth's lines come when ready and are left out)."""
    import threading

    from fsswarp.backends import get_backend
    from fsswarp.carving import MeshJob

    started, job = [], MeshJob.__init__

    def spy(self, *args, **kwargs):
        job(self, *args, **kwargs)
        started.append(self.future is not None)

    monkeypatch.setattr(MeshJob, "__init__", spy)
    _refusing_pose_steps(monkeypatch)
    monkeypatch.setattr(reconstruct_module, "_threads_pay", lambda backend: True)
    pose_threads = _thread_names(monkeypatch, reconstruct_module, "_answer_pose")
    model_threads = _thread_names(monkeypatch, reconstruct_module, "refine_shape")
    runs, poses, models, meshed = {}, {}, {}, {}
    for on in (False, True):
        lines, seen = [], (len(pose_threads), len(model_threads))
        started.clear()
        monkeypatch.setenv("FSSWARP_MESH_WORKERS", "2" if on else "0")
        result = reconstruct(coral_one, settings=dataclasses.replace(FAST, iterations=2, answer_ahead=on,
                                                                     answer_threads=on),
                             backend=get_backend("opencl"), progress=lines.append)
        meshed[on] = list(started)
        summary = result.summary()
        del summary["seconds"]
        runs[on] = (json.dumps(summary, sort_keys=True), result.model.vertices, result.model.faces,
                    [line for line in lines if "against the truth" not in line])
        poses[on], models[on] = pose_threads[seen[0]:], model_threads[seen[1]:]
    assert poses == {False: ["MainThread"], True: ["fsswarp-answer"]}
    assert len(meshed[True]) >= 3 and all(meshed[True])  # the answer's tilt check's three at least
    assert meshed[False] and not any(meshed[False])
    assert any(line.startswith("the answer: refined there") for line in runs[True][3])
    assert sum(name.startswith("fsswarp-answer-model") for name in models[True]) == 2
    assert not any(name.startswith("fsswarp-answer-model") for name in models[False])
    assert runs[True][0] == runs[False][0] and runs[True][3] == runs[False][3]
    np.testing.assert_array_equal(runs[True][1], runs[False][1])
    np.testing.assert_array_equal(runs[True][2], runs[False][2])
    assert not [thread for thread in threading.enumerate() if thread.name.startswith("fsswarp-answer")]


def test_a_loop_that_fails_stops_its_answer_thread(coral_one, monkeypatch):
    """A loop that raises while the answer is worked out ahead raises its own error, and its
    answer's thread has ended when ``reconstruct`` returns."""
    import threading

    from fsswarp.backends import get_backend

    _refusing_pose_steps(monkeypatch)
    started, calls = threading.Event(), []
    answered, refined = reconstruct_module._answer_pose, reconstruct_module.refine_shape

    def answer_pose(*args, **kwargs):
        started.set()
        return answered(*args, **kwargs)

    def failing_shape_step(*args, **kwargs):
        calls.append(threading.current_thread().name)
        if calls.count("MainThread") == 1 or threading.current_thread().name == "fsswarp-answer":
            return refined(*args, **kwargs)  # the carving's before the loop, and the answer's
        assert started.wait(60)  # the answer's thread is running
        raise RuntimeError("a shape step failed")

    monkeypatch.setattr(reconstruct_module, "_answer_pose", answer_pose)
    monkeypatch.setattr(reconstruct_module, "refine_shape", failing_shape_step)
    with pytest.raises(RuntimeError, match="a shape step failed"):
        reconstruct(coral_one, settings=dataclasses.replace(FAST, iterations=2), backend=get_backend("opencl"))
    assert started.is_set()
    assert not [thread for thread in threading.enumerate() if thread.name == "fsswarp-answer"]
