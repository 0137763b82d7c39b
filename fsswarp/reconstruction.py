"""The unified optimization of the paper's Figure 3a (DESIGN §1): carve at the measured
(D0, β0) and refine, then per iteration (lengths m, angles rad, meshes in the reference frame):

1. pose step (``fsswarp.pose.estimate_pose``) on the model carved last, unrefined (a shape
   refined at one (D, β) absorbs the tilt signal; the same model from the same start repeats the
   last step, not run again): a (D, β) proposed only where the posterior cost falls, with 95%
   intervals; if they exclude the last carving's pose, the views are carved again at the proposal;
2. shape step (``fsswarp.refine.refine_shape``) at the proposal, then, if E_I did not fall
   below its lowest, again at the previous (D, β); of the refined and the fresh carving the
   lower E_I goes on (``recarved``);
3. record D, β, intervals, E_mu, AIE, ACE, E_I and, with a truth, E_V, Chamfer and F-score
   (``fsswarp.metrics``; the truth metrics in worker processes while the loop goes on).

One ``fsswarp.compare.ViewComparison`` serves both steps and the metrics. The loop stops
after ``iterations``, after ``patience`` iterations without a new lowest E_I, or when a shape
step leaves the model unchanged. The answer (:func:`_valley_answer`): a free shape absorbs the
tilt, so the images keep only the surface's height above the object, D − L·β (DESIGN §7): at
the lowest E_I's (D, β), carve and refine once (:func:`sighting`), take the pose step's height
and its error, the sensors' priors the rest (``fsswarp.pose.valley_posterior``), made again at
that estimate while it moves (``FIXED_POINT_STEPS``), its tilt checked by carvings
(:func:`carving_descent`); the result is the lowest E_I of three models refined there
(:func:`_answer_model`; ``converged``: stopped, both identified). Without iterations the
sensors' pose stays. Image metrics over the optimized views: Ω_m, the synthetic object above
1% of its peak where ghost and mirrors stay below 10% of it; IE on Ω_m, totals divided by
their means there; CE from the comparison's contours; E_I = (AIE/AIE⁰ + ACE/ACE⁰)/2.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import threading
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .carving import CarveSettings, MeshJob, carve, held, start_mesh_workers
from .errors import InputError, check_depth_tilt, check_integer, is_finite_number
from .compare import PoseSettings, PoseWarning, ViewComparison
from .metrics import (SAMPLES, average_contour_error, average_intensity_error, combine, compare_meshes, image_error,
                      require_triangles, surface_points)
from .pose import (BOUNDS_FACTOR, Prior, check_start, check_uncertainties, estimate_pose, fit_posterior, model_lever,
                   spans_an_area, valley_posterior)
from .refine import RefineSettings, refine_shape
from .rendering import RenderSettings, render, with_total

#: Most times the answer's model is made again at its own estimate.
FIXED_POINT_STEPS = 4
#: The answer's check of its tilt by carvings at its depth: steps (rad) and most steps.
DESCENT_STEP, DESCENT_STEPS = math.radians(0.5), 8


@dataclass(frozen=True)
class ReconstructSettings:
    """Options of :func:`reconstruct`.

    iterations : T, the most pose + shape iterations after the carving
    patience : stop after this many iterations in a row that do not lower E_I below its lowest
    resolution : voxels along the longest side of the carving box
    render : synthetic views for the image metrics; carve, pose, refine : the steps' settings
        (pose also finds E_I's contours; refine.iterations: refinement updates per shape step)
    answer_top_level : ``refine.top_level`` of the shape steps at the answer (:func:`_answer_model`):
        double-bounce votes where the pose is settled (docs/decisions.md); 0: none
    answer_ahead : work the answer's pose out in a thread once the pose step rests, while the
        loop's last shape steps go on (:class:`_AnswerAhead`; the same answer, sooner)
    answer_threads : on a GPU, refine the answer's three models side by side in threads
        (:func:`_answer_model`; the same model, sooner)
    """

    iterations: int = 10
    patience: int = 2
    resolution: int = 128
    carve: CarveSettings = field(default_factory=CarveSettings)
    pose: PoseSettings = field(default_factory=PoseSettings)
    refine: RefineSettings = field(default_factory=lambda: RefineSettings(iterations=3))
    render: RenderSettings = field(default_factory=RenderSettings)
    answer_top_level: float = 2.0
    answer_ahead: bool = True
    answer_threads: bool = True

    def __post_init__(self) -> None:
        for name, lowest in (("iterations", 0), ("patience", 1), ("resolution", 16)):
            check_integer(f"--{name}", getattr(self, name), lowest)
        if not (is_finite_number(self.answer_top_level) and 0 <= self.answer_top_level <= 1e6):
            raise InputError("must be a number in [0, 1000000]", field="answer_top_level", value=self.answer_top_level)
        for name in ("answer_ahead", "answer_threads"):
            if not isinstance(getattr(self, name), bool):
                raise InputError("must be true or false", field=name, value=getattr(self, name))


@dataclass
class ReconstructResult:
    """What :func:`reconstruct` made.

    model : the mesh of the best iteration, the one with the lowest E_I, at the answer
        (:func:`_answer_model`; reference frame of (depth, tilt)); carved : the iteration-0 mesh
    depth (m), tilt (rad) : the best iteration's estimate; best_iteration : its number
    iterations : pose + shape iterations of the loop (the history's last entry, ``"answer"``,
        is the kept model refined at the answer, one more)
    stopped : whether the stopping rule ended it (not the iteration limit)
    converged : stopped, and the posterior identified both D and β
    history : one dict per iteration run (0 = the carved model), the keys of DESIGN §12
    seconds : wall time; backend, device : where the kernels ran
    pose_steps : the PoseResult of every pose step (grid levels, for figures)
    posterior : the fsswarp.pose.Posterior of (depth, tilt): the sensors and the surface's height
    start : (depth m, tilt rad) the loop started from; truth : (depth, tilt) or None
    """

    model: object
    carved: object
    depth: float
    tilt: float
    best_iteration: int
    iterations: int
    stopped: bool
    converged: bool
    history: list[dict]
    seconds: float
    backend: str
    device: str
    pose_steps: list = field(default_factory=list)
    posterior: object = None
    start: tuple[float, float] = (math.nan, math.nan)
    truth: tuple[float, float] | None = None

    def summary(self) -> dict:
        """``result.json`` (DESIGN §12)."""
        def point(depth: float, tilt: float) -> dict:
            return {"depth_m": depth, "tilt_deg": math.degrees(tilt)}

        error = None if self.truth is None else {"depth_m": self.depth - self.truth[0],
                                                 "tilt_deg": math.degrees(self.tilt) - math.degrees(self.truth[1])}
        return {"depth_m": self.depth, "tilt_deg": math.degrees(self.tilt), **self.posterior.summary(),
                "start": point(*self.start), "error_vs_truth": error, "best_iteration": self.best_iteration,
                "iterations": self.iterations, "converged": self.converged, "backend": self.backend,
                "device": self.device, "seconds": self.seconds, "history": self.history}


def reconstruct(dataset, *, depth0: float | None = None, tilt0: float | None = None,
                settings: ReconstructSettings = ReconstructSettings(), backend=None,
                progress: Callable[[str], None] | None = None) -> ReconstructResult:
    """Run the loop of the module docstring on ``dataset`` from (D0, β0).

    depth0 (m), tilt0 (rad) : the start; default the dataset's measured values; a start that
        ``fsswarp.pose.check_start`` refuses is an InputError
    progress : called with one line per stage (``fsswarp reconstruct`` prints them)."""
    from .backends import get_backend

    if dataset.manifest.deep_water:  # no sea surface in view: the loop without its pose step (end of module)
        return reconstruct_shape_only(dataset, depth0=depth0, tilt0=tilt0, settings=settings, backend=backend,
                                      progress=progress)
    surface = dataset.manifest.surface
    depth = surface.depth if depth0 is None else depth0
    tilt = surface.tilt if tilt0 is None else tilt0
    check_depth_tilt(depth, tilt)
    start_pose = (depth, tilt)
    prior = Prior.of(dataset)
    check_start(dataset, depth, tilt)
    check_uncertainties(dataset, depth)  # the pose steps' grids, before the carving
    backend = backend or get_backend()
    say = progress or (lambda line: None)
    start = time.perf_counter()
    # on a many-core host: ready when the loop needs a carving ahead (None: no mesh processes)
    meshing = start_mesh_workers() if settings.iterations else None
    comparison, shaping = _comparisons(dataset, settings, backend)
    truth_pose = None if dataset.manifest.truth is None else (dataset.manifest.truth.depth,
                                                              dataset.manifest.truth.tilt)
    with _TruthMetrics(dataset.truth_mesh(), say, backend) as truth, contextlib.ExitStack() as closing:
        given = "given" if depth0 is not None or tilt0 is not None else "measured"
        say(f"iteration 0: carving at the {given} D0 = {depth:.4f} m, tilt0 = {math.degrees(tilt):.3f} deg")
        carvings = {}  # each pose is carved once (_carving)
        carved = _carving(dataset, depth, tilt, settings, backend, carvings)
        kept = carved  # the model of the best iteration
        first = _complete(_record(0, kept, dataset, depth, tilt, settings, comparison, None), comparison, kept, depth,
                          tilt, truth)
        working = carved  # the model gone on with
        carved_at, sighting = (depth, tilt), carved  # the pose steps' model: the last carving, unrefined
        if settings.iterations:
            working = refine_shape(carved, dataset, depth, tilt, settings=settings.refine, comparison=shaping).mesh
        history = [first]
        say(_line(first))
        best, best_pose, misses, stopped = first, (depth, tilt), 0, False
        pose_steps, asked = [], (None,)  # asked: the last pose step's model and start
        ahead = None  # the answer's pose, worked out in a thread once the pose is settled
        for iteration in range(1, settings.iterations + 1):
            if asked[0] is sighting and asked[1:] == (depth, tilt):
                pose = pose_steps[-1]  # the same model from the same start: the step would repeat itself
                say(f"iteration {iteration}: the pose step's model and start are iteration {iteration - 1}'s; its "
                    "step stands")
            else:
                pose = estimate_pose(sighting, dataset, depth0=depth, tilt0=tilt, comparison=comparison, prior=prior,
                                     posterior_axes=_posterior_axes(pose_steps))
                asked = (sighting, depth, tilt)
            pose_steps.append(pose)
            say(f"iteration {iteration}: pose step {_intervals(pose.depth, pose.tilt, pose.posterior)}")
            if pose.accepted:
                trials = [(pose.depth, pose.tilt), (depth, tilt)]
            else:
                trials = [(depth, tilt)]
                say(f"iteration {iteration}: the pose step found no (D, tilt) with a lower posterior cost; D and tilt "
                    "stay")
                if meshing is not None:  # the answer starts from the best pose's carving: meshed meanwhile
                    _carve_ahead(dataset, *best_pose, settings, backend, carvings)
                if settings.answer_ahead and ahead is None:  # the pose stays from here on (_AnswerAhead)
                    ahead = closing.enter_context(_AnswerAhead(dataset, best_pose, prior, settings, backend,
                                                               carvings))
            for depth_tried, tilt_tried in trials:
                recarve = (depth_tried, tilt_tried) != (depth, tilt) and _outside(carved_at, pose.posterior)
                if recarve:  # its mesh is made while the model is refined
                    _carve_ahead(dataset, depth_tried, tilt_tried, settings, backend, carvings)
                trial = refine_shape(working, dataset, depth_tried, tilt_tried, settings=settings.refine,
                                     comparison=shaping).mesh
                entry = _record(iteration, trial, dataset, depth_tried, tilt_tried, settings, comparison, first)
                entry["recarved"] = False
                if recarve:
                    carved_at = (depth_tried, tilt_tried)  # again only once the pose moves far from here
                    sighting = _carving(dataset, *carved_at, settings, backend, carvings)
                    trial, entry = _recarved(sighting, trial, entry, iteration, dataset, depth_tried, tilt_tried,
                                             settings, comparison, shaping, first, say,
                                             f"iteration {iteration}: the model was carved outside the new 95% "
                                             "intervals")
                improved = entry["E_I"] < best["E_I"]
                if improved:
                    break
                say(f"iteration {iteration}: E_I {entry['E_I']:.3f} at D {depth_tried:.4f} m, tilt "
                    f"{math.degrees(tilt_tried):.3f} deg is not below iteration {best['iteration']}'s "
                    f"{best['E_I']:.3f}")
            # without improvement the last trial was at the current (D, β)
            if not improved and np.array_equal(trial.vertices, working.vertices):
                say(f"iteration {iteration}: the shape step left the model as it was (every update refused), so "
                    f"the next iterations would repeat this one; keeping iteration {best['iteration']} and stopping")
                stopped = True
                break
            working, depth, tilt = trial, depth_tried, tilt_tried
            entry.update(_interval_fields(pose.posterior))
            history.append(_complete(entry, comparison, trial, depth, tilt, truth))
            say(_line(history[-1]))
            truth.collect(wait=False)
            if improved:
                best, best_pose, kept, misses = history[-1], (depth, tilt), trial, 0
                continue
            misses += 1
            if _out_of_patience(misses, settings, best, iteration, say):
                stopped = True
                break
        if ahead is not None and ahead.pose == best_pose:
            posterior = ahead.result(say)
        elif settings.iterations:
            posterior = _answer_pose(dataset, comparison, shaping, best_pose, prior, settings, say, carvings)
        else:
            posterior = _carving_posterior(comparison, carved, best_pose, prior)
        answer = (posterior.depth, posterior.tilt)
        say(f"the answer: {_intervals(*answer, posterior)}")
        ran = len(history) - 1
        if answer != best_pose:  # the kept shape, refined at the answer
            kept, entry = _answer_model(kept, dataset, answer, len(history), settings, comparison, shaping, first, say,
                                        carvings)
            history.append(_complete(dict(entry, answer=True, **_interval_fields(posterior)), comparison, kept,
                                     *answer, truth))
            best = history[-1]
            say(_line(best))
        truth.collect(wait=True)
        identified = posterior.identified()
        return ReconstructResult(model=kept, carved=carved, depth=answer[0], tilt=answer[1],
                                 best_iteration=best["iteration"], iterations=ran, stopped=stopped,
                                 converged=stopped and all(identified.values()), history=history,
                                 seconds=time.perf_counter() - start, backend=backend.name, device=backend.device,
                                 pose_steps=pose_steps, posterior=posterior, start=start_pose, truth=truth_pose)


def _comparisons(dataset, settings: ReconstructSettings, backend) -> tuple[ViewComparison, ViewComparison]:
    """(comparison, shaping): the ViewComparison of E_I, E_mu and the pose steps, and the shape
    steps' (the same one unless ``settings.refine.pose`` differs from ``settings.pose``)."""
    comparison = ViewComparison(dataset, settings=settings.pose, backend=backend)
    shaping = comparison if settings.refine.pose == settings.pose else \
        ViewComparison(dataset, settings=settings.refine.pose, backend=backend)
    return comparison, shaping


def _answer_model(kept, dataset, answer: tuple[float, float], iteration: int, settings: ReconstructSettings,
                  comparison: ViewComparison, shaping: ViewComparison, first: dict, say, carvings: dict | None = None):
    """(model, its history entry) at the ``answer`` (depth m, tilt rad), the lowest E_I of three
    models refined there: ``kept``; ``kept`` held to the views carved there
    (``fsswarp.carving.held``: the voxels of that carving inside it, and those that no view sees
    past it: what the views see empty at the answer is empty, what they cannot see follows the
    carving); and that carving (as :func:`_recarved` in the loop; ``recarved`` tells whether it
    won). Measured (docs/experiments.md): a shape carved at a wrong tilt does not become right by
    refining (coral-two carved 2° off: E_V 0.57 refined, 0.25 held to the carving at the answer),
    and where it lost truth that no view sees, holding it to the voxels inside alone kept the
    loss (coral-one 2° off: E_V 0.355, 0.305 with the unseen voxels). Here refinement takes the
    double-bounce votes of ``settings.answer_top_level``. With ``settings.answer_threads``, on a
    GPU (:func:`_threads_pay`), the kept model is refined in this thread and the others each in a
    thread with comparisons of its own (``_comparisons``): the same models, entries and lines."""
    settings = dataclasses.replace(settings, refine=dataclasses.replace(settings.refine,
                                                                        top_level=settings.answer_top_level))
    backend = shaping.backend
    carving = _carve_voxels(dataset, *answer, settings, backend, carvings)  # its mesh made meanwhile
    rotations, translations = (a[[dataset.rig.index(n) for n in carving.views]]
                               for a in dataset.rig.relative_poses(*answer))
    holding = held(carving.voxels, kept, rotations, translations, dataset.sonar, backend)
    starts = {"the kept model": lambda: kept}
    if holding.kept:  # else no carved voxel lies inside the kept model; its mesh is made while kept is refined
        starts["the kept model held to the carving there"] = MeshJob(holding, smooth=settings.carve.smooth,
                                                                     faces=settings.carve.faces).result
    starts["the carving"] = lambda: _carving(dataset, *answer, settings, backend, carvings)

    def refined(start, comparisons: tuple[ViewComparison, ViewComparison]):
        trial = refine_shape(start(), dataset, *answer, settings=settings.refine, comparison=comparisons[1]).mesh
        return trial, _record(iteration, trial, dataset, *answer, settings, comparisons[0], first)

    names, makers = list(starts), list(starts.values())
    if settings.answer_threads and _threads_pay(backend):
        with ThreadPoolExecutor(len(makers) - 1, thread_name_prefix="fsswarp-answer-model") as pool:
            later = [pool.submit(refined, make, _comparisons(dataset, settings, backend)) for make in makers[1:]]
            outcomes = [refined(makers[0], (comparison, shaping))] + [future.result() for future in later]
    else:
        outcomes = [refined(make, (comparison, shaping)) for make in makers]
    (fresh, again), candidates = outcomes[-1], outcomes[:-1]
    said = [f"{name} E_I {entry['E_I']:.3f}" for name, (_, entry) in zip(names, candidates)]
    say(f"the answer: refined there, {', '.join(said)}")
    best = min(range(len(candidates)), key=lambda k: candidates[k][1]["E_I"])  # the first of equals
    model, entry = candidates[best][0], dict(candidates[best][1], recarved=False)
    return _better_of(model, entry, fresh, again, *answer, comparison, say, f"the answer: {names[best]}, refined there")


def _threads_pay(backend) -> bool:
    """Whether shape steps side by side in threads pay on ``backend``: on a GPU, where much of
    the host's work waits for the device; on a CPU device the kernels keep every core busy
    already (the answer's models in threads: PoCL here 1.08 times slower, bench/notes.md)."""
    return bool(backend.is_gpu)


def _out_of_patience(misses: int, settings: ReconstructSettings, best: dict, iteration: int, say) -> bool:
    """Whether ``misses`` iterations in a row without a new lowest E_I reach the patience (said)."""
    if misses < settings.patience:
        return False
    say(f"iteration {iteration}: E_I has not fallen for {misses} iteration{'s' * (misses > 1)}; keeping iteration "
        f"{best['iteration']} and stopping")
    return True


def sighting(dataset, depth: float, tilt: float, settings: ReconstructSettings, shaping: ViewComparison,
             carvings: dict | None = None):
    """The model the answer's pose steps see at (depth m, tilt rad): the views carved there and
    refined there by one shape step (``settings.refine``). Measured (docs/experiments.md): with
    the carving alone the pose step lay +0.14…+0.24° off on the corals when carved at the
    truth; refined, within 0.12°, and it followed a carving 0.6° off less (0.22–0.26 against
    0.11–0.48 deg/deg). ``carvings``: as :func:`_carve`'s."""
    return refine_shape(_carving(dataset, depth, tilt, settings, shaping.backend, carvings), dataset, depth, tilt,
                        settings=settings.refine, comparison=shaping).mesh


def carving_descent(dataset, comparison: ViewComparison, depth: float, tilt: float, settings: ReconstructSettings,
                    say, carvings: dict | None = None) -> float:
    """The tilt (rad), from ``tilt`` in steps of ``DESCENT_STEP`` (``DESCENT_STEPS`` at most),
    while the views carved at (``depth`` m, that tilt) agree better with themselves: E_mu of the
    carving at its own pose falls (a carving at a wrong tilt is inconsistent with the views
    that made it, which a refined shape hides). A pose where every voxel is carved away or no
    E_mu exists counts as no better. Measured: sharp near the truth (coral-one 7.9 mm there,
    13–20 mm at ±0.5°), not over degrees (docs/experiments.md), hence a local descent."""
    def error(at: float) -> float:
        try:
            carved = _carving(dataset, depth, at, settings, comparison.backend, carvings)
        except InputError:  # every voxel carved away: the views disagree there
            return math.inf
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PoseWarning)  # views without a contour are left out
            comparison.use(carved, depth, at)
        value = comparison.exact(depth, at).value
        return value if math.isfinite(value) else math.inf

    for at in (tilt, tilt - DESCENT_STEP, tilt + DESCENT_STEP):  # their meshes made side by side
        _carve_ahead(dataset, depth, at, settings, comparison.backend, carvings)
    here = error(tilt)
    errors = {sign: error(tilt + sign * DESCENT_STEP) for sign in (-1, 1)}
    sign = min(errors, key=errors.get)
    steps, best = 0, tilt
    while errors[sign] < here and steps < DESCENT_STEPS:
        steps, best, here = steps + 1, best + sign * DESCENT_STEP, errors[sign]
        errors[sign] = error(best + sign * DESCENT_STEP)
    say(f"the answer: carvings at D {depth:.4f} m agree best with the views at tilt {math.degrees(best):.3f} deg "
        f"(E_mu {here * 1000:.2f} mm; {steps} step{'s' * (steps != 1)} of {math.degrees(DESCENT_STEP):g} deg from "
        f"{math.degrees(tilt):.3f} deg)")
    return best


