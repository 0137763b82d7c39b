"""Sonar depth D and tilt β from frontal contours (paper §2.4, eq. 7; DESIGN §7).

:func:`estimate_pose` searches (D, β) for a given model (reference frame) against a dataset's
views marked ``optimize``, with a ``fsswarp.compare.ViewComparison`` (its own, or the one the
caller hands it):

- a ``grid[0]`` × ``grid[1]`` grid of the comparison's surrogate over [D0 ± e_D] × [β0 ± e_β]
  (m, rad), then ``levels − 1`` finer grids, each centred on the previous level's best cell and
  spanning ± two of its cells (the spacing halves), every cell and view of a level in one
  launch; the cap halves per level from ``cap`` to ``min_cap``, and the levels before the
  finest use ``coarse_samples``. After each level the comparison is located at the new best
  cell (data contours and detection shift found again);
- a BOBYQA polish (nlopt) on E_mu (eq. 6, ``ViewComparison.exact``) in a frame fitted to the
  finest level (a quadratic through its 5 × 5 best cells: ± ``POLISH_CELLS`` cells along its
  valley, ± one across);
- greedy acceptance: the estimate moves from (D0, β0) only if E_mu falls there.

:func:`check_uncertainties` gives the grid half-widths; :func:`pose_objective` is E_mu itself.
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

#: Half-width of the polish box in cells of the finest grid level.
POLISH_CELLS = 2
#: Default grid half-widths in units of the manifest's depth and tilt uncertainties.
BOUNDS_FACTOR = 1.2


@dataclass(frozen=True)
class GridLevel:
    """One level of the grid search: depths (nD,) m, tilts (nβ,) rad, costs (nD, nβ) of the
    surrogate (m), and the best cell's (depth, tilt)."""

    depths: np.ndarray
    tilts: np.ndarray
    costs: np.ndarray
    best: tuple[float, float]


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
                            "best": point(*level.best)} for level in self.levels],
                "detection_shift_rows": self.shift, "anchor_views": list(self.anchors), "views": list(self.views),
                "mirror_views": list(self.mirror_views), "search_box_edges": list(self.box_edges()),
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
                  comparison: ViewComparison | None = None) -> PoseResult:
    """Estimate the sonar depth D and tilt β (paper §2.4, eq. 7) for ``model`` (reference frame).

    depth0 (m), tilt0 (rad) : the start, default the dataset's measured values
    bounds : (e_D m, e_β rad), the half-widths of the first grid [D0 ± e_D] × [β0 ± e_β];
        default ``BOUNDS_FACTOR`` × the manifest's uncertainties (``surface.depth_sigma_m``,
        ``tilt_sigma_deg``): 6 cm and 2.4° for the default 5 cm and 2°, so that a start at the
        edge of the stated uncertainty keeps the truth inside the grid, not on its edge
    levels : grid levels (>= 1), each in one launch; the polish follows (``settings.polish``)
    settings : PoseSettings (default ``PoseSettings()``); backend : default ``get_backend()``
    progress : called with one line per step
    comparison : a ViewComparison of ``dataset`` to search with (it carries the settings and the
        backend, so give neither with it); default a new one. It is put to ``model`` at
        (depth0, tilt0) (kept where it is there already, ``ViewComparison.use``), its counters
        restart, and it is left located at the finest level's best cell
    Returns a PoseResult; the estimate moves from (depth0, tilt0) only where E_mu falls.
    """
    start = time.perf_counter()
    surface = dataset.manifest.surface
    depth0 = surface.depth if depth0 is None else float(depth0)
    tilt0 = surface.tilt if tilt0 is None else float(tilt0)
    check_depth_tilt(depth0, tilt0)
    if bounds is None:
        bounds = check_uncertainties(dataset, depth0)
    e_d, e_b = (float(b) for b in bounds) if len(bounds) == 2 else (math.nan, math.nan)
    if not (math.isfinite(e_d) and 0 < e_d < depth0 and math.isfinite(e_b) and 0 < e_b < math.pi / 4):
        raise InputError("must be (e_D, e_beta) with 0 < e_D < depth0 m and 0 < e_beta < 45 deg",
                         field="bounds", value=bounds)
    check_integer("levels", levels, 1)
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
        costs = comparison.surrogate(dd, tt, cap=cap, samples=samples)
        comparison.counters["grid_cells"] += costs.size
        i, j = np.unravel_index(int(np.argmin(costs)), costs.shape)
        best = np.array([dd[i, j], tt[i, j]])
        found.append(GridLevel(axes[0], axes[1], costs, (float(best[0]), float(best[1]))))
        step = 2 * half / (grid - 1)
        say(f"level {level + 1}: {grid[0]} x {grid[1]} cells, spacing {step[0] * 1000:.2f} mm x "
            f"{math.degrees(step[1]):.3f} deg, cap {cap * 1000:.0f} mm; best D {best[0]:.4f} m, beta "
            f"{math.degrees(best[1]):.3f} deg, cost {costs[i, j] * 1000:.3f} mm")
        half = 2 * step
        comparison.locate(*best)  # the data contours and the detection shift, seen from the new estimate

    candidate, polish_error = _polish(comparison, *_valley(found[-1], step), lo, hi, settings.polish)
    say(f"polish: D {candidate[0]:.4f} m, beta {math.degrees(candidate[1]):.3f} deg, E_mu {polish_error * 1000:.3f} mm")
    before, after = comparison.exact(depth0, tilt0).value, polish_error  # the polish evaluated the candidate
    accepted = bool(np.isfinite(after) and (not np.isfinite(before) or after < before))
    depth, tilt = (candidate if accepted else (depth0, tilt0))
    say(f"E_mu {before * 1000:.3f} mm at the start, {after * 1000:.3f} mm at the candidate: "
        f"{'accepted' if accepted else 'rejected (E_mu did not fall)'}")
    return PoseResult(depth=float(depth), tilt=float(tilt), depth0=depth0, tilt0=tilt0,
                      candidate=(float(candidate[0]), float(candidate[1])), accepted=accepted,
                      error_before=float(before), error_after=float(after if accepted else before),
                      levels=tuple(found), polish_error=float(polish_error), shift=comparison.shift,
                      anchors=comparison.anchors, evaluations=dict(comparison.counters),
                      seconds=time.perf_counter() - start, views=comparison.data.names,
                      mirror_views=comparison.data.mirror_views)


