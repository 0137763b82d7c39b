"""Float64 NumPy oracle of sonar image synthesis: the algorithm of ``fsswarp/rendering.py``'s
docstring, written independently of the kernels.

Ray casts go through trimesh's intersector (Embree through embreex when it imports, else
trimesh's pure-NumPy triangle test). Embree computes in float32 internally, so a cast distance
carries ~1e-7 relative error; everything else here is float64, and deposits accumulate with
``np.add.at`` in float64 (no fixed point: the kernels' 2^-24 quantum is far below any test
tolerance).

Everything is vectorised over all sub-rays of all views: one batch of casts per leg.
"""

from __future__ import annotations

import numpy as np
import trimesh

from fsswarp.sonar import SonarSpec

#: ε of the visibility legs (m), as in the spec.
EPSILON = 1e-4


def make_intersector(mesh: trimesh.Trimesh):
    """trimesh's Embree intersector when embreex imports, else the NumPy one."""
    try:
        import embreex  # noqa: F401

        from trimesh.ray.ray_pyembree import RayMeshIntersector
    except ImportError:  # pragma: no cover - depends on the environment
        from trimesh.ray.ray_triangle import RayMeshIntersector
    return RayMeshIntersector(mesh)


def first_hits(intersector, origins, directions):
    """First hit of every ray: (R,) float64 distance (inf: none) and (R,) int64 face (-1: none).

    ``directions`` must be unit vectors (the distance is measured along them)."""
    origins = np.asarray(origins, np.float64).reshape(-1, 3)
    directions = np.asarray(directions, np.float64).reshape(-1, 3)
    dist = np.full(len(origins), np.inf)
    face = np.full(len(origins), -1, np.int64)
    if len(origins) == 0:
        return dist, face
    tri, ray, loc = intersector.intersects_id(origins, directions, multiple_hits=False,
                                              return_locations=True)
    tri, ray = np.asarray(tri, np.int64), np.asarray(ray, np.int64)
    if len(ray):
        d = np.linalg.norm(np.asarray(loc, np.float64) - origins[ray], axis=1)
        # multiple_hits=False gives one hit per ray; keep the nearest should a version give more
        order = np.argsort(-d)
        dist[ray[order]] = d[order]
        face[ray[order]] = tri[order]
    return dist, face


def sub_rays(sonar: SonarSpec, samples):
    """View-frame sub-ray directions of every beam (spec step 1).

    Returns ``(u, beam)``: (M, 3) unit vectors and (M,) beam index, M = beams·K_θ·K_φ, ordered
    beam-major, then i (azimuth), then j (elevation)."""
    k_theta, k_phi = (int(k) for k in samples)
    centres = np.asarray(sonar.beam_centres, np.float64)
    widths = np.gradient(centres)  # Δθ_b: spacing of the centres
    frac = (np.arange(k_theta) + 0.5) / k_theta - 0.5
    theta = centres[:, None] + frac[None, :] * widths[:, None]  # (B, Kθ)
    w = sonar.half_elevation
    phi = -w + (np.arange(k_phi) + 0.5) / k_phi * 2.0 * w  # (Kφ,)
    theta, phi = np.broadcast_arrays(theta[:, :, None], phi[None, None, :])
    u = np.stack([np.cos(phi) * np.sin(theta), np.cos(phi) * np.cos(theta), np.sin(phi)], -1)
    beam = np.broadcast_to(np.arange(sonar.beams)[:, None, None], theta.shape)
    return u.reshape(-1, 3), beam.reshape(-1).copy()


def bin_index(sonar: SonarSpec, rng):
    """bin(R) = floor((R − R_min)/δR + 0.5) as float (inf/nan stay non-finite)."""
    with np.errstate(invalid="ignore", over="ignore"):
        return np.floor((np.asarray(rng, np.float64) - sonar.range_min) / sonar.range_step + 0.5)


def beam_index(sonar: SonarSpec, theta):
    """beam(θ) = floor(beam coordinate + 0.5) as float."""
    return np.floor(sonar.beam_coordinate(theta) + 0.5)


def _deposit(image, view, layer, bins, beams, amp, sonar):
    ok = np.isfinite(bins) & np.isfinite(beams) & (bins >= 0) & (bins < sonar.bins) & \
        (beams >= 0) & (beams < sonar.beams)
    np.add.at(image, (view[ok], np.full(ok.sum(), layer), bins[ok].astype(np.int64),
                      beams[ok].astype(np.int64)), amp[ok])


def _dot(a, b):
    return np.sum(a * b, axis=-1)


