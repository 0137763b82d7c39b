"""Model-accuracy metrics against a true mesh (paper §2.5, DESIGN §9).

- E_V (paper eq. 12): the non-common volume of two closed meshes over their union,
  ``(V_a + V_b − 2 V_ab) / (V_a + V_b − V_ab)``, 0 for identical volumes, 1 for disjoint ones.
  Volumes are exact, by mesh booleans (manifold3d) when both meshes are closed 2-manifolds,
  else counted on a voxel grid (:func:`inside_grid`, ``grid`` samples along the longest side
  of the pair's box).
- Chamfer-L1: the mean of the two directed mean distances from ``samples`` points drawn
  uniformly (area-weighted, seeded) on one surface to the other surface (exact
  point-to-triangle distances), in metres.
- F-score at τ: the harmonic mean of precision (the share of the estimate's sample points
  within τ of the truth's surface) and recall (the share of the truth's points within τ of
  the estimate's). τ defaults to ``TAU_FRACTION`` = 2% of the truth's bounding-box diagonal:
  6.3 mm on coral-one (0.32 m diagonal), between the range bin (3.9 mm) and the beam spacing
  at the target (10 mm at 2 m) of the default sonar, so the score measures what the sonar
  resolves, on an object of any size.
"""

from __future__ import annotations

import math
import os

import numpy as np

from .errors import InputError

#: τ of the F-score as a fraction of the truth's bounding-box diagonal.
TAU_FRACTION = 0.02
#: Points sampled on each surface for Chamfer and F-score.
SAMPLES = 20_000
#: Voxel-grid samples along the longest side for volumes of meshes that are not closed.
GRID = 256


def volumes(a, b, *, method: str = "auto", grid: int = GRID) -> tuple[float, float, float, str]:
    """``(V_a, V_b, V_ab, method)``: the volumes of two meshes and of their intersection (m³)
    by ``method``: "boolean" (exact, manifold3d; both meshes must be closed 2-manifolds),
    "voxels" (``grid`` samples along the longest side of the pair's box) or "auto" (boolean
    when both are closed 2-manifolds, else voxels); returns the method used."""
    import trimesh

    _check_mesh("a", a)
    _check_mesh("b", b)
    if method not in ("auto", "boolean", "voxels"):
        raise InputError("must be auto, boolean or voxels", field="method", value=method)
    closed = a.is_volume and b.is_volume
    if method == "boolean" and not closed:
        raise InputError("mesh booleans need two closed 2-manifold meshes", field="method", value=method)
    if method != "voxels" and closed:
        both = trimesh.boolean.intersection([a, b], engine="manifold")
        return float(a.volume), float(b.volume), float(both.volume if len(both.faces) else 0.0), "boolean"
    lo = np.minimum(a.bounds[0], b.bounds[0])
    hi = np.maximum(a.bounds[1], b.bounds[1])
    step = float((hi - lo).max()) / grid
    shape = tuple(int(n) for n in np.ceil((hi - lo) / step) + 1)
    inside_a = inside_grid(a, lo, step, shape)
    inside_b = inside_grid(b, lo, step, shape)
    cell = step**3
    return (float(inside_a.sum() * cell), float(inside_b.sum() * cell), float((inside_a & inside_b).sum() * cell),
            "voxels")


def volume_error(estimate, truth, *, grid: int = GRID) -> float:
    """E_V of paper eq. (12) between two meshes (symmetric)."""
    va, vb, vab, _ = volumes(estimate, truth, grid=grid)
    union = va + vb - vab
    return float((va + vb - 2.0 * vab) / union) if union > 0 else 0.0


