/* raycast.cl -- first hit of every ray against a host-built BVH (DESIGN §5).
 *
 * Arguments:
 *   nodes, children, tris  the flattened BVH (see bvh.h, fsswarp/backends/bvh.py)
 *   face_index    (Nf,) int    original face index of each reordered triangle
 *   origins, directions  (R, 3) float   rays (directions unit vectors)
 *   n_rays        R
 *   max_distance  hits at t >= max_distance are ignored
 *   distance_out  (R,) float   distance of the first hit, INFINITY when none
 *   face_out      (R,) int     original face index of the first hit, -1 when none
 *
 * Work size: 1-D, global R rounded up to a multiple of the work-group size; one work-item
 * per ray, items with id >= R return at once.
 */
#include "bvh.h"

__kernel void cast_rays(__global const float4 *nodes,
                        __global const int *children,
                        __global const float *tris,
                        __global const int *face_index,
                        __global const float *origins,
                        __global const float *directions,
                        const int n_rays,
                        const float max_distance,
                        __global float *distance_out,
                        __global int *face_out)
{
    const int i = (int)get_global_id(0);
    if (i >= n_rays)
        return;
    int tri;
    const float t = fss_bvh_intersect(nodes, children, tris, vload3(i, origins),
                                      vload3(i, directions), 0.0f, max_distance, &tri);
    distance_out[i] = t;
    face_out[i] = tri >= 0 ? face_index[tri] : -1;
}
