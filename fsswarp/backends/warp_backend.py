"""NVIDIA Warp kernels ("cpu" and "cuda:N") behind the Backend interface.

Kernels and their helper functions first, compiled once per process and device (Warp keeps
the build in its kernel cache, ~/.cache/warp); the wrapper class below. The ``@wp.func``
helpers mirror ``kernels/sonar.h`` operation for operation, so that this backend and the
OpenCL one round alike; change them together.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from .base import Backend, DeviceLayers, SonarConstants
from .constants import FIXED_SCALE, FRONTAL_VISIBLE, INDEX_LIMIT, MAX_DISTANCE, RAY_EPSILON, WARP_FAR
from .select import _warp
from .bvh import triangle_bounds

# No contraction of a*b + c into fma: the watertight ray-triangle test relies on a shared edge
# giving the same float expression in both triangles (with fma on CUDA, 6 of 10,248 rays
# through vertices and edges leaked), and kernels/*.cl build with FP_CONTRACT OFF too.
# No adjoint code: nothing here is differentiated, and without it the module compiles in
# half the time (3.4 s against 7.1 s for the CPU with an empty kernel cache, here).
wp.set_module_options({"fuse_fp": False, "enable_backward": False})

_INDEX_LIMIT = wp.constant(INDEX_LIMIT)
#: ``WarpBackend._constant``: inputs up to this size are kept on the device for reuse ...
CONSTANT_BYTES = 1 << 18
#: ... and this many of them (at most 16 MiB).
CONSTANTS = 64


# --- shared geometry (kernels/sonar.h) -------------------------------------------------------
@wp.func
def to_view(p: wp.vec3, r: wp.mat33, t: wp.vec3):
    """P_view = Rᵀ (p − t)."""
    d0 = p[0] - t[0]
    d1 = p[1] - t[1]
    d2 = p[2] - t[2]
    x = r[0, 0] * d0 + r[1, 0] * d1 + r[2, 0] * d2
    y = r[0, 1] * d0 + r[1, 1] * d1 + r[2, 1] * d2
    z = r[0, 2] * d0 + r[1, 2] * d1 + r[2, 2] * d2
    return wp.vec3(x, y, z)


@wp.func
def sonar_range(q: wp.vec3):
    return wp.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2])


@wp.func
def azimuth(q: wp.vec3):
    return wp.atan2(q[0], q[1])


@wp.func
def elevation(q: wp.vec3):
    return wp.atan2(q[2], wp.sqrt(q[0] * q[0] + q[1] * q[1]))


@wp.struct
class KernelSonar:
    """``SonarConstants`` without the beam table, as one kernel argument (``fss_sonar`` of
    kernels/sonar.h, the same fields in the same order)."""

    use_table: int
    beams: int
    bins: int
    half_azimuth: float
    beam_scale: float
    range_min: float
    inv_range_step: float
    half_elevation: float


def kernel_sonar(sonar: SonarConstants) -> KernelSonar:
    """The Warp struct of ``sonar``'s scalars (float32 fields: the float32 values)."""
    packed = KernelSonar()
    for name in KernelSonar.vars:
        setattr(packed, name, getattr(sonar, name))
    return packed


@wp.func
def beam_coordinate(theta: float, sonar: KernelSonar, table: wp.array2d(dtype=float)):
    """Fractional column of azimuth theta: linear, or interpolated in the angle table (row 0
    the centres, row 1 the inverse spacings) and extrapolated with the outer spacing."""
    if sonar.use_table == 0:
        return (theta + sonar.half_azimuth) * sonar.beam_scale
    last = sonar.beams - 1
    if theta < table[0, 0]:
        return (theta - table[0, 0]) * table[1, 0]
    if theta > table[0, last]:
        return float(last) + (theta - table[0, last]) * table[1, last]
    lo = int(0)  # invariant: table[0, lo] <= theta <= table[0, hi]
    hi = int(last)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if table[0, mid] <= theta:
            lo = mid
        else:
            hi = mid
    return float(lo) + (theta - table[0, lo]) * table[1, lo]


@wp.func
def bin_coordinate(r: float, sonar: KernelSonar):
    return (r - sonar.range_min) * sonar.inv_range_step


@wp.func
def nearest_index(c: float):
    """floor(c + 0.5), clamped to ±2^30."""
    f = wp.floor(c + 0.5)
    return int(wp.clamp(f, -_INDEX_LIMIT, _INDEX_LIMIT))


# --- kernels ---------------------------------------------------------------------------------
@wp.kernel
def project_points(points: wp.array(dtype=wp.vec3), rotations: wp.array(dtype=wp.mat33),
                   translations: wp.array(dtype=wp.vec3), beam_table: wp.array2d(dtype=float),
                   sonar: KernelSonar, beam_out: wp.array2d(dtype=wp.int32), bin_out: wp.array2d(dtype=wp.int32),
                   inside_out: wp.array2d(dtype=wp.uint8)):
    """Thread (v, p): nearest beam and bin of point p in view v, and whether it lands in the
    image with |elevation| <= W_φ (kernels/project.cl documents the arguments)."""
    v, p = wp.tid()
    q = to_view(points[p], rotations[v], translations[v])
    theta = azimuth(q)
    phi = elevation(q)
    r = sonar_range(q)
    b = nearest_index(beam_coordinate(theta, sonar, beam_table))
    bb = nearest_index(bin_coordinate(r, sonar))
    beam_out[v, p] = b
    bin_out[v, p] = bb
    if b >= 0 and b < sonar.beams and bb >= 0 and bb < sonar.bins and wp.abs(phi) <= sonar.half_elevation:
        inside_out[v, p] = wp.uint8(1)
    else:
        inside_out[v, p] = wp.uint8(0)


