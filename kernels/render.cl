/* render.cl -- noise-free multipath sonar layers of many views in one launch (DESIGN §3-4).
 *
 * The algorithm is the docstring of fsswarp/rendering.py, step by step, in float32; the Warp
 * kernel and the float64 oracle (tests/oracle_render.py) implement the same steps.
 *
 * Arguments:
 *   nodes, children, tris  the flattened BVH of the mesh in the reference frame (bvh.h)
 *   rotations     (N, 3, 3) float  R_v row-major: P_ref = R_v P_view + t_v
 *   translations  (N, 3) float     t_v
 *   plane_normals (N, 3) float     n_v, unit, into the air (view frame)
 *   plane_offsets (N,) float       d_v > 0: the surface n·P = d (view frame)
 *   directions    (beams, k_theta, k_phi, 3) float  the sub-rays' view-frame directions (sub_rays)
 *   beam_table, sonar: the beam coordinate and the image (fss_sonar, sonar.h)
 *   k_theta, k_phi   sub-rays per beam; weight = 1 / (k_theta k_phi) (float32)
 *   gamma, surface_reflection   γ and r_s
 *   epsilon       ε (m) of the leg tests, max_distance: the longest ray
 *   first_rows    (N,) int        first image row of each view's band (0 for full layers)
 *   rows          R, rows per band (bins for full layers); 0 <= first_rows[v],
 *                 first_rows[v] + R <= bins (the host validates)
 *   planes        P: 4, the layers; 2, the components' sums (layer l lands in plane l P / 4)
 *   spans         (N, 4) int       view v casts only beams spans[v][0] <= b < spans[v][1] and
 *                 elevation samples spans[v][2] <= j < spans[v][3] (view_spans on a GPU, the
 *                 host's ray_spans on a CPU: the others reach nothing), in chunks of `chunk`
 *                 sub-rays: view v's chunks[v] chunks are chunks offsets[v] .. offsets[v] +
 *                 chunks[v] − 1 of the launch, chunk_views[c] the view of chunk c
 *                 (chunk_offsets, chunk_views)
 *   poses         (N,) int         -1: view v casts its direct leg; p >= 0: it reads it from
 *                 hit_range and hit_tri of pose p (direct_hits, the same float operations)
 *   hit_range, hit_tri  (P, beams, k_theta, k_phi) float and int of direct_hits (unused
 *                 where every poses[v] is -1)
 *   masked, needed  masked 0: every pixel; M >= 1: needed (M, 2, beams) uchar, the beams read
 *                 of each component (0: object + ghost, layers 0-1; 1: mirror + mirror2, layers
 *                 2-3), view v's at row v % M: a return is deposited only where its component's
 *                 beam is needed (the other pixels stay zero), and a leg whose returns land
 *                 nowhere needed is not cast
 *   acc           (N, P, R, beams) int  fixed-point accumulator (2^24 = 1), zeroed by the host:
 *                 a return of view v at image row B lands in acc[v][layer P / 4][B − first_rows[v]]
 *                 when that lies in [0, R) (and its beam in the image), else it is dropped.
 *                 Integer atomics: a pixel's value does not depend on which pixels are kept.
 *   hits, hit_items, hit_ranges, hit_size  the queue of the hits before the surface (hit_returns
 *                 deposits their returns; hit_size 0: no queue, each hit's returns at once): a
 *                 hit counts itself in hits (1,) int, zeroed by the host, and the count before
 *                 it, c, is its slot: where c < hit_size it writes (v, b, i k_phi + j, triangle)
 *                 to hit_items[c] (int4) and r to hit_ranges[c] (the host renders again with a
 *                 larger queue where the count passes hit_size).
 *
 * Work size: 1-D, any (a GPU: its resident work-items; a CPU: one per chunked sub-ray);
 * work-item t takes the launch's sub-rays t, t + size, ... : sub-ray q of chunk c is sub-ray
 * (c − offsets[v]) chunk + q of view v's span, in the order (beam, i, j) (none past the span's
 * count).
 */
#include "sonar.h"
#include "bvh.h"

/* FSS_FIXED (2^24, the accumulator's fixed-point 1) comes from the host's build options. */
#ifndef FSS_FIXED
#error "build with -DFSS_FIXED=... (fsswarp.backends.constants.opencl_defines)"
#endif

