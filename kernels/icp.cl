/* icp.cl -- IRLS-ICP runs of 2-D contours, one work-item per run, in double (fsswarp/icp.py
 * explains the method; fsswarp/backends/warp/icp.py's icp_runs_kernel is the same, line by
 * line). Needs cl_khr_fp64: the host builds it only on a device that has it.
 *
 * Run r: source points P_p = (sx[p], sy[p]) for p in [f, f + n), f = runs[r].x, n = runs[r].w;
 * targets (tx[j], ty[j]) for j in [g, g + m), g = runs[r].y, m = runs[r].z; the transform
 * T(p) = rot(angles[r]) p + trans[r] (in: the start, out: the result). Moved points
 * M_p = T(P_p), computed as (c x − s y) + t_x, (s x + c y) + t_y.
 *
 * Every iteration:
 *   match   the nearest target k(p) of M_p (brute force, the first of equal squared
 *           distances). A point keeps k(p) while it stays within its room, half the gap
 *           between the nearest and second nearest distance (less 1e-9 of the second) at the
 *           point where it last searched, |M_p − anchor_p|² < room2_p; room2_p = −1 (no room:
 *           one target, or a tie) searches every time. d_p = |M_p − target k(p)|; a pair with
 *           d_p > max_distance is not usable (dist −1).
 *   scale   σ = max(median(usable d_p) / √(2 ln 2), floors[r]) (floors[r] when none): the
 *           median by Wirth's selection in scratch, the mean of the two middle values for an
 *           even count.
 *   weights w_p = 1 / (1 + (d_p / (tuning σ))²), 0 when not usable; total = Σ w_p in order;
 *           total <= 0 ends the run (not converged).
 *   solve   with w_p / total: the weighted centroids (cx, cy) of the sources and (gx, gy) of
 *           their targets, h_ij = Σ (P_p,i − c_i) (target_k(p),j − g_j) w_p / total, the angle
 *           atan2(h01 − h10, h00 + h11) and trans = g − rot c; then move the points, and the
 *           run converges when no point moved more than step_tols[r].
 * After the last iteration (converged, no weight left, or max_iterations run) one more match
 * leaves nearest[p] and dist[p] (−1 where not usable) for the host.
 *
 * Arguments:
 *   sx, sy       (F,) double   the runs' source points, run after run
 *   tx, ty       (M,) double   targets
 *   runs         (R,) int4     (first source point, first target, targets, source points)
 *   floors, step_tols (R,) double
 *   angles       (R,) double, trans (R, 2) double   in: start, out: result
 *   iterations, converged (R,) int   out (zeroed by the host)
 *   moved_x, moved_y, dist (F,) double, nearest (F,) int   out
 *   anchor_x, anchor_y, room2, scratch (F,) double   work space (scratch: the distances whose
 *                median is taken, then the weights)
 *
 * Work size: 1-D, R rounded up to the work-group size; items past R return at once.
 * The host validates everything; no checks here.
 */
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF

#define RAYLEIGH_MEDIAN 1.1774100225154747  /* sqrt(2 ln 2), fsswarp.icp.RAYLEIGH_MEDIAN */
#define TIE 1e-9

static double icp_match(const int p, const int4 run, __global const double *tx, __global const double *ty,
                        __global const double *moved_x, __global const double *moved_y,
                        __global double *anchor_x, __global double *anchor_y, __global double *room2,
                        __global int *nearest)
{
    const double x = moved_x[p];
    const double y = moved_y[p];
    const double ax = x - anchor_x[p];
    const double ay = y - anchor_y[p];
    if (ax * ax + ay * ay >= room2[p]) {
        double best = -1.0, second = -1.0;
        int found = -1;
        for (int j = run.y; j < run.y + run.z; ++j) {
            const double dx = x - tx[j];
            const double dy = y - ty[j];
            const double d2 = dx * dx + dy * dy;
            if (found < 0 || d2 < best) {
                second = best;
                best = d2;
                found = j;
            } else if (second < 0.0 || d2 < second) {
                second = d2;
            }
        }
        double room = -1.0;
        if (second >= 0.0)
            room = (sqrt(second) * (1.0 - TIE) - sqrt(best)) / 2.0;
        nearest[p] = found;
        anchor_x[p] = x;
        anchor_y[p] = y;
        room2[p] = room > 0.0 ? room * room : -1.0;
    }
    const int k = nearest[p];
    const double dx = x - tx[k];
    const double dy = y - ty[k];
    return sqrt(dx * dx + dy * dy);
}

/* The value of rank k of a[lo..hi] (inclusive), moved to a[k], with no larger value before it
 * and no smaller one after it (Wirth's selection). */
static double icp_select(__global double *a, const int lo, const int hi, const int k)
{
    int left = lo, right = hi;
    while (left < right) {
        const double pivot = a[k];
        int i = left, j = right;
        while (i <= j) {
            while (a[i] < pivot)
                ++i;
            while (pivot < a[j])
                --j;
            if (i <= j) {
                const double swap = a[i];
                a[i] = a[j];
                a[j] = swap;
                ++i;
                --j;
            }
        }
        if (j < k)
            left = i;
        if (k < i)
            right = j;
    }
    return a[k];
}

