"""Exact distances from points to a mesh's surface, in float64 (``Backend.surface_distances``;
kernels/closest.cl finds the same minimum by another search).

``point_triangle_distance`` is the closest point of a triangle by its Voronoi regions (Ericson,
Real-Time Collision Detection, §5.1.5; ``fsswarp.metrics._point_triangle_distance`` is the
NumPy oracle); where it is not finite (a degenerate triangle), the nearest corner's. The search asks the
BVH over the triangles' float32 boxes (``WarpMesh``) for the boxes that meet a cube of half-side
r about the point, starting at ``start`` and doubling r until the nearest triangle found lies
within r (then no triangle outside the cube can be nearer) or the cube holds the whole mesh.
The cube is widened by the float32 rounding of the point and of r.
"""

from __future__ import annotations

import warp as wp

from .sonar import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)


@wp.func
def point_triangle_distance(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d):
    """Distance from p to triangle (a, b, c) (float64): the closest point of the first region
    that holds p, in Ericson's order; where that is not finite (a degenerate triangle), the
    nearest corner's."""
    zero = wp.float64(0.0)
    ab = b - a
    ac = c - a
    ap = p - a
    bp = p - b
    cp = p - c
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    q = a
    if d1 <= zero and d2 <= zero:
        q = a
    elif d3 >= zero and d4 <= d3:
        q = b
    elif vc <= zero and d1 >= zero and d3 <= zero:
        q = a + ab * (d1 / (d1 - d3))
    elif d6 >= zero and d5 <= d6:
        q = c
    elif vb <= zero and d2 >= zero and d6 <= zero:
        q = a + ac * (d2 / (d2 - d6))
    elif va <= zero and d4 - d3 >= zero and d5 - d6 >= zero:
        q = b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))
    else:
        denom = va + vb + vc
        q = a + ab * (vb / denom) + ac * (vc / denom)
    distance = wp.length(p - q)
    if wp.isfinite(distance):
        return distance
    return wp.min(wp.min(wp.length(ap), wp.length(bp)), wp.length(cp))


@wp.kernel
def surface_distances_kernel(bvh: wp.uint64, corners: wp.array(dtype=wp.vec3d), lower: wp.vec3d, upper: wp.vec3d,
                             start: wp.float64, points: wp.array(dtype=wp.vec3d),
                             distance_out: wp.array(dtype=wp.float64)):
    """Thread i: the distance from point i to the nearest triangle; corners (3F,) float64, the
    corners of face f at 3f, 3f + 1, 3f + 2; lower, upper: the mesh's box."""
    i = wp.tid()
    p = points[i]
    zero = wp.float64(0.0)
    outside = wp.vec3d(wp.max(wp.max(lower[0] - p[0], p[0] - upper[0]), zero),
                       wp.max(wp.max(lower[1] - p[1], p[1] - upper[1]), zero),
                       wp.max(wp.max(lower[2] - p[2], p[2] - upper[2]), zero))
    whole = wp.length(outside) + wp.length(upper - lower)  # a cube of this half-side holds the mesh
    size = wp.max(wp.max(wp.abs(p[0]), wp.abs(p[1])), wp.abs(p[2]))
    centre = wp.vec3(float(p[0]), float(p[1]), float(p[2]))
    best = wp.float64(wp.inf)
    radius = wp.float64(start)
    searching = bool(True)
    while searching:
        half = float(radius * wp.float64(1.000001) + size * wp.float64(1.0e-6))
        query = wp.bvh_query_aabb(bvh, centre - wp.vec3(half, half, half), centre + wp.vec3(half, half, half))
        face = int(0)
        while wp.bvh_query_next(query, face):
            best = wp.min(best, point_triangle_distance(p, corners[3 * face], corners[3 * face + 1],
                                                        corners[3 * face + 2]))
        if best <= radius or radius >= whole:
            searching = False
        radius = radius * wp.float64(2.0)
    distance_out[i] = best