/* Add the return at (range, beam) to view v's band: first image row `first`, R = rows, in plane
 * layer P / 4 of P = planes. */
void fss_deposit(__global int *acc, int v, int layer, int beam, float range, float amplitude,
                 float weight, fss_sonar sonar, int first, int rows, int planes)
{
    const int bin = fss_nearest_index(fss_bin_coordinate(range, sonar)) - first;
    if (beam < 0 || beam >= sonar.beams || bin < 0 || bin >= rows)
        return;
    const int value = (int)(amplitude * weight * FSS_FIXED + 0.5f);
    if (value != 0)
        atomic_add(acc + ((v * planes + layer * planes / 4) * rows + bin) * sonar.beams + beam, value);
}

/* Whether view v's component c is read at `beam` (render_views' masked and needed). */
inline int fss_needed(__global const uchar *needed, int masked, int v, int c, int beam, int beams)
{
    return !masked || (beam >= 0 && beam < beams && needed[((v % masked) * 2 + c) * beams + beam] != 0);
}

/* R q (view-frame direction to reference frame). */
inline float3 fss_rotate(__global const float *rot, float3 q)
{
    return (float3)(rot[0] * q.x + rot[1] * q.y + rot[2] * q.z,
                    rot[3] * q.x + rot[4] * q.y + rot[5] * q.z,
                    rot[6] * q.x + rot[7] * q.y + rot[8] * q.z);
}

/* Unit geometric normal of reordered triangle k (reference frame). */
inline float3 fss_tri_normal(__global const float *tris, int k)
{
    const float3 a = vload3(3 * k, tris);
    const float3 e1 = vload3(3 * k + 1, tris) - a;
    const float3 e2 = vload3(3 * k + 2, tris) - a;
    const float3 nrm = (float3)(e1.y * e2.z - e1.z * e2.y, e1.z * e2.x - e1.x * e2.z,
                                e1.x * e2.y - e1.y * e2.x);
    const float len = sqrt(nrm.x * nrm.x + nrm.y * nrm.y + nrm.z * nrm.z);
    return len > 0.0f ? nrm / len : nrm;
}

inline float fss_dot(float3 a, float3 b)
{
    return a.x * b.x + a.y * b.y + a.z * b.z;
}

/* The sub-ray of item (s, o) over the spans (N, 4), for its view or pose `row`: 1 with its beam
 * *b = first + o, sub-ray *i and elevation sample *j of the s-th sub-ray of that beam; 0 where
 * the item has none (direct_hits' work-items, render_views' chunked sub-rays). */
int fss_span_item(__global const int *spans, int row, int s, int o, int k_theta, int *b, int *i, int *j)
{
    *b = spans[4 * row] + o;
    const int samples = spans[4 * row + 3] - spans[4 * row + 2];
    if (s >= k_theta * samples || *b >= spans[4 * row + 1])
        return 0;
    *i = s / samples;
    *j = spans[4 * row + 2] + s - *i * samples;
    return 1;
}

/* The span (first beam, end beam, first sample, end sample) of the sub-rays that can reach the
 * box (box[0..2] lower, box[3..5] upper corner, reference frame), or with mirror 1 its mirror
 * image in the surface (n, d), from the view (rot, t): fsswarp.backends.base.ray_spans of one
 * view and image, in float32 (inside its margin FSS_SPAN_MARGIN); zeros where none reaches.
 * beam_upper, beam_lower (beams,) the beams' edges made monotone as ray_spans' searches. */