# --- ray casting and image synthesis (fsswarp/rendering.py documents the algorithm) -------------
_EPS = wp.constant(RAY_EPSILON)
_FAR = wp.constant(WARP_FAR)
_FIXED = wp.constant(FIXED_SCALE)


@wp.func
def face_normal(points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32), face: int):
    """Unit geometric normal cross(v1 − v0, v2 − v0) of a triangle (reference frame)."""
    v0 = points[indices[face * 3 + 0]]
    v1 = points[indices[face * 3 + 1]]
    v2 = points[indices[face * 3 + 2]]
    return wp.normalize(wp.cross(v1 - v0, v2 - v0))


@wp.func
def facing_normal(points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32), face: int,
                  r: wp.mat33, u: wp.vec3):
    """View-frame normal Rᵀ N of a face, turned against the view-frame direction u (u·N <= 0)."""
    n = wp.transpose(r) * face_normal(points, indices, face)
    if wp.dot(u, n) > 0.0:
        n = -n
    return n


@wp.func
def deposit(acc: wp.array4d(dtype=wp.int32), v: int, layer: int, bin_index: int, beam: int,
            amplitude: float, weight: float, beams: int, first: int):
    """Add int(amplitude · weight · 2^24 + 0.5) at (v, layer, bin − first, beam) if inside view
    v's band of rows (acc.shape[2] rows from image row ``first``) and the image's beams."""
    row = bin_index - first
    if row >= 0 and row < acc.shape[2] and beam >= 0 and beam < beams:
        wp.atomic_add(acc, v, layer, row, beam, int(amplitude * weight * _FIXED + 0.5))


# --- watertight ray casting against a Warp BVH over the triangles (kernels/bvh.h) ------------
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
def nearest_hit(bvh: wp.uint64, points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32),
                org: wp.vec3, dir: wp.vec3, max_t: float):
    """Nearest watertight hit of the ray in [0, max_t): candidates from the BVH over the
    triangles' boxes, each tested exactly (face -1 and t = inf: none)."""
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
        t = ray_triangle(org, kx, ky, kz, sx, sy, sz, points[indices[face * 3 + 0]],
                         points[indices[face * 3 + 1]], points[indices[face * 3 + 2]], best)
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
def cast_rays_kernel(mesh: wp.uint64, points: wp.array(dtype=wp.vec3),
                     indices: wp.array(dtype=wp.int32), origins: wp.array(dtype=wp.vec3),
                     directions: wp.array(dtype=wp.vec3), max_distance: float,
                     distance_out: wp.array(dtype=float), face_out: wp.array(dtype=wp.int32)):
    """Thread i: nearest hit of ray i within max_distance (inf and -1 if none)."""
    i = wp.tid()
    hit = nearest_hit(mesh, points, indices, origins[i], directions[i], max_distance)
    if hit.face >= 0:
        distance_out[i] = hit.t
        face_out[i] = hit.face
    else:
        distance_out[i] = wp.inf
        face_out[i] = -1


@wp.kernel
def frontal_rays_kernel(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32),
                        rotations: wp.array(dtype=wp.mat33), translations: wp.array(dtype=wp.vec3),
                        plane_normals: wp.array(dtype=wp.vec3), plane_offsets: wp.array(dtype=float),
                        views: wp.array(dtype=wp.int32), azimuths: wp.array(dtype=float), mirror: int,
                        sonar: KernelSonar, epsilon: float, visible: float,
                        max_distance: float, range_out: wp.array2d(dtype=float),
                        face_out: wp.array2d(dtype=wp.int32)):
    """Thread (i, j): elevation ray j of beam i, its (mirror) range and face (Backend.frontal_faces;
    kernels/render.cl)."""
    i, j = wp.tid()
    rays = range_out.shape[1]
    v = views[i]
    rot = rotations[v]
    org = translations[v]
    n = plane_normals[v]
    d = plane_offsets[v]
    theta = azimuths[i]
    phi = -sonar.half_elevation + (float(j) + 0.5) / float(rays) * (2.0 * sonar.half_elevation)
    cphi = wp.cos(phi)
    u = wp.vec3(cphi * wp.sin(theta), cphi * wp.cos(theta), wp.sin(phi))
    up = wp.dot(u, n)
    s = float(wp.inf)
    if up > 0.0:
        s = d / up
    hit = nearest_hit(mesh, points, indices, org, rot * u, max_distance)
    rng = float(wp.inf)
    face = int(-1)
    if mirror == 0:
        if hit.t < s:
            rng = hit.t
            face = hit.face
    elif s < hit.t:
        q = s * u
        w = u - (2.0 * up) * n
        leg = nearest_hit(mesh, points, indices, rot * (q + epsilon * w) + org, rot * w, max_distance)
        if leg.face >= 0:
            r2 = leg.t + epsilon
            p = q + r2 * w
            length = wp.length(p)
            back = nearest_hit(mesh, points, indices, org, rot * (p / length), max_distance)
            if (wp.abs(elevation(p)) <= sonar.half_elevation and wp.abs(azimuth(p)) <= sonar.half_azimuth
                    and back.t >= length - visible):
                rng = 0.5 * (length + s + r2)
                face = leg.face
    range_out[i, j] = rng
    face_out[i, j] = face


