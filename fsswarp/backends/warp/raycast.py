"""Watertight ray casting against a Warp BVH over a mesh's triangles (kernels/bvh.h, raycast.cl).

``nearest_hit`` is the first hit of one ray (the render and frontal kernels use it);
``cast_rays_kernel`` is ``Backend.cast_rays``: origins and directions (R,) vec3, distances
(R,) float32 (inf: none), faces (R,) int32 (-1: none).
"""

from __future__ import annotations

import warp as wp

from .sonar import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

_TINY_DIR = wp.constant(1.0e-30)  # stands in for a zero direction component (1/0 -> 1e30, no NaN)


@wp.func
def ray_triangle(org: wp.vec3, kx: int, ky: int, kz: int, sx: float, sy: float, sz: float,
                 a: wp.vec3, b: wp.vec3, c: wp.vec3, t_best: float):
    """Watertight test of triangle (a, b, c) (Woop, Benthin & Wald 2013; fss_ray_triangle of
    kernels/bvh.h, operation for operation, edge values of exactly 0 inside); returns t in
    [0, t_best) or inf."""
    A = a - org
    B = b - org
    C = c - org
    az = A[kz]
    bz = B[kz]
    cz = C[kz]
    ax = A[kx] - sx * az
    ay = A[ky] - sy * az
    bx = B[kx] - sx * bz
    by = B[ky] - sy * bz
    cx = C[kx] - sx * cz
    cy = C[ky] - sy * cz
    uu = cx * by - cy * bx
    vv = ax * cy - ay * cx
    ww = bx * ay - by * ax
    if (uu < 0.0 or vv < 0.0 or ww < 0.0) and (uu > 0.0 or vv > 0.0 or ww > 0.0):
        return wp.inf
    det = uu + vv + ww
    if det == 0.0:
        return wp.inf
    tt = uu * (sz * az) + vv * (sz * bz) + ww * (sz * cz)
    if det < 0.0:
        det = -det
        tt = -tt
    if not (tt >= 0.0) or not (tt < t_best * det):
        return wp.inf
    t = tt / det
    if t >= 0.0 and t < t_best:
        return t
    return wp.inf


@wp.struct
class RayHit:
    t: float
    face: int


@wp.func
def nearest_hit(bvh: wp.uint64, corners: wp.array(dtype=wp.vec3), org: wp.vec3, dir: wp.vec3, max_t: float):
    """Nearest watertight hit of the ray in [0, max_t): candidates from the BVH over the
    triangles' boxes, each tested exactly (face -1 and t = inf: none). corners (3F,): the
    corners of face f at 3f, 3f + 1, 3f + 2 (``WarpMesh.corners``)."""
    # dominant axis, shear constants (fss_make_ray)
    ax = wp.abs(dir[0])
    ay = wp.abs(dir[1])
    az = wp.abs(dir[2])
    kz = int(2)
    if ax > ay:
        if ax > az:
            kz = 0
    else:
        if ay > az:
            kz = 1
    kx = kz + 1
    if kx == 3:
        kx = 0
    ky = kx + 1
    if ky == 3:
        ky = 0
    dz = dir[kz]
    if dz < 0.0:
        tmp = kx
        kx = ky
        ky = tmp
    sx = dir[kx] / dz
    sy = dir[ky] / dz
    sz = 1.0 / dz
    # the BVH takes 1/dir: keep zero components finite so the slab test has no 0·inf NaN
    qdir = dir
    for k in range(3):
        if qdir[k] == 0.0:
            qdir[k] = _TINY_DIR
    best = max_t
    best_face = int(-1)
    query = wp.bvh_query_ray(bvh, org, qdir)
    face = int(0)
    while wp.bvh_query_next(query, face, best * 1.000001):
        t = ray_triangle(org, kx, ky, kz, sx, sy, sz, corners[face * 3 + 0],
                         corners[face * 3 + 1], corners[face * 3 + 2], best)
        if t < best or (t == best and best_face >= 0 and face < best_face):
            best = t
            best_face = face
    hit = RayHit()
    hit.face = best_face
    if best_face >= 0:
        hit.t = best
    else:
        hit.t = wp.inf
    return hit


@wp.kernel
def cast_rays_kernel(mesh: wp.uint64, corners: wp.array(dtype=wp.vec3), origins: wp.array(dtype=wp.vec3),
                     directions: wp.array(dtype=wp.vec3), max_distance: float,
                     distance_out: wp.array(dtype=float), face_out: wp.array(dtype=wp.int32)):
    """Thread i: nearest hit of ray i within max_distance (inf and -1 if none)."""
    i = wp.tid()
    hit = nearest_hit(mesh, corners, origins[i], directions[i], max_distance)
    if hit.face >= 0:
        distance_out[i] = hit.t
        face_out[i] = hit.face
    else:
        distance_out[i] = wp.inf
        face_out[i] = -1