def _answer_pose(dataset, comparison: ViewComparison, shaping: ViewComparison, pose: tuple[float, float],
                 prior: Prior, settings: ReconstructSettings, say, carvings: dict | None = None):
    """The answer's Posterior from the best ``pose`` (m, rad): :func:`_valley_answer` there,
    its tilt checked by :func:`carving_descent`, and the valley answer again from a tilt whose
    carving agrees better with the views."""
    heights = []  # the surface's height above every model made for the answer
    posterior = _valley_answer(dataset, comparison, shaping, pose, prior, settings, say, heights, carvings)
    tilt = carving_descent(dataset, comparison, posterior.depth, posterior.tilt, settings, say, carvings)
    if tilt != posterior.tilt:  # a carving there agrees better with the views: start again from it
        posterior = _valley_answer(dataset, comparison, shaping, (posterior.depth, tilt), prior, settings, say,
                                   heights, carvings)
    return posterior


class _AnswerAhead:
    """:func:`_answer_pose` from ``pose`` (m, rad) in a thread of its own, with comparisons of its
    own, while the loop goes on: once a pose step proposes nothing better, the pose and the
    best pose stay for the rest of the loop (a shape step at the same pose moves neither), and
    the answer's pose depends on nothing else, so it is the answer the loop's end would find.
    Its progress lines are kept and said by :meth:`result`, where the loop's end would say them.
    Leaving it (a context manager) stops the thread at its next line and waits for it.
    Measured: docs/decisions.md, "Threads"."""

    def __init__(self, dataset, pose: tuple[float, float], prior: Prior, settings: ReconstructSettings, backend,
                 carvings: dict | None):
        self.pose, self._lines, self._stop = pose, [], threading.Event()
        self._outcome: list = []  # (posterior, None) or (None, the exception)
        self._thread = threading.Thread(target=self._run, args=(dataset, prior, settings, backend, carvings),
                                        name="fsswarp-answer")
        self._thread.start()

    def _run(self, dataset, prior, settings, backend, carvings) -> None:
        try:
            comparison, shaping = _comparisons(dataset, settings, backend)
            self._outcome.append((_answer_pose(dataset, comparison, shaping, self.pose, prior, settings, self._say,
                                               carvings), None))
        except BaseException as error:  # noqa: BLE001 - raised by result(), in the loop's thread
            self._outcome.append((None, error))

    def _say(self, line: str) -> None:
        if self._stop.is_set():
            raise _Stopped
        self._lines.append(line)

    def result(self, say):
        """The Posterior (or the exception it raised), once the thread ends; its lines said first."""
        self._thread.join()
        posterior, error = self._outcome[0]
        for line in self._lines:
            say(line)
        if error is not None:
            raise error
        return posterior

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


