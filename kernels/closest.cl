/* closest.cl -- exact distance from every point to a mesh's surface, in double
 * (Backend.surface_distances; fsswarp/backends/warp/closest.py finds the same minimum by
 * another search). Needs cl_khr_fp64: the host builds it only on a device that has it.
 *
 * fss_point_triangle: the closest point of a triangle by its Voronoi regions (Ericson,
 * Real-Time Collision Detection, §5.1.5; fsswarp.metrics._point_triangle_distance is the NumPy
 * oracle); where it is not finite (a degenerate triangle), the nearest corner's distance. The search walks the
 * BVH (bvh.h's layout) nearer child first and skips a box farther than the nearest triangle
 * found so far plus slack (the float32 boxes' rounding of the float64 corners).
 *
 * Arguments:
 *   nodes, children  the flattened BVH (bvh.h, fsswarp/backends/bvh.py)
 *   corners    (Nf, 9) double   v0, v1, v2 of the triangles in leaf order
 *   points     (N, 3) double
 *   n_points   N
 *   slack      distance a float32 box may fall short of its triangle's float64 corners
 *   distance_out  (N,) double
 *
 * Work size: 1-D, global N rounded up to a multiple of the work-group size; one work-item
 * per point, items with id >= N return at once.
 */
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#include "bvh.h"

double fss_point_triangle(const double3 p, const double3 a, const double3 b, const double3 c)
{
    const double3 ab = b - a, ac = c - a, ap = p - a, bp = p - b, cp = p - c;
    const double d1 = dot(ab, ap), d2 = dot(ac, ap), d3 = dot(ab, bp), d4 = dot(ac, bp);
    const double d5 = dot(ab, cp), d6 = dot(ac, cp);
    const double va = d3 * d6 - d5 * d4, vb = d5 * d2 - d1 * d6, vc = d1 * d4 - d3 * d2;
    double3 q;
    if (d1 <= 0.0 && d2 <= 0.0)
        q = a;
    else if (d3 >= 0.0 && d4 <= d3)
        q = b;
    else if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0)
        q = a + ab * (d1 / (d1 - d3));
    else if (d6 >= 0.0 && d5 <= d6)
        q = c;
    else if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0)
        q = a + ac * (d2 / (d2 - d6));
    else if (va <= 0.0 && d4 - d3 >= 0.0 && d5 - d6 >= 0.0)
        q = b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    else {
        const double denom = va + vb + vc;
        q = a + ab * (vb / denom) + ac * (vc / denom);
    }
    const double distance = length(p - q);
    if (isfinite(distance))
        return distance;
    return fmin(fmin(length(ap), length(bp)), length(cp)); /* degenerate: the nearest corner */
}

/* Distance from p to box [lo, hi] (float32 corners; infinite for an empty child's inverted box). */
inline double fss_point_box(const double3 p, const float4 lo, const float4 hi)
{
    const double3 l = convert_double3(lo.xyz), h = convert_double3(hi.xyz);
    const double3 d = fmax(fmax(l - p, p - h), (double3)(0.0));
    return length(d);
}

__kernel void surface_distances(__global const float4 *nodes,
                                __global const int *children,
                                __global const double *corners,
                                __global const double *points,
                                const int n_points,
                                const double slack,
                                __global double *distance_out)
{
    const int i = (int)get_global_id(0);
    if (i >= n_points)
        return;
    const double3 p = vload3(i, points);
    int stack[FSS_BVH_STACK];
    double stack_d[FSS_BVH_STACK];
    int sp = 0;
    int node = 0;
    double best = INFINITY;
    for (;;) {
        __global const float4 *nb = nodes + 4 * node;
        const int2 ch = vload2(node, children);
        double d0 = fss_point_box(p, nb[0], nb[1]), d1 = fss_point_box(p, nb[2], nb[3]);
        int c0 = ch.x, c1 = ch.y;
        if (d1 < d0) {
            const int tc = c0; c0 = c1; c1 = tc;
            const double td = d0; d0 = d1; d1 = td;
        }
        int go0 = d0 <= best + slack, go1 = d1 <= best + slack;
        for (int side = 0; side < 2; ++side) { /* leaves now, the nearer first */
            const int c = side ? c1 : c0;
            if (c < 0 && (side ? go1 : go0)) {
                const int e = ~c;
                const int first = e >> 3, end = first + (e & 7);
                for (int k = first; k < end; ++k)
                    best = fmin(best, fss_point_triangle(p, vload3(3 * k, corners), vload3(3 * k + 1, corners),
                                                         vload3(3 * k + 2, corners)));
                if (side)
                    go1 = 0;
                else
                    go0 = 0;
            }
        }
        go0 = go0 && d0 <= best + slack;
        go1 = go1 && d1 <= best + slack;
        if (go0 && go1) {
            if (sp < FSS_BVH_STACK) {
                stack[sp] = c1;
                stack_d[sp] = d1;
                ++sp;
            }
            node = c0;
            continue;
        }
        if (go0 || go1) {
            node = go0 ? c0 : c1;
            continue;
        }
        node = -1; /* pop the next subtree that may still hold a nearer triangle */
        while (sp > 0) {
            --sp;
            if (stack_d[sp] <= best + slack) {
                node = stack[sp];
                break;
            }
        }
        if (node < 0)
            break;
    }
    distance_out[i] = best;
}