int4 fss_image_span(__global const float *box, __global const float *rot, __global const float *t, float3 n,
                    float d, int mirror, __global const float *beam_upper, __global const float *beam_lower,
                    int beams, float half_elevation, int k_phi)
{
    int ahead = 1;
    float s_lo = INFINITY, s_hi = -INFINITY, near = INFINITY, far = 0.0f, low = INFINITY, high = -INFINITY;
    for (int k = 0; k < 8; ++k) {
        const float3 c = (float3)(box[(k & 1) ? 3 : 0], box[(k & 2) ? 4 : 1], box[(k & 4) ? 5 : 2]);
        float3 p = fss_to_view(c, rot, t);
        if (mirror)
            p = p - (2.0f * (fss_dot(p, n) - d)) * n;
        if (p.y > 0.0f) {
            const float slope = p.x / p.y;
            s_lo = fmin(s_lo, slope);
            s_hi = fmax(s_hi, slope);
            near = fmin(near, p.y);
            far = fmax(far, sqrt(p.x * p.x + p.y * p.y));
        } else {
            ahead = 0;
        }
        low = fmin(low, p.z);
        high = fmax(high, p.z);
    }
    int first = 0, end = beams, j_first = 0, j_end = k_phi;
    if (ahead) {
        const float lo = atan(s_lo) - FSS_SPAN_MARGIN;
        const float hi = atan(s_hi) + FSS_SPAN_MARGIN;
        while (first < beams && beam_upper[first] < lo)
            ++first;
        end = 0;
        while (end < beams && beam_lower[end] <= hi)
            ++end;
        const float down = atan(low / (low < 0.0f ? near : far)) - FSS_SPAN_MARGIN;
        const float up = atan(high / (high > 0.0f ? near : far)) + FSS_SPAN_MARGIN;
        const float step = 2.0f * half_elevation / (float)k_phi;
        j_first = (int)clamp(ceil((down + half_elevation) / step - 0.5f), 0.0f, (float)k_phi);
        j_end = (int)clamp(floor((up + half_elevation) / step - 0.5f) + 1.0f, 0.0f, (float)k_phi);
    }
    if (first >= end || j_first >= j_end)
        return (int4)(0, 0, 0, 0);
    return (int4)(first, end, j_first, j_end);
}

/* view_spans -- the span of each view's sub-rays that can reach the mesh's box directly or by the
 * surface first (the hull of fss_image_span's two), into spans (N, 4) int, and its chunks of
 * `chunk` sub-rays, ceil((end − first) k_theta (end − first sample) / chunk), into chunks (N,).
 * box (6,) float the mesh's box; poses and planes as render_views. Work size: N, rounded up. */
__kernel void view_spans(__global const float *box,
                         __global const float *rotations,
                         __global const float *translations,
                         __global const float *plane_normals,
                         __global const float *plane_offsets,
                         __global const float *beam_upper,
                         __global const float *beam_lower,
                         const int beams,
                         const float half_elevation,
                         const int k_theta,
                         const int k_phi,
                         const int chunk,
                         const int n_views,
                         __global int *spans,
                         __global int *chunks)
{
    const int v = (int)get_global_id(0);
    if (v >= n_views)
        return;
    int4 hull = (int4)(0, 0, 0, 0);
    for (int mirror = 0; mirror < 2; ++mirror) {
        const int4 span = fss_image_span(box, rotations + 9 * v, translations + 3 * v, vload3(v, plane_normals),
                                         plane_offsets[v], mirror, beam_upper, beam_lower, beams, half_elevation,
                                         k_phi);
        if (span.y > span.x)
            hull = hull.y > hull.x ? (int4)(min(hull.x, span.x), max(hull.y, span.y), min(hull.z, span.z),
                                            max(hull.w, span.w)) : span;
    }
    vstore4(hull, v, spans);
    chunks[v] = ((hull.y - hull.x) * k_theta * (hull.w - hull.z) + chunk - 1) / chunk;
}

/* chunk_offsets -- the exclusive prefix sums of chunks (N,) into offsets (N,), in one work-group
 * (work size: its local size, partial of that many ints): each item sums a block in turn. */