class _Stopped(Exception):
    """Ends an :class:`_AnswerAhead` whose loop has ended without it."""


def _valley_answer(dataset, comparison: ViewComparison, shaping: ViewComparison, pose: tuple[float, float],
                   prior: Prior, settings: ReconstructSettings, say, heights: list, carvings: dict | None = None):
    """The answer's Posterior (``fsswarp.pose.valley_posterior``: the data keep only the
    surface's height above the object, the sensors the rest): from ``pose`` (m, rad) take the
    :func:`sighting` model there, its pose step's posterior about its proposal (the least
    posterior cost, kept even where greedy acceptance refuses it) and the valley posterior; while
    its mean lies more than half a posterior σ from where the model was made, make it there
    again (``FIXED_POINT_STEPS`` at most). ``heights`` (m), the heights above the models made
    for this answer so far, gains each model's; their sample variance counts as a further error
    of the height (``unsettled``): a shape that follows its making leaves the height uncertain
    by as much (the table's drifted 78 → 93 mm over five models, docs/experiments.md)."""
    at = np.array(pose, np.float64)
    for _ in range(FIXED_POINT_STEPS + 1):
        model = sighting(dataset, float(at[0]), float(at[1]), settings, shaping, carvings)
        step = estimate_pose(model, dataset, depth0=float(at[0]), tilt0=float(at[1]), comparison=comparison,
                             prior=prior)
        conditional = dataclasses.replace(step.posterior, depth=step.candidate[0], tilt=step.candidate[1])
        lever = model_lever(model, dataset.rig, *at)
        posterior = valley_posterior(conditional, lever)
        heights.append(posterior.valley_depth - lever * posterior.tilt)
        mean = np.array([posterior.depth, posterior.tilt])
        say(f"the answer: made at D {at[0]:.4f} m, tilt {math.degrees(at[1]):.3f} deg, the surface's height fixed at "
            f"{heights[-1]:.4f} m + {lever * math.pi / 180 * 100:.2f} cm/deg: D {mean[0]:.4f} m, tilt "
            f"{math.degrees(mean[1]):.3f} deg")
        if np.all(np.abs(mean - at) <= 0.5 * np.sqrt(np.diag(posterior.covariance))):
            break
        at = mean
    if len(heights) < 2:
        return posterior
    return valley_posterior(conditional, lever, unsettled=float(np.var(heights, ddof=1)))


