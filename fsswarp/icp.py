"""IRLS-ICP of 2-D contours: the rigid motion that aligns a synthetic contour with the data's
(paper §2.4, eq. 5; DESIGN §7).

Plane: contours are (N, 2) points in a metric 2-D plane. The engine uses the fan plane of
paper eq. (3), ``(x, y) = R (sin θ, cos θ)`` in metres (``fsswarp.sonar.fan_xy``): both axes
are metres, so distances, the in-plane rotation and CE are well defined, while (θ, R) mixes
radians and metres. Any other metric plane works alike.

Method (iteratively reweighted least squares, refs [46, 47] of the paper): every iteration
matches each transformed source point to its nearest target point (``scipy.spatial.cKDTree``;
unequal, unmatched sets, several source points may share one target point), weighs the pairs
with Cauchy weights ``w = 1 / (1 + (r / (c σ))²)``, c = 2.3849 (95 % Gaussian efficiency), on
the residual distances r with the robust scale ``σ = median(r) / √(2 ln 2)`` (the median
absolute residual, made consistent for the distance of a 2-D Gaussian error of per-axis σ,
which is Rayleigh), and solves the weighted Procrustes problem for the whole rotation and
translation from the original source in closed form. It stops when no transformed source point
moves more than ``tol`` × the source's RMS radius between iterations.

Starts: nearest-neighbour matching is local, and a contour with a stretch the other lacks plus
false highlights can hold a wrong minimum a few degrees from the truth (a probe found one at
0.064 rad from a start at the true angle). ICP therefore runs from three deterministic starts,
the identity and rotations by ``±START_ANGLE`` (0.05 rad) about the source's centroid, and keeps
the run with the smallest final robust scale σ (the median residual: outliers and unmatched
stretches do not move it); ties go to the earlier start, so exact matches return the identity.

Batches: ``icp_many`` runs many pairs in lockstep over padded arrays, one vectorised
reweighting and Procrustes step per iteration for all of their runs, and one k-d tree query
for all of them (each pair's targets in a plane of their own, far from the others'); each
pair gets ``icp``'s result for it alone up to rounding, and ``icp`` is the batch of one.

Inliers: after the last iteration a pair (i, k(i)) is an inlier when ``r ≤ gate · σ``
(default 3σ) and, if given, ``r ≤ max_distance``. CE (eq. 5) is the mean distance of the
inlier pairs after alignment.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

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
             min_scale: float | None = None) -> list[ICPResult]:
    """:func:`icp` of every (source, target) pair of ``problems``, with the same options, run
    in lockstep: one vectorised reweighting and Procrustes step per iteration for all of them
    (a view's contours cost one Python-level step, not one per pair). Each pair's result is
    :func:`icp`'s for that pair alone, up to rounding (sums over padded arrays)."""
    pairs = [(_points("source", s, minimum=2), _points("target", t, minimum=2)) for s, t in problems]
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
    runs.iterate(max_iterations, max_distance, tuning)
    dist, nearest, usable, sigma = runs.match(max_distance)
    results = []
    for p, (src, tgt) in enumerate(pairs):
        r = 3 * p + int(np.argmin(sigma[3 * p:3 * p + 3]))  # the first of equal scales
        n = len(src)
        d, k, ok = dist[r, :n], nearest[r, :n], usable[r, :n]
        weights = np.where(ok, 1.0 / (1.0 + (d / (tuning * sigma[r])) ** 2), 0.0)
        index = np.flatnonzero(ok & (d <= gate * sigma[r]))
        moved = runs.moved[r, :n]
        rot = _rotation(runs.angle[r])
        results.append(ICPResult(rotation=rot, angle=float(math.atan2(rot[1, 0], rot[0, 0])),
                                 translation=runs.trans[r].copy(),
                                 pairs=np.stack([index, k[index]], axis=1).astype(np.int64), motions=moved - src,
                                 error=contour_error(tgt[k[index]], moved[index]), scale=float(sigma[r]),
                                 weights=weights, iterations=int(runs.iterations[r]),
                                 converged=bool(runs.converged[r])))
    return results


class _Runs:
    """Three IRLS-ICP runs per pair (the identity and ±START_ANGLE about the source's centroid),
    as padded arrays: (R = 3P, N) source points, their valid mask, transforms (angle, trans),
    moved points, iterations run and whether each converged or stopped."""

    def __init__(self, pairs, min_scale: float | None, tol: float):
        size = max(len(src) for src, _ in pairs)
        count = 3 * len(pairs)
        self.targets = np.concatenate([tgt for _, tgt in pairs])  # all pairs' targets, one after another
        self.first = np.repeat(np.cumsum([0] + [len(tgt) for _, tgt in pairs[:-1]]), 3)  # run -> its first
        self.lengths = np.repeat([len(src) for src, _ in pairs], 3)
        # one k-d tree for every pair: pair p's targets and queries lie in the plane z = lift·p,
        # so a query's nearest target is its own pair's, at its in-plane distance (dz = 0)
        reach = max(float(np.abs(points).max()) for pair in pairs for points in pair)
        self.lift = 1e3 * (1.0 + reach)
        owner = np.repeat(np.arange(len(pairs)), [len(tgt) for _, tgt in pairs])
        self.tree = cKDTree(np.column_stack([self.targets, self.lift * owner]))
        self.valid = np.arange(size)[None, :] < self.lengths[:, None]
        self.src = np.zeros((count, size, 2))
        self.floor, self.step_tol = np.empty(count), np.empty(count)
        self.angle, self.trans = np.zeros(count), np.zeros((count, 2))
        for p, (src, tgt) in enumerate(pairs):
            src_size = _rms_radius(src)
            floor = min_scale if min_scale is not None else 1e-9 * max(_rms_radius(tgt), src_size, 1e-300)
            centre = src.mean(axis=0)
            for i, angle in enumerate((0.0, START_ANGLE, -START_ANGLE)):
                r = 3 * p + i
                self.src[r, :len(src)] = src
                self.floor[r], self.step_tol[r] = floor, tol * max(src_size, floor)
                self.angle[r], self.trans[r] = angle, centre - _rotation(angle) @ centre
        self.moved = self._apply(np.arange(count))
        self.iterations = np.zeros(count, np.int64)
        self.converged, self.done = np.zeros(count, bool), np.zeros(count, bool)

    def _apply(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows), N, 2) source points of the runs ``rows`` moved by their transforms."""
        return _turn(self.angle[rows], self.src[rows]) + self.trans[rows, None, :]

    def match(self, max_distance: float | None, rows: np.ndarray | None = None):
        """For the runs ``rows`` (default all), (rows, N) distances and nearest targets of the
        moved points (one k-d tree query for all), which pairs count, and the robust scale σ."""
        rows = np.arange(len(self.src)) if rows is None else rows
        valid = self.valid[rows]
        dist = np.full(valid.shape, np.inf)
        nearest = np.zeros(valid.shape, np.int64)
        lift = np.broadcast_to((self.lift * (rows // 3))[:, None], valid.shape)
        dist[valid], found = self.tree.query(np.column_stack([self.moved[rows][valid], lift[valid]]), k=1)
        nearest[valid] = found - np.broadcast_to(self.first[rows, None], valid.shape)[valid]
        usable = valid & (True if max_distance is None else dist <= max_distance)
        sigma = np.where(usable.any(axis=1), _medians(dist, usable) / RAYLEIGH_MEDIAN, self.floor[rows])
        return dist, nearest, usable, np.maximum(sigma, self.floor[rows])

    def iterate(self, max_iterations: int, max_distance: float | None, tuning: float) -> None:
        """Reweight and solve the weighted Procrustes problem for every run not yet done, until
        each converges, loses all its weight, or ``max_iterations`` have run."""
        for iteration in range(1, max_iterations + 1):
            rows = np.flatnonzero(~self.done)
            if not len(rows):
                break
            dist, nearest, usable, sigma = self.match(max_distance, rows)
            self.iterations[rows] = iteration
            weights = np.where(usable, 1.0 / (1.0 + (dist / (tuning * sigma[:, None])) ** 2), 0.0)
            total = weights.sum(axis=1)
            dead = total <= 0.0
            self.done[rows[dead]] = True
            rows, weights, nearest, total = rows[~dead], weights[~dead], nearest[~dead], total[~dead]
            w = weights / total[:, None]
            src = self.src[rows]
            dst = self.targets[nearest + self.first[rows, None]]
            cs, cd = np.einsum("rn,rnd->rd", w, src), np.einsum("rn,rnd->rd", w, dst)
            h = np.einsum("rni,rnj->rij", src - cs[:, None, :], (dst - cd[:, None, :]) * w[:, :, None])
            self.angle[rows] = np.arctan2(h[:, 0, 1] - h[:, 1, 0], h[:, 0, 0] + h[:, 1, 1])
            self.trans[rows] = cd - _turn(self.angle[rows], cs)
            new = self._apply(rows)
            step = np.max(np.where(self.valid[rows], np.linalg.norm(new - self.moved[rows], axis=2), 0.0), axis=1)
            self.moved[rows] = new
            still = step <= self.step_tol[rows]
            self.converged[rows[still]] = self.done[rows[still]] = True


def _rotation(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def _turn(angle: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (R, ..., 2) turned counter-clockwise by their row's angle (R,) (rad)."""
    shape = angle.shape + (1,) * (points.ndim - 2)
    c, s = np.cos(angle).reshape(shape), np.sin(angle).reshape(shape)
    x, y = points[..., 0], points[..., 1]
    return np.stack([c * x - s * y, s * x + c * y], axis=-1)


def _rms_radius(points: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))


def _points(name: str, value, *, minimum: int) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 2:
        raise ValueError(f"{name} must have shape (N, 2), got {array.shape}")
    if len(array) < minimum:
        raise ValueError(f"{name} needs at least {minimum} points, got {len(array)}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} holds non-finite values")
    return array


def _medians(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(R,) np.median of each row's values (R, N) where ``mask`` (R, N) holds (NaN-free): the
    middle one, or the mean of the middle two; NaN for an empty row."""
    count = mask.sum(axis=1)
    kept = np.sort(np.where(mask, values, np.inf), axis=1)
    rows = np.arange(len(values))
    low = kept[rows, np.maximum(count - 1, 0) // 2]
    high = kept[rows, np.minimum(count // 2, values.shape[1] - 1)]
    with np.errstate(invalid="ignore"):
        return np.where(count > 0, (low + high) / 2.0, np.nan)