@wp.kernel
def render_kernel(mesh: wp.uint64, points: wp.array(dtype=wp.vec3),
                  indices: wp.array(dtype=wp.int32), rotations: wp.array(dtype=wp.mat33),
                  translations: wp.array(dtype=wp.vec3), plane_normals: wp.array(dtype=wp.vec3),
                  plane_offsets: wp.array(dtype=float), beam_centres: wp.array(dtype=float),
                  beam_widths: wp.array(dtype=float), beam_table: wp.array2d(dtype=float),
                  sonar: KernelSonar, k_theta: int, k_phi: int, weight: float, gamma: float, surface_reflection: float,
                  first_rows: wp.array(dtype=wp.int32), acc: wp.array4d(dtype=wp.int32)):
    """Thread (v, b, k): sub-ray (i, j) = divmod(k, K_φ) of beam b in view v; deposits its
    object, ghost, mirror and mirror2 returns into acc (N, 4, R, beams), view v's image row B
    at row B − first_rows[v] when that lies in [0, R), else nowhere (kernels/render.cl)."""
    v, b, k = wp.tid()
    i = k // k_phi
    j = k - i * k_phi
    rot = rotations[v]
    org = translations[v]
    n = plane_normals[v]
    d = plane_offsets[v]
    first = first_rows[v]

    # 1. sub-ray direction (view frame)
    theta = beam_centres[b] + ((float(i) + 0.5) / float(k_theta) - 0.5) * beam_widths[b]
    phi = -sonar.half_elevation + (float(j) + 0.5) / float(k_phi) * (2.0 * sonar.half_elevation)
    cphi = wp.cos(phi)
    u = wp.vec3(cphi * wp.sin(theta), cphi * wp.cos(theta), wp.sin(phi))

    # 2. direct leg: surface at s, first mesh hit before it
    nu = wp.dot(n, u)
    s = _FAR
    has_surface = False
    if nu > 0.0:
        s = d / nu
        has_surface = True
    hit = nearest_hit(mesh, points, indices, org, rot * u, wp.min(s, _FAR))
    if hit.face >= 0:
        # 3. hit before the surface
        r = hit.t
        nrm = facing_normal(points, indices, hit.face, rot, u)
        c = -wp.dot(u, nrm)
        deposit(acc, v, 0, nearest_index(bin_coordinate(r, sonar)), b,
                wp.pow(c, gamma), weight, sonar.beams, first)
        p = r * u
        o_m = (2.0 * d) * n
        q = wp.length(p - o_m)
        n_p = wp.dot(n, p)
        lam = d / (2.0 * d - n_p)
        qq = o_m + lam * (p - o_m)
        if qq[1] > 0.0:
            bq = beam_coordinate(azimuth(qq), sonar, beam_table)
            if bq >= -0.5 and bq < float(sonar.beams) - 0.5 and wp.abs(elevation(qq)) <= sonar.half_elevation:
                pq = p - qq
                l_pq = wp.length(pq)
                w = pq / l_pq
                c_in = -wp.dot(w, nrm)
                if c_in > 0.0:
                    l_q = wp.length(qq)
                    leg1 = nearest_hit(mesh, points, indices, org, rot * (qq / l_q), l_q - _EPS)
                    if leg1.face < 0:
                        leg2 = nearest_hit(mesh, points, indices, rot * qq + org, rot * w, l_pq - _EPS)
                        if leg2.face < 0:
                            a_s = surface_reflection * wp.pow(c * c_in, 0.5 * gamma)
                            rb = nearest_index(bin_coordinate(0.5 * (r + q), sonar))
                            deposit(acc, v, 1, rb, b, a_s, weight, sonar.beams, first)
                            pm = p - (2.0 * (n_p - d)) * n
                            mb = nearest_index(beam_coordinate(azimuth(pm), sonar, beam_table))
                            deposit(acc, v, 2, rb, mb, a_s, weight, sonar.beams, first)
    elif has_surface:
        # 4. surface first: mirror2 along the reflected ray
        qs = s * u
        u2 = u - (2.0 * nu) * n
        dir2 = rot * u2
        hit2 = nearest_hit(mesh, points, indices, rot * qs + org + _EPS * dir2, dir2, _FAR)
        if hit2.face >= 0:
            r2 = _EPS + hit2.t
            nrm2 = facing_normal(points, indices, hit2.face, rot, u2)
            c2 = -wp.dot(u2, nrm2)
            deposit(acc, v, 3, nearest_index(bin_coordinate(s + r2, sonar)), b,
                    surface_reflection * surface_reflection * wp.pow(c2, gamma), weight, sonar.beams, first)


@wp.kernel
def fixed_to_float(acc: wp.array(dtype=wp.int32), layers: wp.array(dtype=float)):
    """Thread i: layers[i] = acc[i] / 2^24 (the accumulator's fixed point)."""
    i = wp.tid()
    layers[i] = float(acc[i]) * (1.0 / _FIXED)