def _carving_posterior(comparison: ViewComparison, carved, pose: tuple[float, float], prior: Prior):
    """Without loop iterations (``--iterations 0``: carving alone) no answer step runs: the
    Posterior at the sensors' ``pose`` (m, rad) with the ``carved`` model, its first grid ±
    ``BOUNDS_FACTOR`` prior σ."""
    comparison.use(carved, *pose)
    return fit_posterior(comparison, prior, *pose, np.diag([BOUNDS_FACTOR * prior.depth_sigma,
                                                            BOUNDS_FACTOR * prior.tilt_sigma]))


def _carving(dataset, depth: float, tilt: float, settings: ReconstructSettings, backend, carvings: dict | None = None):
    """The mesh of :func:`_carve`."""
    return _carve(dataset, depth, tilt, settings, backend, carvings).mesh


def _carve(dataset, depth: float, tilt: float, settings: ReconstructSettings, backend, carvings: dict | None = None):
    """The CarveResult of the views carved at (depth m, tilt rad) at ``settings``' resolution.
    ``carvings``, a reconstruction's (depth, tilt) -> CarveResult or _Ahead: a pose carved
    already is not carved again (a carving depends on nothing else; the answer carves some poses
    twice), and one started by :func:`_carve_ahead` is finished (or raises its InputError)."""
    key = (float(depth), float(tilt))
    if carvings is not None and key in carvings:
        if isinstance(carvings[key], _Ahead):
            carvings[key] = carvings[key].result()
        return carvings[key]
    result = carve(dataset, depth, tilt, resolution=settings.resolution, settings=settings.carve, backend=backend)
    if carvings is not None:
        carvings[key] = result
    return result


