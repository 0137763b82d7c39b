/* pose.cl -- frontal contours of synthetic views and their distance to the data's contours:
 * the surrogate of the (D, β) grid search (DESIGN §7; fsswarp/pose.py explains it).
 *
 * Purpose: N rendered views ("pairs": one grid cell and one data view each, from
 * render_views) are compared with V data views. Component c of pair n is the sum of two
 * layers: c = 0 object + ghost (layers 0, 1), c = 1 mirror + double-bounce mirror (layers 2, 3);
 * or, with planes 2, plane c of the components' sums. Fixed-point layers are summed as
 * integers before their conversion, so both give the same values.
 *
 * frontal_contour, work-item (k, n) = (item, pair), v = view_index[n]: item k of view v,
 *   items[v][k] = c · beams + b (-1: none; the masked beams of each component, host's
 *   fsswarp.backends.base.mask_items), finds contour[n][c][b]; the host sets every other entry
 *   to -1 (the beams that mask[v][c] leaves out). The component is smoothed with the
 *   separable weights (wB: 2 rB + 1 taps along range, wb: 2 rb + 1 taps across beams; indices
 *   clamped to the image, scipy's "nearest" border), C[n][c] the component:
 *     row_i = Σ_j wb[j] · C[n][c][B_i][b_j],  s(B) = Σ_i wB[i] · row_i
 *   with B_i = clamp(B + i − rB), b_j = clamp(b + j − rb), sums in index order (each row_i is
 *   summed once per row, kept in a ring of 2 rB + 1 rows up to RING_TAPS); C[n][c][B] is
 *   image row B of pair n, stored at row B − first_rows[n] of its band. The first row B
 *   of the window lo <= B < hi (window[v]) where f(B) = s(B) − threshold[v][B] > 0 gives the
 *   crossing: lo when B == lo, else (B − 1) + f(B − 1) / (f(B − 1) − f(B)) (fractional row,
 *   linear interpolation); -1 when no row of the window crosses.
 * contour_cost, work-item (s, c, n) = (shift, component, pair), v = view_index[n]:
 *   over the beams b (in order) with contour x = contour[n][c][b] >= 0, the data distance
 *   min(dist[v][c][·][b], cap) read at y = clamp(x + shift[s], 0, bins − 1) by linear
 *   interpolation between rows floor(y) and floor(y) + 1 (clamped): sums[n][c][s] = Σ_b of it, and
 *   counts[n][c] = the number of such beams (written by s == 0).
 * view_cost, work-item (s, n) = (shift, pair), v = view_index[n]: the pair's surrogate view cost
 *   costs[n][s] = Σ_c (sums[n][c][s] + cap · max(0, m − k)) / max(k, m), k = counts[n][c],
 *   m = data_counts[v][c] (the data's contour points), a term 0 where k = m = 0; c in order.
 *
 * Bands: the clamping is to the image [0, bins − 1], never to the band; the host guarantees
 * that every row a pair's window reads, [max(lo − rB, 0), min(hi + rB, bins)), lies in its
 * band [first_rows[n], first_rows[n] + rows), so results equal those of full layers bit for bit.
 *
 * Arguments:
 *   layers       (N, P, rows, beams) float32 (fixed 0) or render_views' fixed-point int
 *                accumulator (fixed 1; 2^24 = 1, read as fixed_to_float converts it), in a
 *                buffer read as int: band n holds image rows first_rows[n] ..
 *                first_rows[n] + rows − 1 (full layers: first_rows 0, rows = bins); P = planes,
 *                4 (the layers) or 2 (the components' sums)
 *   first_rows   (N,) int;  rows  R, the rows of every band
 *   view_index   (N,) int        data view of each pair
 *   threshold    (V, bins) float  detection threshold of each data view and row
 *   window       (V, 2) int       rows lo, hi scanned (0 <= lo < hi <= bins)
 *   items, n_items  (V, n_items) int  each view's masked (component, beam) items, -1 padded
 *   wB, rB       (2 rB + 1,) float range weights;  wb, rb  (2 rb + 1,) float beam weights
 *   dist         (V, 2, bins, beams) float  distance (m) of every pixel to the data's contour
 *   cap          float            distances above it count as cap (m)
 *   shifts       (S,) float       range shifts (rows)
 *   contour      (N, 2, beams) float  out (frontal_contour), in (contour_cost)
 *   sums         (N, 2, S) float;  counts (N, 2) int   out (contour_cost), in (view_cost)
 *   data_counts  (V, 2) int       data contour points of each view and component
 *   costs        (N, S) float     out (view_cost)
 *
 * Work size: frontal_contour 2-D, (n_items rounded up to the work-group size, N); contour_cost
 * 3-D, (S rounded up, 2, N); view_cost 2-D, (S rounded up, N); items past the first
 * dimension's extent return at once. The host validates everything; no checks here.
 */
#include "sonar.h"

/* Range taps kept in frontal_contour's ring of beam-smoothed rows (Warp: RING_TAPS); a wider
 * smoothing sums every tap's row afresh. Either way the same sums in the same order. */
#define RING_TAPS 33

/* Value k of a component: planes l0 + l1 (two 1) or l0 alone (two 0), fixed-point (fixed 1,
 * summed as integers, then as fixed_to_float converts it) or float32 bits. */
inline float component_value(__global const int *l0, __global const int *l1, const int two, const size_t k,
                             const int fixed)
{
    if (fixed)
        return (float)(two ? l0[k] + l1[k] : l0[k]) * (1.0f / FSS_FIXED);
    return two ? as_float(l0[k]) + as_float(l1[k]) : as_float(l0[k]);
}

