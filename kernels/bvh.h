/* bvh.h -- BVH traversal and watertight ray-triangle intersection (DESIGN §5).
 *
 * The BVH is built on the host (fsswarp/backends/bvh.py): a binary tree whose every node holds
 * the boxes of its two children.
 *   nodes     (Nn, 2, 2) float4  [node][child][lo | hi], xyz used
 *   children  (Nn, 2) int        c >= 0: inner node; c < 0: leaf, ~c = (first << 3) | count
 *   tris      (Nf, 9) float      v0, v1, v2 of the triangles in leaf order
 * Ray-triangle test: Woop, Benthin & Wald 2013, "Watertight Ray/Triangle Intersection"
 * (dominant-axis permutation, shear, edge functions). A shared edge's edge function is the
 * same float expression, negated, in both triangles, so a ray through it never leaks
 * (edge values of exactly zero count as inside). Float32, no contraction into fma.
 */
#ifndef FSSWARP_BVH_H
#define FSSWARP_BVH_H

#pragma OPENCL FP_CONTRACT OFF

#define FSS_BVH_STACK 64

/* Per-ray constants of the watertight test and the slab test. */
typedef struct {
    float3 org;
    float3 inv_dir;
    int kx, ky, kz;
    float sx, sy, sz;
} fss_ray;

inline float fss_comp(float3 v, int k)
{
    return k == 0 ? v.x : (k == 1 ? v.y : v.z);
}

fss_ray fss_make_ray(float3 org, float3 dir)
{
    fss_ray r;
    r.org = org;
    /* 1/0 = inf would give 0 * inf = NaN in the slab test for a ray lying in a box face:
     * FLT_MAX instead keeps such rays inside the slab (0 * FLT_MAX = 0). */
    const float3 inv = (float3)(1.0f) / dir;
    r.inv_dir = select(inv, copysign((float3)(FLT_MAX), inv), isinf(inv));
    const float3 a = fabs(dir);
    int kz = (a.x > a.y) ? (a.x > a.z ? 0 : 2) : (a.y > a.z ? 1 : 2);
    int kx = kz + 1 == 3 ? 0 : kz + 1;
    int ky = kx + 1 == 3 ? 0 : kx + 1;
    const float dz = fss_comp(dir, kz);
    if (dz < 0.0f) {            /* keep the winding: swap kx and ky */
        const int tmp = kx;
        kx = ky;
        ky = tmp;
    }
    r.kx = kx;
    r.ky = ky;
    r.kz = kz;
    r.sx = fss_comp(dir, kx) / dz;
    r.sy = fss_comp(dir, ky) / dz;
    r.sz = 1.0f / dz;
    return r;
}

/* Watertight test of triangle (a, b, c); returns t in (t_min, t_best) or INFINITY. */
float fss_ray_triangle(const fss_ray *ray, float3 a, float3 b, float3 c, float t_min, float t_best)
{
    const float3 A = a - ray->org;
    const float3 B = b - ray->org;
    const float3 C = c - ray->org;
    const float Az = fss_comp(A, ray->kz), Bz = fss_comp(B, ray->kz), Cz = fss_comp(C, ray->kz);
    const float Ax = fss_comp(A, ray->kx) - ray->sx * Az;
    const float Ay = fss_comp(A, ray->ky) - ray->sy * Az;
    const float Bx = fss_comp(B, ray->kx) - ray->sx * Bz;
    const float By = fss_comp(B, ray->ky) - ray->sy * Bz;
    const float Cx = fss_comp(C, ray->kx) - ray->sx * Cz;
    const float Cy = fss_comp(C, ray->ky) - ray->sy * Cz;
    const float U = Cx * By - Cy * Bx;
    const float V = Ax * Cy - Ay * Cx;
    const float W = Bx * Ay - By * Ax;
    if ((U < 0.0f || V < 0.0f || W < 0.0f) && (U > 0.0f || V > 0.0f || W > 0.0f))
        return INFINITY;
    float det = U + V + W;
    if (det == 0.0f)
        return INFINITY;
    float T = U * (ray->sz * Az) + V * (ray->sz * Bz) + W * (ray->sz * Cz);
    if (det < 0.0f) {
        det = -det;
        T = -T;
    }
    if (!(T > t_min * det) || !(T < t_best * det))
        return INFINITY;
    const float t = T / det;
    return (t > t_min && t < t_best) ? t : INFINITY;
}

/* Entry distance of the ray into box [lo, hi] within (t_min, t_best), else INFINITY.
 * The exit distance is widened by 2 gamma(3) (Ize 2013) so rounding never loses a box. */
