"""Sonar depth D and tilt β from frontal contours and the sensors (paper §2.3–2.4, eq. 7;
DESIGN §7). The sensors' D0 and β0 (manifest ``surface``) are 1-σ Gaussian priors
(:class:`Prior`); :func:`estimate_pose` minimises, for a model (reference frame) against the
views marked ``optimize`` (a ``fsswarp.compare.ViewComparison``), the posterior cost

    J(D, β) = E(D, β) + s · P(D, β),   P = ½((D − D0)/σ_D)² + ½((β − β0)/σ_β)²

E is the data term (m): the surrogate on the grids, E_mu (eq. 6) in the polish and the
acceptance. s is its noise (:func:`noise_level`: the standard error of a cell's mean once each
view's own offset is removed), so exp(−(E − min E)/s) is the likelihood, a Gibbs posterior
with no hand-tuned weight. Steps: grids of J over [D0 ± e_D] × [β0 ± e_β], each level centred
on the last's best cell at half its spacing, one launch per level; a BOBYQA polish (nlopt) of
E_mu + s · P; greedy acceptance where J falls; the :class:`Posterior` from a grid around the
estimate (:func:`fit_posterior`): 95% intervals, the valley (D − L·β const.) and whether each
parameter is identified (its interval at most half the prior's). :func:`check_uncertainties`
gives the box, :func:`check_start` refuses starts that cannot be right.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass
from typing import Callable

import nlopt
import numpy as np

from .atomic import json_number
from .compare import PoseSettings, PoseWarning, ViewComparison
from .dataset import MANIFEST_NAME
from .errors import InputError, check_depth_tilt, check_integer
from .surface import surface_in_reference

#: Half-width of the polish box in cells of the finest grid level.
POLISH_CELLS = 2
#: Default grid half-widths in units of the manifest's depth and tilt uncertainties: the
#: posterior lies inside ± 3 σ of the priors.
BOUNDS_FACTOR = 3.0
#: Two-sided 95% point of the normal distribution.
Z95 = 1.959963984540054
#: A start farther than this many σ of the prior from the measured value is refused.
START_SIGMAS = 5.0
#: Cells along each axis of the posterior's grid.
POSTERIOR_CELLS = 11
#: Lowest noise level s of a data term (m): float32 distances resolve no finer.
MIN_NOISE = 1e-6


def _covariance(depth_sigma: float, tilt_sigma: float, correlation: float) -> np.ndarray:
    off = correlation * depth_sigma * tilt_sigma
    return np.array([[depth_sigma ** 2, off], [off, tilt_sigma ** 2]])


#: (2, 2) covariance (m, rad) of the pose step's own error with the answer's model
#: (``fsswarp.reconstruction.sighting``: carved and refined once) made at the true pose: the
#: likelihood's minimum lay 6.1 mm (RMS) deeper and 0.10° steeper than the truth, correlation
#: 0.83, along the valley (bench/interval_study.py: the built-in scenes, seeds 3–5, both sensor
#: classes, 36 runs; docs/experiments.md). :func:`valley_posterior` adds its part along the
#: surface's height to the data's noise: the shape's error, which no single grid sees.
CARVING_ERROR = _covariance(0.0061, math.radians(0.099), 0.83)


@dataclass(frozen=True)
class Prior:
    """The sensors' measured depth (m) and tilt (rad) and their 1-σ uncertainties (m, rad; inf:
    no prior). ``penalty`` is P = ½((D − D0)/σ_D)² + ½((β − β0)/σ_β)² (arrays broadcast)."""

    depth: float
    tilt: float
    depth_sigma: float
    tilt_sigma: float

    @classmethod
    def of(cls, dataset) -> "Prior":
        """The manifest's ``surface``; InputError naming its file and field unless both
        sigmas are finite and > 0 (the pose step needs both priors)."""
        surface = dataset.manifest.surface
        file = _manifest_file(dataset)
        for field, value, degrees in (("surface.depth_sigma_m", surface.depth_sigma, False),
                                      ("surface.tilt_sigma_deg", surface.tilt_sigma, True)):
            if not (math.isfinite(value) and value > 0):
                raise InputError("must be > 0: the pose step weighs the sensor by it", file=file, field=field,
                                 value=math.degrees(value) if degrees else value)
        return cls(surface.depth, surface.tilt, surface.depth_sigma, surface.tilt_sigma)

    def penalty(self, depth, tilt):
        return 0.5 * (((np.asarray(depth) - self.depth) / self.depth_sigma) ** 2
                      + ((np.asarray(tilt) - self.tilt) / self.tilt_sigma) ** 2)

    def curvature(self) -> np.ndarray:
        """(2, 2) Hessian of ``penalty`` in (m, rad)."""
        return np.diag([self.depth_sigma ** -2.0, self.tilt_sigma ** -2.0])


@dataclass(frozen=True)
class GridLevel:
    """One level of the grid search: depths (nD,) m, tilts (nβ,) rad, costs (nD, nβ) of the
    surrogate (m), noise its level s (m), posterior (nD, nβ) the cost J = costs + s · P (m),
    and the best cell's (depth, tilt) (least J)."""

    depths: np.ndarray
    tilts: np.ndarray
    costs: np.ndarray
    best: tuple[float, float]
    noise: float = math.nan
    posterior: np.ndarray | None = None


