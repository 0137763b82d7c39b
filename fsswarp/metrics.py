"""Every error measure of the paper (§2.4–2.5, eq. 6 and 8–12; DESIGN §7, §9). Lengths in m.

Model against a true mesh (both in the reference frame):

- E_V (eq. 12, :func:`volume_error`): ``(V_a + V_b − 2 V_ab) / (V_a + V_b − V_ab)``, volumes
  by mesh booleans (manifold3d) when both meshes are closed 2-manifolds, else on a voxel grid
  (:func:`inside_grid`, ``grid`` samples along the pair's longest side);
- Chamfer-L1 (:func:`chamfer`): the mean of the two directed mean distances from ``samples``
  seeded surface points of one mesh to the other's surface (exact point-to-triangle);
- F-score at τ (:func:`fscore`): precision and recall of those points within τ, by default
  ``TAU_FRACTION`` of the truth's bounding-box diagonal; :func:`compare` gives them all.

Pose error (eq. 6): μ_m per view from the 3-D motions (K, 3) of the frontal object and mirror
patches (:func:`view_errors`), E_mu their mean (:func:`pose_error`).

Images (eq. 8–11), over views stacked (M, bins, beams): IE and AIE (:func:`intensity_error`,
:func:`average_intensity_error`) on the uncorrupted object regions Ω_m, ACE the mean of the
views' CE (:func:`average_contour_error`), NAIE and NACE relative to iteration 0
(:func:`normalized_errors`) and E_I = (NAIE + NACE) / 2 (:func:`image_error`). NaN stands for
"no value" (a view without a region or a contour) and is left out of the means.
"""

from __future__ import annotations

import math
import os

import numpy as np