/* The component (l0, l1, two) in band row Bi smoothed across the beams at beam b. */
static float beam_row(__global const int *l0, __global const int *l1, const int two, const int fixed, const int Bi,
                      const int b, const int beams, __global const float *wb, const int rb)
{
    float row = 0.0f;
    for (int j = 0; j <= 2 * rb; ++j) {
        const size_t k = (size_t)Bi * beams + clamp(b + j - rb, 0, beams - 1);
        row += wb[j] * component_value(l0, l1, two, k, fixed);
    }
    return row;
}

__kernel void frontal_contour(__global const int *layers,
                              const int fixed,
                              __global const int *view_index,
                              __global const float *threshold,
                              __global const int *window,
                              __global const int *items,
                              const int n_items,
                              __global const float *wB,
                              const int rB,
                              __global const float *wb,
                              const int rb,
                              const int bins,
                              const int beams,
                              __global const int *first_rows,
                              const int rows,
                              const int planes,
                              __global float *contour)
{
    const int k = get_global_id(0);
    const int n = get_global_id(1);
    if (k >= n_items)
        return;
    const int v = view_index[n];
    const int item = items[(size_t)v * n_items + k];
    if (item < 0)
        return;
    const int c = item / beams;
    const int b = item - c * beams;
    __global float *out = contour + ((size_t)n * 2 + c) * beams + b;
    const size_t plane = (size_t)rows * beams;
    const int first = first_rows[n];
    const int two = planes == 4;
    __global const int *l0 = layers + ((size_t)n * planes + c * (planes / 2)) * plane;
    __global const int *l1 = l0 + plane; /* read where two */
    __global const float *thr = threshold + (size_t)v * bins;
    const int lo = window[2 * v];
    const int hi = window[2 * v + 1];
    const int taps = 2 * rB + 1;
    const int cached = taps <= RING_TAPS;
    /* row k (image row clamp(k), k > -taps) in slot (k + taps) % taps, stepped to rather than
     * divided for (an integer division per tap: 21% of Warp's kernel time on an H200) */
    float ring[RING_TAPS];
    int oldest = (lo - rB + taps) % taps; /* the slot of row B - rB */
    if (cached)
        for (int row = lo - rB, slot = oldest; row < lo + rB; ++row, slot = slot + 1 == taps ? 0 : slot + 1)
            ring[slot] = beam_row(l0, l1, two, fixed, clamp(row, 0, bins - 1) - first, b, beams, wb, rb);
    float previous = 0.0f;
    for (int B = lo; B < hi; ++B) {
        float s = 0.0f;
        if (cached) { /* row B + rB takes the slot of row B - rB - 1 */
            ring[oldest == 0 ? taps - 1 : oldest - 1] = beam_row(l0, l1, two, fixed,
                                                                 clamp(B + rB, 0, bins - 1) - first, b, beams, wb,
                                                                 rb);
            for (int i = 0, slot = oldest; i < taps; ++i, slot = slot + 1 == taps ? 0 : slot + 1)
                s += wB[i] * ring[slot];
            oldest = oldest + 1 == taps ? 0 : oldest + 1;
        } else {
            for (int i = 0; i < taps; ++i)
                s += wB[i] * beam_row(l0, l1, two, fixed, clamp(B + i - rB, 0, bins - 1) - first, b, beams, wb,
                                      rb);
        }
        const float f = s - thr[B];
        if (f > 0.0f) {
            *out = (B == lo) ? (float)lo : (float)(B - 1) + previous / (previous - f);
            return;
        }
        previous = f;
    }
    *out = -1.0f;
}

__kernel void contour_cost(__global const float *contour,
                           __global const int *view_index,
                           __global const float *dist,
                           const float cap,
                           __global const float *shifts,
                           const int n_shifts,
                           const int bins,
                           const int beams,
                           __global float *sums,
                           __global int *counts)
{
    const int s = get_global_id(0);
    const int c = get_global_id(1);
    const int n = get_global_id(2);
    if (s >= n_shifts)
        return;
    const int v = view_index[n];
    __global const float *x = contour + ((size_t)n * 2 + c) * beams;
    __global const float *d = dist + ((size_t)v * 2 + c) * (size_t)bins * beams;
    const float shift = shifts[s];
    const float last = (float)(bins - 1);
    float total = 0.0f;
    int count = 0;
    for (int b = 0; b < beams; ++b) {
        if (x[b] < 0.0f)
            continue;
        const float y = clamp(x[b] + shift, 0.0f, last);
        const int B0 = (int)floor(y);
        const int B1 = min(B0 + 1, bins - 1);
        const float t = y - (float)B0;
        total += (1.0f - t) * fmin(d[(size_t)B0 * beams + b], cap) + t * fmin(d[(size_t)B1 * beams + b], cap);
        count += 1;
    }
    sums[((size_t)n * 2 + c) * n_shifts + s] = total;
    if (s == 0)
        counts[(size_t)n * 2 + c] = count;
}

__kernel void view_cost(__global const float *sums,
                        __global const int *counts,
                        __global const int *view_index,
                        __global const int *data_counts,
                        const float cap,
                        const int n_shifts,
                        __global float *costs)
{
    const int s = get_global_id(0);
    const int n = get_global_id(1);
    if (s >= n_shifts)
        return;
    const int v = view_index[n];
    float total = 0.0f;
    for (int c = 0; c < 2; ++c) {
        const int k = counts[(size_t)n * 2 + c];
        const int m = data_counts[(size_t)v * 2 + c];
        const int most = max(k, m);
        if (most > 0)
            total += (sums[((size_t)n * 2 + c) * n_shifts + s] + cap * (float)max(m - k, 0)) / (float)most;
    }
    costs[(size_t)n * n_shifts + s] = total;
}