@dataclass(frozen=True)
class Posterior:
    """The posterior of (D, β) around an estimate (the module docstring).

    depth (m), tilt (rad) : the estimate, the intervals' centre; covariance : (2, 2) in (m, rad)
    prior : the Prior; valley_slope : dD/dβ along the likelihood's long axis (m/rad);
    valley_depth : the depth of that axis at the estimated tilt (m); noise : s (m)
    """

    depth: float
    tilt: float
    covariance: np.ndarray
    prior: Prior
    valley_slope: float
    valley_depth: float
    noise: float

    def interval(self, index: int) -> tuple[float, float]:
        """The 95% interval of depth (0, m) or tilt (1, rad)."""
        centre = (self.depth, self.tilt)[index]
        half = Z95 * math.sqrt(max(float(self.covariance[index, index]), 0.0))
        return centre - half, centre + half

    def axes(self, sigmas: float = 4.0) -> np.ndarray:
        """(2, 2) columns: the covariance's principal axes, ``sigmas`` σ long (m, rad)."""
        return _principal_axes(self.covariance, sigmas)

    def identified(self) -> dict:
        """{"depth", "tilt"}: whether the 95% interval is at most half as wide as the prior's."""
        sigmas = (self.prior.depth_sigma, self.prior.tilt_sigma)
        return {name: bool(math.sqrt(max(float(self.covariance[i, i]), 0.0)) <= 0.5 * sigmas[i])
                for i, name in enumerate(("depth", "tilt"))}

    def summary(self) -> dict:
        """The fields of result.json and pose.json (docs/formats.md): m and degrees."""
        return {"depth_interval_m": list(self.interval(0)),
                "tilt_interval_deg": [math.degrees(v) for v in self.interval(1)],
                "valley": {"slope_m_per_deg": json_number(self.valley_slope * math.pi / 180.0),
                           "depth_m_at_estimated_tilt": json_number(self.valley_depth)},
                "identified": self.identified()}


@dataclass(frozen=True)
class PoseResult:
    """What :func:`estimate_pose` found.

    depth, tilt : the accepted estimate (m, rad); depth0, tilt0 : where it started
    candidate : (depth, tilt) the search proposed; accepted : whether E_mu fell there
    error_before, error_after : E_mu at the start and at the accepted estimate (m)
    levels : the grid levels, coarse to fine; polish_error : E_mu after the polish
    shift : the detection shift (rows; None: per cell); anchors : the anchor views
    evaluations : {"grid_cells", "surrogate_cells", "exact"} counts; seconds : wall time
    views, mirror_views : view names used, and those with a mirror term
    posterior : the Posterior around (depth, tilt); noise : s of the finest level (m), the
        prior's weight in the polish and the acceptance
    cost_before, cost_after : J (E_mu + noise · P, m) at the start and at the accepted estimate
    """

    depth: float
    tilt: float
    depth0: float
    tilt0: float
    candidate: tuple[float, float]
    accepted: bool
    error_before: float
    error_after: float
    levels: tuple[GridLevel, ...]
    polish_error: float
    shift: float | None
    anchors: tuple[str, ...]
    evaluations: dict
    seconds: float
    views: tuple[str, ...]
    mirror_views: tuple[str, ...]
    posterior: Posterior
    noise: float
    cost_before: float
    cost_after: float

    def box_edges(self) -> tuple[str, ...]:
        """The edges of the search box (the first grid level's span) that the finest grid
        level's best cell lies on, within half of its cell: any of "lowest depth", "highest
        depth", "lowest tilt", "highest tilt"; () inside. The levels stay inside the box, so a
        best cell on its edge means the search pressed against it: the truth may lie beyond."""
        first, last = self.levels[0], self.levels[-1]
        edges = []
        for name, value, span, fine in (("depth", last.best[0], first.depths, last.depths),
                                        ("tilt", last.best[1], first.tilts, last.tilts)):
            half = 0.5 * (fine[1] - fine[0])
            if value - span[0] < half:
                edges.append(f"lowest {name}")
            if span[-1] - value < half:
                edges.append(f"highest {name}")
        return tuple(edges)

    def summary(self) -> dict:
        """``pose.json`` of ``fsswarp pose`` (README): lengths in m, angles in degrees, E_mu in
        m; a value that is not finite (E_mu where no patch was found) is null."""
        def point(depth: float, tilt: float) -> dict:
            return {"depth_m": depth, "tilt_deg": math.degrees(tilt)}

        return {**point(self.depth, self.tilt), "start": point(self.depth0, self.tilt0),
                "candidate": point(*self.candidate), "accepted": self.accepted,
                "E_mu_start_m": json_number(self.error_before), "E_mu_m": json_number(self.error_after),
                "E_mu_candidate_m": json_number(self.polish_error),
                "levels": [{"depths_m": level.depths.tolist(), "tilts_deg": np.degrees(level.tilts).tolist(),
                            "costs_m": [[json_number(c) for c in row] for row in level.costs.tolist()],
                            "noise_m": json_number(level.noise), "best": point(*level.best)}
                           for level in self.levels],
                "detection_shift_rows": self.shift, "anchor_views": list(self.anchors), "views": list(self.views),
                "mirror_views": list(self.mirror_views), "search_box_edges": list(self.box_edges()),
                "noise_m": json_number(self.noise), "cost_start_m": json_number(self.cost_before),
                "cost_m": json_number(self.cost_after), **self.posterior.summary(),
                "evaluations": dict(self.evaluations), "seconds": self.seconds}