def _carve_voxels(dataset, depth: float, tilt: float, settings: ReconstructSettings, backend,
                  carvings: dict | None):
    """The CarveResult at (depth m, tilt rad) for its voxels and views, its mesh, where mesh
    processes run, still being made (:func:`_carve_ahead`; :func:`_carve` finishes it)."""
    _carve_ahead(dataset, depth, tilt, settings, backend, carvings)
    pending = None if carvings is None else carvings.get((float(depth), float(tilt)))
    if isinstance(pending, _Ahead) and pending.error is None:
        return pending.carving
    return _carve(dataset, depth, tilt, settings, backend, carvings)


def _carve_ahead(dataset, depth: float, tilt: float, settings: ReconstructSettings, backend,
                 carvings: dict | None) -> None:
    """Start the carving at (depth m, tilt rad) that a later :func:`_carve` with ``carvings``
    will ask for: the voxels now, the mesh in a mesh process while the caller goes on
    (``fsswarp.carving.MeshJob``; without mesh processes, at that ``_carve``). Nothing where
    ``carvings`` is None or holds the pose."""
    key = (float(depth), float(tilt))
    if carvings is None or key in carvings:
        return
    try:
        result = carve(dataset, depth, tilt, resolution=settings.resolution, settings=settings.carve,
                       backend=backend, mesh=False)
    except InputError as error:  # raised by the _carve that asks for it
        carvings[key] = _Ahead(None, None, error)
        return
    carvings[key] = _Ahead(result, MeshJob(result.voxels, smooth=settings.carve.smooth, faces=settings.carve.faces))


