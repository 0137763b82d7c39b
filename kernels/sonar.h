/* sonar.h -- shared sonar geometry for fsswarp's OpenCL kernels (DESIGN §2).
 *
 * Sonar frame: +Y the viewing axis, +X right (azimuth θ grows toward +X), +Z up (elevation φ).
 *   θ = atan2(X, Y),  φ = atan2(Z, hypot(X, Y)),  R = |P|.
 * A view's pose maps view-frame points into the reference frame, P_ref = R P_view + t, so a
 * reference-frame point is seen at P_view = Rᵀ (P_ref − t).
 * Beam-bin image: column b has azimuth −W_θ + b δθ (or a per-beam angle table), row B range
 * R_min + B δR; a return lands in the nearest column and row, floor(coordinate + 0.5).
 *
 * Float32, OpenCL C 1.2. The host inlines this file into every program that includes it
 * (include paths are not portable across ICDs). The Warp kernels in
 * fsswarp/backends/warp/sonar.py mirror these functions operation for operation; keep the
 * two in step (same order of operations, no contraction into fma) so that both backends
 * round alike.
 */
#ifndef FSSWARP_SONAR_H
#define FSSWARP_SONAR_H

#pragma OPENCL FP_CONTRACT OFF

/* FSS_INDEX_LIMIT (±2^30, indices are clamped to it before conversion so that far-away points
 * cannot overflow) comes from the host's build options (fsswarp/backends/constants.py). */
#ifndef FSS_INDEX_LIMIT
#error "build with -DFSS_INDEX_LIMIT=... (fsswarp.backends.constants.opencl_defines)"
#endif

/* The scalars of one sonar, one kernel argument (fsswarp.backends.base.SonarConstants; the
 * host's numpy dtype SONAR_DTYPE and the Warp struct KernelSonar list the same fields in the
 * same order: 3 ints and 5 floats, 32 bytes, no padding).
 *   use_table     0: linear beams, else the angle table
 *   beams, bins   image columns and rows
 *   half_azimuth  W_θ (rad); beam_scale = (beams − 1) / (2 W_θ)   (linear beams only)
 *   range_min     R_min (m); inv_range_step = 1 / δR (1/m)
 *   half_elevation  W_φ (rad) */
typedef struct {
    int use_table;
    int beams;
    int bins;
    float half_azimuth;
    float beam_scale;
    float range_min;
    float inv_range_step;
    float half_elevation;
} fss_sonar;

/* P_view = Rᵀ (p − t). rot: 9 floats, R row-major; trans: 3 floats. */
float3 fss_to_view(float3 p, __global const float *rot, __global const float *trans)
{
    const float d0 = p.x - trans[0];
    const float d1 = p.y - trans[1];
    const float d2 = p.z - trans[2];
    const float x = rot[0] * d0 + rot[3] * d1 + rot[6] * d2;
    const float y = rot[1] * d0 + rot[4] * d1 + rot[7] * d2;
    const float z = rot[2] * d0 + rot[5] * d1 + rot[8] * d2;
    return (float3)(x, y, z);
}

/* Range R = |q| (m) of a sonar-frame point. */
float fss_range(float3 q)
{
    return sqrt(q.x * q.x + q.y * q.y + q.z * q.z);
}

/* Azimuth θ = atan2(X, Y) (rad). */
float fss_azimuth(float3 q)
{
    return atan2(q.x, q.y);
}

/* Elevation φ = atan2(Z, hypot(X, Y)) (rad). */
float fss_elevation(float3 q)
{
    return atan2(q.z, sqrt(q.x * q.x + q.y * q.y));
}

/* Fractional column index of azimuth theta; integers at beam centres.
 * Linear sonar (use_table == 0): (θ + W_θ) · beam_scale, beam_scale = (beams − 1) / (2 W_θ).
 * Angle table (use_table != 0): table is (2, beams) row-major, row 0 the increasing beam
 * centres c_i, row 1 the inverse spacings 1 / (c_{i+1} − c_i) (the last entry repeats the
 * outer one). Linear interpolation between neighbouring centres, extrapolated beyond the
 * outer beams with the outer spacing (numpy.interp inside, SonarSpec.beam_coordinate
 * outside). */
float fss_beam_coordinate(float theta, fss_sonar sonar, __global const float *table)
{
    if (sonar.use_table == 0)
        return (theta + sonar.half_azimuth) * sonar.beam_scale;
    __global const float *centre = table;
    __global const float *inverse = table + sonar.beams;
    const int last = sonar.beams - 1;
    if (theta < centre[0])
        return (theta - centre[0]) * inverse[0];
    if (theta > centre[last])
        return (float)last + (theta - centre[last]) * inverse[last];
    int lo = 0;             /* invariant: centre[lo] <= theta <= centre[hi] */
    int hi = last;
    while (hi - lo > 1) {
        const int mid = (lo + hi) / 2;
        if (centre[mid] <= theta)
            lo = mid;
        else
            hi = mid;
    }
    return (float)lo + (theta - centre[lo]) * inverse[lo];
}

/* Fractional row index of range r (m): (r − R_min) / δR, with inv_range_step = 1 / δR. */
float fss_bin_coordinate(float r, fss_sonar sonar)
{
    return (r - sonar.range_min) * sonar.inv_range_step;
}

/* Nearest integer index of a fractional coordinate: floor(c + 0.5), clamped to ±2^30. */
int fss_nearest_index(float c)
{
    const float f = floor(c + 0.5f);
    return (int)clamp(f, -FSS_INDEX_LIMIT, FSS_INDEX_LIMIT);
}

#endif /* FSSWARP_SONAR_H */
