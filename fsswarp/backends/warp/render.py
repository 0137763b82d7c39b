"""Warp kernels of image synthesis (kernels/render.cl; fsswarp/rendering.py documents the algorithm).

``render_kernel`` deposits every sub-ray's mirror2 return into a fixed-point (N, 4, R, beams)
int32 accumulator (or (N, 2, R, beams), the components' sums) and queues its hit before the
surface, whose object, ghost and mirror returns ``hits_kernel`` deposits
(``Backend.hit_queue``); its threads take the sub-rays that can reach
the mesh, found on the device (``view_spans_kernel``) and packed in chunks per view
(``chunk_views_kernel``), in turn; ``fixed_to_float`` converts the accumulator to
float32 layers, and ``frontal_rays_kernel`` finds the frontal patch of beams (``Backend.frontal_faces``).
``triangle_boxes_kernel`` gathers a mesh's corners and padded boxes for ``Backend.load_mesh``
(here, so that a synthesis compiles this module alone).
"""

from __future__ import annotations

import warp as wp

from ..constants import FIXED_SCALE, RAY_EPSILON, SPAN_MARGIN, WARP_FAR
from .raycast import nearest_hit
from .sonar import (MODULE_OPTIONS, KernelSonar, azimuth, beam_coordinate, bin_coordinate, elevation, nearest_index,
                    to_view)