@dataclass(frozen=True)
class _Ahead:
    """A carving started by :func:`_carve_ahead`: its CarveResult without the mesh and the
    mesh's job, or the InputError that carving raised."""

    carving: object
    job: MeshJob | None
    error: InputError | None = None

    def result(self):
        """The CarveResult, its mesh filled in; raises the carving's InputError."""
        if self.error is not None:
            raise self.error
        self.carving.mesh = self.job.result()
        return self.carving


def _posterior_axes(steps: list):
    """The last pose step's posterior axes (``Posterior.axes``), the loop's next step's first
    posterior grid: the posterior moves little from one step to the next, so that grid mostly
    fits at once; None without steps or where those axes span no area."""
    if not steps:
        return None
    axes = steps[-1].posterior.axes()
    return axes if spans_an_area(axes) else None


def _outside(pose: tuple[float, float], posterior) -> bool:
    """Whether (depth m, tilt rad) lies outside either 95% interval of ``posterior``."""
    return any(not lo <= value <= hi for value, (lo, hi) in zip(pose, (posterior.interval(0), posterior.interval(1))))


def _recarved(carved, trial, entry: dict, iteration: int, dataset, depth: float, tilt: float,
              settings: ReconstructSettings, comparison: ViewComparison, shaping: ViewComparison, first: dict, say,
              why: str):
    """The better, by E_I, of (``trial``, ``entry``) and ``carved``, carved afresh at (depth m,
    tilt rad), refined there (:func:`_better_of`)."""
    fresh = refine_shape(carved, dataset, depth, tilt, settings=settings.refine, comparison=shaping).mesh
    again = _record(iteration, fresh, dataset, depth, tilt, settings, comparison, first)
    return _better_of(trial, entry, fresh, again, depth, tilt, comparison, say, why)


def _better_of(trial, entry: dict, fresh, again: dict, depth: float, tilt: float, comparison: ViewComparison, say,
               why: str):
    """(model, its entry, ``recarved`` set): ``fresh``, the fresh carving refined at (depth m,
    tilt rad), with its entry ``again`` where its E_I is lower, else (``trial``, ``entry``);
    ``comparison`` is left on that model, and ``why`` opens the line said."""
    say(f"{why}; carved again at D {depth:.4f} m, tilt {math.degrees(tilt):.3f} deg: E_I {again['E_I']:.3f} against "
        f"{entry['E_I']:.3f} for the moved model")
    if again["E_I"] < entry["E_I"]:
        comparison.use(fresh, depth, tilt)  # where another thread's comparison recorded it
        return fresh, dict(again, recarved=True)
    comparison.use(trial, depth, tilt)  # _record left it on the fresh model
    return trial, entry


def _interval_fields(posterior) -> dict:
    """A history entry's ``depth_interval_m`` and ``tilt_interval_deg`` from ``posterior``."""
    fields = posterior.summary()
    return {key: fields[key] for key in ("depth_interval_m", "tilt_interval_deg")}


def _intervals(depth: float, tilt: float, posterior) -> str:
    (d0, d1), (t0, t1) = posterior.interval(0), posterior.interval(1)
    return (f"D {depth:.4f} m (95%: {d0:.4f}-{d1:.4f}), tilt {math.degrees(tilt):.2f} deg (95%: "
            f"{math.degrees(t0):.2f}-{math.degrees(t1):.2f})")


def image_errors(model, dataset, depth: float, tilt: float, *, settings: ReconstructSettings = ReconstructSettings(),
                 backend=None) -> dict:
    """AIE and ACE (paper eq. 8–9, as the module docstring defines them) of ``model`` at
    (depth, tilt) over the dataset's optimized views: {"AIE", "ACE", "views": {name: {"CE"}}}."""
    comparison = ViewComparison(dataset, settings=settings.pose, backend=backend)
    return _image_errors(model, dataset, depth, tilt, settings, comparison)


def _image_errors(model, dataset, depth: float, tilt: float, settings: ReconstructSettings,
                  comparison: ViewComparison) -> dict:
    """:func:`image_errors`' dict, with ``comparison`` put to ``model`` at (depth, tilt) (kept
    where it is there already), whose contours give CE; E_mu and the next pose step go on with it."""
    names = [v.name for v in dataset.rig.views if v.optimize]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoseWarning)  # a view without the model gets no CE
        comparison.use(model, depth, tilt)
    views = _synthetic_views(model, dataset, depth, tilt, names, settings, comparison)
    synthetic, data, regions = [], [], []
    for name in names:
        obj, ghost, mirror, mirror2, total = views[name]
        region = (obj > 0.01 * max(float(obj.max()), 1e-30)) & (ghost + mirror + mirror2 < 0.1 * obj)
        image = dataset.images[name].astype(np.float64)
        if region.any():
            synthetic.append(total / total[region].mean())
            data.append(image / max(image[region].mean(), 1e-30))
            regions.append(region)
    aie = average_intensity_error(np.stack(synthetic), np.stack(data), np.stack(regions)) if regions else math.nan
    seen = dict(zip(comparison.data.names, comparison.contour_errors(depth, tilt)))
    errors = np.array([seen.get(name, math.nan) for name in names])
    return {"AIE": aie, "ACE": average_contour_error(errors),
            "views": {name: {"CE": float(ce)} for name, ce in zip(names, errors)}}


def _synthetic_views(model, dataset, depth: float, tilt: float, names, settings: ReconstructSettings,
                     comparison: ViewComparison) -> dict[str, np.ndarray]:
    """{view name: (5, bins, beams) float32} of ``render`` at ``settings.render`` for the views
    ``names``: the layers ``comparison`` rendered when it was located at (depth, tilt) with the
    same samples, γ and surface reflection (the same launch, so the same pixels; their total
    by ``with_total``, as ``render``'s), and a render of the other views (those where it saw
    no model)."""
    views = {}
    if comparison.estimate == (float(depth), float(tilt)) and settings.render == comparison.prediction_settings:
        views.update(zip(comparison.data.names, with_total(comparison.predicted)))
    rest = [name for name in names if name not in views]
    if rest:
        views.update(render(model, dataset.sonar, dataset.rig, depth, tilt, views=rest, settings=settings.render,
                            backend=comparison.backend))
    return views