# --- public functions --------------------------------------------------------------------------

def pose_objective(model, dataset, depth: float, tilt: float, *, settings: PoseSettings = PoseSettings(),
                   backend=None) -> float:
    """E_mu (eq. 6, m) of ``model`` (reference frame) against ``dataset`` at (depth m, tilt rad),
    the data contours found at the same (depth, tilt)."""
    comparison = ViewComparison(dataset, settings=settings, backend=backend).use(model, depth, tilt)
    return comparison.exact(depth, tilt).value


def estimate_pose(model, dataset, *, depth0: float | None = None, tilt0: float | None = None,
                  bounds: tuple[float, float] | None = None, levels: int = 3,
                  settings: PoseSettings | None = None, backend=None,
                  progress: Callable[[str], None] | None = None,
                  comparison: ViewComparison | None = None, prior: Prior | None = None,
                  posterior_axes=None) -> PoseResult:
    """Estimate the sonar depth D and tilt β (paper §2.4, eq. 7) for ``model`` (reference frame)
    by the posterior cost of the module docstring.

    depth0 (m), tilt0 (rad) : the start, default the dataset's measured values
    bounds : (e_D m, e_β rad), the half-widths of the first grid [D0 ± e_D] × [β0 ± e_β];
        default ``BOUNDS_FACTOR`` × the priors' sigmas (:func:`check_uncertainties`)
    levels : grid levels (>= 1), each in one launch; the polish follows (``settings.polish``)
    settings : PoseSettings (default ``PoseSettings()``); backend : default ``get_backend()``
    progress : called with one line per step
    comparison : a ViewComparison of ``dataset`` to search with (it carries the settings and the
        backend, so give neither with it); default a new one. It is put to ``model`` at
        (depth0, tilt0) (``ViewComparison.use``), its counters restart, and it is left located
        at the finest level's best cell
    prior : default ``Prior.of(dataset)``, the manifest's sensors
    posterior_axes : (2, 2) columns (m, rad) spanning an area, the first posterior grid's
        half-axes (:func:`fit_posterior`), e.g. an earlier step's ``posterior.axes()`` with the
        same data, evaluated at once at the finest samples (``fine_first``); default the
        finest level's valley frame. Either way a grid that does not fit is refitted.
    Returns a PoseResult; the estimate moves from (depth0, tilt0) only where J falls.
    """
    start = time.perf_counter()
    surface = dataset.manifest.surface
    depth0 = surface.depth if depth0 is None else float(depth0)
    tilt0 = surface.tilt if tilt0 is None else float(tilt0)
    check_depth_tilt(depth0, tilt0)
    prior = Prior.of(dataset) if prior is None else prior
    if bounds is None:
        bounds = check_uncertainties(dataset, depth0)
    e_d, e_b = (float(b) for b in bounds) if len(bounds) == 2 else (math.nan, math.nan)
    if not (math.isfinite(e_d) and 0 < e_d < depth0 and math.isfinite(e_b) and 0 < e_b < math.pi / 4):
        raise InputError("must be (e_D, e_beta) with 0 < e_D < depth0 m and 0 < e_beta < 45 deg",
                         field="bounds", value=bounds)
    check_integer("levels", levels, 1)
    if posterior_axes is not None:
        posterior_axes = np.asarray(posterior_axes, np.float64)
        if posterior_axes.shape != (2, 2) or not spans_an_area(posterior_axes):
            raise InputError("must be (2, 2) finite axes spanning an area", field="posterior_axes",
                             value=posterior_axes.tolist())
    say = progress or (lambda line: None)
    if comparison is None:
        comparison = ViewComparison(dataset, settings=settings or PoseSettings(), backend=backend)
    elif settings is not None or backend is not None:
        raise ValueError("settings and backend come with the comparison: give either them or a comparison")
    settings = comparison.settings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoseWarning)  # restart warns about the views left out
        comparison.use(model, depth0, tilt0)
    comparison.restart(stacklevel=3)
    say(f"start: D {depth0:.4f} m, beta {math.degrees(tilt0):.3f} deg; {len(comparison.data.views)} views, "
        f"mirror term in {len(comparison.data.mirror_views)}")

    lo = np.array([depth0 - e_d, tilt0 - e_b])
    hi = np.array([depth0 + e_d, tilt0 + e_b])
    best, half = np.array([depth0, tilt0]), np.array([e_d, e_b])
    grid = np.asarray(settings.grid)
    found = []
    for level in range(levels):
        low = np.clip(best - half, lo, hi - 2 * half)
        axes = [np.linspace(low[i], low[i] + 2 * half[i], grid[i]) for i in (0, 1)]
        dd, tt = np.meshgrid(*axes, indexing="ij")
        cap = max(settings.cap / 2 ** level, settings.min_cap)
        samples = settings.samples if level == levels - 1 else settings.coarse_samples
        per_view = comparison.surrogate_views(dd, tt, cap=cap, samples=samples)
        costs = per_view.mean(axis=-1)
        comparison.counters["grid_cells"] += costs.size
        noise = noise_level(per_view)
        posterior = costs + noise * prior.penalty(dd, tt)
        i, j = np.unravel_index(int(np.argmin(posterior)), costs.shape)
        best = np.array([dd[i, j], tt[i, j]])
        found.append(GridLevel(axes[0], axes[1], costs, (float(best[0]), float(best[1])), noise, posterior))
        step = 2 * half / (grid - 1)
        say(f"level {level + 1}: {grid[0]} x {grid[1]} cells, spacing {step[0] * 1000:.2f} mm x "
            f"{math.degrees(step[1]):.3f} deg, cap {cap * 1000:.0f} mm; best D {best[0]:.4f} m, beta "
            f"{math.degrees(best[1]):.3f} deg, cost {costs[i, j] * 1000:.3f} mm (noise {noise * 1000:.3f} mm)")
        half = 2 * step
        comparison.locate(*best)  # the data contours and the detection shift, seen from the new estimate

    noise = found[-1].noise
    centre, frame = _valley(found[-1], step)
    candidate, polish_error, after = _polish(comparison, centre, frame, lo, hi, settings.polish, prior, noise)
    say(f"polish: D {candidate[0]:.4f} m, beta {math.degrees(candidate[1]):.3f} deg, E_mu {polish_error * 1000:.3f} mm")
    before = comparison.exact(depth0, tilt0).value
    cost_before = before + noise * float(prior.penalty(depth0, tilt0))
    accepted = bool(np.isfinite(after) and (not np.isfinite(cost_before) or after < cost_before))
    depth, tilt = (candidate if accepted else (depth0, tilt0))
    say(f"E_mu {before * 1000:.3f} mm and J {cost_before * 1000:.3f} mm at the start, E_mu "
        f"{polish_error * 1000:.3f} mm and J {after * 1000:.3f} mm at the candidate: "
        f"{'accepted' if accepted else 'rejected (J did not fall)'}")
    first_grid = frame if posterior_axes is None else posterior_axes
    posterior = fit_posterior(comparison, prior, float(depth), float(tilt), first_grid,
                              fine_first=posterior_axes is not None)
    return PoseResult(depth=float(depth), tilt=float(tilt), depth0=depth0, tilt0=tilt0,
                      candidate=(float(candidate[0]), float(candidate[1])), accepted=accepted,
                      error_before=float(before), error_after=float(polish_error if accepted else before),
                      levels=tuple(found), polish_error=float(polish_error), shift=comparison.shift,
                      anchors=comparison.anchors, evaluations=dict(comparison.counters),
                      seconds=time.perf_counter() - start, views=comparison.data.names,
                      mirror_views=comparison.data.mirror_views, posterior=posterior, noise=float(noise),
                      cost_before=float(cost_before), cost_after=float(after if accepted else cost_before))