static double icp_weight(const double d, const double tuning, const double sigma)
{
    if (d < 0.0)
        return 0.0;
    const double u = d / (tuning * sigma);
    return 1.0 / (1.0 + u * u);
}

__kernel void icp_runs(__global const double *sx, __global const double *sy,
                       __global const double *tx, __global const double *ty,
                       __global const int4 *runs, __global const double *floors,
                       __global const double *step_tols, const int max_iterations,
                       const double max_distance, const double tuning, const int n_runs,
                       __global double *angles, __global double *trans,
                       __global int *iterations, __global int *converged,
                       __global double *moved_x, __global double *moved_y,
                       __global int *nearest, __global double *dist,
                       __global double *anchor_x, __global double *anchor_y,
                       __global double *room2, __global double *scratch, const int lanes)
{
    /* work-item r * lanes runs run r; the run's other lanes - 1 return (GPU_ICP_LANES) */
    const int r = get_global_id(0) / lanes;
    if (get_global_id(0) % lanes != 0 || r >= n_runs)
        return;
    const int4 run = runs[r];
    const int first = run.x;
    const int end = first + run.w;
    double c = cos(angles[r]);
    double s = sin(angles[r]);
    for (int p = first; p < end; ++p) {
        moved_x[p] = c * sx[p] - s * sy[p] + trans[2 * r];
        moved_y[p] = s * sx[p] + c * sy[p] + trans[2 * r + 1];
        anchor_x[p] = 0.0;
        anchor_y[p] = 0.0;
        room2[p] = -1.0; /* search at once */
    }
    int done = 0;
    int iteration = 0;
    for (;;) {
        int count = 0;
        for (int p = first; p < end; ++p) {
            const double d = icp_match(p, run, tx, ty, moved_x, moved_y, anchor_x, anchor_y, room2, nearest);
            if (d <= max_distance) {
                dist[p] = d;
                scratch[first + count] = d;
                ++count;
            } else {
                dist[p] = -1.0;
            }
        }
        if (iteration == max_iterations || done)
            break; /* the final match after the last move */
        ++iteration;
        iterations[r] = iteration;
        double sigma = floors[r];
        if (count > 0) {
            const int low = first + (count - 1) / 2;
            const double a = icp_select(scratch, first, first + count - 1, low);
            double b = a;
            if (count % 2 == 0) {
                b = scratch[low + 1];
                for (int q = low + 2; q < first + count; ++q)
                    b = fmin(b, scratch[q]);
            }
            sigma = fmax((a + b) / 2.0 / RAYLEIGH_MEDIAN, floors[r]);
        }
        double total = 0.0;
        for (int p = first; p < end; ++p) { /* the weights, in scratch (the median is taken) */
            scratch[p] = icp_weight(dist[p], tuning, sigma);
            total += scratch[p];
        }
        if (total <= 0.0) {
            done = 1; /* no weight left */
            continue;
        }
        /* weighted Procrustes from the original points, with the weights divided by their total */
        double cx = 0.0, cy = 0.0, gx = 0.0, gy = 0.0;
        for (int p = first; p < end; ++p) {
            const double w = scratch[p] / total;
            scratch[p] = w;
            const int k = nearest[p];
            cx += sx[p] * w;
            cy += sy[p] * w;
            gx += tx[k] * w;
            gy += ty[k] * w;
        }
        double h00 = 0.0, h01 = 0.0, h10 = 0.0, h11 = 0.0;
        for (int p = first; p < end; ++p) {
            const double w = scratch[p];
            const int k = nearest[p];
            const double bx = (tx[k] - gx) * w;
            const double by = (ty[k] - gy) * w;
            h00 += (sx[p] - cx) * bx;
            h01 += (sx[p] - cx) * by;
            h10 += (sy[p] - cy) * bx;
            h11 += (sy[p] - cy) * by;
        }
        const double angle = atan2(h01 - h10, h00 + h11);
        c = cos(angle);
        s = sin(angle);
        angles[r] = angle;
        trans[2 * r] = gx - (c * cx - s * cy);
        trans[2 * r + 1] = gy - (s * cx + c * cy);
        double step2 = 0.0;
        for (int p = first; p < end; ++p) {
            const double x = c * sx[p] - s * sy[p] + trans[2 * r];
            const double y = s * sx[p] + c * sy[p] + trans[2 * r + 1];
            const double dx = x - moved_x[p];
            const double dy = y - moved_y[p];
            step2 = fmax(step2, dx * dx + dy * dy);
            moved_x[p] = x;
            moved_y[p] = y;
        }
        if (sqrt(step2) <= step_tols[r]) {
            converged[r] = 1;
            done = 1;
        }
    }
}