def _record(iteration: int, model, dataset, depth: float, tilt: float, settings: ReconstructSettings,
            comparison: ViewComparison, first: dict | None) -> dict:
    """What decides whether a trial is kept: AIE, ACE and E_I (relative to ``first``), with
    ``comparison`` left on the trial's model at (depth, tilt) for its E_mu."""
    images = _image_errors(model, dataset, depth, tilt, settings, comparison)
    entry = {"iteration": iteration, "depth_m": depth, "tilt_deg": math.degrees(tilt),
             "AIE": images["AIE"], "ACE": images["ACE"]}
    base = first or entry
    entry["E_I"] = image_error(entry["AIE"], entry["ACE"], base["AIE"], base["ACE"])
    return entry


def _complete(entry: dict, comparison: ViewComparison, model, depth: float, tilt: float, truth) -> dict:
    """The history entry (DESIGN §12's keys) of a kept trial at (depth m, tilt rad): ``entry``
    with E_mu (``comparison`` on ``model`` there, as _record left it); ``truth``
    (_TruthMetrics) adds E_V, Chamfer and F-score later. Only kept trials pay for these."""
    done = {key: entry[key] for key in ("iteration", "depth_m", "tilt_deg")}
    done["E_mu"] = comparison.use(model, depth, tilt).exact(depth, tilt).value
    done.update((key, entry[key]) for key in ("depth_interval_m", "tilt_interval_deg", "recarved", "answer",
                                              "AIE", "ACE", "E_I") if key in entry)
    truth.submit(done, model)
    return done


#: Truth-metric worker processes: the volumes of a compare take ~0.15 s of a GPU host's CPU, and
#: one process kept up with coral-one's loop there, where four made the loop 0.6–1.2 s slower
#: (docs/decisions.md, "Truth metrics").
TRUTH_WORKERS = 1