def fit_posterior(comparison: ViewComparison, prior: Prior, depth: float, tilt: float, axes: np.ndarray, *,
              cells: int = POSTERIOR_CELLS, launches: int = 3, fine_first: bool = False) -> Posterior:
    """The Posterior around the estimate (depth m, tilt rad) from ``comparison``'s surrogate at
    ``min_cap`` on a ``cells`` × ``cells`` grid x + axes @ u, u in [-1, 1]², one launch each:
    J = (E − min E)/s + P, weights exp(−J), their covariance (the intervals: the estimate ±
    1.96 σ). The grid is fitted at the coarse samples, refitted to ± 4 posterior σ along its
    axes while it reaches less than 3.5 σ or more than 6 σ along one, then evaluated at the
    finest (``launches`` at most in all). Every grid is sheared to rows of one tilt
    (``_tilt_rows``), so that a row's cells share their views' poses. The valley: the
    least-curved axis of a quadratic fitted to (E − min E)/s (in prior-σ units), through its
    minimum.
    axes : (2, 2) columns in (m, rad), the first grid's half-spans
    fine_first : evaluate the first grid at the finest samples, and keep it where it fits (for
        axes from an earlier posterior of the same data, which mostly fit: one launch)"""
    settings = comparison.settings
    u = np.linspace(-1.0, 1.0, cells)
    centre = np.array([depth, tilt], np.float64)
    scale = np.array([prior.depth_sigma, prior.tilt_sigma])
    scale = np.where(np.isfinite(scale), scale, np.abs(axes).max(axis=1))
    def evaluate(axes, samples):
        grid = centre + np.einsum("ij,abj->abi", axes, np.stack(np.meshgrid(u, u, indexing="ij"), axis=-1))
        dd, tt = grid[..., 0], grid[..., 1]
        per_view = comparison.surrogate_views(dd, tt, cap=settings.min_cap, samples=samples)
        comparison.counters["grid_cells"] += dd.size
        costs = per_view.mean(axis=-1)
        noise = noise_level(per_view)
        data = (costs - np.nanmin(costs)) / noise
        return grid, data, noise, _weighted_covariance(grid, data + prior.penalty(dd, tt))

    axes = _tilt_rows(axes)
    for launch in range(launches):
        last = launch == launches - 1
        fine = last or (fine_first and launch == 0)
        grid, data, noise, covariance = evaluate(axes, settings.samples if fine else settings.coarse_samples)
        sigmas, directions = np.linalg.eigh(covariance / np.outer(scale, scale))  # in prior-σ units
        sigmas = np.sqrt(np.maximum(sigmas, 0.0))
        extent = np.abs(directions.T @ (axes / scale[:, None])).sum(axis=1)  # the grid's reach along each
        if last or not np.all(sigmas > 0):
            break
        if np.all((extent >= 3.5 * sigmas) & (extent <= 6.0 * sigmas)):
            if not fine:
                grid, data, noise, covariance = evaluate(axes, settings.samples)  # the fitted grid, finely
            break
        axes = _tilt_rows(_principal_axes(covariance, 4.0))
    finite = np.isfinite(data)
    offsets = (grid[finite] - centre) / scale
    c = _quadratic_fit(offsets[:, 0], offsets[:, 1], data[finite])
    hessian = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
    curvature, vectors = np.linalg.eigh(hessian)
    along = vectors[:, 0] * scale  # the least-curved axis, in (m, rad)
    lowest = np.linalg.pinv(hessian) @ -c[1:3] * scale + centre
    slope = along[0] / along[1] if along[1] != 0 else math.inf
    valley_depth = lowest[0] + slope * (tilt - lowest[1]) if math.isfinite(slope) else math.nan
    return Posterior(depth, tilt, covariance, prior, float(slope), float(valley_depth), float(noise))


