"""Warp kernels of image synthesis (kernels/render.cl; fsswarp/rendering.py documents the algorithm).

``render_kernel`` deposits every sub-ray's mirror2 return into a fixed-point (N, 4, R, beams)
int32 accumulator and queues its hit before the surface, whose object, ghost and mirror returns
``hits_kernel`` deposits (``Backend.hit_queue``); ``fixed_to_float`` converts the accumulator to
float32 layers, and ``frontal_rays_kernel`` finds the frontal patch of beams (``Backend.frontal_faces``).
``triangle_boxes_kernel`` gathers a mesh's corners and padded boxes for ``Backend.load_mesh``
(here, so that a synthesis compiles this module alone).
"""

from __future__ import annotations

import warp as wp

from ..constants import FIXED_SCALE, RAY_EPSILON, WARP_FAR
from .raycast import nearest_hit
from .sonar import MODULE_OPTIONS, KernelSonar, azimuth, beam_coordinate, bin_coordinate, elevation, nearest_index

_EPS = wp.constant(RAY_EPSILON)
_FAR = wp.constant(WARP_FAR)
_FIXED = wp.constant(FIXED_SCALE)
_BOX_PAD = wp.constant(wp.float32(1.0e-6))  # a box's pad per unit of its longest side (load_mesh)
#: CUDA threads per block of this module's kernels (its option, which every launch follows): the
#: render kernel of a 64 × 64 pose grid took 107 ms at 128 against 131 ms at Warp's 256 (H200;
#: 116 ms at 64, 110 ms at 32), the same layers. A CPU launch runs one thread per block either way.
RAY_BLOCK = 128

wp.set_module_options({**MODULE_OPTIONS, "block_dim": RAY_BLOCK})


@wp.func
def face_normal(corners: wp.array(dtype=wp.vec3), face: int):
    """Unit geometric normal cross(v1 − v0, v2 − v0) of a triangle (reference frame)."""
    v0 = corners[face * 3 + 0]
    v1 = corners[face * 3 + 1]
    v2 = corners[face * 3 + 2]
    return wp.normalize(wp.cross(v1 - v0, v2 - v0))


@wp.func
def facing_normal(corners: wp.array(dtype=wp.vec3), face: int, r: wp.mat33, u: wp.vec3):
    """View-frame normal Rᵀ N of a face, turned against the view-frame direction u (u·N <= 0)."""
    n = wp.transpose(r) * face_normal(corners, face)
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


@wp.func
def needed_at(needed: wp.array3d(dtype=wp.uint8), masked: int, v: int, c: int, beam: int):
    """Whether view v's component c is read at ``beam`` (render_kernel's masked and needed)."""
    if masked == 0:
        return True
    if beam < 0 or beam >= needed.shape[2]:
        return False
    return needed[v, c, beam] != wp.uint8(0)


@wp.kernel
def frontal_rays_kernel(mesh: wp.uint64, corners: wp.array(dtype=wp.vec3),
                        rotations: wp.array(dtype=wp.mat33), translations: wp.array(dtype=wp.vec3),
                        plane_normals: wp.array(dtype=wp.vec3), plane_offsets: wp.array(dtype=float),
                        views: wp.array(dtype=wp.int32), azimuths: wp.array(dtype=float),
                        mirrors: wp.array(dtype=wp.uint8),
                        sonar: KernelSonar, epsilon: float, visible: float,
                        max_distance: float, range_out: wp.array2d(dtype=float),
                        face_out: wp.array2d(dtype=wp.int32)):
    """Thread (i, j): elevation ray j of beam i, its range and face, or its mirror range and face
    where mirrors[i] is 1 (Backend.frontal_faces; kernels/render.cl)."""
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
    hit = nearest_hit(mesh, corners, org, rot * u, max_distance)
    rng = float(wp.inf)
    face = int(-1)
    if mirrors[i] == wp.uint8(0):
        if hit.t < s:
            rng = hit.t
            face = hit.face
    elif s < hit.t:
        q = s * u
        w = u - (2.0 * up) * n
        leg = nearest_hit(mesh, corners, rot * (q + epsilon * w) + org, rot * w, max_distance)
        if leg.face >= 0:
            r2 = leg.t + epsilon
            p = q + r2 * w
            length = wp.length(p)
            back = nearest_hit(mesh, corners, org, rot * (p / length), max_distance)
            if (wp.abs(elevation(p)) <= sonar.half_elevation and wp.abs(azimuth(p)) <= sonar.half_azimuth
                    and back.t >= length - visible):
                rng = 0.5 * (length + s + r2)
                face = leg.face
    range_out[i, j] = rng
    face_out[i, j] = face