# --- voxel space carving (kernels/carve.cl documents the rule and the arguments) -------------
@wp.func
def carve_test(c: wp.vec3, r: wp.mat33, t: wp.vec3, integral: wp.array3d(dtype=wp.int32), v: int,
               beam_table: wp.array2d(dtype=float), sonar: KernelSonar, radius: float):
    """0: view v does not see the voxel at c (wholly); 1: sees and keeps it; 2: sees and rejects
    it (fss_carve_test of kernels/carve.cl, operation for operation)."""
    q = to_view(c, r, t)
    rho = wp.sqrt(q[0] * q[0] + q[1] * q[1])
    if not (radius < rho):
        return 0
    theta = azimuth(q)
    phi = elevation(q)
    rng = sonar_range(q)
    d_phi = wp.asin(radius / rng)
    if not (wp.abs(phi) + d_phi <= sonar.half_elevation):
        return 0
    d_theta = wp.asin(radius / rho)
    b_lo = nearest_index(beam_coordinate(theta - d_theta, sonar, beam_table))
    b_hi = nearest_index(beam_coordinate(theta + d_theta, sonar, beam_table))
    bin_lo = nearest_index(bin_coordinate(rng - radius, sonar))
    bin_hi = nearest_index(bin_coordinate(rng + radius, sonar))
    if b_lo < 0 or b_hi >= sonar.beams or bin_lo < 0 or bin_hi >= sonar.bins:
        return 0
    count = (integral[v, bin_hi + 1, b_hi + 1] - integral[v, bin_lo, b_hi + 1]
             - integral[v, bin_hi + 1, b_lo] + integral[v, bin_lo, b_lo])
    if count == 0:
        return 2
    return 1


@wp.func
def carve_voxel(c: wp.vec3, p: int, rotations: wp.array(dtype=wp.mat33), translations: wp.array(dtype=wp.vec3),
                integral: wp.array3d(dtype=wp.int32), beam_table: wp.array2d(dtype=float), sonar: KernelSonar,
                radius: float, seen_out: wp.array(dtype=wp.uint8), rejected_out: wp.array(dtype=wp.uint8)):
    """Views that see the voxel at c up to the first that rejects it, and whether one does
    (written at p; the loop stops at the first rejection)."""
    seen = int(0)
    rejected = int(0)
    for v in range(rotations.shape[0]):
        test = carve_test(c, rotations[v], translations[v], integral, v, beam_table, sonar, radius)
        if test > 0:
            seen += 1
        if test == 2:
            rejected = 1
            break
    seen_out[p] = wp.uint8(seen)
    rejected_out[p] = wp.uint8(rejected)