def valley_posterior(conditional: Posterior, lever: float, *, carving_error: np.ndarray = CARVING_ERROR,
                     unsettled: float = 0.0) -> Posterior:
    """The posterior of (D, β) when the shape is free: the data keep only the surface's height
    above the object, h = D − L·β (DESIGN §7), and the sensors tell the rest.

    conditional : the pose step's Posterior with one model held fixed (its mean f, covariance
        Σ_c, its Prior: μ0, Σ0); lever : L = ∂h/∂β · (−1), the horizontal distance (m) from
        the reference sonar to the model, in m/rad
    carving_error : (2, 2) covariance of the pose step's error with a model made at the truth
        (``CARVING_ERROR``); its variance along a = (1, −L) widens the height's
    unsettled : a further variance of the height (m²): the spread of the heights of the models
        made for the answer (``fsswarp.reconstruction``)
    With a = (1, −L): the height's likelihood is the conditional's marginal of aᵀθ with the
    prior's divided out, N(g, v) with 1/v = 1/(aᵀΣ_c a) − 1/(aᵀΣ0 a), g = v (aᵀf/(aᵀΣ_c a) −
    aᵀμ0/(aᵀΣ0 a)), plus aᵀ carving_error a; the posterior is N(μ0, Σ0) × N(aᵀθ; g, v):
    precision Λ0 + a aᵀ/v, mean by the same weights, clipped to the sensors' ± ``BOUNDS_FACTOR``
    σ box. Returns a Posterior with that mean and covariance, the valley (slope L, the depth
    g + L·β at the estimated tilt) and the conditional's noise. A conditional that adds nothing
    to the prior on h gives the prior back."""
    prior = conditional.prior
    a = np.array([1.0, -float(lever)])
    mu0 = np.array([prior.depth, prior.tilt])
    sigma0 = np.array([prior.depth_sigma, prior.tilt_sigma])
    cov0 = np.diag(sigma0 ** 2)
    f = np.array([conditional.depth, conditional.tilt])
    v_c, v_0 = float(a @ conditional.covariance @ a), float(a @ cov0 @ a)
    gained = 1.0 / v_c - 1.0 / v_0
    precision = prior.curvature()
    pulled = precision @ mu0
    if gained > 0:
        variance = 1.0 / gained + float(a @ np.asarray(carving_error, np.float64) @ a) + float(unsettled)
        height = (a @ f / v_c - a @ mu0 / v_0) / gained
        precision = precision + np.outer(a, a) / variance
        pulled = pulled + a * height / variance
    else:
        height = float(a @ mu0)
    covariance = np.linalg.inv(precision)
    box = BOUNDS_FACTOR * sigma0
    mean = np.clip(covariance @ pulled, mu0 - box, mu0 + box)
    return Posterior(float(mean[0]), float(mean[1]), covariance, prior, float(lever),
                     float(height + lever * mean[1]), conditional.noise)