def inside_grid(mesh, origin, step: float, shape) -> np.ndarray:
    """(nx, ny, nz) bool: which sample points ``origin + step·(i, j, k)`` lie inside ``mesh``.

    Vertical scanlines: every triangle adds its winding (−sign of its normal's z) above the
    height where it crosses each column it covers; a point is inside where the sum is not 0
    (exact for closed meshes of either orientation, a fair answer for nearly closed ones).
    Sample columns are shifted by 1e-6 of a step so that they miss shared edges and vertices
    of meshes built on round coordinates."""
    origin = np.asarray(origin, np.float64) + 1e-6 * step * np.array([math.sqrt(2.0), math.sqrt(3.0), 0.0])
    nx, ny, nz = (int(n) for n in shape)
    tri = np.asarray(mesh.triangles, np.float64)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    cross_z = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    use = cross_z != 0
    a, b, c, cross_z = a[use], b[use], c[use], cross_z[use]
    lo = np.ceil((np.minimum(np.minimum(a, b), c)[:, :2] - origin[:2]) / step).astype(np.int64)
    hi = np.floor((np.maximum(np.maximum(a, b), c)[:, :2] - origin[:2]) / step).astype(np.int64)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, [nx - 1, ny - 1])
    width = np.maximum(hi - lo + 1, 0)
    counts = width[:, 0] * width[:, 1]
    winding = np.zeros((nx * ny, nz + 1), np.int32)
    for chunk in np.array_split(np.arange(len(a)), max(1, int(counts.sum()) // 2_000_000 + 1)):
        owner = np.repeat(chunk, counts[chunk])
        if len(owner) == 0:
            continue
        first = np.cumsum(counts[chunk]) - counts[chunk]
        local = np.arange(len(owner)) - np.repeat(first, counts[chunk])
        i = lo[owner, 0] + local // width[owner, 1]
        j = lo[owner, 1] + local % width[owner, 1]
        x = origin[0] + step * i
        y = origin[1] + step * j
        ta, tb, tc = a[owner], b[owner], c[owner]
        # barycentric weights of (x, y) in the triangle's projection
        wa = ((tb[:, 0] - x) * (tc[:, 1] - y) - (tb[:, 1] - y) * (tc[:, 0] - x)) / cross_z[owner]
        wb = ((tc[:, 0] - x) * (ta[:, 1] - y) - (tc[:, 1] - y) * (ta[:, 0] - x)) / cross_z[owner]
        wc = 1.0 - wa - wb
        hit = (wa >= 0) & (wb >= 0) & (wc >= 0)
        z = wa[hit] * ta[hit, 2] + wb[hit] * tb[hit, 2] + wc[hit] * tc[hit, 2]
        k = np.clip(np.ceil((z - origin[2]) / step).astype(np.int64), 0, nz)
        np.add.at(winding, (i[hit] * ny + j[hit], k), -np.sign(cross_z[owner][hit]).astype(np.int32))
    return (np.cumsum(winding, axis=1)[:, :nz] != 0).reshape(nx, ny, nz)


def surface_distances(a, b, *, samples: int = SAMPLES, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Distances (m) from ``samples`` seeded surface points of ``a`` to the surface of ``b``
    and from as many points of ``b`` to ``a``: ((samples,), (samples,))."""
    _check_mesh("a", a)
    _check_mesh("b", b)
    return _directed_distances(a, b, samples, [seed, 0]), _directed_distances(b, a, samples, [seed, 1])


def _directed_distances(a, b, samples: int, seed: list[int]) -> np.ndarray:
    """(samples,) distances (m) from points sampled on ``a`` (generator seeded with ``seed``)
    to the surface of ``b``."""
    import trimesh

    points, _ = trimesh.sample.sample_surface(a, samples, seed=np.random.default_rng(seed))
    return point_mesh_distance(points, b)


def chamfer(a, b, *, samples: int = SAMPLES, seed: int = 0) -> float:
    """Chamfer-L1 distance (m): the mean of the two directed mean surface distances."""
    d_ab, d_ba = surface_distances(a, b, samples=samples, seed=seed)
    return 0.5 * float(d_ab.mean() + d_ba.mean())


def fscore(estimate, truth, *, tau: float | None = None, samples: int = SAMPLES,
           seed: int = 0) -> tuple[float, float, float, float]:
    """``(F, precision, recall, tau)`` at distance τ (m; default 2% of the truth's
    bounding-box diagonal)."""
    tau = default_tau(truth) if tau is None else float(tau)
    d_et, d_te = surface_distances(estimate, truth, samples=samples, seed=seed)
    return _fscore(d_et, d_te, tau) + (tau,)


def default_tau(truth) -> float:
    """τ = TAU_FRACTION × the truth's bounding-box diagonal (m)."""
    return TAU_FRACTION * float(np.linalg.norm(np.ptp(np.asarray(truth.bounds), axis=0)))


def compare(estimate, truth, *, samples: int = SAMPLES, seed: int = 0) -> dict:
    """Every metric of an estimate against the truth, for reports (JSON-ready): E_V, the share
    of the true volume inside the estimate, volumes (m³), Chamfer-L1 (m), F-score, precision,
    recall and τ (m), and how volumes and points were obtained."""
    return combine(truth, *(compare_part(estimate, truth, part, samples=samples, seed=seed) for part in (0, 1)),
                   samples=samples, seed=seed)


def compare_part(estimate, truth, part: int, *, samples: int = SAMPLES, seed: int = 0) -> tuple:
    """Half of :func:`compare`'s work, so that two processes can share one compare: part 0,
    (the volumes of :func:`volumes`, the (samples,) distances from the estimate to the truth);
    part 1, (the distances from the truth to the estimate,)."""
    _check_mesh("estimate", estimate)
    _check_mesh("truth", truth)
    if part == 0:
        return volumes(estimate, truth), _directed_distances(estimate, truth, samples, [seed, 0])
    return (_directed_distances(truth, estimate, samples, [seed, 1]),)


def combine(truth, first: tuple, second: tuple, *, samples: int = SAMPLES, seed: int = 0) -> dict:
    """:func:`compare`'s dict from its two :func:`compare_part` results."""
    (va, vt, both, method), d_et = first
    (d_te,) = second
    tau = default_tau(truth)
    f, precision, recall = _fscore(d_et, d_te, tau)
    union = va + vt - both
    return {"E_V": (va + vt - 2.0 * both) / union if union > 0 else 0.0,
            "truth_volume_kept": both / vt if vt > 0 else 0.0,
            "volume_m3": va, "truth_volume_m3": vt, "common_volume_m3": both, "volume_method": method,
            "chamfer_m": 0.5 * float(d_et.mean() + d_te.mean()), "fscore": f, "precision": precision,
            "recall": recall, "tau_m": tau, "samples": samples, "seed": seed}


def point_mesh_distance(points, mesh, *, chunk: int = 2048) -> np.ndarray:
    """(N,) exact distance (m) from each point to the nearest triangle of ``mesh``.

    Candidates come from a k-d tree over sites on the triangles, such that every point of a
    triangle lies within ρ of one of its sites (ρ: the 90th percentile of the triangles' largest
    centroid-to-vertex distance): the centroid where that distance is at most ρ, else a
    barycentric grid with edges under ρ. The triangle of the nearest site bounds the distance
    from above by U; only triangles with a site within U + ρ can be closer. A site at distance
    s whose triangle lies within r of it (its centroid spread, else ρ) bounds that triangle's
    distance from below by s − r, so only triangles with a site where s − r < U are tested
    exactly, each once per point. Chunks of ``chunk`` points run on a thread pool (NumPy and the
    k-d tree release the GIL); the result does not depend on the number of threads."""
    from concurrent.futures import ThreadPoolExecutor

    from scipy.spatial import cKDTree

    points = np.asarray(points, np.float64)
    tri = np.asarray(mesh.triangles, np.float64)
    centroids = tri.mean(axis=1)
    spread = np.linalg.norm(tri - centroids[:, None, :], axis=2).max(axis=1)
    rho = max(float(np.percentile(spread, 90)), 1e-12)
    small = spread <= rho
    sites, owners, reach = [centroids[small]], [np.flatnonzero(small)], [spread[small]]
    edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)
    splits = np.where(small, 0, np.ceil(edges / rho).astype(np.int64))
    for n in np.unique(splits[~small]):
        faces = np.flatnonzero(splits == n)
        i, j = np.divmod(np.arange((n + 1) ** 2), n + 1)
        keep = i + j <= n
        u, v = i[keep] / n, j[keep] / n
        corner = tri[faces]
        grid = corner[:, None, 0] + u[None, :, None] * (corner[:, None, 1] - corner[:, None, 0]) \
            + v[None, :, None] * (corner[:, None, 2] - corner[:, None, 0])
        sites.append(grid.reshape(-1, 3))
        owners.append(np.repeat(faces, len(u)))
        reach.append(np.full(len(faces) * len(u), rho))
    sites, owners, reach = np.concatenate(sites), np.concatenate(owners), np.concatenate(reach)
    tree = cKDTree(sites)
    out = np.empty(len(points))

    def nearest(start: int) -> None:
        p = points[start:start + chunk]
        _, first = tree.query(p)
        bound = _point_triangle_distance(p, tri[owners[first]])
        lists = tree.query_ball_point(p, bound + rho, return_sorted=False)
        owner = np.repeat(np.arange(len(p)), [len(x) for x in lists])
        site = np.concatenate(lists).astype(np.int64)
        below = np.linalg.norm(sites[site] - p[owner], axis=1) - reach[site] < bound[owner]
        owner, face = np.divmod(np.unique(owner[below] * len(tri) + owners[site[below]]), len(tri))
        best = bound.copy()
        np.minimum.at(best, owner, _point_triangle_distance(p[owner], tri[face]))
        out[start:start + chunk] = best

    starts = range(0, len(points), chunk)
    with ThreadPoolExecutor(max(1, min(len(starts), os.cpu_count() or 1))) as pool:
        list(pool.map(nearest, starts))
    return out


def _point_triangle_distance(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(N,) distance from points (N, 3) to triangles (N, 3, 3): the closest point by the
    Voronoi regions of the triangle (Ericson, Real-Time Collision Detection, §5.1.5)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac = b - a, c - a
    dot = lambda u, v: np.einsum("ij,ij->i", u, v)  # noqa: E731
    ap, bp, cp = p - a, p - b, p - c
    d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        q = a + ab * (vb / denom)[:, None] + ac * (vc / denom)[:, None]
        rules = [  # later rules take precedence, as the earlier tests of Ericson's code do
            ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))[:, None]),
            ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * (d2 / (d2 - d6))[:, None]),
            ((d6 >= 0) & (d5 <= d6), c),
            ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * (d1 / (d1 - d3))[:, None]),
            ((d3 >= 0) & (d4 <= d3), b),
            ((d1 <= 0) & (d2 <= 0), a),
        ]
        for where, point in rules:
            q = np.where(where[:, None], point, q)
    distance = np.linalg.norm(p - q, axis=1)
    bad = ~np.isfinite(distance)  # degenerate triangles: their nearest vertex
    if bad.any():
        distance[bad] = np.linalg.norm(p[bad, None, :] - tri[bad], axis=2).min(axis=1)
    return distance


def _fscore(d_et: np.ndarray, d_te: np.ndarray, tau: float) -> tuple[float, float, float]:
    precision = float((d_et <= tau).mean())
    recall = float((d_te <= tau).mean())
    f = 2.0 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return f, precision, recall


def _check_mesh(name: str, mesh) -> None:
    faces = getattr(mesh, "faces", None)
    if faces is None or len(faces) == 0:
        raise InputError("holds no triangles", field=name, value=0)


def serve_compare() -> None:
    """The loop of a ``compare`` worker process (fsswarp.reconstruction's truth metrics): from
    stdin, pickled objects, the truth mesh first, then (mesh, part) requests; to stdout, one
    pickled ``compare_part(mesh, truth, part)`` (or the exception it raised) per request, in
    order; returns at end of input. Anything the code prints goes to stderr, so that stdout
    carries the replies alone."""
    import os
    import pickle
    import sys

    replies = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    requests = sys.stdin.buffer
    truth = pickle.load(requests)
    while True:
        try:
            model, part = pickle.load(requests)
        except EOFError:
            return
        try:
            reply = compare_part(model, truth, part)
        except Exception as error:  # handed to the parent, which raises it
            reply = error
        pickle.dump(reply, replies)
        replies.flush()
