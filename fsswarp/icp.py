"""IRLS-ICP of 2-D contours: the rigid motion that aligns a synthetic contour with the data's
(paper §2.4, eq. 5; DESIGN §7).

Contours are (n, 2) float64 points in a metric plane; the engine uses the fan plane of paper
eq. (3), ``(x, y) = R (sin θ, cos θ)`` in metres (``fsswarp.sonar.fan_xy``).

:func:`icp` (source, target) returns an :class:`ICPResult`: the rotation (2, 2) and
translation (2,), the inlier pairs, every source point's 2-D motion (n, 2) m, and CE (eq. 5),
the mean inlier distance after alignment (m). Each iteration matches every transformed source
point to its nearest target point (unequal, unmatched sets), weighs the pairs with Cauchy
weights on a median-based robust scale, and solves the weighted Procrustes problem in closed
form. It runs from three starts (the identity and ±``START_ANGLE`` rad about the source's
centroid) and keeps the run with the smallest robust scale. Inliers lie within ``gate`` robust
scales (and ``max_distance``, if given).

:func:`icp_many` runs many pairs in lockstep over padded arrays, each with ``icp``'s result for
that pair up to rounding; with ``backend=`` it runs the iterations on the device, one thread
per run in float64 (``Backend.icp_runs``: kernels/icp.cl and its Warp twin).
:func:`contour_error` is CE of two point sets. Why three starts and the scale: docs/decisions.md.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from .errors import is_integer

#: Cauchy tuning constant: 95 % asymptotic efficiency for Gaussian residuals.
CAUCHY_C = 2.3849
#: median(r) / σ for the distance r of a 2-D Gaussian error with per-axis σ (Rayleigh median).
RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))
#: Rotation (rad) of the two extra starts about the source's centroid.
START_ANGLE = 0.05
#: The pipeline's ``tol`` (pose, refinement, E_I): with contours of RMS radius ~5 cm ICP stops
#: once no point moves 0.05 µm, 3–4× fewer iterations than the default 1e-10.
CONTOUR_TOL = 1e-6


@dataclass(frozen=True)
class ICPResult:
    """The rigid transform ``T(p) = rotation @ p + translation`` that moves the source onto
    the target, and what it leaves.

    rotation : (2, 2); angle : its angle (rad, counter-clockwise); translation : (2,)
    pairs : (N', 2) int inlier pairs (i, k(i)) of source and target indices, sorted by i
    motions : (N, 2) 2-D motion of every source point, ``T(c̃_i) - c̃_i`` (paper §2.4)
    error : CE (eq. 5), mean distance of the inlier pairs after alignment (NaN if none)
    scale : the final robust scale σ (plane units); weights : (N,) final Cauchy weights
    iterations : iterations run; converged : whether the tolerance was met
    """

    rotation: np.ndarray
    angle: float
    translation: np.ndarray
    pairs: np.ndarray
    motions: np.ndarray
    error: float
    scale: float
    weights: np.ndarray
    iterations: int
    converged: bool

    def apply(self, points) -> np.ndarray:
        """(..., 2) points moved by the transform."""
        return np.asarray(points, np.float64) @ self.rotation.T + self.translation


def contour_error(data_points, synthetic_points) -> float:
    """CE of paper eq. (5): ``(1/N') Σ_i |c_k(i) - c̃'_i|``, the mean Euclidean distance of N'
    matched pairs of data contour points and transformed synthetic contour points.

    data_points, synthetic_points : (N', 2), row i of one matched to row i of the other.
    Returns NaN for N' = 0."""
    a = _points("data_points", data_points, minimum=0)
    b = _points("synthetic_points", synthetic_points, minimum=0)
    if a.shape != b.shape:
        raise ValueError(f"data_points {a.shape} and synthetic_points {b.shape} must match")
    if len(a) == 0:
        return math.nan
    return float(np.mean(np.linalg.norm(a - b, axis=1)))


def icp(source, target, *, max_iterations: int = 200, tol: float = 1e-10, gate: float = 3.0,
        max_distance: float | None = None, tuning: float = CAUCHY_C,
        min_scale: float | None = None) -> ICPResult:
    """Align ``source`` (the synthetic contour C̃_m) to ``target`` (the data contour C_m).

    source : (N, 2), target : (M, 2) finite points, N, M ≥ 2, in one metric plane.
    max_iterations : ICP iterations at most; tol : stop when no source point moves more than
        ``tol`` × the source's RMS radius about its centroid in one iteration.
    gate : inlier gate in units of the robust scale σ; max_distance : optional hard gate
        (plane units): farther pairs get weight 0 and are never inliers.
    tuning : Cauchy constant c; min_scale : floor of σ (default 1e-9 × the larger RMS radius
        of the two sets, so that exact matches keep finite weights).
    Deterministic: no randomness; the result depends only on the inputs.
    """
    return icp_many([(source, target)], max_iterations=max_iterations, tol=tol, gate=gate,
                    max_distance=max_distance, tuning=tuning, min_scale=min_scale)[0]


def icp_many(problems, *, max_iterations: int = 200, tol: float = 1e-10, gate: float = 3.0,
             max_distance: float | None = None, tuning: float = CAUCHY_C,
             min_scale: float | None = None, backend=None) -> list[ICPResult]:
    """:func:`icp` of every (source, target) pair of ``problems``, with the same options, run
    in lockstep: one vectorised reweighting and Procrustes step per iteration for all of them
    (a view's contours cost one Python-level step, not one per pair). Each pair's result is
    :func:`icp`'s for that pair alone, up to rounding (sums over padded arrays).

    backend : None to iterate on the host (NumPy, a k-d tree), or a Backend with float64
        (``has_float64``) to iterate on its device, one thread per run (``Backend.icp_runs``:
        brute-force matching); the same results up to rounding and ties of the nearest target."""
    pairs = [(_points("source", s, minimum=2, finite=False), _points("target", t, minimum=2, finite=False))
             for s, t in problems]
    for name, side in (("source", 0), ("target", 1)):
        if pairs and not np.isfinite(np.concatenate([pair[side] for pair in pairs])).all():
            raise ValueError(f"{name} holds non-finite values")
    if not (is_integer(max_iterations) and max_iterations >= 1):
        raise ValueError(f"max_iterations must be an integer >= 1, got {max_iterations!r}")
    for name, value in (("tol", tol), ("gate", gate), ("tuning", tuning)):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    for name, value in (("max_distance", max_distance), ("min_scale", min_scale)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be None or a finite number > 0, got {value!r}")
    if not pairs:
        return []
    runs = _Runs(pairs, min_scale, tol)
    if backend is None:
        runs.iterate(max_iterations, max_distance, tuning)
        final = _Active(runs, np.arange(len(runs.lengths))).match(max_distance)
    else:
        final = runs.iterate_on(backend, max_iterations, max_distance, tuning)
    return _results(pairs, runs, final, tuning, gate)


def _results(pairs, runs: _Runs, final, tuning: float, gate: float) -> list[ICPResult]:
    """Every pair's result: that of its run with the smallest final robust scale. ``final``:
    the runs' last match, (R, N) distances (+inf where not usable), (N, R) target indices and
    (R,) robust scales (``_Active.match``)."""
    near, index, sigma = final
    best = 3 * np.arange(len(pairs)) + np.argmin(sigma.reshape(-1, 3), axis=1)  # the first of equal scales
    dist = near[best]  # (P, N), +inf where not usable
    weights = 1.0 / (1.0 + (dist / (tuning * sigma[best])[:, None]) ** 2)
    sizes = runs.lengths[best]
    pair, kept = np.nonzero((dist <= (gate * sigma[best])[:, None]) & (np.arange(dist.shape[1]) < sizes[:, None]))
    inliers = np.column_stack([kept, index[kept, best[pair]] - runs.first[best[pair]]]).astype(np.int64)
    near_in = dist[pair, kept]
    moved = np.column_stack([runs.moved_x, runs.moved_y])
    column = np.arange(len(runs.sources)) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    motions = moved[np.repeat(runs.offsets[best], sizes) + column] - runs.sources
    ends, inlier_ends = np.cumsum(sizes).tolist(), np.cumsum(np.bincount(pair, minlength=len(pairs))).tolist()
    results = []
    spans = zip(best.tolist(), [0] + ends[:-1], ends, [0] + inlier_ends[:-1], inlier_ends)
    for p, (r, a, b, i, j) in enumerate(spans):  # pair p: source points a:b, inlier pairs i:j
        rot = _rotation(runs.angle[r])
        error = float(near_in[i:j].sum() / (j - i)) if j > i else math.nan  # np.mean's sum and division
        results.append(ICPResult(rotation=rot, angle=float(math.atan2(rot[1, 0], rot[0, 0])),
                                 translation=np.array([runs.trans_x[r], runs.trans_y[r]]), pairs=inliers[i:j],
                                 motions=motions[a:b], error=error, scale=float(sigma[r]), weights=weights[p, :b - a],
                                 iterations=int(runs.iterations[r]), converged=bool(runs.converged[r])))
    return results


class _Runs:
    """Three IRLS-ICP runs per pair (the identity and ±START_ANGLE about the source's centroid):
    R = 3P runs, of sources of up to N points.

    The pairs' source points, pair after pair: ``sources`` (F/3, 2). Their F source points, run
    after run: ``x``, ``y`` (F,), run r's ``lengths[r]`` from ``offsets[r]``; the same padded
    with zeros: ``src`` (N, 2, R). Each run's transform
    (``angle``, ``trans_x``, ``trans_y``, (R,)), moved points (``moved_x``, ``moved_y``, (F,)),
    what they know of their nearest targets (``nearest``, ``anchor_x``, ``anchor_y``,
    ``room2``, (F,): see :class:`_Active`), iterations run, and whether it converged or stopped.
    Targets: ``target_x``, ``target_y`` (M,), all pairs' one after another, pair p's ``counts[p]``,
    run r's pair's from ``first[r]``; on the host in one k-d tree (``tree``): pair p's in the
    plane z = ``lift``·p, far from the others, so that a query in that plane finds its own
    pair's targets, at their in-plane distances."""

    def __init__(self, pairs, min_scale: float | None, tol: float):
        sources, targets = (np.concatenate(points) for points in zip(*pairs))
        sizes, counts = (np.array([len(points) for points in group]) for group in zip(*pairs))
        self.lengths = np.repeat(sizes, 3)
        self.offsets = np.cumsum(self.lengths) - self.lengths
        self.first = np.repeat(np.cumsum(counts) - counts, 3)
        self.target_x, self.target_y = targets.T.copy()
        self.counts = counts
        self.lift = 1e3 * (1.0 + max(float(np.abs(sources).max()), float(np.abs(targets).max())))
        centres, floor, step_tol = _scales(sources, sizes, targets, counts, min_scale, tol)
        self.floor, self.step_tol = np.repeat(floor, 3), np.repeat(step_tol, 3)
        starts = (0.0, START_ANGLE, -START_ANGLE)
        self.angle = np.tile(starts, len(pairs))
        turns = np.array([_rotation(angle) for angle in starts])
        self.trans_x, self.trans_y = np.concatenate([centre - turns @ centre for centre in centres]).T.copy()
        run = np.repeat(np.arange(len(self.lengths)), self.lengths)  # of each point
        self.sources = sources
        pair_first = np.repeat(np.cumsum(sizes) - sizes, 3)  # each run's pair's first source point
        self.x, self.y = sources[np.arange(len(run)) - self.offsets[run] + pair_first[run]].T
        self.src = np.zeros((max(sizes), 2, len(self.lengths)))
        self.src[np.arange(len(run)) - self.offsets[run], :, run] = np.column_stack([self.x, self.y])
        x, y = _turn(np.cos(self.angle)[run], np.sin(self.angle)[run], self.x, self.y)
        self.moved_x, self.moved_y = x + self.trans_x[run], y + self.trans_y[run]
        self.nearest, self.room2 = np.zeros(len(run), np.intp), np.full(len(run), -1.0)
        self.anchor_x, self.anchor_y = np.zeros(len(run)), np.zeros(len(run))
        self.iterations = np.zeros(len(self.lengths), np.int64)
        self.converged, self.done = np.zeros(len(self.lengths), bool), np.zeros(len(self.lengths), bool)

    @functools.cached_property
    def tree(self) -> "cKDTree":
        """The k-d tree of the host iterations (``_Active``): pair p's targets in the plane
        z = ``lift``·p."""
        from scipy.spatial import cKDTree

        pair = np.repeat(np.arange(len(self.counts)), self.counts)
        return cKDTree(np.column_stack([self.target_x, self.target_y, self.lift * pair]))

    def iterate_on(self, backend, max_iterations: int, max_distance: float | None, tuning: float):
        """``iterate`` on ``backend``'s device, then the runs' last match, as ``_Active.match``
        gives it: (R, N) distances (+inf where not usable), (N, R) target indices, (R,) σ."""
        table = np.column_stack([self.first, np.repeat(self.counts, 3), self.lengths])
        out = backend.icp_runs(self.x, self.y, self.target_x, self.target_y, table, self.angle,
                               np.column_stack([self.trans_x, self.trans_y]), self.floor, self.step_tol,
                               max_iterations=max_iterations,
                               max_distance=math.inf if max_distance is None else max_distance, tuning=tuning)
        self.angle, (self.trans_x, self.trans_y) = out.angles, out.translations.T.copy()
        self.iterations, self.converged = out.iterations.astype(np.int64), out.converged
        self.moved_x, self.moved_y = out.moved.T.copy()
        return _Active(self, np.arange(len(self.lengths))).scaled(out.distances, out.nearest, max_distance)

    def iterate(self, max_iterations: int, max_distance: float | None, tuning: float) -> None:
        """Reweight and solve the weighted Procrustes problem for every run not yet done, until
        each converges, loses all its weight, or ``max_iterations`` have run."""
        active = _Active(self, np.arange(len(self.lengths)))
        for iteration in range(1, max_iterations + 1):
            if not len(active.rows):
                break
            near, index, sigma = active.match(max_distance)
            self.iterations[active.rows] = iteration
            weights = 1.0 / (1.0 + (near / (tuning * sigma[:, None])) ** 2)  # 0 where not usable (inf)
            total = weights.sum(axis=1)
            dead = total <= 0.0
            if dead.any():
                self.done[active.rows[dead]] = True
                active, weights, index, total = active.subset(~dead), weights[~dead], index[:, ~dead], total[~dead]
            still = active.move(np.divide(weights.T, total, order="C"), index)
            if still.any():
                self.converged[active.rows[still]] = self.done[active.rows[still]] = True
                active = active.subset(~still)
        active.save()


class _Active:
    """The A runs ``rows`` of ``runs`` still iterating: their state while they do (``save``
    puts it back in ``runs``), and what their iterations reuse until the set changes.

    Their F' points in run order: ``points`` (F',) into the runs' points, ``rank`` (F',) into
    ``rows``, ``starts`` (A,) each row's first, and ``spot``, ``spot_t`` (F',), their flat
    positions in (A, N) and (N, A) padded arrays. ``coords`` (N, 4, A): the padded sources'
    x, y and their matched targets' x, y. Templates: the (A, N) distances (inf) and (N, A)
    indices of the matched targets (the pair's first: padding).

    Nearest targets: each point keeps the nearest target ``nearest`` (F',) that its last k-d
    tree query found, at (``anchor_x``, ``anchor_y``), and ``room2`` (F',), the square of how
    far it may move from there and keep that nearest target (half the gap to the second
    nearest, less 1e-9 of it, far above rounding; -1: none). Only the points that leave their
    room query the tree again; the others' distances are computed as the tree computes them."""

    def __init__(self, runs: _Runs, rows: np.ndarray):
        self.runs, self.rows = runs, rows
        lengths, size = runs.lengths[rows], len(runs.src)
        self.rank = np.repeat(np.arange(len(rows)), lengths)
        self.starts = np.cumsum(lengths) - lengths
        column = np.arange(len(self.rank)) - self.starts[self.rank]
        self.points = runs.offsets[rows][self.rank] + column
        self.spot, self.spot_t = self.rank * size + column, column * len(rows) + self.rank
        self.x, self.y = runs.x[self.points], runs.y[self.points]
        self.angle, self.trans_x, self.trans_y = runs.angle[rows], runs.trans_x[rows], runs.trans_y[rows]
        self.moved_x, self.moved_y = runs.moved_x[self.points], runs.moved_y[self.points]
        self.nearest, self.room2 = runs.nearest[self.points], runs.room2[self.points]
        self.anchor_x, self.anchor_y = runs.anchor_x[self.points], runs.anchor_y[self.points]
        self.coords = np.empty((size, 4, len(rows)))
        self.coords[:, :2] = runs.src[:, :, rows]
        self.blank = np.full((len(rows), size), np.inf)
        self.base = np.repeat(runs.first[rows][None, :], size, axis=0)
        self.floor, self.step_tol = runs.floor[rows], runs.step_tol[rows]
        self.count, self.middles = lengths, _middles(lengths, size)

    def save(self) -> None:
        """Put the rows' transforms, moved points and nearest targets back in ``runs``."""
        runs, rows, points = self.runs, self.rows, self.points
        runs.angle[rows], runs.trans_x[rows], runs.trans_y[rows] = self.angle, self.trans_x, self.trans_y
        runs.moved_x[points], runs.moved_y[points] = self.moved_x, self.moved_y
        runs.nearest[points], runs.room2[points] = self.nearest, self.room2
        runs.anchor_x[points], runs.anchor_y[points] = self.anchor_x, self.anchor_y

    def subset(self, keep: np.ndarray) -> _Active:
        """The rows ``keep`` (A,) of this set (after saving it)."""
        self.save()
        return _Active(self.runs, self.rows[keep])

    def match(self, max_distance: float | None):
        """(A, N) distances of the moved points to their nearest targets, +inf where a pair
        does not count (padding, farther than ``max_distance``), the (N, A) indices of those
        targets, and the (A,) robust scales σ."""
        distances = self.distances()
        return self.scaled(distances, self.nearest, max_distance)

    def scaled(self, distances: np.ndarray, nearest: np.ndarray, max_distance: float | None):
        """``match``'s result from the points' (F',) ``distances`` to their ``nearest`` (F',)
        targets (the host's matching, or the device's after its last iteration)."""
        dist, index = self.blank.copy(), self.base.copy()
        dist.reshape(-1)[self.spot], index.reshape(-1)[self.spot_t] = distances, nearest
        if max_distance is None:
            near, count, middles = dist, self.count, self.middles
        else:
            near = np.where(dist <= max_distance, dist, np.inf)
            count, middles = np.count_nonzero(dist <= max_distance, axis=1), None
        return near, index, np.fmax(_medians(near, count, middles) / RAYLEIGH_MEDIAN, self.floor)  # floor if none

    def distances(self) -> np.ndarray:
        """(F',) distances of the moved points to their nearest targets (``nearest``), which
        the points that left their rooms query again."""
        x, y = self.moved_x, self.moved_y
        dx, dy = x - self.anchor_x, y - self.anchor_y
        out = np.flatnonzero(dx * dx + dy * dy >= self.room2)
        if len(out):
            self._query(out)
        dx, dy = x - self.runs.target_x[self.nearest], y - self.runs.target_y[self.nearest]
        return np.sqrt(dx * dx + dy * dy)  # as the tree: (dx² + dy²) + dz², dz = 0

    def _query(self, out: np.ndarray) -> None:
        """Query the k-d tree, at once, for the two nearest targets of the points ``out``
        (F'',) and set their rooms. Where the two are as near to 1e-9 (ties, rounding), the
        nearest is the one that a query for the nearest alone finds, and the room is none."""
        runs = self.runs
        queries = np.column_stack([self.moved_x[out], self.moved_y[out], runs.lift * (self.rows // 3)[self.rank[out]]])
        dist, found = runs.tree.query(queries, k=2)
        room = (dist[:, 1] * (1.0 - 1e-9) - dist[:, 0]) / 2.0
        close = room <= 0.0
        if close.any():
            found[close, 0] = runs.tree.query(queries[close], k=1)[1]
        self.nearest[out], self.anchor_x[out], self.anchor_y[out] = found[:, 0], queries[:, 0], queries[:, 1]
        self.room2[out] = np.where(close, -1.0, room * room)

    def move(self, w: np.ndarray, index: np.ndarray) -> np.ndarray:
        """Solve the weighted Procrustes problem of the weights (N, A) (each row's summing to 1)
        and matched targets ``index`` (N, A), move the rows' points, and say which rows (A,)
        moved no point more than their tolerance. The weighted sums run over the points one
        after another from 0 (axis 0, the outermost, of contiguous arrays), as
        ``np.einsum("rn,rnd->rd", w, src)`` and ``np.einsum("rni,rnj->rij", a, b)`` sum them."""
        q, rank = self.coords, self.rank
        q[:, 2], q[:, 3] = self.runs.target_x[index], self.runs.target_y[index]
        centres = np.add.reduce(q * w[:, None, :], axis=0, initial=0.0)  # (4, A): source's, target's
        diff = q - centres
        b = diff[:, 2:] * w[:, None, :]
        h = np.add.reduce(diff[:, :2, None, :] * b[:, None, :, :], axis=0, initial=0.0)  # (2, 2, A)
        self.angle = np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
        cos, sin = np.cos(self.angle), np.sin(self.angle)
        x, y = _turn(cos, sin, centres[0], centres[1])
        self.trans_x, self.trans_y = centres[2] - x, centres[3] - y
        x, y = _turn(cos[rank], sin[rank], self.x, self.y)
        x, y = x + self.trans_x[rank], y + self.trans_y[rank]
        dx, dy = x - self.moved_x, y - self.moved_y
        step = np.sqrt(np.maximum.reduceat(dx * dx + dy * dy, self.starts))  # each row's largest
        self.moved_x, self.moved_y = x, y
        return step <= self.step_tol


def _rotation(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def _turn(cos: np.ndarray, sin: np.ndarray, x: np.ndarray, y: np.ndarray):
    """Points (x, y) turned counter-clockwise by the angles of cosines and sines ``cos``,
    ``sin``, all of one shape: ``(c x - s y, s x + c y)``."""
    return cos * x - sin * y, sin * x + cos * y


def _scales(sources: np.ndarray, sizes: np.ndarray, targets: np.ndarray, counts: np.ndarray,
            min_scale: float | None, tol: float):
    """Of P pairs of sources (F, 2) and targets (M, 2), one pair's after another's, of
    ``sizes``, ``counts`` (P,) points: the (P, 2) centroids of the sources, the (P,) floors of
    σ (``min_scale``, or 1e-9 × the larger RMS radius of the two sets) and step tolerances
    (``tol`` × the source's RMS radius, at least the floor)."""
    centres = _centroids(sources, sizes)
    src_size = _rms_radii(sources, sizes, centres)
    if min_scale is not None:
        floor = np.full(len(sizes), min_scale)
    else:
        tgt_size = _rms_radii(targets, counts, _centroids(targets, counts))
        floor = 1e-9 * np.maximum(np.maximum(tgt_size, src_size), 1e-300)
    return centres, floor, tol * np.maximum(src_size, floor)


def _centroids(points: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """(P, 2) centroids of P point sets, one after another in points (F, 2), of ``lengths`` (P,)
    points: each set's ``mean(axis=0)`` (its points summed in order, then zeros)."""
    owner = np.repeat(np.arange(len(lengths)), lengths)
    padded = np.zeros((max(lengths), len(lengths), 2))
    padded[np.arange(len(points)) - (np.cumsum(lengths) - lengths)[owner], owner] = points
    return np.add.reduce(padded, axis=0) / lengths[:, None]


def _rms_radii(points: np.ndarray, lengths: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(P,) RMS distances of P point sets, as in :func:`_centroids`, from their centroids
    ``centres`` (P, 2)."""
    d = points - np.repeat(centres, lengths, axis=0)
    squares = np.sum(d * d, axis=1)
    ends = np.cumsum(lengths).tolist()
    return np.array([math.sqrt(squares[a:b].sum() / (b - a)) for a, b in zip([0] + ends[:-1], ends)])


def _points(name: str, value, *, minimum: int, finite: bool = True) -> np.ndarray:
    """``value`` as (N, 2) float64 points, N >= ``minimum``, finite unless ``finite`` is False
    (the caller checks), or ValueError naming ``name``."""
    array = np.asarray(value, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 2:
        raise ValueError(f"{name} must have shape (N, 2), got {array.shape}")
    if len(array) < minimum:
        raise ValueError(f"{name} needs at least {minimum} points, got {len(array)}")
    if finite and not np.all(np.isfinite(array)):
        raise ValueError(f"{name} holds non-finite values")
    return array


def _medians(values: np.ndarray, count: np.ndarray, middles=None) -> np.ndarray:
    """(R,) np.median of each row of values (R, N) that holds ``count`` (R,) values and +inf
    elsewhere (NaN-free); NaN for an empty row. ``middles``: ``_middles(count, N)``, if known."""
    low, high = _middles(count, values.shape[1]) if middles is None else middles
    kept = np.sort(values, axis=1).reshape(-1)
    return np.where(count > 0, (kept[low] + kept[high]) / 2.0, np.nan)


def _middles(count: np.ndarray, size: int):
    """Flat indices (R,) into sorted rows (R, size) that hold count (R,) values each, of their
    lower and upper middle values (the same for an odd count; for none, of some value)."""
    start = np.arange(len(count)) * size
    return start + (count - 1) // 2, start + count // 2