class _TruthMetrics:
    """E_V, Chamfer and F-score of recorded models against the truth mesh (None: no truth, and
    nothing to do), made while the loop goes on. The surface distances (``fsswarp.metrics``'
    20,000 seeded points each way) come from ``backend``'s exact search
    (``Backend.surface_distances``), one model after another in a thread of their own: ~30 ms a
    model on an H200's host and ~95 ms on PoCL here, against ~0.5 s of a CPU for NumPy's search,
    which as the loop's truth work held coral-one's loop up to 1.8 s on an H200
    (docs/decisions.md, "Truth metrics").
    The volumes (mesh booleans) and, without a backend with float64, the distances too, come
    from worker processes (``fsswarp.processes``; each job gets both meshes,
    ``fsswarp.metrics.compare_meshes``): in a thread of the loop's process they held the GIL
    against it (bench/notes.md). ``workers`` processes (default ``TRUTH_WORKERS``) start at
    once. Where processes cannot start, or one dies (killed, out of memory), one line said and
    each job from then on is made in this process, when collected. The values do not depend on
    where they are made (the backend's distances agree with NumPy's to ~1e-11 relative).
    ``collect`` writes them into the history entries, in order, and reports each with ``say``.
    A context manager: leaving it stops the processes."""

    def __init__(self, mesh, say: Callable[[str], None], backend=None, workers: int | None = None):
        from .processes import WorkerProcesses

        self.mesh, self.say, self.processes, self.searching = mesh, say, None, None
        self.backend = backend if backend is not None and backend.has_float64 else None
        self.workers = TRUTH_WORKERS if workers is None else workers
        self.pending = []  # (history entry, the model's (vertices, faces), distances' future or None, pool, future)
        if mesh is not None:
            self.truth = (np.asarray(mesh.vertices), np.asarray(mesh.faces))
            if self.backend is not None:  # the searches, in turn, in a thread of their own
                self.searching = ThreadPoolExecutor(1, thread_name_prefix="fsswarp-truth")
                self.truth_side = self.searching.submit(self._truth_side)
            try:
                self.processes = WorkerProcesses(self.workers, lost=self._lost)
            except OSError as error:
                say(f"truth metrics: worker processes could not start ({error}); computing them in this process")

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        if self.searching is not None:
            self.searching.shutdown(cancel_futures=True)
        if self.processes is not None:
            self.processes.close()

    def _truth_side(self):
        """The truth's exact-search handle and its seeded surface points (the searches' thread)."""
        return self.backend.load_mesh(*self.truth, exact=True), surface_points(_mesh(*self.truth), SAMPLES, [0, 1])

    def _distances(self, estimate: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """(truth → estimate, estimate → truth) surface distances on the backend, for the
        estimate's (vertices, faces) (the searches' thread: meshes of its own, no cache shared)."""
        truth_handle, truth_points = self.truth_side.result()
        handle = self.backend.load_mesh(*estimate, exact=True)
        return (self.backend.surface_distances(truth_handle, surface_points(_mesh(*estimate), SAMPLES, [0, 0])),
                self.backend.surface_distances(handle, truth_points))

    def submit(self, entry: dict, model) -> None:
        """Start the compare of ``model`` against the truth, for ``entry``: its distances on the
        backend in the searches' thread, the rest in a process (without processes, when collected)."""
        if self.mesh is None:
            return
        estimate, processes = (np.asarray(model.vertices), np.asarray(model.faces)), self.processes
        distances = None
        if self.searching is not None:
            require_triangles("estimate", model)
            distances = self.searching.submit(self._distances, estimate)
        future = None if processes is None else processes.submit(compare_meshes, estimate, self.truth,
                                                                 distances=distances is None)
        self.pending.append((entry, estimate, distances, processes, future))

    def _lost(self) -> None:
        """A worker process died (``WorkerProcesses``' ``lost``): one line said, and every compare
        from now on made here."""
        self.say("truth metrics: a worker process ended unexpectedly; computing them in this process")
        self.processes = None

    def collect(self, *, wait: bool) -> None:
        """Fill in the finished entries (all of them, waiting, with ``wait``)."""
        while self.pending and (wait or all(_collectable(self.pending[0][k]) for k in (2, 4))):
            entry, estimate, distances, processes, future = self.pending.pop(0)
            outcome = None if future is None else processes.outcome(future)
            if outcome is None:  # no processes, or one died: made here
                outcome = compare_meshes(estimate, self.truth, distances=distances is None)
            volume, made = outcome
            metrics = combine(self.mesh, volume, *(distances.result() if distances is not None else made))
            entry.update(E_V=metrics["E_V"], chamfer_m=metrics["chamfer_m"], fscore=metrics["fscore"])
            self.say(f"iteration {entry['iteration']} against the truth: E_V {entry['E_V']:.3f}, Chamfer "
                     f"{entry['chamfer_m'] * 1e3:.2f} mm, F {entry['fscore']:.3f}")


def _mesh(vertices: np.ndarray, faces: np.ndarray):
    """A trimesh of (vertices, faces), as given."""
    import trimesh

    return trimesh.Trimesh(vertices, faces, process=False)


def _collectable(future) -> bool:
    """Whether a part of a truth compare (``_TruthMetrics.pending``: its distances' or its
    process's future) can be collected without waiting: done, or none (made elsewhere or here)."""
    return future is None or future.done()


def _line(entry: dict) -> str:
    return (f"iteration {entry['iteration']}: D {entry['depth_m']:.4f} m, tilt {entry['tilt_deg']:.3f} deg, "
            f"E_mu {entry['E_mu'] * 1e3:.2f} mm, AIE {entry['AIE']:.3f}, ACE {entry['ACE'] * 1e3:.2f} mm, "
            f"E_I {entry['E_I']:.3f}")


# --- deep water: no sea surface in view --------------------------------------------------------

#: result.json's ``pose_step`` for a dataset without a sea surface (deep water).
NO_POSE_STEP = "skipped: no sea surface in the dataset"


@dataclass
class ShapeOnlyResult(ReconstructResult):
    """What :func:`reconstruct_shape_only` made: ``depth`` and ``tilt`` are the (D m, β rad)
    its views were synthesized at (``fsswarp.dataset.deep_water_pose``), ``known`` the
    manifest's known [rig] depth (m) and tilt (rad), which ``summary`` reports."""

    known: tuple[float, float] = (math.nan, math.nan)

    def summary(self) -> dict:
        """``result.json`` of a deep-water dataset: no surface, no pose step (docs/formats.md)."""
        return {"depth_m": self.known[0], "tilt_deg": math.degrees(self.known[1]), "surface": None,
                "pose_step": NO_POSE_STEP, "best_iteration": self.best_iteration, "iterations": self.iterations,
                "converged": self.converged, "backend": self.backend, "device": self.device, "seconds": self.seconds,
                "history": self.history}


def reconstruct_shape_only(dataset, *, depth0: float | None = None, tilt0: float | None = None,
                           settings: ReconstructSettings = ReconstructSettings(), backend=None,
                           progress: Callable[[str], None] | None = None) -> ShapeOnlyResult:
    """The loop of the module docstring without its pose step, for a deep-water dataset (no
    [surface]: known depth and tilt): carve at ``fsswarp.dataset.deep_water_pose``, which puts
    the surface beyond every range window (no multipath layers, no surface rule), then shape
    steps while E_I falls, under the same stopping rules. ``depth0``/``tilt0`` must be None (the
    depth and tilt are known). History entries hold the known depth and tilt."""
    from .backends import get_backend
    from .dataset import deep_water_pose
    from .errors import InputError
    from .rendering import RenderWarning

    if depth0 is not None or tilt0 is not None:
        raise InputError("the dataset has no sea surface (deep water): its depth and tilt are known ([rig] depth_m, "
                         "tilt_deg), there is no start to give", field="--depth" if depth0 is not None else "--tilt",
                         value=depth0 if depth0 is not None else math.degrees(tilt0))
    depth, tilt = deep_water_pose(dataset.manifest)
    known = (dataset.manifest.known_pose.depth, dataset.manifest.known_pose.tilt)
    backend = backend or get_backend()
    say = progress or (lambda line: None)
    start = time.perf_counter()
    comparison, shaping = _comparisons(dataset, settings, backend)
    with warnings.catch_warnings(), _TruthMetrics(dataset.truth_mesh(), say, backend) as truth:
        warnings.filterwarnings("ignore", "view .*: ghost returns reach", RenderWarning)  # beyond the windows on purpose
        say(f"iteration 0: carving at the known D = {known[0]:.4f} m, tilt = {math.degrees(known[1]):.3f} deg "
            f"({NO_POSE_STEP}: no pose step, no ghost or mirror)")
        carved = _carving(dataset, depth, tilt, settings, backend)
        first = _complete(_record(0, carved, dataset, depth, tilt, settings, comparison, None), comparison, carved,
                          depth, tilt, truth)
        history, best, kept, working, misses, stopped = [first], first, carved, carved, 0, False
        say(_line(first))
        for iteration in range(1, settings.iterations + 1):
            trial = refine_shape(working, dataset, depth, tilt, settings=settings.refine, comparison=shaping).mesh
            if np.array_equal(trial.vertices, working.vertices):
                say(f"iteration {iteration}: the shape step left the model as it was (every update refused); keeping "
                    f"iteration {best['iteration']} and stopping")
                stopped = True
                break
            entry = _record(iteration, trial, dataset, depth, tilt, settings, comparison, first)
            history.append(_complete(entry, comparison, trial, depth, tilt, truth))
            say(_line(history[-1]))
            truth.collect(wait=False)
            working = trial
            if history[-1]["E_I"] < best["E_I"]:
                best, kept, misses = history[-1], trial, 0
                continue
            misses += 1
            if _out_of_patience(misses, settings, best, iteration, say):
                stopped = True
                break
        truth.collect(wait=True)
    for entry in history:
        entry.update(depth_m=known[0], tilt_deg=math.degrees(known[1]))
    return ShapeOnlyResult(model=kept, carved=carved, depth=depth, tilt=tilt, best_iteration=best["iteration"],
                           iterations=len(history) - 1, stopped=stopped, converged=stopped, history=history,
                           seconds=time.perf_counter() - start, backend=backend.name, device=backend.device,
                           start=(depth, tilt), known=known)