@wp.kernel
def sub_rays_kernel(beam_centres: wp.array(dtype=float), beam_widths: wp.array(dtype=float), sonar: KernelSonar,
                    directions: wp.array3d(dtype=wp.vec3)):
    """Thread (b, i, j): step 1 once per render, the view-frame direction of sub-ray (i, j) of
    beam b into directions (beams, K_θ, K_φ) (kernels/render.cl, sub_rays)."""
    b, i, j = wp.tid()
    theta = beam_centres[b] + ((float(i) + 0.5) / float(directions.shape[1]) - 0.5) * beam_widths[b]
    phi = -sonar.half_elevation + (float(j) + 0.5) / float(directions.shape[2]) * (2.0 * sonar.half_elevation)
    cphi = wp.cos(phi)
    directions[b, i, j] = wp.vec3(cphi * wp.sin(theta), cphi * wp.cos(theta), wp.sin(phi))


@wp.func
def span_item(spans: wp.array2d(dtype=wp.int32), row: int, o: int, k: int, k_theta: int):
    """(b, i, j) of thread (row, o, k) of a launch over the spans (N, 4) (render_kernel's
    threads): beam b, sub-ray i, elevation sample j; b = -1 where the thread has none."""
    b = spans[row, 0] + o
    samples = spans[row, 3] - spans[row, 2]
    if b >= spans[row, 1] or k >= k_theta * samples:
        return wp.vec3i(-1, 0, 0)
    i = k // samples
    return wp.vec3i(b, i, spans[row, 2] + k - i * samples)


@wp.kernel
def direct_hits_kernel(mesh: wp.uint64, corners: wp.array(dtype=wp.vec3),
                       rotations: wp.array(dtype=wp.mat33), translations: wp.array(dtype=wp.vec3),
                       directions: wp.array3d(dtype=wp.vec3), k_theta: int, spans: wp.array2d(dtype=wp.int32),
                       hit_range: wp.array4d(dtype=float), hit_face: wp.array4d(dtype=wp.int32)):
    """Thread (p, o, k): the direct leg of sub-ray (i, j) of beam b of distinct pose p (as
    render_kernel's threads), its first hit's distance (inf: none) and face (-1) into
    hit_range and hit_face (P, beams, K_θ, K_φ) (kernels/render.cl, direct_hits)."""
    p, o, k = wp.tid()
    item = span_item(spans, p, o, k, k_theta)
    b = item[0]
    if b < 0:
        return
    i = item[1]
    j = item[2]
    u = directions[b, i, j]
    hit = nearest_hit(mesh, corners, translations[p], rotations[p] * u, _FAR)
    hit_range[p, b, i, j] = hit.t
    hit_face[p, b, i, j] = hit.face