def oracle_render(mesh, sonar: SonarSpec, rotations, translations, plane_normals, plane_offsets,
                  samples=(2, 64), gamma: float = 1.0, surface_reflection: float = 0.9):
    """(N, 4, bins, beams) float64 layers object, ghost, mirror, mirror2 of N views.

    mesh : trimesh.Trimesh in the reference frame, or a (vertices, faces) pair
    rotations (N, 3, 3), translations (N, 3): ``P_ref = R @ P_view + t``
    plane_normals (N, 3), plane_offsets (N,): the surface ``n·P = d`` in each view frame
    """
    if not isinstance(mesh, trimesh.Trimesh):
        vertices, faces = mesh
        mesh = trimesh.Trimesh(vertices=np.asarray(vertices, np.float64),
                               faces=np.asarray(faces), process=False)
    rot = np.asarray(rotations, np.float64).reshape(-1, 3, 3)
    trans = np.asarray(translations, np.float64).reshape(-1, 3)
    normal = np.asarray(plane_normals, np.float64).reshape(-1, 3)
    offset = np.asarray(plane_offsets, np.float64).reshape(-1)
    n_views = rot.shape[0]
    image = np.zeros((n_views, 4, sonar.bins, sonar.beams), np.float64)
    if n_views == 0:
        return image
    k_theta, k_phi = (int(k) for k in samples)
    weight = 1.0 / (k_theta * k_phi)
    rs = float(surface_reflection)
    eps = EPSILON
    intersector = make_intersector(mesh)
    face_normals = np.asarray(mesh.face_normals, np.float64)

    u1, beam1 = sub_rays(sonar, samples)
    m = len(u1)
    # flattened over (view, sub-ray)
    view = np.repeat(np.arange(n_views), m)
    beam = np.tile(beam1, n_views).astype(np.float64)
    u = np.tile(u1, (n_views, 1))
    R = rot[view]
    t = trans[view]
    n = normal[view]
    d = offset[view]

    def to_ref_dir(v_view, rr):  # R @ v
        return np.einsum("kij,kj->ki", rr, v_view)

    def to_ref_point(p_view, rr, tt):
        return np.einsum("kij,kj->ki", rr, p_view) + tt

    def view_normal(faces, rr):  # Rᵀ N_ref for faces >= 0 (zero elsewhere)
        nr = np.where((faces >= 0)[:, None], face_normals[np.maximum(faces, 0)], 0.0)
        return np.einsum("kji,kj->ki", rr, nr)

    # 2. direct leg
    r, face = first_hits(intersector, t, to_ref_dir(u, R))
    nv = view_normal(face, R)
    un = _dot(u, nv)
    nf = np.where((un > 0)[:, None], -nv, nv)  # normal facing the ray
    c = -_dot(u, nf)
    nu = _dot(n, u)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(nu > 0, d / np.where(nu > 0, nu, 1.0), np.inf)
    hit = np.isfinite(r) & (r < s)

    # 3a. object
    _deposit(image, view[hit], 0, bin_index(sonar, r[hit]), beam[hit],
             np.power(c[hit], gamma) * weight, sonar)

    # 3b. surface path (ghost and mirror)
    k = np.flatnonzero(hit)
    P = r[k, None] * u[k]
    nk, dk = n[k], d[k]
    o_mirror = 2.0 * dk[:, None] * nk
    q = np.linalg.norm(P - o_mirror, axis=1)
    nP = _dot(nk, P)
    lam = dk / (2.0 * dk - nP)
    Q = o_mirror + lam[:, None] * (P - o_mirror)
    theta_q = np.arctan2(Q[:, 0], Q[:, 1])
    phi_q = np.arctan2(Q[:, 2], np.hypot(Q[:, 0], Q[:, 1]))
    bc_q = sonar.beam_coordinate(theta_q)
    ok = (Q[:, 1] > 0) & (bc_q >= -0.5) & (bc_q < sonar.beams - 0.5) & \
        (np.abs(phi_q) <= sonar.half_elevation)
    k, P, Q, q, nP, nk, dk = k[ok], P[ok], Q[ok], q[ok], nP[ok], nk[ok], dk[ok]
    Rk, tk = R[k], t[k]
    # leg O -> Q clear
    q_len = np.linalg.norm(Q, axis=1)
    dist_oq, _ = first_hits(intersector, tk, to_ref_dir(Q / q_len[:, None], Rk))
    clear = dist_oq >= q_len - eps
    # leg Q -> P clear
    pq = P - Q
    pq_len = np.linalg.norm(pq, axis=1)
    w = pq / pq_len[:, None]
    dist_qp, _ = first_hits(intersector, to_ref_point(Q, Rk, tk), to_ref_dir(w, Rk))
    clear &= dist_qp >= pq_len - eps
    c_in = -_dot(w, nf[k])
    clear &= c_in > 0
    k, P, q, nP, nk, dk, c_in = k[clear], P[clear], q[clear], nP[clear], nk[clear], dk[clear], c_in[clear]
    a_s = rs * np.power(c[k] * c_in, 0.5 * gamma) * weight
    half = 0.5 * (r[k] + q)
    _deposit(image, view[k], 1, bin_index(sonar, half), beam[k], a_s, sonar)
    P_mirror = P - 2.0 * (nP - dk)[:, None] * nk
    _deposit(image, view[k], 2, bin_index(sonar, half),
             beam_index(sonar, np.arctan2(P_mirror[:, 0], P_mirror[:, 1])), a_s, sonar)

    # 4. surface first: mirror2
    k = np.flatnonzero(np.isfinite(s) & (s < r))
    uk, nk = u[k], n[k]
    Q2 = s[k, None] * uk
    u_ref = uk - 2.0 * _dot(uk, nk)[:, None] * nk
    Rk, tk = R[k], t[k]
    dist2, face2 = first_hits(intersector, to_ref_point(Q2 + eps * u_ref, Rk, tk), to_ref_dir(u_ref, Rk))
    r2 = eps + dist2
    found = np.isfinite(dist2)
    n2 = view_normal(face2, Rk)
    c2 = np.abs(_dot(u_ref, n2))  # = −u'·N2 with N2 turned to face the ray
    k, r2, c2, sk = k[found], r2[found], c2[found], s[k][found]
    _deposit(image, view[k], 3, bin_index(sonar, sk + r2), beam[k],
             rs * rs * np.power(c2, gamma) * weight, sonar)
    return image