def model_lever(model, rig, depth: float, tilt: float, *, step: float = 1e-4) -> float:
    """L (m/rad): how fast the surface's height above ``model``'s centroid (reference frame)
    falls as the tilt grows, −∂(D − n(β)·c)/∂β at (depth m, tilt rad); for the usual reference
    the horizontal distance from the reference sonar to the centroid."""
    centroid = np.asarray(model.vertices, np.float64).mean(axis=0)
    normals = [surface_in_reference(rig, depth, tilt + s)[0] for s in (step, -step)]
    return float((normals[0] - normals[1]) @ centroid / (2 * step))


def _principal_axes(covariance: np.ndarray, sigmas: float) -> np.ndarray:
    values, vectors = np.linalg.eigh(covariance)
    return vectors * (sigmas * np.sqrt(np.maximum(values, 0.0)))


def spans_an_area(axes: np.ndarray) -> bool:
    """Whether (2, 2) grid axes (columns) are finite and span an area: a grid x + axes @ u whose
    cells do not collapse onto a line (``estimate_pose``'s ``posterior_axes``)."""
    return bool(np.all(np.isfinite(axes)) and abs(np.linalg.det(axes)) > 0)


def _tilt_rows(axes: np.ndarray) -> np.ndarray:
    """(2, 2) axes T with T Tᵀ = axes axesᵀ and T[1, 0] = 0: the grid x + T u, u in [-1, 1]²,
    holds the same ellipse as x + axes u (the unit disc's image), and its tilt depends on u[1]
    alone. Its cells then share a tilt along each row, and the renderer casts the direct legs of
    a row's poses once (``fsswarp.backends.base.shared_poses``). Axes without tilt are kept."""
    shape = axes @ axes.T
    if not shape[1, 1] > 0:
        return axes
    tilt = math.sqrt(shape[1, 1])
    along = shape[0, 1] / tilt
    return np.array([[math.sqrt(max(shape[0, 0] - along * along, 0.0)), along], [0.0, tilt]])


def _weighted_covariance(grid: np.ndarray, cost: np.ndarray) -> np.ndarray:
    """(2, 2) covariance of the cells grid (..., 2) weighted by exp(−cost)."""
    finite = np.isfinite(cost)
    points, weights = grid[finite], np.exp(-(cost[finite] - cost[finite].min()))
    weights /= weights.sum()
    offsets = points - weights @ points
    return (weights[:, None] * offsets).T @ offsets