@wp.kernel
def render_kernel(mesh: wp.uint64, corners: wp.array(dtype=wp.vec3), rotations: wp.array(dtype=wp.mat33),
                  translations: wp.array(dtype=wp.vec3), plane_normals: wp.array(dtype=wp.vec3),
                  plane_offsets: wp.array(dtype=float), directions: wp.array3d(dtype=wp.vec3),
                  sonar: KernelSonar, k_theta: int, weight: float, gamma: float,
                  surface_reflection: float,
                  first_rows: wp.array(dtype=wp.int32), spans: wp.array2d(dtype=wp.int32),
                  poses: wp.array(dtype=wp.int32), hit_range: wp.array4d(dtype=float),
                  hit_face: wp.array4d(dtype=wp.int32), masked: int, needed: wp.array3d(dtype=wp.uint8),
                  acc: wp.array4d(dtype=wp.int32), hits: wp.array(dtype=wp.int32), hit_items: wp.array(dtype=wp.vec4i),
                  hit_ranges: wp.array(dtype=float)):
    """Thread (v, o, k): sub-ray (i, spans[v, 2] + q), (i, q) = divmod(k, J_v), of beam
    b = spans[v, 0] + o in view v, J_v = spans[v, 3] − spans[v, 2] (none where b >= spans[v, 1]
    or k >= K_θ J_v); deposits its mirror2 return into acc (N, 4, R, beams), view v's image row
    B at row B − first_rows[v] when that lies in [0, R), else nowhere, and queues its hit before
    the surface for hits_kernel, which deposits the object, ghost and mirror returns
    (kernels/render.cl). Where poses[v] = p >= 0 the direct leg is hit_range and
    hit_face[p, b, i, j] (direct_hits_kernel), else cast here. With masked 1 a return lands only
    where its component's beam is needed[v, c, beam] (N, 2, beams) (c 0: object and ghost, 1:
    mirror and mirror2), and a leg whose returns land nowhere needed is not cast. The queue: a
    hit counts itself in hits (1,) int32, zeroed, and the count before it, c, is its slot: where
    c < L it writes (v, b, i K_φ + j, face) to hit_items[c] and r to hit_ranges[c], hit_items
    (L,) vec4i, hit_ranges (L,) float (the host renders again with a larger queue where the
    count passes L)."""
    v, o, k = wp.tid()
    item = span_item(spans, v, o, k, k_theta)
    b = item[0]
    if b < 0:
        return
    i = item[1]
    j = item[2]
    rot = rotations[v]
    org = translations[v]
    n = plane_normals[v]
    d = plane_offsets[v]
    first = first_rows[v]

    # 1. sub-ray direction (view frame)
    u = directions[b, i, j]

    # 2. direct leg: surface at s, first mesh hit before it
    nu = wp.dot(n, u)
    s = _FAR
    has_surface = False
    if nu > 0.0:
        s = d / nu
        has_surface = True
    r = float(wp.inf)
    face = int(-1)
    pose = poses[v]
    if pose >= 0:
        r = hit_range[pose, b, i, j]
        face = hit_face[pose, b, i, j]
    else:
        hit = nearest_hit(mesh, corners, org, rot * u, _FAR)
        r = hit.t
        face = hit.face
    if face >= 0 and r < s:
        # 3. hit before the surface: queued for hits_kernel (the object, then the path via the surface)
        slot = wp.atomic_add(hits, 0, 1)
        if slot < hit_items.shape[0]:
            hit_items[slot] = wp.vec4i(v, b, i * directions.shape[2] + j, face)
            hit_ranges[slot] = r
    elif has_surface and needed_at(needed, masked, v, 1, b):
        # 4. surface first: mirror2 along the reflected ray
        qs = s * u
        u2 = u - (2.0 * nu) * n
        dir2 = rot * u2
        hit2 = nearest_hit(mesh, corners, rot * qs + org + _EPS * dir2, dir2, _FAR)
        if hit2.face >= 0:
            r2 = _EPS + hit2.t
            nrm2 = facing_normal(corners, hit2.face, rot, u2)
            c2 = -wp.dot(u2, nrm2)
            deposit(acc, v, 3, nearest_index(bin_coordinate(s + r2, sonar)), b,
                    surface_reflection * surface_reflection * wp.pow(c2, gamma), weight, sonar.beams, first)