from .errors import InputError
from .surface import check_plane, mirror_vectors

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

    require_triangles("a", a)
    require_triangles("b", b)
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
    and from as many points of ``b`` to ``a``: ((samples,), (samples,)); the points are
    :func:`surface_points` ``(a, samples, [seed, 0])`` and ``(b, samples, [seed, 1])``."""
    require_triangles("a", a)
    require_triangles("b", b)
    return (point_mesh_distance(surface_points(a, samples, [seed, 0]), b),
            point_mesh_distance(surface_points(b, samples, [seed, 1]), a))


def surface_points(mesh, samples: int, seed: list[int]) -> np.ndarray:
    """(samples, 3) points on ``mesh``'s surface, uniform over its area (trimesh's sampler, its
    generator seeded with ``seed``)."""
    import trimesh

    return trimesh.sample.sample_surface(mesh, samples, seed=np.random.default_rng(seed))[0]


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
    require_triangles("estimate", estimate)
    require_triangles("truth", truth)
    return combine(truth, volumes(estimate, truth), *surface_distances(estimate, truth, samples=samples, seed=seed),
                   samples=samples, seed=seed)


def combine(truth, volume: tuple, d_et: np.ndarray, d_te: np.ndarray, *, samples: int = SAMPLES,
            seed: int = 0) -> dict:
    """:func:`compare`'s dict from :func:`volumes`' tuple and :func:`surface_distances`' two
    arrays (estimate to truth, truth to estimate), however they were computed."""
    va, vt, both, method = volume
    tau = default_tau(truth)
    f, precision, recall = _fscore(d_et, d_te, tau)
    union = va + vt - both
    return {"E_V": (va + vt - 2.0 * both) / union if union > 0 else 0.0,
            "truth_volume_kept": both / vt if vt > 0 else 0.0,
            "volume_m3": va, "truth_volume_m3": vt, "common_volume_m3": both, "volume_method": method,
            "chamfer_m": 0.5 * float(d_et.mean() + d_te.mean()), "fscore": f, "precision": precision,
            "recall": recall, "tau_m": tau, "samples": samples, "seed": seed}


def point_mesh_distance(points, mesh, *, chunk: int = 2048, threads: int | None = None) -> np.ndarray:
    """(N,) exact distance (m) from each point to the nearest triangle of ``mesh``.

    Candidates come from a k-d tree over sites on the triangles, such that every point of a
    triangle lies within ρ of one of its sites (ρ: the 90th percentile of the triangles' largest
    centroid-to-vertex distance): the centroid where that distance is at most ρ, else a
    barycentric grid with edges under ρ. The triangle of the nearest site bounds the distance
    from above by U; only triangles with a site within U + ρ can be closer. A site at distance
    s whose triangle lies within r of it (its centroid spread, else ρ) bounds that triangle's
    distance from below by s − r, so only triangles with a site where s − r < U are tested
    exactly, each once per point. Chunks of ``chunk`` points run on a pool of ``threads`` threads
    (default: one per CPU; NumPy and the k-d tree release the GIL); the result does not depend
    on the number of threads."""
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
    with ThreadPoolExecutor(max(1, min(len(starts), threads or os.cpu_count() or 1))) as pool:
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


# --- the pose error E_mu (eq. 6) ------------------------------------------------------------------

def view_errors(object_motion, object_frontal, *, mirror_motion=None, mirror_frontal=None,
                normal=None) -> np.ndarray:
    """μ^m of paper eq. (6) for every view: ``μ^m = (1/Z_m) Σ_z ‖V_z^O‖ + ‖V_z^M - Ṽ_z^M‖``.

    V_z^O is the 3-D motion of object patch z (from the object contours), Ṽ_z^M the motion of
    its mirror patch from the mirror contours, and V_z^M = H V_z^O, ``H = I - 2 n nᵀ``, the
    object motion mapped onto the virtual mirror object across the sea surface. Z_m counts the
    frontal patches of view m. The object and mirror sums run over their own frontal sets of
    view m and each is divided by its own count: ``μ^m = mean_{z∈O_m} ‖V_z^O‖ +
    mean_{z∈M_m} ‖H V_z^O - Ṽ_z^M‖``, which is eq. (6) when the sets agree; the mirror term is
    0 in a view with no distinct mirror (M_m empty); μ^m is NaN when O_m is empty.

    object_motion : (..., K, 3); object_frontal : (..., M, K) bool, patch z frontal in view m.
    mirror_motion : (..., K, 3) Ṽ^M; mirror_frontal : (..., M, K) bool, the mirror patch of z
        frontal in view m; normal : (..., 3) unit surface normal in the reference frame.
    Motions of patches in no frontal set are ignored (may be NaN). Returns (..., M).
    """
    vo = np.asarray(object_motion, np.float64)
    if vo.ndim < 2 or vo.shape[-1] != 3:
        raise ValueError(f"object_motion must have shape (..., K, 3), got {vo.shape}")
    fo = _mask("object_frontal", object_frontal, vo.shape[-2])
    mirror = (mirror_motion, mirror_frontal, normal)
    if any(x is None for x in mirror) and not all(x is None for x in mirror):
        raise ValueError("mirror_motion, mirror_frontal and normal go together")
    used = fo.any(axis=-2)
    if mirror_motion is not None:
        vm = np.asarray(mirror_motion, np.float64)
        if vm.shape[-2:] != vo.shape[-2:]:
            raise ValueError(f"mirror_motion must have shape (..., K, 3) like object_motion, got {vm.shape}")
        fm = _mask("mirror_frontal", mirror_frontal, vo.shape[-2])
        n, _ = check_plane((normal, 0.0))
        used_m = fm.any(axis=-2)
        if not np.all(np.isfinite(vm[np.broadcast_to(used_m, vm.shape[:-1])])):
            raise ValueError("mirror_motion of frontal mirror patches holds non-finite values")
        used = used | used_m
    if not np.all(np.isfinite(vo[np.broadcast_to(used, vo.shape[:-1])])):
        raise ValueError("object_motion of frontal patches holds non-finite values")

    speed = np.linalg.norm(np.where(used[..., None], vo, 0.0), axis=-1)
    mu = _masked_mean(speed, fo)
    if mirror_motion is not None:
        expected = mirror_vectors(np.where(used[..., None], vo, 0.0), n[..., None, :])
        gap = np.linalg.norm(expected - np.where(used_m[..., None], vm, 0.0), axis=-1)
        mu = mu + np.nan_to_num(_masked_mean(gap, fm), nan=0.0)
    return mu


def pose_error(object_motion, object_frontal, *, mirror_motion=None, mirror_frontal=None,
               normal=None) -> np.ndarray:
    """E_mu(D, β) of paper eq. (6): ``(1/M) Σ_m μ^m``, the mean of ``view_errors`` over the M
    views with a defined μ^m (at least one frontal object patch); NaN if none.
    Arguments as ``view_errors``; returns (...) (a 0-d array for unbatched inputs)."""
    mu = view_errors(object_motion, object_frontal, mirror_motion=mirror_motion,
                     mirror_frontal=mirror_frontal, normal=normal)
    return _nanmean_last(mu)


# --- image metrics (eq. 8–11) ----------------------------------------------------------------------

def intensity_error(synthetic, data, region) -> np.ndarray:
    """IE of paper eq. (8): ``(1/|Ω|) Σ_{(b,B)∈Ω} |Ĩ(b,B) - I(b,B)|``.

    synthetic, data : (..., bins, beams) beam-bin images; region : (..., bins, beams) bool, Ω
    (the uncorrupted object region of the synthetic view). Returns (...); NaN where Ω is empty.
    Pixels outside Ω are ignored (may be NaN)."""
    syn = np.asarray(synthetic, np.float64)
    dat = np.asarray(data, np.float64)
    if syn.ndim < 2 or syn.shape != dat.shape:
        raise ValueError(f"synthetic {syn.shape} and data {dat.shape} must be images of one shape")
    omega = np.asarray(region)
    if omega.dtype != np.bool_ or omega.shape != syn.shape:
        raise ValueError(f"region must be a bool array of shape {syn.shape}, got {omega.dtype} {omega.shape}")
    diff = np.abs(np.where(omega, syn, 0.0) - np.where(omega, dat, 0.0))
    if not np.all(np.isfinite(diff)):
        raise ValueError("images hold non-finite values inside the region")
    count = omega.sum(axis=(-2, -1))
    return np.divide(diff.sum(axis=(-2, -1)), count, out=np.full(count.shape, np.nan), where=count > 0)


def average_intensity_error(synthetic, data, regions) -> float:
    """AIE of paper eq. (8): ``(1/M) Σ_m IE(Ĩ_m)`` over the M views, stacks (M, bins, beams)
    as ``intensity_error``. Views with an empty Ω_m have no IE and are left out of the mean
    (M counts the others); NaN if every Ω_m is empty."""
    ie = intensity_error(synthetic, data, regions)
    if ie.ndim != 1:
        raise ValueError(f"expected stacks of shape (M, bins, beams), got {np.shape(synthetic)}")
    return float(_nanmean_last(ie))


def average_contour_error(contour_errors) -> float:
    """ACE of paper eq. (9): ``(1/M) Σ_m CE(Ĩ_m)``, the mean of the views' CE (eq. 5,
    ``ICPResult.error``), (M,). NaN entries (no inlier pair) are left out; NaN if all are."""
    ce = np.asarray(contour_errors, np.float64)
    if ce.ndim != 1 or np.any(np.isinf(ce)) or np.any(ce < 0):
        raise ValueError("contour_errors must be a 1-D array of values >= 0 (or NaN)")
    return float(_nanmean_last(ce))


def normalized_errors(aie: float, ace: float, aie0: float, ace0: float) -> tuple[float, float]:
    """(NAIE, NACE) of paper eq. (10): ``AIE^t / AIE^0`` and ``ACE^t / ACE^0``, the initial
    values being those of the space-carving model (iteration 0). A NaN error (no view with a
    value) gives NaN."""
    values = [float(x) for x in (aie, ace, aie0, ace0)]
    if not all(math.isnan(x) or (math.isfinite(x) and x >= 0) for x in values):
        raise ValueError(f"errors must be finite and >= 0 (or NaN), got {values}")
    if values[2] == 0 or values[3] == 0:
        raise ValueError("initial errors AIE^0 and ACE^0 must be > 0 to normalize")
    return values[0] / values[2], values[1] / values[3]


def image_error(aie: float, ace: float, aie0: float, ace0: float) -> float:
    """E_I of paper eq. (11): ``(NAIE + NACE) / 2`` (1 at iteration 0, falls as images agree),
    computed as ``0.5 * (aie / aie0 + ace / ace0)``."""
    naie, nace = normalized_errors(aie, ace, aie0, ace0)
    return 0.5 * (naie + nace)



# --- helpers of the image and pose metrics ----------------------------------------------------------

def _masked_mean(values: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """(..., M) mean of (..., K) values over each of (..., M, K) masks; NaN for empty masks."""
    total = np.einsum("...mk,...k->...m", masks.astype(np.float64), values)
    count = masks.sum(axis=-1)
    return np.divide(total, count, out=np.full(total.shape, np.nan), where=count > 0)


def _nanmean_last(values: np.ndarray) -> np.ndarray:
    ok = np.isfinite(values)
    count = ok.sum(axis=-1)
    total = np.where(ok, values, 0.0).sum(axis=-1)
    return np.divide(total, count, out=np.full(count.shape, np.nan), where=count > 0)


def _mask(name: str, value, k: int) -> np.ndarray:
    mask = np.asarray(value)
    if mask.dtype != np.bool_ or mask.ndim < 2 or mask.shape[-1] != k:
        raise ValueError(f"{name} must be a bool array of shape (..., M, {k}), got {mask.dtype} {mask.shape}")
    return mask


def _fscore(d_et: np.ndarray, d_te: np.ndarray, tau: float) -> tuple[float, float, float]:
    precision = float((d_et <= tau).mean())
    recall = float((d_te <= tau).mean())
    f = 2.0 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return f, precision, recall


def require_triangles(name: str, mesh) -> None:
    """InputError naming ``name`` where ``mesh`` (a trimesh) holds no triangles."""
    faces = getattr(mesh, "faces", None)
    if faces is None or len(faces) == 0:
        raise InputError("holds no triangles", field=name, value=0)


def compare_meshes(estimate: tuple, truth: tuple, *, distances: bool) -> tuple:
    """(:func:`volumes`' tuple, :func:`surface_distances`' two arrays with ``distances``, else
    None) of two meshes given as (vertices (V, 3), faces (F, 3)) arrays (a truth-metrics worker
    process's job, fsswarp.reconstruction: arrays pickle in a tenth of the bytes of a trimesh
    with its caches)."""
    import trimesh

    estimate, truth = trimesh.Trimesh(*estimate, process=False), trimesh.Trimesh(*truth, process=False)
    return volumes(estimate, truth), surface_distances(estimate, truth) if distances else None