def noise_level(per_view: np.ndarray) -> float:
    """The standard error (m) of a cell's mean cost for comparisons between cells: per_view
    (..., V) costs of cells × views (NaN: a view without a value; views not finite in every
    cell are left out) fitted by cell + view effects; s = σ_ε / √V from the residuals (the
    views' own offsets cancel between cells). At least ``MIN_NOISE``; one cell or one view: the
    standard error of its values."""
    table = np.asarray(per_view, np.float64).reshape(-1, np.shape(per_view)[-1])
    table = table[:, np.all(np.isfinite(table), axis=0)]
    cells, views = table.shape
    if cells < 2 or views < 2:
        values = table.ravel()
        spread = float(np.std(values, ddof=1) / math.sqrt(values.size)) if values.size > 1 else \
            (float(values[0]) if values.size else 0.0)
        return max(spread, MIN_NOISE)
    residual = table - table.mean(axis=1, keepdims=True) - table.mean(axis=0, keepdims=True) + table.mean()
    variance = float(np.sum(residual ** 2)) / ((cells - 1) * (views - 1))
    return max(math.sqrt(variance / views), MIN_NOISE)


def check_start(dataset, depth: float, tilt: float) -> None:
    """InputError (``--depth`` or ``--tilt``) unless (depth m, tilt rad) lies within
    ``START_SIGMAS`` σ of the sensors' measured values and puts the sea surface inside some
    view's range window (else no ghost or mirror can be seen, and nothing fixes D or β)."""
    prior = Prior.of(dataset)
    for field, value, measured, sigma, unit in (("--depth", depth, prior.depth, prior.depth_sigma, "m"),
                                                ("--tilt", tilt, prior.tilt, prior.tilt_sigma, "deg")):
        if abs(value - measured) > START_SIGMAS * sigma:
            shown = (lambda v: v) if unit == "m" else math.degrees
            raise InputError(f"is {abs(value - measured) / sigma:.3g} sigma from the measured {shown(measured):.4g} "
                             f"{unit} (sigma {shown(sigma):.3g} {unit}); more than {START_SIGMAS:g} is refused: "
                             f"check the units ({unit})", field=field, value=round(shown(value), 6))
    nearest = surface_range(dataset, depth, tilt)
    if not nearest < dataset.sonar.range_max:
        raise InputError(f"puts the sea surface {nearest:.3g} m or farther along every beam, beyond the range window "
                         f"(up to {dataset.sonar.range_max:g} m): no ghost or mirror could be seen; check the units "
                         "(m)", field="--depth", value=depth)


def surface_range(dataset, depth: float, tilt: float, *, rays: int = 33) -> float:
    """The least range (m) at which any view's beam fan (``rays`` × ``rays`` directions over
    its azimuth and elevation apertures) meets the sea surface at (depth m, tilt rad); inf where
    none looks up at it."""
    from .surface import surface_in_views

    sonar = dataset.sonar
    theta = np.linspace(-0.5, 0.5, rays) * sonar.azimuth_fov
    phi = np.linspace(-0.5, 0.5, rays) * sonar.elevation_fov
    t, p = np.meshgrid(theta, phi, indexing="ij")
    directions = np.stack([np.cos(p) * np.sin(t), np.cos(p) * np.cos(t), np.sin(p)], axis=-1).reshape(-1, 3)
    normals, offsets = surface_in_views(dataset.rig, depth, tilt)
    nearest = math.inf
    for normal, offset in zip(np.atleast_2d(normals), np.atleast_1d(offsets)):
        along = directions @ normal
        up = along > 1e-12
        if up.any():
            nearest = min(nearest, float(np.min(offset / along[up])))
    return nearest


# --- helpers -------------------------------------------------------------------------------

def check_uncertainties(dataset, depth0: float, *, depth_range: float | None = None,
                        tilt_range: float | None = None) -> tuple[float, float]:
    """The grid half-widths (e_D m, e_β rad): ``depth_range`` (m) and ``tilt_range`` (rad) where
    given (``--depth-range``, ``--tilt-range``), else ``BOUNDS_FACTOR`` × the manifest's
    uncertainties; InputError naming the option or the manifest's field unless they span a
    search from ``depth0`` (m): 0 < e_D < depth0 and 0 < e_β < 45°."""
    file = _manifest_file(dataset)
    surface = dataset.manifest.surface
    default = (BOUNDS_FACTOR * surface.depth_sigma, BOUNDS_FACTOR * surface.tilt_sigma)
    if depth_range is not None:
        if not (math.isfinite(depth_range) and 0 < depth_range < depth0):
            raise InputError(f"must be > 0 and below the start depth {depth0:g} m", field="--depth-range",
                             value=depth_range)
    elif not 0 < default[0] < depth0:
        raise InputError(f"must be > 0 and, times {BOUNDS_FACTOR:g}, below the start depth {depth0:g} m: the depth "
                         "search spans that many sigmas", file=file, field="surface.depth_sigma_m",
                         value=surface.depth_sigma)
    if tilt_range is not None:
        if not (math.isfinite(tilt_range) and 0 < tilt_range < math.pi / 4):
            raise InputError("must be > 0 and below 45 (deg)", field="--tilt-range", value=math.degrees(tilt_range))
    elif not 0 < default[1] < math.pi / 4:
        raise InputError(f"must be > 0 and, times {BOUNDS_FACTOR:g}, below 45 deg: the tilt search spans that many "
                         "sigmas", file=file, field="surface.tilt_sigma_deg", value=math.degrees(surface.tilt_sigma))
    return (default[0] if depth_range is None else float(depth_range),
            default[1] if tilt_range is None else float(tilt_range))