/* Test the triangles of leaf reference c (~c = first << 3 | count), keeping the nearest hit
   below *best in (*best, *best_tri). */
inline void fss_intersect_leaf(const fss_ray *ray, __global const float *tris, const int c,
                               const float t_min, float *best, int *best_tri)
{
    const int e = ~c;
    const int first = e >> 3, end = first + (e & 7);
    for (int k = first; k < end; ++k) {
        const float t = fss_ray_triangle(ray, vload3(3 * k, tris), vload3(3 * k + 1, tris),
                                         vload3(3 * k + 2, tris), t_min, *best);
        if (t < *best) {
            *best = t;
            *best_tri = k;
        }
    }
}

inline float fss_ray_box(const fss_ray *ray, float4 lo, float4 hi, float t_min, float t_best)
{
    const float3 t0 = (lo.xyz - ray->org) * ray->inv_dir;
    const float3 t1 = (hi.xyz - ray->org) * ray->inv_dir;
    const float3 tn = fmin(t0, t1);
    const float3 tf = fmax(t0, t1);
    const float t_near = fmax(fmax(tn.x, tn.y), fmax(tn.z, t_min));
    const float t_far = fmin(fmin(tf.x, tf.y), fmin(tf.z, t_best)) * 1.00000036f;
    return t_near <= t_far ? t_near : INFINITY;
}

/* Nearest hit in (t_min, t_max) (any_hit 0), or the first one found (any_hit 1: whether the
 * segment is blocked; until its first hit the traversal is the nearest's, so it finds one
 * exactly where the nearest does): returns its distance (INFINITY: none) and writes the
 * reordered triangle index to *tri_out (-1: none). */
float fss_bvh_trace(__global const float4 *nodes, __global const int *children,
                    __global const float *tris, float3 org, float3 dir, float t_min,
                    float t_max, const int any_hit, int *tri_out)
{
    const fss_ray ray = fss_make_ray(org, dir);
    int stack[FSS_BVH_STACK];
    float stack_t[FSS_BVH_STACK];
    int sp = 0;
    int node = 0;
    float best = t_max;
    int best_tri = -1;
    for (;;) {
        __global const float4 *nb = nodes + 4 * node;
        const int2 ch = vload2(node, children);
        float t0 = fss_ray_box(&ray, nb[0], nb[1], t_min, best);
        float t1 = fss_ray_box(&ray, nb[2], nb[3], t_min, best);
        int c0 = ch.x, c1 = ch.y;
        /* leaves: intersect now, nearer one first */
        if (t1 < t0) {
            const int tc = c0; c0 = c1; c1 = tc;
            const float tt = t0; t0 = t1; t1 = tt;
        }
        if (c0 < 0 && t0 < INFINITY) {
            fss_intersect_leaf(&ray, tris, c0, t_min, &best, &best_tri);
            if (any_hit && best_tri >= 0)
                break;
            t0 = INFINITY;
        }
        if (c1 < 0 && t1 < best) {
            fss_intersect_leaf(&ray, tris, c1, t_min, &best, &best_tri);
            if (any_hit && best_tri >= 0)
                break;
            t1 = INFINITY;
        }
        const int go0 = t0 < best;
        const int go1 = t1 < best;
        if (go0 && go1) {
            if (sp < FSS_BVH_STACK) {
                stack[sp] = c1;
                stack_t[sp] = t1;
                ++sp;
            }
            node = c0;
            continue;
        }
        if (go0) {
            node = c0;
            continue;
        }
        if (go1) {
            node = c1;
            continue;
        }
        /* pop the next subtree the ray may still reach */
        node = -1;
        while (sp > 0) {
            --sp;
            if (stack_t[sp] < best) {
                node = stack[sp];
                break;
            }
        }
        if (node < 0)
            break;
    }
    *tri_out = best_tri;
    return best_tri >= 0 ? best : INFINITY;
}

/* Nearest hit in (t_min, t_max) (fss_bvh_trace). */
inline float fss_bvh_intersect(__global const float4 *nodes, __global const int *children,
                               __global const float *tris, float3 org, float3 dir, float t_min,
                               float t_max, int *tri_out)
{
    return fss_bvh_trace(nodes, children, tris, org, dir, t_min, t_max, 0, tri_out);
}

/* Whether the mesh blocks the ray within (t_min, t_max) (fss_bvh_trace's any_hit). */
inline int fss_bvh_blocked(__global const float4 *nodes, __global const int *children,
                           __global const float *tris, float3 org, float3 dir, float t_min, float t_max)
{
    int tri;
    fss_bvh_trace(nodes, children, tris, org, dir, t_min, t_max, 1, &tri);
    return tri >= 0;
}

#endif /* FSSWARP_BVH_H */
