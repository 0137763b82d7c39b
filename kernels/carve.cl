/* carve.cl -- voxel space carving against every view's feasible mask (DESIGN §6).
 *
 * Purpose: for voxel p (a cube of side h, centre c_p, circumradius r = h·√3/2) and every view
 * v, whether v sees the voxel and whether v rejects it (the rule: fsswarp/carving.py's module
 * docstring; the float64 oracle: fsswarp.carving.carve_reference). With c_p seen at
 * (θ, φ, R) (sonar.h) and ρ = hypot(X, Y):
 *   seen      the voxel's bounding sphere lies wholly in the window: r < ρ,
 *             |φ| + asin(r/R) <= W_φ, and the box
 *             beams [beam(θ − asin(r/ρ)), beam(θ + asin(r/ρ))] × bins [bin(R − r), bin(R + r)]
 *             (nearest indices, the rule of project.cl) lies inside the image;
 *   rejected  seen, and that box holds no feasible pixel.
 * The box bounds the projection of the whole sphere, so a voxel that holds any point whose
 * pixel is feasible is never rejected (conservative), and a child voxel is seen and rejected
 * by every view that sees and rejects its parent (coarse-to-fine is exact).
 *
 * Arguments:
 *   carve_grid:   origin (3) float, the centre of voxel (0, 0, 0); voxel_size h (m);
 *                 nx, ny, nz: centre of voxel p = (i·ny + j)·nz + k is
 *                 origin + h·(i, j, k), each coordinate origin_a + h·(float)index_a
 *   carve_points: centres (P, 3) float
 *   n_voxels      P
 *   rotations     (V, 3, 3) float  R_v row-major: P_ref = R_v P_view + t_v
 *   translations  (V, 3) float   t_v (m)
 *   integral      (V, bins + 1, beams + 1) int  summed-area table of the feasible masks:
 *                 element [v][B][b] = number of feasible pixels in rows < B, columns < b
 *   n_views       V
 *   beam_table, sonar: the sonar, as in project.cl
 *   radius        r = h·√3/2 (m), rounded once on the host
 *   seen_out      (P,) uchar  number of views that see the voxel, counted in view order up to
 *                 and including the first view that rejects it (every view when none does)
 *   rejected_out  (P,) uchar  1 when a view rejects it, else 0 (the loop stops there)
 *
 * Work size: 1-D, global P rounded up to a multiple of the work-group size; items with
 * p >= P return at once. The host validates everything (V <= 255); no checks here.
 */
#include "sonar.h"

/* 0: view does not see the voxel (wholly); 1: sees and keeps it; 2: sees and rejects it. */
int fss_carve_test(float3 c, __global const float *rot, __global const float *trans,
                   __global const int *integral, __global const float *beam_table,
                   fss_sonar sonar, float radius)
{
    const float3 q = fss_to_view(c, rot, trans);
    const float rho = sqrt(q.x * q.x + q.y * q.y);
    if (!(radius < rho))
        return 0;
    const float theta = fss_azimuth(q);
    const float phi = fss_elevation(q);
    const float r = fss_range(q);
    const float d_phi = asin(radius / r);
    if (!(fabs(phi) + d_phi <= sonar.half_elevation))
        return 0;
    const float d_theta = asin(radius / rho);
    const int b_lo = fss_nearest_index(fss_beam_coordinate(theta - d_theta, sonar, beam_table));
    const int b_hi = fss_nearest_index(fss_beam_coordinate(theta + d_theta, sonar, beam_table));
    const int B_lo = fss_nearest_index(fss_bin_coordinate(r - radius, sonar));
    const int B_hi = fss_nearest_index(fss_bin_coordinate(r + radius, sonar));
    if (b_lo < 0 || b_hi >= sonar.beams || B_lo < 0 || B_hi >= sonar.bins)
        return 0;
    const int row = sonar.beams + 1;
    const int count = integral[(B_hi + 1) * row + b_hi + 1] - integral[B_lo * row + b_hi + 1]
                      - integral[(B_hi + 1) * row + b_lo] + integral[B_lo * row + b_lo];
    return count == 0 ? 2 : 1;
}

void fss_carve_voxel(float3 c, int p, __global const float *rotations,
                     __global const float *translations, __global const int *integral,
                     int n_views, __global const float *beam_table, fss_sonar sonar, float radius,
                     __global uchar *seen_out, __global uchar *rejected_out)
{
    const size_t plane = (size_t)(sonar.bins + 1) * (size_t)(sonar.beams + 1);
    int seen = 0;
    int rejected = 0;
    for (int v = 0; v < n_views; ++v) {
        const int test = fss_carve_test(c, rotations + 9 * v, translations + 3 * v,
                                        integral + plane * (size_t)v, beam_table, sonar, radius);
        seen += test > 0;
        if (test == 2) {
            rejected = 1;
            break;
        }
    }
    seen_out[p] = (uchar)seen;
    rejected_out[p] = (uchar)rejected;
}

__kernel void carve_grid(__global const float *origin,
                         const float voxel_size,
                         const int nx,
                         const int ny,
                         const int nz,
                         const int n_voxels,
                         __global const float *rotations,
                         __global const float *translations,
                         __global const int *integral,
                         const int n_views,
                         __global const float *beam_table,
                         const fss_sonar sonar,
                         const float radius,
                         __global uchar *seen_out,
                         __global uchar *rejected_out)
{
    const int p = (int)get_global_id(0);
    if (p >= n_voxels)
        return;
    const int k = p % nz;
    const int j = (p / nz) % ny;
    const int i = p / (nz * ny);
    const float3 c = (float3)(origin[0] + voxel_size * (float)i, origin[1] + voxel_size * (float)j,
                              origin[2] + voxel_size * (float)k);
    fss_carve_voxel(c, p, rotations, translations, integral, n_views, beam_table, sonar, radius,
                    seen_out, rejected_out);
}

__kernel void carve_points(__global const float *centres,
                           const int n_voxels,
                           __global const float *rotations,
                           __global const float *translations,
                           __global const int *integral,
                           const int n_views,
                           __global const float *beam_table,
                           const fss_sonar sonar,
                           const float radius,
                           __global uchar *seen_out,
                           __global uchar *rejected_out)
{
    const int p = (int)get_global_id(0);
    if (p >= n_voxels)
        return;
    fss_carve_voxel(vload3(p, centres), p, rotations, translations, integral, n_views, beam_table,
                    sonar, radius, seen_out, rejected_out);
}