# --- helpers -------------------------------------------------------------------------------

def check_uncertainties(dataset, depth0: float, *, depth_range: float | None = None,
                        tilt_range: float | None = None) -> tuple[float, float]:
    """The grid half-widths (e_D m, e_β rad): ``depth_range`` (m) and ``tilt_range`` (rad) where
    given (``--depth-range``, ``--tilt-range``), else ``BOUNDS_FACTOR`` × the manifest's
    uncertainties; InputError naming the option or the manifest's field unless they span a
    search from ``depth0`` (m): 0 < e_D < depth0 and 0 < e_β < 45°."""
    file = dataset.root / MANIFEST_NAME if getattr(dataset, "root", None) is not None else None
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



def _valley(level: GridLevel, step: np.ndarray):
    """The polish frame from a quadratic fitted (least squares) to the level's costs at the
    5 × 5 cells around its minimum: (centre (2,), axes (2, 2)) in (m, rad); column 0 runs
    along the fit's valley (smallest curvature) over ``POLISH_CELLS`` cells, column 1 across it
    over one cell (cells scaled to the grid spacing ``step``). The centre is the fit's minimum
    when that lies within one cell of the best cell, else the best cell; without a convex fit
    the axes are the grid's, ``POLISH_CELLS`` cells each."""
    costs = level.costs
    i, j = np.unravel_index(int(np.argmin(costs)), costs.shape)
    rows = np.arange(max(i - 2, 0), min(i + 3, costs.shape[0]))
    cols = np.arange(max(j - 2, 0), min(j + 3, costs.shape[1]))
    x, y = (a.ravel().astype(np.float64) for a in np.meshgrid(rows - i, cols - j, indexing="ij"))
    design = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)
    best = np.array([level.depths[i], level.tilts[j]])
    if len(rows) < 3 or len(cols) < 3:
        return best, np.diag(POLISH_CELLS * step)
    c = np.linalg.lstsq(design, costs[np.ix_(rows, cols)].ravel(), rcond=None)[0]
    hessian = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
    curvature, vectors = np.linalg.eigh(hessian)
    if curvature[0] <= 0:
        return best, np.diag(POLISH_CELLS * step)
    shift = -np.linalg.solve(hessian, c[1:3])
    centre = best + (shift * step if np.all(np.abs(shift) <= 1.0) else 0.0)
    return centre, np.stack([POLISH_CELLS * vectors[:, 0] * step, vectors[:, 1] * step], axis=1)


def _polish(comparison: ViewComparison, centre, axes, lo, hi, evaluations: int):
    """BOBYQA (nlopt) on E_mu over ``centre + axes @ u``, u in [-1, 1]² (points clipped to the
    bounds ``lo``, ``hi``), from u = 0. Returns the best point seen and its E_mu."""
    def point(u):
        return np.clip(centre + axes @ np.asarray(u, np.float64), lo, hi)

    start = comparison.exact(*point((0.0, 0.0)))
    seen = {"x": point((0.0, 0.0)), "f": start.value}
    if evaluations == 0 or not math.isfinite(start.value):
        return seen["x"], seen["f"]
    def objective(u, grad):
        x = point(u)
        value = start.value if np.all(np.asarray(u) == 0.0) else comparison.exact(x[0], x[1]).value
        if value < seen["f"]:
            seen["x"], seen["f"] = x, value
        return value if math.isfinite(value) else 1.0  # 1 m: far worse than any E_mu seen

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
    return seen["x"], seen["f"]