__kernel void chunk_offsets(__global const int *chunks, const int n, __global int *offsets, __local int *partial)
{
    const int k = (int)get_local_id(0);
    const int size = (int)get_local_size(0);
    const int per = (n + size - 1) / size;
    const int lo = min(n, k * per), hi = min(n, k * per + per);
    int sum = 0;
    for (int q = lo; q < hi; ++q)
        sum += chunks[q];
    partial[k] = sum;
    barrier(CLK_LOCAL_MEM_FENCE);
    if (k == 0) {
        int run = 0;
        for (int q = 0; q < size; ++q) {
            const int here = partial[q];
            partial[q] = run;
            run += here;
        }
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    int run = partial[k];
    for (int q = lo; q < hi; ++q) {
        offsets[q] = run;
        run += chunks[q];
    }
}

/* chunk_views -- view v owns chunks offsets[v] .. offsets[v] + chunks[v] − 1: chunk_views[c] = v
 * for each. Work size: N, rounded up. */
__kernel void chunk_views(__global const int *chunks, __global const int *offsets, const int n_views,
                          __global int *chunk_views)
{
    const int v = (int)get_global_id(0);
    if (v >= n_views)
        return;
    for (int q = 0; q < chunks[v]; ++q)
        chunk_views[offsets[v] + q] = v;
}

/* sub_rays -- step 1 once per render: the view-frame direction of every sub-ray (i, j) of every
 * beam b, into directions (beams, k_theta, k_phi, 3) float (render_views and direct_hits read
 * them). beam_centres, beam_widths (beams,) float: θ_b and Δθ_b (rad). Work size: 1-D,
 * beams * k_theta * k_phi rounded up; item ((b * k_theta) + i) * k_phi + j. */
__kernel void sub_rays(__global const float *beam_centres,
                       __global const float *beam_widths,
                       const fss_sonar sonar,
                       const int k_theta,
                       const int k_phi,
                       __global float *directions)
{
    const int k = (int)get_global_id(0);
    if (k >= sonar.beams * k_theta * k_phi)
        return;
    const int j = k % k_phi;
    const int i = (k / k_phi) % k_theta;
    const int b = k / (k_phi * k_theta);
    const float theta = beam_centres[b] + (((float)i + 0.5f) / (float)k_theta - 0.5f) * beam_widths[b];
    const float phi = -sonar.half_elevation + ((float)j + 0.5f) / (float)k_phi * (2.0f * sonar.half_elevation);
    const float cp = cos(phi);
    vstore3((float3)(cp * sin(theta), cp * cos(theta), sin(phi)), k, directions);
}

/* direct_hits -- the direct leg of every sub-ray of P distinct poses, for the views of a render
 * that share a pose (render_views' poses): a (D, β) grid changes only the surface in views whose
 * pose does not depend on β, and the depth never moves a pose.
 *
 * Arguments: nodes, children, tris, directions, sonar, k_theta, k_phi, max_distance as
 * render_views; rotations (P, 3, 3), translations (P, 3) the poses; spans (P, 4)
 * the sub-rays to cast (the hull of the spans of the views with that pose); hit_range and
 * hit_tri (P, beams, k_theta, k_phi): the first hit's distance (INFINITY: none) and reordered
 * triangle (-1: none). Work size as render_views, over the P poses. */
__kernel void direct_hits(__global const float4 *nodes,
                          __global const int *children,
                          __global const float *tris,
                          __global const float *rotations,
                          __global const float *translations,
                          __global const float *directions,
                          const fss_sonar sonar,
                          const int k_theta,
                          const int k_phi,
                          const float max_distance,
                          __global const int *spans,
                          __global float *hit_range,
                          __global int *hit_tri)
{
    const int p = (int)get_global_id(2);
    int b, i, j;
    if (!fss_span_item(spans, p, (int)get_global_id(0), (int)get_global_id(1), k_theta, &b, &i, &j))
        return;
    const float3 u = vload3((b * k_theta + i) * k_phi + j, directions);
    int tri;
    const float r = fss_bvh_intersect(nodes, children, tris, vload3(p, translations),
                                      fss_rotate(rotations + 9 * p, u), 0.0f, max_distance, &tri);
    const int k = ((p * sonar.beams + b) * k_theta + i) * k_phi + j;
    hit_range[k] = r;
    hit_tri[k] = tri;
}

/* The returns of view v's hit before the surface at r on triangle tri, sub-ray item.z = i k_phi
 * + j of beam b (step 3): the object's, then, where both legs of its path via the surface are
 * clear, its ghost (layer 1, beam b) and mirror (layer 2), each where it is read. Arguments as
 * render_views; render_views calls it, or hit_returns for the queued hits. */
void fss_hit_returns(__global const float4 *nodes, __global const int *children, __global const float *tris,
                     __global const float *rotations, __global const float *translations,
                     __global const float *plane_normals, __global const float *plane_offsets,
                     __global const float *directions, __global const float *beam_table, const fss_sonar sonar,
                     const int k_theta, const int k_phi, const float weight, const float gamma,
                     const float surface_reflection, const float epsilon, __global const int *first_rows,
                     const int rows, const int planes, const int masked, __global const uchar *needed,
                     const int4 item, const float r,
                     __global int *acc)
{
    const int v = item.x;
    const int b = item.y;
    const int first = first_rows[v];
    __global const float *rot = rotations + 9 * v;
    const float3 t = vload3(v, translations);
    const float3 u = vload3(b * k_theta * k_phi + item.z, directions);
    const float3 n = vload3(v, plane_normals);
    const float d = plane_offsets[v];
    float3 N = fss_tri_normal(tris, item.w);
    float un = fss_dot(fss_rotate(rot, u), N);
    if (un > 0.0f) {
        N = -N;
        un = -un;
    }
    const float c = -un;
    const int want_object = fss_needed(needed, masked, v, 0, b, sonar.beams);
    if (want_object)
        fss_deposit(acc, v, 0, b, r, pow(c, gamma), weight, sonar, first, rows, planes);
    /* the path via the surface: Q on the surface, between the mirror sonar O2 and P */
    const float3 P = r * u;
    const float3 O2 = (2.0f * d) * n;
    const float3 PO = P - O2;
    const float q_len = sqrt(fss_dot(PO, PO));
    const float nP = fss_dot(n, P);
    const float lambda = d / (2.0f * d - nP);
    const float3 Q = O2 + lambda * PO;
    if (!(Q.y > 0.0f))
        return;
    const float bq = fss_beam_coordinate(fss_azimuth(Q), sonar, beam_table);
    if (!(bq >= -0.5f && bq < (float)sonar.beams - 0.5f))
        return;
    if (!(fabs(fss_elevation(Q)) <= sonar.half_elevation))
        return;
    const float3 Pm = P - (2.0f * (nP - d)) * n;
    const int bm = fss_nearest_index(fss_beam_coordinate(fss_azimuth(Pm), sonar, beam_table));
    const int want_mirror = fss_needed(needed, masked, v, 1, bm, sonar.beams);
    if (!want_object && !want_mirror)
        return;
    /* the leg Q -> P lights the face (tested first: it needs no traversal) */
    const float3 QP = P - Q;
    const float qp = sqrt(fss_dot(QP, QP));
    const float3 w_ref = fss_rotate(rot, QP / qp);
    const float c_in = -fss_dot(w_ref, N);
    if (!(c_in > 0.0f))
        return;
    /* legs O -> Q and Q -> P clear */
    const float qlen = fss_range(Q);
    if (fss_bvh_blocked(nodes, children, tris, t, fss_rotate(rot, Q / qlen), 0.0f, qlen - epsilon))
        return;
    if (fss_bvh_blocked(nodes, children, tris, fss_rotate(rot, Q) + t, w_ref, 0.0f, qp - epsilon))
        return;
    const float a_s = surface_reflection * pow(c * c_in, 0.5f * gamma);
    const float R_s = (r + q_len) * 0.5f;
    if (want_object)
        fss_deposit(acc, v, 1, b, R_s, a_s, weight, sonar, first, rows, planes);
    if (want_mirror)
        fss_deposit(acc, v, 2, bm, R_s, a_s, weight, sonar, first, rows, planes);
}

__kernel void render_views(__global const float4 *nodes,
                           __global const int *children,
                           __global const float *tris,
                           __global const float *rotations,
                           __global const float *translations,
                           __global const float *plane_normals,
                           __global const float *plane_offsets,
                           __global const float *directions,
                           __global const float *beam_table,
                           const fss_sonar sonar,
                           const int k_theta,
                           const int k_phi,
                           const float weight,
                           const float gamma,
                           const float surface_reflection,
                           const float epsilon,
                           const float max_distance,
                           __global const int *first_rows,
                           const int rows,
                           const int planes,
                           __global const int *spans,
                           __global const int *chunks,
                           __global const int *offsets,
                           __global const int *chunk_views,
                           const int chunk,
                           const int n_views,
                           __global const int *poses,
                           __global const float *hit_range,
                           __global const int *hit_tri,
                           const int masked,
                           __global const uchar *needed,
                           __global int *acc,
                           __global int *hits,
                           __global int4 *hit_items,
                           __global float *hit_ranges,
                           const int hit_size)
{
    const int stride = (int)get_global_size(0);
    const int items = (offsets[n_views - 1] + chunks[n_views - 1]) * chunk;
    for (int item = (int)get_global_id(0); item < items; item += stride) {
        const int c = item / chunk;
        const int v = chunk_views[c];
        const int local_item = (c - offsets[v]) * chunk + item - c * chunk;
        const int per_beam = k_theta * (spans[4 * v + 3] - spans[4 * v + 2]); /* > 0: v owns chunks */
        const int o = local_item / per_beam;
        int b, i, j;
        if (!fss_span_item(spans, v, local_item - o * per_beam, o, k_theta, &b, &i, &j))
            continue;
        __global const float *rot = rotations + 9 * v;
        const float3 t = vload3(v, translations);
        const float3 n = vload3(v, plane_normals);
        const float d = plane_offsets[v];
        const int first = first_rows[v];

        /* 1. sub-ray */
        const float3 u = vload3((b * k_theta + i) * k_phi + j, directions);
        const float3 u_ref = fss_rotate(rot, u);

        /* 2. direct leg */
        int tri;
        float r;
        const int pose = poses[v];
        if (pose >= 0) {
            const int k = ((pose * sonar.beams + b) * k_theta + i) * k_phi + j;
            r = hit_range[k];
            tri = hit_tri[k];
        } else {
            r = fss_bvh_intersect(nodes, children, tris, t, u_ref, 0.0f, max_distance, &tri);
        }
        const float nu = fss_dot(n, u);
        const float s_surf = nu > 0.0f ? d / nu : INFINITY;

        if (tri >= 0 && r < s_surf) {
            /* 3. hit: its returns now (hit_size 0), or queued for hit_returns */
            const int4 queued = (int4)(v, b, i * k_phi + j, tri);
            if (hit_size == 0) {
                fss_hit_returns(nodes, children, tris, rotations, translations, plane_normals, plane_offsets,
                                directions, beam_table, sonar, k_theta, k_phi, weight, gamma, surface_reflection,
                                epsilon, first_rows, rows, planes, masked, needed, queued, r, acc);
            } else {
                const int slot = atomic_inc(hits);
                if (slot < hit_size) {
                    hit_items[slot] = queued;
                    hit_ranges[slot] = r;
                }
            }
        } else if (s_surf < r && s_surf < INFINITY) {
            /* 4. surface first: mirror2 */
            if (!fss_needed(needed, masked, v, 1, b, sonar.beams))
                continue;
            const float3 Q = s_surf * u;
            const float3 u2 = u - (2.0f * nu) * n;
            const float3 u2_ref = fss_rotate(rot, u2);
            const float3 Q_ref = fss_rotate(rot, Q) + t;
            int tri2;
            const float r2 = fss_bvh_intersect(nodes, children, tris, Q_ref, u2_ref, epsilon,
                                               max_distance, &tri2);
            if (tri2 < 0)
                continue;
            const float c2 = fabs(fss_dot(u2_ref, fss_tri_normal(tris, tri2)));
            fss_deposit(acc, v, 3, b, s_surf + r2, surface_reflection * surface_reflection * pow(c2, gamma),
                        weight, sonar, first, rows, planes);
        }
    }
}

/* hit_returns -- the returns of render_views' queued hits (fss_hit_returns). Arguments as
 * render_views, and its queue: work-item q takes queued hits q, q + G, ... below min(hits[0],
 * hit_size), G the work size (hit_size rounded up, at most the work-items the device keeps
 * running: the queue is sized for the most hits a launch can have, several times those it has,
 * and a work-item per slot would run for every empty one). */
__kernel void hit_returns(__global const float4 *nodes,
                          __global const int *children,
                          __global const float *tris,
                          __global const float *rotations,
                          __global const float *translations,
                          __global const float *plane_normals,
                          __global const float *plane_offsets,
                          __global const float *directions,
                          __global const float *beam_table,
                          const fss_sonar sonar,
                          const int k_theta,
                          const int k_phi,
                          const float weight,
                          const float gamma,
                          const float surface_reflection,
                          const float epsilon,
                          __global const int *first_rows,
                          const int rows,
                          const int planes,
                          const int masked,
                          __global const uchar *needed,
                          __global const int *hits,
                          __global const int4 *hit_items,
                          __global const float *hit_ranges,
                          const int hit_size,
                          __global int *acc)
{
    const int count = min(hits[0], hit_size);
    for (int q = (int)get_global_id(0); q < count; q += (int)get_global_size(0))
        fss_hit_returns(nodes, children, tris, rotations, translations, plane_normals, plane_offsets, directions,
                        beam_table, sonar, k_theta, k_phi, weight, gamma, surface_reflection, epsilon, first_rows,
                        rows, planes, masked, needed, hit_items[q], hit_ranges[q], acc);
}

/* frontal_rays -- the elevation rays of the beams whose frontal patch Backend.frontal_faces
 * finds (fsswarp/backends): per ray its range and face; the host keeps each beam's nearest.
 *
 * Arguments: nodes, children, tris, face_index: the BVH (bvh.h); rotations, translations,
 * plane_normals, plane_offsets as render_views for V views; views (B,) int and azimuths (B,)
 * float: the beams; n_items = B * rays; mirrors (B,) uchar, per beam 0: the first hit before
 * the surface, 1: the first hit of the ray reflected at the surface (cast from epsilon past it)
 * when it lies in the fan and the sonar sees it (the first hit toward it is not nearer than
 * |P| - visible), at the mirror range (|P| + s + |P - Q|) / 2; sonar: the fan (its
 * half_azimuth and half_elevation, fss_sonar); range_out (B, rays) float (INFINITY: none) and
 * face_out (B, rays) int (the original face, -1: none).
 * Work size: 1-D, n_items rounded up; item k is ray k % rays of beam k / rays. */
__kernel void frontal_rays(__global const float4 *nodes,
                           __global const int *children,
                           __global const float *tris,
                           __global const int *face_index,
                           __global const float *rotations,
                           __global const float *translations,
                           __global const float *plane_normals,
                           __global const float *plane_offsets,
                           __global const int *views,
                           __global const float *azimuths,
                           const int n_items,
                           const int rays,
                           __global const uchar *mirrors,
                           const fss_sonar sonar,
                           const float epsilon,
                           const float visible,
                           const float max_distance,
                           __global float *range_out,
                           __global int *face_out)
{
    const int k = (int)get_global_id(0);
    if (k >= n_items)
        return;
    const int i = k / rays;
    const int j = k - i * rays;
    const int v = views[i];
    __global const float *rot = rotations + 9 * v;
    const float3 t = vload3(v, translations);
    const float3 n = vload3(v, plane_normals);
    const float d = plane_offsets[v];
    const float theta = azimuths[i];
    const float phi = -sonar.half_elevation + ((float)j + 0.5f) / (float)rays * (2.0f * sonar.half_elevation);
    const float cp = cos(phi);
    const float3 u = (float3)(cp * sin(theta), cp * cos(theta), sin(phi));
    const float up = fss_dot(u, n);
    const float s = up > 0.0f ? d / up : INFINITY;
    int tri;
    const float r = fss_bvh_intersect(nodes, children, tris, t, fss_rotate(rot, u), 0.0f, max_distance, &tri);
    float range = INFINITY;
    int found = -1;
    if (!mirrors[i]) {
        if (r < s) {
            range = r;
            found = tri;
        }
    } else if (s < r) {
        const float3 q = s * u;
        const float3 w = u - (2.0f * up) * n;
        int leg;
        const float r2 = fss_bvh_intersect(nodes, children, tris, fss_rotate(rot, q + epsilon * w) + t,
                                           fss_rotate(rot, w), 0.0f, max_distance, &leg) + epsilon;
        if (leg >= 0) {
            const float3 p = q + r2 * w;
            const float length = fss_range(p);
            int blocker;
            const float back = fss_bvh_intersect(nodes, children, tris, t, fss_rotate(rot, p / length), 0.0f,
                                                 max_distance, &blocker);
            if (fabs(fss_elevation(p)) <= sonar.half_elevation && fabs(fss_azimuth(p)) <= sonar.half_azimuth
                && back >= length - visible) {
                range = 0.5f * (length + s + r2);
                found = leg;
            }
        }
    }
    range_out[k] = range;
    face_out[k] = found >= 0 ? face_index[found] : -1;
}

/* layers[i] = acc[i] / 2^24: the accumulator's fixed point as float (n items). */
__kernel void fixed_to_float(__global const int *acc, __global float *layers, const int n)
{
    const int i = get_global_id(0);
    if (i < n)
        layers[i] = (float)acc[i] * (1.0f / FSS_FIXED);
}