_EPS = wp.constant(RAY_EPSILON)
_FAR = wp.constant(WARP_FAR)
_FIXED = wp.constant(FIXED_SCALE)
_MARGIN = wp.constant(SPAN_MARGIN)
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
    """Add int(amplitude · weight · 2^24 + 0.5) at (v, layer P / 4, bin − first, beam), P =
    acc.shape[1] (4 layers, or 2 components' sums), if inside view v's band of rows (acc.shape[2]
    rows from image row ``first``) and the image's beams."""
    row = bin_index - first
    if row >= 0 and row < acc.shape[2] and beam >= 0 and beam < beams:
        wp.atomic_add(acc, v, layer * acc.shape[1] // 4, row, beam, int(amplitude * weight * _FIXED + 0.5))


@wp.func
def needed_at(needed: wp.array3d(dtype=wp.uint8), masked: int, v: int, c: int, beam: int):
    """Whether view v's component c is read at ``beam`` (render_kernel's masked and needed: view
    v's beams at row v % M of the (M, 2, beams) needed)."""
    if masked == 0:
        return True
    if beam < 0 or beam >= needed.shape[2]:
        return False
    return needed[v % needed.shape[0], c, beam] != wp.uint8(0)


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
    """(b, i, j) of item (row, o, k) over the spans (N, 4): beam b = first + o, sub-ray i and
    elevation sample j of the k-th sub-ray of that beam (i K_span + j); b = -1 where the item has
    none (direct_hits_kernel's threads, render_kernel's chunked sub-rays)."""
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


@wp.func
def image_span(lower: wp.vec3, upper: wp.vec3, rot: wp.mat33, org: wp.vec3, n: wp.vec3, d: float, mirror: int,
               beam_upper: wp.array(dtype=float), beam_lower: wp.array(dtype=float), half_elevation: float,
               k_phi: int):
    """(first beam, end beam, first sample, end sample) of the sub-rays that can reach the box
    [lower, upper] (reference frame), or with mirror 1 its mirror image in the surface (n, d),
    from the view at (rot, org): ``fsswarp.backends.base.ray_spans`` of one view and image, in
    float32 (inside its margin); an empty span where none reaches."""
    ahead = int(1)
    s_lo = float(_FAR)
    s_hi = float(-_FAR)
    near = float(_FAR)
    far = float(0.0)
    low = float(_FAR)
    high = float(-_FAR)
    for k in range(8):
        c = lower
        if k % 2 == 1:
            c = wp.vec3(upper[0], c[1], c[2])
        if (k // 2) % 2 == 1:
            c = wp.vec3(c[0], upper[1], c[2])
        if k // 4 == 1:
            c = wp.vec3(c[0], c[1], upper[2])
        p = to_view(c, rot, org)
        if mirror == 1:
            p = p - (2.0 * (wp.dot(p, n) - d)) * n
        if p[1] > 0.0:
            slope = p[0] / p[1]
            s_lo = wp.min(s_lo, slope)
            s_hi = wp.max(s_hi, slope)
            near = wp.min(near, p[1])
            far = wp.max(far, wp.sqrt(p[0] * p[0] + p[1] * p[1]))
        else:
            ahead = 0
        low = wp.min(low, p[2])
        high = wp.max(high, p[2])
    beams = beam_upper.shape[0]
    first = int(0)
    end = int(beams)
    j_first = int(0)
    j_end = int(k_phi)
    if ahead == 1:
        lo = wp.atan(s_lo) - _MARGIN
        hi = wp.atan(s_hi) + _MARGIN
        first = int(0)  # the first beam whose upper edge reaches lo (beam_upper nondecreasing)
        while first < beams and beam_upper[first] < lo:
            first += 1
        end = int(0)  # past the last beam whose lower edge starts below hi (beam_lower nondecreasing)
        while end < beams and beam_lower[end] <= hi:
            end += 1
        down_over = far
        if low < 0.0:
            down_over = near
        up_over = far
        if high > 0.0:
            up_over = near
        down = wp.atan(low / down_over) - _MARGIN
        up = wp.atan(high / up_over) + _MARGIN
        step = 2.0 * half_elevation / float(k_phi)
        j_first = int(wp.clamp(wp.ceil((down + half_elevation) / step - 0.5), 0.0, float(k_phi)))
        j_end = int(wp.clamp(wp.floor((up + half_elevation) / step - 0.5) + 1.0, 0.0, float(k_phi)))
    if first >= end or j_first >= j_end:
        return wp.vec4i(0, 0, 0, 0)
    return wp.vec4i(first, end, j_first, j_end)


@wp.kernel
def view_spans_kernel(lower: wp.vec3, upper: wp.vec3, rotations: wp.array(dtype=wp.mat33),
                      translations: wp.array(dtype=wp.vec3), plane_normals: wp.array(dtype=wp.vec3),
                      plane_offsets: wp.array(dtype=float), beam_upper: wp.array(dtype=float),
                      beam_lower: wp.array(dtype=float), half_elevation: float, k_theta: int, k_phi: int,
                      chunk: int, spans: wp.array2d(dtype=wp.int32), chunks: wp.array(dtype=wp.int32)):
    """Thread v: view v's span of sub-rays, the hull of those that can reach the mesh's box
    [lower, upper] directly or by the surface first (image_span), into spans[v] (first beam,
    end beam, first sample, end sample; zeros: none), and its chunks of ``chunk`` sub-rays,
    ceil((end − first) K_θ (end − first sample) / chunk), into chunks[v]."""
    v = wp.tid()
    rot = rotations[v]
    org = translations[v]
    hull = wp.vec4i(0, 0, 0, 0)
    for mirror in range(2):
        span = image_span(lower, upper, rot, org, plane_normals[v], plane_offsets[v], mirror, beam_upper,
                          beam_lower, half_elevation, k_phi)
        if span[1] > span[0]:
            if hull[1] > hull[0]:
                hull = wp.vec4i(wp.min(hull[0], span[0]), wp.max(hull[1], span[1]), wp.min(hull[2], span[2]),
                                wp.max(hull[3], span[3]))
            else:
                hull = span
    for k in range(4):
        spans[v, k] = hull[k]
    chunks[v] = ((hull[1] - hull[0]) * k_theta * (hull[3] - hull[2]) + chunk - 1) // chunk


@wp.kernel
def chunk_views_kernel(chunks: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32),
                       chunk_views: wp.array(dtype=wp.int32)):
    """Thread v: view v owns chunks offsets[v] .. offsets[v] + chunks[v] − 1 (offsets, the
    chunks' exclusive prefix sum): chunk_views[c] = v for each."""
    v = wp.tid()
    start = offsets[v]
    for q in range(chunks[v]):
        chunk_views[start + q] = v


@wp.func
def render_sub_ray(mesh: wp.uint64, corners: wp.array(dtype=wp.vec3), rotations: wp.array(dtype=wp.mat33),
                   translations: wp.array(dtype=wp.vec3), plane_normals: wp.array(dtype=wp.vec3),
                   plane_offsets: wp.array(dtype=float), directions: wp.array3d(dtype=wp.vec3),
                   sonar: KernelSonar, weight: float, gamma: float, surface_reflection: float,
                   first_rows: wp.array(dtype=wp.int32), poses: wp.array(dtype=wp.int32),
                   hit_range: wp.array4d(dtype=float), hit_face: wp.array4d(dtype=wp.int32), masked: int,
                   needed: wp.array3d(dtype=wp.uint8), acc: wp.array4d(dtype=wp.int32), hits: wp.array(dtype=wp.int32),
                   hit_items: wp.array(dtype=wp.vec4i), hit_ranges: wp.array(dtype=float), v: int, b: int, i: int,
                   j: int):
    """Sub-ray (i, j) of beam b in view v (render_kernel)."""
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
def render_kernel(mesh: wp.uint64, corners: wp.array(dtype=wp.vec3), rotations: wp.array(dtype=wp.mat33),
                  translations: wp.array(dtype=wp.vec3), plane_normals: wp.array(dtype=wp.vec3),
                  plane_offsets: wp.array(dtype=float), directions: wp.array3d(dtype=wp.vec3),
                  sonar: KernelSonar, k_theta: int, weight: float, gamma: float,
                  surface_reflection: float,
                  first_rows: wp.array(dtype=wp.int32), spans: wp.array2d(dtype=wp.int32),
                  chunks: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32),
                  chunk_views: wp.array(dtype=wp.int32), chunk: int, stride: int,
                  poses: wp.array(dtype=wp.int32), hit_range: wp.array4d(dtype=float),
                  hit_face: wp.array4d(dtype=wp.int32), masked: int, needed: wp.array3d(dtype=wp.uint8),
                  acc: wp.array4d(dtype=wp.int32), hits: wp.array(dtype=wp.int32), hit_items: wp.array(dtype=wp.vec4i),
                  hit_ranges: wp.array(dtype=float)):
    """Thread t: sub-rays t, t + stride, ... of the launch's chunks (view_spans_kernel,
    chunk_views_kernel): chunk c of ``chunk`` sub-rays belongs to view v = chunk_views[c], and
    its sub-ray q is sub-ray (c − offsets[v]) chunk + q of the view's span, in the order (beam,
    i, j) (none past the span's count). Each deposits its mirror2 return into acc (N, P, R,
    beams) (P: 4 layers or 2 components' sums, ``deposit``), view v's image row B at row B −
    first_rows[v] when that lies in [0, R), else
    nowhere, and queues its hit before the surface for hits_kernel, which deposits the object,
    ghost and mirror returns (kernels/render.cl). Where poses[v] = p >= 0 the direct leg is
    hit_range and hit_face[p, b, i, j] (direct_hits_kernel), else cast here. With masked 1 a
    return lands only where its component's beam is needed[v % M, c, beam] (M, 2, beams) (c 0:
    object and ghost, 1: mirror and mirror2), and a leg whose returns land nowhere needed is not
    cast. The queue: a hit counts itself in hits (1,) int32, zeroed, and the count before it,
    c, is its slot: where c < L it writes (v, b, i K_φ + j, face) to hit_items[c] and r to
    hit_ranges[c], hit_items (L,) vec4i, hit_ranges (L,) float (the host renders again with a
    larger queue where the count passes L)."""
    t = wp.tid()
    last = chunks.shape[0] - 1
    items = (offsets[last] + chunks[last]) * chunk
    item = t
    while item < items:
        c = item // chunk
        v = chunk_views[c]
        local = (c - offsets[v]) * chunk + item - c * chunk
        per_beam = k_theta * (spans[v, 3] - spans[v, 2])  # > 0: a view owns chunks only where it casts
        o = local // per_beam
        sub = span_item(spans, v, o, local - o * per_beam, k_theta)
        if sub[0] >= 0:
            render_sub_ray(mesh, corners, rotations, translations, plane_normals, plane_offsets, directions, sonar,
                           weight, gamma, surface_reflection, first_rows, poses, hit_range, hit_face, masked, needed,
                           acc, hits, hit_items, hit_ranges, v, sub[0], sub[1], sub[2])
        item += stride


