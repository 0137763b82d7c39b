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
    src = _points("source", source, minimum=2)
    tgt = _points("target", target, minimum=2)
    if not (is_integer(max_iterations) and max_iterations >= 1):
        raise ValueError(f"max_iterations must be an integer >= 1, got {max_iterations!r}")
    for name, value in (("tol", tol), ("gate", gate), ("tuning", tuning)):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    for name, value in (("max_distance", max_distance), ("min_scale", min_scale)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be None or a finite number > 0, got {value!r}")
    src_size = _rms_radius(src)
    floor = min_scale if min_scale is not None else 1e-9 * max(_rms_radius(tgt), src_size, 1e-300)
    step_tol = tol * max(src_size, floor)
    tree = cKDTree(tgt)
    centre = src.mean(axis=0)
    runs = [_Run(src, rot, centre - rot @ centre) for rot in map(_rotation, (0.0, START_ANGLE, -START_ANGLE))]
    _irls(runs, src, tree, tgt, max_iterations, step_tol, max_distance, floor, tuning)
    best = min(runs, key=lambda run: run.match[3])  # the first of equal scales
    dist, nearest, usable, sigma = best.match
    moved = best.moved
    weights = np.where(usable, 1.0 / (1.0 + (dist / (tuning * sigma)) ** 2), 0.0)
    inlier = usable & (dist <= gate * sigma)
    index = np.flatnonzero(inlier)
    pairs = np.stack([index, nearest[index]], axis=1).astype(np.int64)
    error = contour_error(tgt[nearest[index]], moved[index])
    rot = best.rot
    return ICPResult(rotation=rot, angle=float(math.atan2(rot[1, 0], rot[0, 0])), translation=best.trans,
                     pairs=pairs, motions=moved - src, error=error, scale=sigma, weights=weights,
                     iterations=best.iterations, converged=best.converged)


class _Run:
    """One IRLS-ICP run from the transform (rot, trans): its transform, moved source,
    iterations, whether it converged, whether it stopped, and the final match."""

    def __init__(self, src: np.ndarray, rot: np.ndarray, trans: np.ndarray):
        self.rot, self.trans, self.moved = rot, trans, src @ rot.T + trans
        self.iterations, self.converged, self.done, self.match = 0, False, False, None


def _irls(runs: list[_Run], src: np.ndarray, tree: cKDTree, tgt: np.ndarray, max_iterations: int,
          step_tol: float, max_distance: float | None, floor: float, tuning: float) -> None:
    """Iterate the runs in lockstep, one k-d tree query per iteration for all of them (each
    run's arithmetic is its own; the query's per-point results do not depend on the batch),
    then give each its final match (distances, nearest, usable, σ)."""
    for iteration in range(1, max_iterations + 1):
        active = [run for run in runs if not run.done]
        if not active:
            break
        for run, (dist, nearest, usable, sigma) in zip(active, _match(tree, [r.moved for r in active],
                                                                      max_distance, floor)):
            run.iterations = iteration
            weights = np.where(usable, 1.0 / (1.0 + (dist / (tuning * sigma)) ** 2), 0.0)
            if weights.sum() <= 0.0:
                run.done = True
                continue
            run.rot, run.trans = _weighted_procrustes(src, tgt[nearest], weights)
            new = src @ run.rot.T + run.trans
            step = float(np.max(np.linalg.norm(new - run.moved, axis=1)))
            run.moved = new
            if step <= step_tol:
                run.converged = run.done = True
    for run, match in zip(runs, _match(tree, [run.moved for run in runs], max_distance, floor)):
        run.match = match


def _rotation(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def _match(tree: cKDTree, moved: list[np.ndarray], max_distance: float | None, floor: float) -> list[tuple]:
    """Per set of moved source points (one query for all): the nearest target of every point,
    which pairs count, and the robust scale."""
    dist_all, nearest_all = tree.query(np.concatenate(moved), k=1)
    out, start = [], 0
    for points in moved:
        dist, nearest = dist_all[start:start + len(points)], nearest_all[start:start + len(points)]
        start += len(points)
        usable = np.ones(len(points), dtype=bool) if max_distance is None else dist <= max_distance
        kept = dist if max_distance is None else dist[usable]
        sigma = _median(kept) / RAYLEIGH_MEDIAN if len(kept) else floor
        out.append((dist, nearest, usable, max(sigma, floor)))
    return out


def _median(values: np.ndarray) -> float:
    """np.median of a non-empty 1-D array without NaN, at a fraction of its call overhead
    (ICP calls it every iteration): the middle element, or the mean of the middle two."""
    half = len(values) // 2
    if len(values) % 2:
        return float(np.partition(values, half)[half])
    low, high = np.partition(values, (half - 1, half))[half - 1:half + 1]
    return float((low + high) / 2.0)


def _weighted_procrustes(src: np.ndarray, dst: np.ndarray, weights: np.ndarray):
    """Rotation (2, 2) and translation (2,) minimising ``Σ w_i |R s_i + t - d_i|²`` (closed form)."""
    w = weights / weights.sum()
    cs, cd = w @ src, w @ dst
    h = (src - cs).T @ ((dst - cd) * w[:, None])  # Σ w s̄ d̄ᵀ
    rot = _rotation(math.atan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1]))
    return rot, cd - rot @ cs


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