@wp.kernel
def carve_grid(origin: wp.vec3, voxel_size: float, ny: int, nz: int, rotations: wp.array(dtype=wp.mat33),
               translations: wp.array(dtype=wp.vec3), integral: wp.array3d(dtype=wp.int32),
               beam_table: wp.array2d(dtype=float), sonar: KernelSonar, radius: float,
               seen_out: wp.array(dtype=wp.uint8),
               rejected_out: wp.array(dtype=wp.uint8)):
    """Thread p = (i·ny + j)·nz + k: the voxel centred at origin + h·(i, j, k)."""
    p = wp.tid()
    k = p % nz
    j = (p // nz) % ny
    i = p // (nz * ny)
    c = wp.vec3(origin[0] + voxel_size * float(i), origin[1] + voxel_size * float(j),
                origin[2] + voxel_size * float(k))
    carve_voxel(c, p, rotations, translations, integral, beam_table, sonar, radius, seen_out, rejected_out)


@wp.kernel
def carve_points(centres: wp.array(dtype=wp.vec3), rotations: wp.array(dtype=wp.mat33),
                 translations: wp.array(dtype=wp.vec3), integral: wp.array3d(dtype=wp.int32),
                 beam_table: wp.array2d(dtype=float), sonar: KernelSonar, radius: float,
                 seen_out: wp.array(dtype=wp.uint8),
                 rejected_out: wp.array(dtype=wp.uint8)):
    """Thread p: the voxel centred at centres[p]."""
    p = wp.tid()
    carve_voxel(centres[p], p, rotations, translations, integral, beam_table, sonar, radius, seen_out,
                rejected_out)


# --- the backend -----------------------------------------------------------------------------
class WarpLayers(DeviceLayers):
    """Rendered layers in a (N, 4, bins, beams) float32 ``wp.array`` (``.array``), or (N, 4,
    R, beams) for bands of rows (``first_rows``)."""

    def __init__(self, array: wp.array):
        self.array = array
        self.shape = tuple(array.shape)

    def numpy(self) -> np.ndarray:
        return self.array.numpy()


class _WarpMesh:
    """Handle of a mesh uploaded to one Warp device: a ``wp.Bvh`` over the triangles' (padded)
    boxes and the arrays (kept alive with it; the kernels read the triangles for the watertight
    test and their geometric normals)."""

    def __init__(self, bvh, points, indices, lowers, uppers, device):
        self.bvh = bvh
        self.points = points
        self.indices = indices
        self.lowers = lowers
        self.uppers = uppers
        self.device = device

    @property
    def id(self):
        return self.bvh.id

    def __repr__(self) -> str:
        return (f"<warp mesh: {self.points.shape[0]} vertices, {self.indices.shape[0] // 3} faces "
                f"on {self.device}>")


class WarpBackend(Backend):
    """Warp on one device ("cpu", "cuda:N"). Create through ``get_backend("warp", device)``."""

    name = "warp"

    def __init__(self, device: str):
        _warp()  # initialized quietly
        self._device = wp.get_device(device)
        self.device = str(self._device.alias)
        self.is_gpu = bool(self._device.is_cuda)
        self.has_float64 = True
        self._constants: dict[tuple, wp.array] = {}  # _constant's uploads, least recently used first

    def _array(self, data: np.ndarray, dtype) -> wp.array:
        return wp.array(data, dtype=dtype, device=self._device)

    def _constant(self, data: np.ndarray, dtype) -> wp.array:
        """``_array`` of a kernel input that no kernel writes, reused while the same bytes come
        again: a pose step passes the same thresholds, windows, masks, weights and beam tables
        to hundreds of launches, and each upload waits for its copy. Inputs above
        ``CONSTANT_BYTES`` are uploaded each time; the last ``CONSTANTS`` are kept."""
        data = np.ascontiguousarray(data)
        if data.nbytes > CONSTANT_BYTES:
            return self._array(data, dtype)
        key = (dtype, data.shape, data.dtype.str, data.tobytes())
        array = self._constants.pop(key, None)
        if array is None:
            array = self._array(data, dtype)
            if len(self._constants) >= CONSTANTS:
                self._constants.pop(next(iter(self._constants)))  # the least recently used
        self._constants[key] = array
        return array

    def _upload(self, array: np.ndarray) -> wp.array:
        return self._array(array, float)

    def _project(self, points, rotations, translations, sonar: SonarConstants):
        n_views, n_points = rotations.shape[0], points.shape[0]
        with wp.ScopedDevice(self._device):
            beam = wp.empty((n_views, n_points), dtype=wp.int32)
            bin_ = wp.empty((n_views, n_points), dtype=wp.int32)
            inside = wp.empty((n_views, n_points), dtype=wp.uint8)
            wp.launch(project_points, dim=(n_views, n_points),
                      inputs=[self._array(points, wp.vec3), self._array(rotations, wp.mat33),
                              self._array(translations, wp.vec3), self._constant(sonar.beam_table, float),
                              kernel_sonar(sonar)],
                      outputs=[beam, bin_, inside])
            wp.synchronize_device(self._device)
            return beam.numpy(), bin_.numpy(), inside.numpy()

    # --- ray casting and image synthesis ------------------------------------------------------
    def _load_mesh(self, vertices, faces):
        with wp.ScopedDevice(self._device):
            points = self._array(vertices, wp.vec3)
            indices = self._array(np.ascontiguousarray(faces.reshape(-1), dtype=np.int32), wp.int32)
            lo, hi = triangle_bounds(np.asarray(vertices, np.float32), np.asarray(faces, np.int64).reshape(-1, 3))
            # pad so boxes of axis-aligned triangles have volume (and rounding never loses one)
            extent = float(np.max(np.abs(vertices))) if len(vertices) else 1.0
            pad = np.float32(1.0e-6 * max(extent, 1.0e-12)) + 1.0e-6 * (hi - lo).max(axis=1, keepdims=True)
            lowers = self._array(np.ascontiguousarray(lo - pad, np.float32), wp.vec3)
            uppers = self._array(np.ascontiguousarray(hi + pad, np.float32), wp.vec3)
            bvh = wp.Bvh(lowers, uppers)
        return _WarpMesh(bvh, points, indices, lowers, uppers, self.device)

    def _check_mesh(self, mesh) -> "_WarpMesh":
        if not isinstance(mesh, _WarpMesh):
            raise TypeError(f"mesh must be a handle from this backend's load_mesh, got {type(mesh).__name__}")
        if mesh.device != self.device:
            raise ValueError(f"mesh was loaded on {mesh.device!r}, this backend runs on {self.device!r}")
        return mesh

    def _cast_rays(self, mesh, origins, directions, max_distance):
        mesh = self._check_mesh(mesh)
        n_rays = origins.shape[0]
        with wp.ScopedDevice(self._device):
            distance = wp.empty(n_rays, dtype=float)
            face = wp.empty(n_rays, dtype=wp.int32)
            wp.launch(cast_rays_kernel, dim=n_rays,
                      inputs=[mesh.id, mesh.points, mesh.indices, self._array(origins, wp.vec3), self._array(directions, wp.vec3),
                              float(np.float32(min(max_distance, WARP_FAR)))],
                      outputs=[distance, face])
            wp.synchronize_device(self._device)
            return distance.numpy(), face.numpy()

    def _frontal_rays(self, mesh, sonar: SonarConstants, rotations, translations, plane_normals, plane_offsets,
                      views, azimuths, rays, mirror):
        mesh = self._check_mesh(mesh)
        shape = (views.shape[0], rays)
        with wp.ScopedDevice(self._device):
            rng = wp.empty(shape, dtype=float)
            face = wp.empty(shape, dtype=wp.int32)
            wp.launch(frontal_rays_kernel, dim=shape,
                      inputs=[mesh.id, mesh.points, mesh.indices, self._array(rotations, wp.mat33),
                              self._array(translations, wp.vec3), self._array(plane_normals, wp.vec3),
                              self._array(plane_offsets, float), self._constant(views, wp.int32),
                              self._array(azimuths, float), int(mirror), kernel_sonar(sonar),
                              float(np.float32(RAY_EPSILON)),
                              float(np.float32(FRONTAL_VISIBLE)), float(np.float32(MAX_DISTANCE))],
                      outputs=[rng, face])
            wp.synchronize_device(self._device)
            return rng.numpy(), face.numpy()

    def _render(self, mesh, sonar: SonarConstants, beam_widths, rotations, translations,
                plane_normals, plane_offsets, k_theta, k_phi, gamma, surface_reflection, first_rows, rows):
        mesh = self._check_mesh(mesh)
        n_views = rotations.shape[0]
        if sonar.use_table:
            centres = np.ascontiguousarray(sonar.beam_table[0], np.float32)
        else:  # the centres of SonarSpec.beam_centres
            half = float(sonar.half_azimuth)
            centres = (-half + np.arange(sonar.beams) * (2.0 * half / max(sonar.beams - 1, 1))).astype(np.float32)
        weight = float(np.float32(1.0 / (k_theta * k_phi)))
        shape = (n_views, 4, rows, sonar.beams)
        with wp.ScopedDevice(self._device):
            acc = wp.zeros(shape, dtype=wp.int32)
            wp.launch(render_kernel, dim=(n_views, sonar.beams, k_theta * k_phi),
                      inputs=[mesh.id, mesh.points, mesh.indices, self._array(rotations, wp.mat33),
                              self._array(translations, wp.vec3), self._array(plane_normals, wp.vec3),
                              self._array(plane_offsets, float), self._constant(centres, float),
                              self._constant(np.asarray(beam_widths, np.float32), float),
                              self._constant(sonar.beam_table, float), kernel_sonar(sonar), int(k_theta), int(k_phi),
                              weight, float(gamma), float(surface_reflection),
                              self._constant(first_rows, wp.int32)],
                      outputs=[acc])
            layers = wp.empty(shape, dtype=float)
            wp.launch(fixed_to_float, dim=acc.size, inputs=[acc.flatten()], outputs=[layers.flatten()])
            wp.synchronize_device(self._device)
            return WarpLayers(layers)

    # --- voxel space carving -------------------------------------------------------------------
    def _carve(self, integral, rotations, translations, sonar: SonarConstants, voxel_size, radius, origin,
               shape, centres):
        n_voxels = centres.shape[0] if centres is not None else shape[0] * shape[1] * shape[2]
        with wp.ScopedDevice(self._device):
            seen = wp.empty(n_voxels, dtype=wp.uint8)
            rejected = wp.empty(n_voxels, dtype=wp.uint8)
            common = [self._array(rotations, wp.mat33), self._array(translations, wp.vec3),
                      self._array(integral, wp.int32), self._constant(sonar.beam_table, float),
                      kernel_sonar(sonar), radius]
            if centres is not None:
                wp.launch(carve_points, dim=n_voxels, inputs=[self._array(centres, wp.vec3), *common],
                          outputs=[seen, rejected])
            else:
                wp.launch(carve_grid, dim=n_voxels,
                          inputs=[wp.vec3(*(float(x) for x in origin)), voxel_size, shape[1], shape[2], *common],
                          outputs=[seen, rejected])
            wp.synchronize_device(self._device)
            return seen.numpy(), rejected.numpy()

    # --- frontal contours and their distance to the data's (kernels after the class) ---------
    def _contour_cost(self, layers, first_rows, view_index, thresholds, windows, masks, range_weights,
                      beam_weights, distances, cap, shifts):
        n_pairs, beams = view_index.shape[0], distances.shape[3]
        with wp.ScopedDevice(self._device):
            if isinstance(layers, WarpLayers) and layers.array.device == self._device:
                stack = layers.array
            else:
                stack = self._array(np.ascontiguousarray(layers.numpy(), np.float32), float)
            index = self._constant(view_index, wp.int32)
            contour = wp.empty((n_pairs, 2, beams), dtype=float)
            wp.launch(frontal_contour, dim=(n_pairs, 2, beams),
                      inputs=[stack, self._constant(first_rows, wp.int32), index, self._constant(thresholds, float),
                              self._constant(windows, wp.int32),
                              self._constant(masks, wp.uint8), self._constant(range_weights, float),
                              (range_weights.shape[0] - 1) // 2, self._constant(beam_weights, float),
                              (beam_weights.shape[0] - 1) // 2],
                      outputs=[contour])
            sums = wp.empty((n_pairs, 2, shifts.shape[0]), dtype=float)
            counts = wp.empty((n_pairs, 2), dtype=wp.int32)
            wp.launch(contour_cost_kernel, dim=(n_pairs, 2, shifts.shape[0]),
                      inputs=[contour, index, distances.data, float(np.float32(cap)), self._constant(shifts, float)],
                      outputs=[sums, counts])
            wp.synchronize_device(self._device)
            return contour.numpy(), sums.numpy(), counts.numpy()

    # --- IRLS-ICP runs (kernels after the class) ------------------------------------------------
    def _icp_runs(self, source_x, source_y, target_x, target_y, runs, angles, translations, floors, step_tols,
                  max_iterations, max_distance, tuning):
        n_runs, n_points = runs.shape[0], source_x.shape[0]
        with wp.ScopedDevice(self._device):
            f64 = [self._array(a, wp.float64) for a in (source_x, source_y, target_x, target_y)]
            angle = self._array(angles, wp.float64)
            trans = self._array(translations, wp.float64)
            iterations = wp.zeros(n_runs, dtype=wp.int32)
            converged = wp.zeros(n_runs, dtype=wp.int32)
            moved_x, moved_y, dist, anchor_x, anchor_y, room2, scratch = (
                wp.empty(n_points, dtype=wp.float64) for _ in range(7))
            nearest = wp.empty(n_points, dtype=wp.int32)
            wp.launch(icp_runs_kernel, dim=n_runs,
                      inputs=[*f64, self._array(runs, wp.int32), self._array(floors, wp.float64),
                              self._array(step_tols, wp.float64), max_iterations, wp.float64(max_distance),
                              wp.float64(tuning)],
                      outputs=[angle, trans, iterations, converged, moved_x, moved_y, nearest, dist, anchor_x,
                               anchor_y, room2, scratch])
            wp.synchronize_device(self._device)
            return tuple(a.numpy() for a in (angle, trans, iterations, converged, moved_x, moved_y, nearest, dist))


# --- frontal contours and their distance to the data's (kernels/pose.cl documents the rule) --
@wp.kernel
def frontal_contour(layers: wp.array4d(dtype=float), first_rows: wp.array(dtype=wp.int32),
                    view_index: wp.array(dtype=wp.int32),
                    threshold: wp.array2d(dtype=float), window: wp.array2d(dtype=wp.int32),
                    mask: wp.array3d(dtype=wp.uint8), w_range: wp.array(dtype=float), r_range: int,
                    w_beam: wp.array(dtype=float), r_beam: int, contour: wp.array3d(dtype=float)):
    """Thread (n, c, b): first threshold crossing of the smoothed component c of pair n in beam b.
    layers (N, 4, R, beams): image row B of pair n at row B − first_rows[n] (full layers: zeros,
    R = bins); rows clamp to the image, and the host guarantees the band holds every row read."""
    n, c, b = wp.tid()
    v = view_index[n]
    bins = threshold.shape[1]
    beams = layers.shape[3]
    first = first_rows[n]
    result = float(-1.0)
    if mask[v, c, b] != wp.uint8(0):
        lo = window[v, 0]
        hi = window[v, 1]
        previous = float(0.0)
        row_index = int(lo)
        while row_index < hi:
            s = float(0.0)
            for i in range(2 * r_range + 1):
                bi = wp.clamp(row_index + i - r_range, 0, bins - 1) - first
                row = float(0.0)
                for j in range(2 * r_beam + 1):
                    bj = wp.clamp(b + j - r_beam, 0, beams - 1)
                    row += w_beam[j] * (layers[n, 2 * c, bi, bj] + layers[n, 2 * c + 1, bi, bj])
                s += w_range[i] * row
            f = s - threshold[v, row_index]
            if f > 0.0:
                if row_index == lo:
                    result = float(lo)
                else:
                    result = float(row_index - 1) + previous / (previous - f)
                row_index = hi
            else:
                previous = f
                row_index += 1
    contour[n, c, b] = result


@wp.kernel
def contour_cost_kernel(contour: wp.array3d(dtype=float), view_index: wp.array(dtype=wp.int32),
                        dist: wp.array4d(dtype=float), cap: float, shifts: wp.array(dtype=float),
                        sums: wp.array3d(dtype=float), counts: wp.array2d(dtype=wp.int32)):
    """Thread (n, c, s): distances of pair n's contour c to the data's, read at shift s."""
    n, c, s = wp.tid()
    v = view_index[n]
    bins = dist.shape[2]
    beams = dist.shape[3]
    shift = shifts[s]
    last = float(bins - 1)
    total = float(0.0)
    count = int(0)
    for b in range(beams):
        x = contour[n, c, b]
        if x >= 0.0:
            y = wp.clamp(x + shift, 0.0, last)
            b0 = int(wp.floor(y))
            b1 = wp.min(b0 + 1, bins - 1)
            t = y - float(b0)
            total += (1.0 - t) * wp.min(dist[v, c, b0, b], cap) + t * wp.min(dist[v, c, b1, b], cap)
            count += 1
    sums[n, c, s] = total
    if s == 0:
        counts[n, c] = count



# --- IRLS-ICP runs of 2-D contours (fsswarp/icp.py; kernels/icp.cl is the same, line by line) --
_RAYLEIGH_MEDIAN = wp.constant(wp.float64(math.sqrt(2.0 * math.log(2.0))))  # fsswarp.icp.RAYLEIGH_MEDIAN
_TIE = wp.constant(wp.float64(1e-9))  # a second nearest within this share is a tie (fsswarp.icp)


@wp.func
def icp_match(r: int, p: int, tx: wp.array(dtype=wp.float64), ty: wp.array(dtype=wp.float64),
              runs: wp.array2d(dtype=wp.int32), moved_x: wp.array(dtype=wp.float64),
              moved_y: wp.array(dtype=wp.float64), anchor_x: wp.array(dtype=wp.float64),
              anchor_y: wp.array(dtype=wp.float64), room2: wp.array(dtype=wp.float64),
              nearest: wp.array(dtype=wp.int32)):
    """Distance of run r's moved point p to its nearest target. The point keeps the target of
    its last search while it stays within its room (half the gap to the second nearest, less
    1e-9 of it, of where it searched); else all the run's targets are searched again."""
    x = moved_x[p]
    y = moved_y[p]
    ax = x - anchor_x[p]
    ay = y - anchor_y[p]
    if ax * ax + ay * ay >= room2[p]:
        best = wp.float64(-1.0)
        second = wp.float64(-1.0)
        found = int(-1)
        for j in range(runs[r, 1], runs[r, 1] + runs[r, 2]):
            dx = x - tx[j]
            dy = y - ty[j]
            d2 = dx * dx + dy * dy
            if found < 0 or d2 < best:
                second = best
                best = d2
                found = j
            elif second < wp.float64(0.0) or d2 < second:
                second = d2
        room = wp.float64(-1.0)
        if second >= wp.float64(0.0):
            room = (wp.sqrt(second) * (wp.float64(1.0) - _TIE) - wp.sqrt(best)) / wp.float64(2.0)
        nearest[p] = found
        anchor_x[p] = x
        anchor_y[p] = y
        if room > wp.float64(0.0):
            room2[p] = room * room
        else:
            room2[p] = wp.float64(-1.0)
    k = nearest[p]
    dx = x - tx[k]
    dy = y - ty[k]
    return wp.sqrt(dx * dx + dy * dy)


@wp.func
def icp_select(a: wp.array(dtype=wp.float64), lo: int, hi: int, k: int):
    """The value of rank k of a[lo..hi] (inclusive), moved to a[k], with no larger value
    before it and no smaller one after it (Wirth's selection)."""
    left = lo
    right = hi
    while left < right:
        pivot = a[k]
        i = left
        j = right
        while i <= j:
            while a[i] < pivot:
                i += 1
            while pivot < a[j]:
                j -= 1
            if i <= j:
                swap = a[i]
                a[i] = a[j]
                a[j] = swap
                i += 1
                j -= 1
        if j < k:
            left = i
        if k < i:
            right = j
    return a[k]


@wp.func
def icp_weight(d: wp.float64, tuning: wp.float64, sigma: wp.float64):
    """Cauchy weight of a pair at distance d (-1: not usable, weight 0)."""
    if d < wp.float64(0.0):
        return wp.float64(0.0)
    u = d / (tuning * sigma)
    return wp.float64(1.0) / (wp.float64(1.0) + u * u)


@wp.kernel
def icp_runs_kernel(sx: wp.array(dtype=wp.float64), sy: wp.array(dtype=wp.float64),
                    tx: wp.array(dtype=wp.float64), ty: wp.array(dtype=wp.float64),
                    runs: wp.array2d(dtype=wp.int32), floors: wp.array(dtype=wp.float64),
                    step_tols: wp.array(dtype=wp.float64), max_iterations: int, max_distance: wp.float64,
                    tuning: wp.float64, angles: wp.array(dtype=wp.float64), trans: wp.array2d(dtype=wp.float64),
                    iterations: wp.array(dtype=wp.int32), converged: wp.array(dtype=wp.int32),
                    moved_x: wp.array(dtype=wp.float64), moved_y: wp.array(dtype=wp.float64),
                    nearest: wp.array(dtype=wp.int32), dist: wp.array(dtype=wp.float64),
                    anchor_x: wp.array(dtype=wp.float64), anchor_y: wp.array(dtype=wp.float64),
                    room2: wp.array(dtype=wp.float64), scratch: wp.array(dtype=wp.float64)):
    """Thread r: IRLS-ICP run r (Backend.icp_runs). runs[r] = (first source point, first
    target, targets, source points); angles, trans hold the start and receive the result; dist
    receives the distances after the last move, -1 where a pair is not usable."""
    r = wp.tid()
    first = runs[r, 0]
    end = first + runs[r, 3]
    c = wp.cos(angles[r])
    s = wp.sin(angles[r])
    for p in range(first, end):
        moved_x[p] = c * sx[p] - s * sy[p] + trans[r, 0]
        moved_y[p] = s * sx[p] + c * sy[p] + trans[r, 1]
        anchor_x[p] = wp.float64(0.0)
        anchor_y[p] = wp.float64(0.0)
        room2[p] = wp.float64(-1.0)  # search at once
    done = int(0)
    iteration = int(0)
    while iteration <= max_iterations:
        # match: distances, -1 where not usable; sigma from their median
        count = int(0)
        for p in range(first, end):
            d = icp_match(r, p, tx, ty, runs, moved_x, moved_y, anchor_x, anchor_y, room2, nearest)
            if d <= max_distance:
                dist[p] = d
                scratch[first + count] = d
                count += 1
            else:
                dist[p] = wp.float64(-1.0)
        if iteration == max_iterations or done != 0:
            break  # the final match after the last move
        iteration += 1
        iterations[r] = iteration
        sigma = floors[r]
        if count > 0:
            low = first + (count - 1) // 2
            a = icp_select(scratch, first, first + count - 1, low)
            b = a
            if count % 2 == 0:
                b = scratch[low + 1]
                for q in range(low + 2, first + count):
                    b = wp.min(b, scratch[q])
            sigma = wp.max((a + b) / wp.float64(2.0) / _RAYLEIGH_MEDIAN, floors[r])
        total = wp.float64(0.0)
        for p in range(first, end):  # the weights, in scratch (the median is taken)
            scratch[p] = icp_weight(dist[p], tuning, sigma)
            total += scratch[p]
        if total <= wp.float64(0.0):
            done = 1  # no weight left
        else:
            # weighted Procrustes from the original points, with the weights divided by their total
            cx = wp.float64(0.0)
            cy = wp.float64(0.0)
            gx = wp.float64(0.0)
            gy = wp.float64(0.0)
            for p in range(first, end):
                w = scratch[p] / total
                scratch[p] = w
                k = nearest[p]
                cx += sx[p] * w
                cy += sy[p] * w
                gx += tx[k] * w
                gy += ty[k] * w
            h00 = wp.float64(0.0)
            h01 = wp.float64(0.0)
            h10 = wp.float64(0.0)
            h11 = wp.float64(0.0)
            for p in range(first, end):
                w = scratch[p]
                k = nearest[p]
                bx = (tx[k] - gx) * w
                by = (ty[k] - gy) * w
                h00 += (sx[p] - cx) * bx
                h01 += (sx[p] - cx) * by
                h10 += (sy[p] - cy) * bx
                h11 += (sy[p] - cy) * by
            angle = wp.atan2(h01 - h10, h00 + h11)
            ca = wp.cos(angle)
            sa = wp.sin(angle)
            angles[r] = angle
            trans[r, 0] = gx - (ca * cx - sa * cy)
            trans[r, 1] = gy - (sa * cx + ca * cy)
            step2 = wp.float64(0.0)
            for p in range(first, end):
                x = ca * sx[p] - sa * sy[p] + trans[r, 0]
                y = sa * sx[p] + ca * sy[p] + trans[r, 1]
                dx = x - moved_x[p]
                dy = y - moved_y[p]
                step2 = wp.max(step2, dx * dx + dy * dy)
                moved_x[p] = x
                moved_y[p] = y
            if wp.sqrt(step2) <= step_tols[r]:
                converged[r] = 1
                done = 1