@wp.func
def hit_returns(mesh: wp.uint64, corners: wp.array(dtype=wp.vec3), rotations: wp.array(dtype=wp.mat33),
                translations: wp.array(dtype=wp.vec3), plane_normals: wp.array(dtype=wp.vec3),
                plane_offsets: wp.array(dtype=float), directions: wp.array3d(dtype=wp.vec3),
                beam_table: wp.array2d(dtype=float), sonar: KernelSonar, weight: float, gamma: float,
                surface_reflection: float, first_rows: wp.array(dtype=wp.int32), masked: int,
                needed: wp.array3d(dtype=wp.uint8), item: wp.vec4i, r: float, acc: wp.array4d(dtype=wp.int32)):
    """The returns of one queued hit, ``item`` (v, b, i K_φ + j, face) at range ``r`` (step 3 of
    kernels/render.cl): its object return, then, where both legs of its path via the surface
    are clear, its ghost and mirror returns, each where it is read."""
    v = item[0]
    b = item[1]
    face = item[3]
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
def hits_kernel(mesh: wp.uint64, corners: wp.array(dtype=wp.vec3), rotations: wp.array(dtype=wp.mat33),
                translations: wp.array(dtype=wp.vec3), plane_normals: wp.array(dtype=wp.vec3),
                plane_offsets: wp.array(dtype=float), directions: wp.array3d(dtype=wp.vec3),
                beam_table: wp.array2d(dtype=float), sonar: KernelSonar, weight: float, gamma: float,
                surface_reflection: float, first_rows: wp.array(dtype=wp.int32), masked: int,
                needed: wp.array3d(dtype=wp.uint8), hits: wp.array(dtype=wp.int32),
                hit_items: wp.array(dtype=wp.vec4i), hit_ranges: wp.array(dtype=float), stride: int,
                acc: wp.array4d(dtype=wp.int32)):
    """Thread t: render_kernel's queued hits t, t + stride, ... below min(hits[0], L) in turn
    (``hit_returns``): the queue is sized for the most hits a launch can have, several times
    those it has, and a thread per slot would launch for every empty one."""
    count = wp.min(hits[0], hit_items.shape[0])
    item = wp.tid()
    while item < count:
        hit_returns(mesh, corners, rotations, translations, plane_normals, plane_offsets, directions, beam_table,
                    sonar, weight, gamma, surface_reflection, first_rows, masked, needed, hit_items[item],
                    hit_ranges[item], acc)
        item += stride


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