def _manifest_file(dataset):
    return dataset.root / MANIFEST_NAME if getattr(dataset, "root", None) is not None else None


def _quadratic_fit(x: np.ndarray, y: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Least-squares coefficients (6,) of c0 + c1 x + c2 y + c3 x² + c4 xy + c5 y² through
    points (N,) x, y with ``values`` (N,)."""
    x, y = (np.asarray(a, np.float64).ravel() for a in (x, y))
    design = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)
    return np.linalg.lstsq(design, np.asarray(values, np.float64).ravel(), rcond=None)[0]


def _valley(level: GridLevel, step: np.ndarray):
    """The polish frame from a quadratic fitted (least squares) to the level's posterior cost at
    the 5 × 5 cells around its minimum: (centre (2,), axes (2, 2)) in (m, rad); column 0 runs
    along the fit's valley (smallest curvature) over ``POLISH_CELLS`` cells, column 1 across it
    over one cell (cells scaled to the grid spacing ``step``). The centre is the fit's minimum
    when that lies within one cell of the best cell, else the best cell; without a convex fit
    the axes are the grid's, ``POLISH_CELLS`` cells each."""
    costs = level.posterior
    i, j = np.unravel_index(int(np.argmin(costs)), costs.shape)
    rows = np.arange(max(i - 2, 0), min(i + 3, costs.shape[0]))
    cols = np.arange(max(j - 2, 0), min(j + 3, costs.shape[1]))
    best = np.array([level.depths[i], level.tilts[j]])
    if len(rows) < 3 or len(cols) < 3:
        return best, np.diag(POLISH_CELLS * step)
    x, y = np.meshgrid(rows - i, cols - j, indexing="ij")
    c = _quadratic_fit(x, y, costs[np.ix_(rows, cols)])
    hessian = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
    curvature, vectors = np.linalg.eigh(hessian)
    if curvature[0] <= 0:
        return best, np.diag(POLISH_CELLS * step)
    shift = -np.linalg.solve(hessian, c[1:3])
    centre = best + (shift * step if np.all(np.abs(shift) <= 1.0) else 0.0)
    return centre, np.stack([POLISH_CELLS * vectors[:, 0] * step, vectors[:, 1] * step], axis=1)


def _polish(comparison: ViewComparison, centre, axes, lo, hi, evaluations: int, prior: Prior, noise: float):
    """BOBYQA (nlopt) on J = E_mu + noise · P over ``centre + axes @ u``, u in [-1, 1]² (points
    clipped to the bounds ``lo``, ``hi``), from u = 0. Returns the best point seen, its E_mu and
    its J."""
    def point(u):
        return np.clip(centre + axes @ np.asarray(u, np.float64), lo, hi)

    first = comparison.exact(*point((0.0, 0.0)))

    def cost(x, value):
        return value + noise * float(prior.penalty(x[0], x[1]))

    seen = {"x": point((0.0, 0.0)), "E": first.value, "J": cost(point((0.0, 0.0)), first.value)}
    if evaluations == 0 or not math.isfinite(first.value):
        return seen["x"], seen["E"], seen["J"]

    def objective(u, grad):
        x = point(u)
        value = first.value if np.all(np.asarray(u) == 0.0) else comparison.exact(x[0], x[1]).value
        total = cost(x, value)
        if total < seen["J"]:
            seen.update(x=x, E=value, J=total)
        return total if math.isfinite(total) else 1.0  # 1 m: far worse than any E_mu seen

    opt = nlopt.opt(nlopt.LN_BOBYQA, 2)
    opt.set_lower_bounds([-1.0, -1.0])
    opt.set_upper_bounds([1.0, 1.0])
    opt.set_min_objective(objective)
    opt.set_maxeval(evaluations)
    opt.set_initial_step(0.25)
    opt.set_xtol_abs(0.01)
    try:
        opt.optimize([0.0, 0.0])
    except nlopt.RoundoffLimited:
        pass
    return seen["x"], seen["E"], seen["J"]