@wp.kernel
def hits_kernel(mesh: wp.uint64, corners: wp.array(dtype=wp.vec3), rotations: wp.array(dtype=wp.mat33),
                translations: wp.array(dtype=wp.vec3), plane_normals: wp.array(dtype=wp.vec3),
                plane_offsets: wp.array(dtype=float), directions: wp.array3d(dtype=wp.vec3),
                beam_table: wp.array2d(dtype=float), sonar: KernelSonar, weight: float, gamma: float,
                surface_reflection: float, first_rows: wp.array(dtype=wp.int32), masked: int,
                needed: wp.array3d(dtype=wp.uint8), hits: wp.array(dtype=wp.int32),
                hit_items: wp.array(dtype=wp.vec4i), hit_ranges: wp.array(dtype=float),
                acc: wp.array4d(dtype=wp.int32)):
    """Thread t < min(hits[0], L): render_kernel's queued hit t (step 3 of kernels/render.cl): its
    object return, then, where both legs of its path via the surface are clear, its ghost and
    mirror returns, each where it is read."""
    t = wp.tid()
    if t >= hits[0]:
        return
    item = hit_items[t]
    v = item[0]
    b = item[1]
    face = item[3]
    r = hit_ranges[t]
    rot = rotations[v]
    first = first_rows[v]
    k_phi = directions.shape[2]
    u = directions[b, item[2] // k_phi, item[2] % k_phi]
    n = plane_normals[v]
    d = plane_offsets[v]
    nrm = facing_normal(corners, face, rot, u)
    c = -wp.dot(u, nrm)
    want_object = needed_at(needed, masked, v, 0, b)
    if want_object:
        deposit(acc, v, 0, nearest_index(bin_coordinate(r, sonar)), b, wp.pow(c, gamma), weight, sonar.beams, first)
    # the path via the surface: Q on the surface, between the mirror sonar O_m and P
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
            pm = p - (2.0 * (n_p - d)) * n
            mb = nearest_index(beam_coordinate(azimuth(pm), sonar, beam_table))
            want_mirror = needed_at(needed, masked, v, 1, mb)
            if c_in > 0.0 and (want_object or want_mirror):
                org = translations[v]
                l_q = wp.length(qq)
                leg1 = nearest_hit(mesh, corners, org, rot * (qq / l_q), l_q - _EPS)
                if leg1.face < 0:
                    leg2 = nearest_hit(mesh, corners, rot * qq + org, rot * w, l_pq - _EPS)
                    if leg2.face < 0:
                        a_s = surface_reflection * wp.pow(c * c_in, 0.5 * gamma)
                        rb = nearest_index(bin_coordinate(0.5 * (r + q), sonar))
                        if want_object:
                            deposit(acc, v, 1, rb, b, a_s, weight, sonar.beams, first)
                        if want_mirror:
                            deposit(acc, v, 2, rb, mb, a_s, weight, sonar.beams, first)


@wp.kernel
def fixed_to_float(acc: wp.array(dtype=wp.int32), layers: wp.array(dtype=float)):
    """Thread i: layers[i] = acc[i] / 2^24 (the accumulator's fixed point)."""
    i = wp.tid()
    layers[i] = float(acc[i]) * (1.0 / _FIXED)


@wp.kernel
def triangle_boxes_kernel(points: wp.array(dtype=wp.vec3), faces: wp.array(dtype=wp.int32), pad: float,
                          corners: wp.array(dtype=wp.vec3), lowers: wp.array(dtype=wp.vec3),
                          uppers: wp.array(dtype=wp.vec3)):
    """Thread f: triangle f's corners (faces (3F,): its points in turn) into corners[3f..3f+2],
    and its box, the corners' minimum and maximum each moved out by pad + 1e-6 × the box's
    longest side, into lowers[f] and uppers[f] (float32, as ``WarpBackend._load_mesh`` says)."""
    f = wp.tid()
    a = points[faces[3 * f]]
    b = points[faces[3 * f + 1]]
    c = points[faces[3 * f + 2]]
    corners[3 * f] = a
    corners[3 * f + 1] = b
    corners[3 * f + 2] = c
    lo = wp.min(wp.min(a, b), c)
    hi = wp.max(wp.max(a, b), c)
    side = hi - lo
    margin = pad + _BOX_PAD * wp.max(wp.max(side[0], side[1]), side[2])
    lowers[f] = lo - wp.vec3(margin, margin, margin)
    uppers[f] = hi + wp.vec3(margin, margin, margin)
