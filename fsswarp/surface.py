"""The sea surface (a plane) and the multipath returns it causes (DESIGN §2–3).

A plane is ``n·P = d`` with unit normal n pointing into the air; in a view frame the sonar
(origin) lies below it, so d > 0. Mirroring across it: ``P' = P - 2 (n·P - d) n``.
"""

from __future__ import annotations

import numpy as np

from .errors import finite_vectors
from .rig import Rig
from .sonar import to_polar

#: The image layers of a synthetic view, in the order the kernels write them.
COMPONENTS = ("object", "ghost", "mirror", "mirror2")


def surface_in_reference(rig: Rig, depth, tilt):
    """The surface in the reference frame for shared ``depth`` (m) and ``tilt`` (rad).

    Returns ``(n, d)``: (*G, 3) unit normals ``(R_ref^W)ᵀ e_z`` and (*G,) offsets
    ``D + δD_ref``; for a reference with zero heading and offsets ``n = (0, sin β, cos β)``."""
    rot_ref, s_ref = rig.reference_pose(depth, tilt)
    return rot_ref[..., 2, :], -s_ref[..., 2]


def surface_in_views(rig: Rig, depth, tilt):
    """The surface in every view frame: ``n_m = R_mᵀ n``, ``d_m = d - n·t_m``
    (:func:`view_planes`' last two).

    Returns ``(n, d)`` of shapes (*G, V, 3) and (*G, V)."""
    return view_planes(rig, depth, tilt)[2:]


def view_planes(rig: Rig, depth, tilt):
    """Every view's pose and the surface in its frame for shared ``depth`` (m) and ``tilt``
    (rad), broadcast to (*G,): ``(R, t, n, d)``, the poses of ``rig.relative_poses`` and the
    planes ``n_m = R_mᵀ n``, ``d_m = d - n·t_m``. All but d depend on β alone: they are found once
    per distinct tilt (a (D, β) grid repeats each along D; the same operations, so the same bits
    as one candidate's), then spread over the candidates.

    Returns arrays of shapes (*G, V, 3, 3), (*G, V, 3), (*G, V, 3) and (*G, V)."""
    depth, tilt = np.broadcast_arrays(np.asarray(depth, np.float64), np.asarray(tilt, np.float64))
    tilts, inverse = np.unique(tilt, return_inverse=True)
    at = (np.zeros(tilts.shape), tilts)
    rot, t = rig.relative_poses(*at)
    normal, _ = surface_in_reference(rig, *at)
    n_views = np.einsum("...vij,...i->...vj", rot, normal)
    heights = np.einsum("...vi,...i->...v", t, normal)
    inverse = inverse.reshape(-1)
    rot, t, n_views, heights = (a[inverse].reshape(tilt.shape + a.shape[1:]) for a in (rot, t, n_views, heights))
    offset = depth + rig.views[rig.reference].depth_offset  # d = D + δD_ref (surface_in_reference's)
    return rot, t, n_views, offset[..., None] - heights


def mirror_points(points, normal, offset) -> np.ndarray:
    """(..., 3) mirror images of points across the plane ``normal·P = offset``."""
    p = np.asarray(points, np.float64)
    n = np.asarray(normal, np.float64)
    h = np.sum(p * n, axis=-1, keepdims=True) - np.asarray(offset, np.float64)[..., None]
    return p - 2.0 * h * n


def mirror_vectors(vectors, normal) -> np.ndarray:
    """(..., 3) mirror images of directions (normals, rays) across a plane of ``normal``."""
    v = np.asarray(vectors, np.float64)
    n = np.asarray(normal, np.float64)
    return v - 2.0 * np.sum(v * n, axis=-1, keepdims=True) * n


def apparent_returns(points, normal, offset) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Where a view-frame point appears in each component (the table in DESIGN §3).

    points : (..., 3) in the view frame; normal, offset : the surface in that frame.
    Returns ``{component: (theta, range)}`` for ``object``, ``ghost``, ``mirror`` and
    ``mirror2``: the arrival azimuth (rad) and the apparent range (m), each (...,).
    Geometry only: visibility and field-of-view tests belong to the renderer.
    """
    p = np.asarray(points, np.float64)
    q = mirror_points(p, normal, offset)
    r_p, theta_p, _ = to_polar(p)
    r_q, theta_q, _ = to_polar(q)
    half = 0.5 * (r_p + r_q)
    return {"object": (theta_p, r_p), "ghost": (theta_p, half),
            "mirror": (theta_q, half), "mirror2": (theta_q, r_q)}


def check_plane(surface) -> tuple[np.ndarray, np.ndarray]:
    """(normal (..., 3), offset (...)) of a plane, checked: finite, unit normals."""
    normal = finite_vectors("surface normal", surface[0], 3)
    offset = np.asarray(surface[1], np.float64)
    if not np.all(np.isfinite(offset)):
        raise ValueError("surface offset holds non-finite values")
    if not np.allclose(np.linalg.norm(normal, axis=-1), 1.0, rtol=0.0, atol=1e-9):
        raise ValueError("surface normal must be a unit vector")
    return normal, offset
