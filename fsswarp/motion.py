"""From 2-D contour motions to 3-D patch motions (paper §2.4, eq. 6; DESIGN §7).

Image planes (``plane``): ``"fan"``, paper eq. (3), ``(x, y) = R (sin θ, cos θ)`` in metres,
the plane ``fsswarp.icp`` aligns contours in (default); ``"polar"``, (θ, R) in radians and
metres. A 2-D motion moves a synthetic contour point onto the data (``ICPResult.motions``), so
a 3-D motion moves a model patch centre toward the truth (the paper's ``Ṽ = P̃ − P`` has the
opposite sign, which no norm of eq. 6 sees); mirror and object motions share one sign.

- :func:`image_jacobian`: (..., 2, 3) derivative of a return's image coordinates with respect
  to the 3-D point (object return, or the single-bounce mirror return of a virtual point);
- :func:`patch_motions`: least-squares 3-D motions (..., K, 3) of K patch centres from their
  2-D motions in V views;
- :func:`truncated_lstsq`: the minimum-norm solve behind it. One view leaves elevation
  unobserved (the Jacobian's null direction ∂P/∂φ); several views with different rolls
  recover it, and directions still unobserved are left at zero motion.

The error measures built on these motions (μ_m, E_mu) are in ``fsswarp.metrics``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import finite_vectors
from .surface import check_plane, mirror_points, mirror_vectors

PLANES = ("fan", "polar")


# --- Jacobians -------------------------------------------------------------------------------

def image_jacobian(points, *, plane: str = "fan", surface=None) -> np.ndarray:
    """(..., 2, 3) derivative of a return's image coordinates with respect to the 3-D point.

    points : (..., 3) in the view frame (sonar at the origin, R > 0 and hypot(X, Y) > 0).
    plane : ``"fan"`` gives rows d(x, y)/dP, ``"polar"`` rows d(θ, R)/dP.
    surface : None for the object return at (θ(P), |P|); or ``(normal (..., 3), offset (...))``
        of the sea surface in the view frame (unit normal into the air), and then ``points``
        are virtual mirror points Q whose single-bounce mirror return lies at
        (θ(Q), (|Q| + |Q'|)/2), Q' the mirror of Q (DESIGN §3): the Jacobian is with respect to Q.
    Closed form: ``dθ/dP = (Y, -X, 0)/(X² + Y²)``, ``dR/dP = P/|P|``;
    ``dx = sinθ dR + R cosθ dθ``, ``dy = cosθ dR - R sinθ dθ``.
    """
    if plane not in PLANES:
        raise ValueError(f"plane must be one of {PLANES}, got {plane!r}")
    return _jacobian(finite_vectors("points", points, 3), plane, None if surface is None else check_plane(surface))


def _jacobian(p: np.ndarray, plane: str, surface) -> np.ndarray:
    """:func:`image_jacobian` of checked float64 points (..., 3) and plane (or None); raises
    ValueError for points on the vertical axis alone."""
    x, y = p[..., 0], p[..., 1]
    rho2 = x * x + y * y
    rng = np.linalg.norm(p, axis=-1)
    if np.any(rho2 <= 0.0):
        raise ValueError("points on the sonar's vertical axis (X = Y = 0) have no azimuth")
    d_theta = np.stack([y / rho2, -x / rho2, np.zeros_like(x)], axis=-1)
    d_rng = p / rng[..., None]
    if surface is not None:
        normal, offset = surface
        q = mirror_points(p, normal, offset)
        q_rng = np.linalg.norm(q, axis=-1)
        d_rng = 0.5 * (d_rng + mirror_vectors(q / q_rng[..., None], normal))
        rng = 0.5 * (rng + q_rng)
    if plane == "polar":
        return np.stack([d_theta, d_rng], axis=-2)
    theta = np.arctan2(x, y)
    s, c = np.sin(theta)[..., None], np.cos(theta)[..., None]
    r = rng[..., None]
    return np.stack([s * d_rng + r * c * d_theta, c * d_rng - r * s * d_theta], axis=-2)


# --- 3-D patch motions -------------------------------------------------------------------------

@dataclass(frozen=True)
class PatchMotions:
    """3-D motions of patch centres from their 2-D motions in the views that see them.

    motion : (..., K, 3) in the reference frame; rank : (..., K) rank of the stacked view
    Jacobians kept by the solve (3 = fully observed, 2 = one direction left at zero, 0 = seen
    in no view); views : (..., K) number of views used; residual : (..., K) RMS of the 2-D
    misfit ``J δ - v`` over those views (plane units; 0 where none).
    """

    motion: np.ndarray
    rank: np.ndarray
    views: np.ndarray
    residual: np.ndarray


def patch_motions(centres, motions, visible, rotations, translations, *, plane: str = "fan",
                  surface=None, rcond: float = 1e-2) -> PatchMotions:
    """Least-squares 3-D motions δ_k of K patch centres from 2-D motions in V views.

    For patch k, minimise ``Σ_{v visible} |J_kv δ_k - m_kv|²`` with the reference-frame Jacobian
    ``J_kv = J_view(P_kv) R_vᵀ``, ``P_kv = R_vᵀ (c_k - t_v)`` (from ``P_ref = R_v P_view + t_v``).
    Solved by a truncated SVD of the stacked (2V, 3) system: singular values below
    ``rcond × the largest`` are dropped (pseudo-inverse, minimum-norm solution), so a patch seen
    in one view, or in views that share its elevation direction, gets zero motion along what
    they cannot observe. Only the (patch, view) pairs seen are computed: each patch's system
    holds the rows of its views, in their order (those of the others would be zero).

    centres : (..., K, 3) patch centres in the reference frame (virtual mirror centres Q when
        ``surface`` is given). motions : (..., K, V, 2) 2-D motions in ``plane``; entries of
        invisible views are ignored (may be NaN). visible : (..., K, V) bool.
    rotations, translations : (..., V, 3, 3) and (..., V, 3), ``Rig.relative_poses``.
    surface : None (object returns) or ``(normal (..., 3), offset (...))`` of the sea surface
        in the reference frame (``surface.surface_in_reference``): mirror returns.
    rcond : relative cut-off; the default 1e-2 leaves a direction seen 100× more weakly than the
        best one at zero rather than amplify the 2-D motion errors up to 100× along it.
    Leading dimensions ``...`` broadcast (e.g. a grid of (D, β) candidates).
    """
    if not (np.isfinite(rcond) and 0 < rcond < 1):
        raise ValueError(f"rcond must lie in (0, 1), got {rcond!r}")
    if plane not in PLANES:
        raise ValueError(f"plane must be one of {PLANES}, got {plane!r}")
    c = finite_vectors("centres", centres, 3)
    rot = finite_vectors("rotations", rotations, 3)
    t = finite_vectors("translations", translations, 3)
    m = np.asarray(motions, dtype=np.float64)
    vis = np.asarray(visible)
    if vis.dtype != np.bool_:
        raise ValueError(f"visible must be a bool array, got dtype {vis.dtype}")
    if c.ndim < 2 or rot.ndim < 3 or rot.shape[-2] != 3 or t.ndim < 2 or m.ndim < 3 \
            or m.shape[-1] != 2 or vis.ndim < 2:
        raise ValueError(f"expected centres (..., K, 3), motions (..., K, V, 2), visible (..., K, V), "
                         f"rotations (..., V, 3, 3), translations (..., V, 3); got {c.shape}, "
                         f"{m.shape}, {vis.shape}, {rot.shape}, {t.shape}")
    k, v = c.shape[-2], rot.shape[-3]
    if t.shape[-2] != v or m.shape[-3:-1] != (k, v) or vis.shape[-2:] != (k, v):
        raise ValueError(f"shapes disagree: centres {c.shape}, motions {m.shape}, visible {vis.shape}, "
                         f"rotations {rot.shape}, translations {t.shape}")
    if not np.all(np.isfinite(m[np.broadcast_to(vis, m.shape[:-1])])):
        raise ValueError("motions of visible views hold non-finite values")

    shape = np.broadcast_shapes(c.shape[:-2] + (k, 1), rot.shape[:-3] + (1, v), t.shape[:-2] + (1, v),
                                m.shape[:-1], vis.shape)
    lead, vis = shape[:-2], np.broadcast_to(vis, shape)
    views = vis.sum(axis=-1)
    motion, rank, residual = np.zeros(shape[:-1] + (3,)), np.zeros(shape[:-1], np.intp), np.zeros(shape[:-1])
    seen = np.nonzero(vis)  # the (patch, view) pairs that count, patch after patch, each its views in order
    if not len(seen[0]):
        return PatchMotions(motion=motion, rank=rank, views=views, residual=residual)
    at_patch, at_view = seen[:-1], seen[:-2] + seen[-1:]
    rot_s = np.broadcast_to(rot, lead + (v, 3, 3))[at_view]
    p_view = np.einsum("ni,nij->nj", np.broadcast_to(c, lead + (k, 3))[at_patch]
                       - np.broadcast_to(t, lead + (v, 3))[at_view], rot_s)
    view_surface = None
    if surface is not None:
        normal, offset = check_plane(surface)
        n_view = np.einsum("...vij,...i->...vj", rot, normal)
        d_view = offset[..., None] - np.einsum("...vi,...i->...v", t, normal)
        view_surface = (np.broadcast_to(n_view, lead + (v, 3))[at_view], np.broadcast_to(d_view, lead + (v,))[at_view])
    jac = np.einsum("naj,nij->nai", _jacobian(p_view, plane, view_surface), rot_s)  # the unit normals turned
    # each patch's rows (2 per view that sees it, in the views' order), padded with zero rows:
    # the sums over rows of truncated_lstsq are those over all 2V rows with the others zero
    patch = np.ravel_multi_index(at_patch, shape[:-1])
    patches, first, count = np.unique(patch, return_index=True, return_counts=True)
    row = np.repeat(np.arange(len(patches)), count)
    slot = np.arange(len(patch)) - first[row]
    a = np.zeros((len(patches), int(count.max()), 2, 3))
    b = np.zeros((len(patches), int(count.max()), 2))
    a[row, slot], b[row, slot] = jac, np.broadcast_to(m, shape + (2,))[seen]
    a, b = a.reshape(len(patches), -1, 3), b.reshape(len(patches), -1)
    delta, kept = truncated_lstsq(a, b, rcond)
    misfit = np.einsum("...ri,...i->...r", a, delta) - b
    squares = np.zeros((len(patches), v, 2))  # in the rows of all V views, summed as they are
    squares[row, seen[-1]] = (misfit * misfit).reshape(len(patches), -1, 2)[row, slot]
    motion.reshape(-1, 3)[patches], rank.reshape(-1)[patches] = delta, kept
    residual.reshape(-1)[patches] = np.sqrt(np.sum(squares.reshape(len(patches), -1), axis=-1)
                                            / (2 * views.reshape(-1)[patches]))
    return PatchMotions(motion=motion, rank=rank, views=views, residual=residual)


def truncated_lstsq(a: np.ndarray, b: np.ndarray, rcond: float) -> tuple[np.ndarray, np.ndarray]:
    """(..., 3) minimum-norm least-squares solutions of the systems a δ = b, a (..., R, 3),
    b (..., R), with the directions whose singular value lies at or below ``rcond`` × the
    largest dropped, and their ranks (...,). The SVD of a comes from the eigen-decomposition
    of the 3×3 normal matrix aᵀa (eigenvalues s², eigenvectors the right singular vectors);
    the squaring costs a kept direction at most a factor 1/rcond² in rounding error."""
    value, vector = np.linalg.eigh(np.einsum("...ri,...rj->...ij", a, a))  # ascending
    keep = value > rcond * rcond * value[..., -1:]
    inverse = np.divide(1.0, value, out=np.zeros_like(value), where=keep)
    along = inverse * np.einsum("...ij,...i->...j", vector, np.einsum("...ri,...r->...i", a, b))
    return np.einsum("...ij,...j->...i", vector, along), keep.sum(axis=-1)


# --- helpers --------------------------------------------------------------------------------
