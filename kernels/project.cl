/* project.cl -- project reference-frame points into every view's beam-bin image.
 *
 * Purpose: the core of voxel space carving (DESIGN §6). For point p and view v, the nearest
 * beam and bin of P_view = R_vᵀ (P_p − t_v), and whether that return lands in the image
 * (0 <= beam < beams, 0 <= bin < bins) with its elevation inside the aperture (|φ| <= W_φ).
 * Same rule as SonarSpec.beam_bin / SonarSpec.in_elevation, in float32.
 *
 * Arguments:
 *   points        (P, 3) float   reference-frame points (m)
 *   rotations     (V, 3, 3) float  R_v row-major: P_ref = R_v P_view + t_v
 *   translations  (V, 3) float   t_v (m)
 *   beam_table    (2, beams) float  beam centres (rad) and inverse spacings (1/rad) when
 *                                use_table != 0 (see sonar.h), else a two-element dummy
 *   sonar         the sonar's scalars (fss_sonar, sonar.h)
 *   n_points      P
 *   beam_out, bin_out  (V, P) int    nearest beam and bin (clamped to ±2^30)
 *   inside_out    (V, P) uchar  1 when inside the image and the elevation aperture, else 0
 *
 * Work size: 2-D, global (P rounded up to a multiple of the work-group size, V); work-item
 * (p, v) = (get_global_id(0), get_global_id(1)); items with p >= P return at once.
 * Outputs are row-major, element v * P + p. The host validates everything; no checks here.
 */
#include "sonar.h"

__kernel void project_points(__global const float *points,
                             __global const float *rotations,
                             __global const float *translations,
                             __global const float *beam_table,
                             const fss_sonar sonar,
                             const int n_points,
                             __global int *beam_out,
                             __global int *bin_out,
                             __global uchar *inside_out)
{
    const int p = (int)get_global_id(0);
    const int v = (int)get_global_id(1);
    if (p >= n_points)
        return;

    const float3 q = fss_to_view(vload3(p, points), rotations + 9 * v, translations + 3 * v);
    const float theta = fss_azimuth(q);
    const float phi = fss_elevation(q);
    const float r = fss_range(q);

    const int b = fss_nearest_index(
        fss_beam_coordinate(theta, sonar, beam_table));
    const int B = fss_nearest_index(fss_bin_coordinate(r, sonar));
    const int inside = b >= 0 && b < sonar.beams && B >= 0 && B < sonar.bins
                       && fabs(phi) <= sonar.half_elevation;

    const size_t o = (size_t)v * (size_t)n_points + (size_t)p;
    beam_out[o] = b;
    bin_out[o] = B;
    inside_out[o] = (uchar)inside;
}
