"""Warp kernels of ``Backend.contour_cost``: frontal contours and their distances to the data's.

kernels/pose.cl documents the rule. ``frontal_contour`` reads float32 layers or the render's
fixed-point accumulator (int32, ``scale`` 2^-24: the same floats as ``fixed_to_float``'s), four
layers or the two components' sums, and
writes (N, 2, beams) float32 rows (-1: none); ``contour_cost_kernel`` (N, 2, S) float32 sums and
(N, 2) int32 counts; ``view_cost_kernel`` (N, S) float32 view costs from them.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from .sonar import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)


#: Range taps of the smoothing that ``frontal_contour`` keeps in a ring of smoothed rows (pose.cl
#: ``RING_TAPS``); a wider smoothing sums every tap's row afresh (the same sums).
RING_TAPS = 33
Ring = wp.types.vector(length=RING_TAPS, dtype=float)


@wp.func
def beam_row(layers: wp.array4d(dtype=Any), scale: float, n: int, c: int, bi: int, b: int, beams: int,
             w_beam: wp.array(dtype=float), r_beam: int):
    """Component c of pair n in band row bi smoothed across the beams at beam b: the sum of
    layers 2c and 2c + 1 (four layers) or plane c (the components' sums), summed in the layers'
    type, times ``scale`` (1, or the power of two of the fixed point: exact)."""
    row = float(0.0)
    for j in range(2 * r_beam + 1):
        bj = wp.clamp(b + j - r_beam, 0, beams - 1)
        if layers.shape[1] == 4:
            value = layers[n, 2 * c, bi, bj] + layers[n, 2 * c + 1, bi, bj]
        else:
            value = layers[n, c, bi, bj]
        row += w_beam[j] * (float(value) * scale)
    return row


@wp.func
def _next_slot(slot: int, taps: int):
    """The ring's slot after ``slot`` (0 after taps − 1)."""
    following = slot + 1
    if following == taps:
        following = 0
    return following


@wp.kernel
def frontal_contour(layers: wp.array4d(dtype=Any), scale: float, first_rows: wp.array(dtype=wp.int32),
                    view_index: wp.array(dtype=wp.int32),
                    threshold: wp.array2d(dtype=float), window: wp.array2d(dtype=wp.int32),
                    items: wp.array2d(dtype=wp.int32), w_range: wp.array(dtype=float), r_range: int,
                    w_beam: wp.array(dtype=float), r_beam: int, contour: wp.array3d(dtype=float)):
    """Thread (n, k): item k = c · beams + b of pair n's view (``base.mask_items``; -1: none),
    the first threshold crossing of the smoothed component c of pair n in beam b, into contour
    (N, 2, beams), whose other entries the host sets to -1.
    layers (N, 4 or 2, R, beams) float32 (scale 1) or fixed-point int32 (scale 2^-24): image row B of
    pair n at row B − first_rows[n] (full layers: zeros, R = bins); rows clamp to the image,
    and the host guarantees the band holds every row read.
    Each row's beam smoothing is summed once into a ring of the last 2 r_range + 1 rows
    (at most RING_TAPS; else afresh per tap): the same sums in the same order. Row k lies in
    slot (k + taps) % taps (k > −taps), stepped to rather than divided for (an integer
    division per tap: 21% of the kernel's time on an H200)."""
    n, k = wp.tid()
    v = view_index[n]
    item = items[v, k]
    bins = threshold.shape[1]
    beams = layers.shape[3]
    c = item // beams
    b = item - c * beams
    first = first_rows[n]
    taps = 2 * r_range + 1
    result = float(-1.0)
    if item >= 0:
        lo = window[v, 0]
        hi = window[v, 1]
        ring = Ring()
        cached = taps <= RING_TAPS
        oldest = (lo - r_range + taps) % taps  # the slot of row row_index − r_range
        if cached:  # rows lo − r_range .. lo + r_range − 1
            slot = oldest
            for row in range(lo - r_range, lo + r_range):
                ring[slot] = beam_row(layers, scale, n, c, wp.clamp(row, 0, bins - 1) - first, b, beams, w_beam,
                                      r_beam)
                slot = _next_slot(slot, taps)
        previous = float(0.0)
        row_index = int(lo)
        while row_index < hi:
            s = float(0.0)
            if cached:  # row row_index + r_range takes the slot of row row_index − r_range − 1
                newest = oldest - 1
                if newest < 0:
                    newest = taps - 1
                ring[newest] = beam_row(layers, scale, n, c, wp.clamp(row_index + r_range, 0, bins - 1) - first, b,
                                        beams, w_beam, r_beam)
                slot = oldest
                for i in range(taps):
                    s += w_range[i] * ring[slot]
                    slot = _next_slot(slot, taps)
                oldest = _next_slot(oldest, taps)
            else:
                for i in range(taps):
                    bi = wp.clamp(row_index + i - r_range, 0, bins - 1) - first
                    s += w_range[i] * beam_row(layers, scale, n, c, bi, b, beams, w_beam, r_beam)
            f = s - threshold[v, row_index]
            if f > 0.0:
                if row_index == lo:
                    result = float(lo)
                else:
                    result = float(row_index - 1) + previous / (previous - f)
                row_index = hi
            else:
                previous = f
                row_index += 1
        contour[n, c, b] = result


for _dtype in (wp.float32, wp.int32):  # float layers from the host, the accumulator on the device
    wp.overload(frontal_contour, {"layers": wp.array4d(dtype=_dtype)})


@wp.kernel
def contour_cost_kernel(contour: wp.array3d(dtype=float), view_index: wp.array(dtype=wp.int32),
                        dist: wp.array4d(dtype=float), cap: float, shifts: wp.array(dtype=float),
                        sums: wp.array3d(dtype=float), counts: wp.array2d(dtype=wp.int32)):
    """Thread (n, c, s): distances of pair n's contour c to the data's, read at shift s."""
    n, c, s = wp.tid()
    v = view_index[n]
    bins = dist.shape[2]
    beams = dist.shape[3]
    shift = shifts[s]
    last = float(bins - 1)
    total = float(0.0)
    count = int(0)
    for b in range(beams):
        x = contour[n, c, b]
        if x >= 0.0:
            y = wp.clamp(x + shift, 0.0, last)
            b0 = int(wp.floor(y))
            b1 = wp.min(b0 + 1, bins - 1)
            t = y - float(b0)
            total += (1.0 - t) * wp.min(dist[v, c, b0, b], cap) + t * wp.min(dist[v, c, b1, b], cap)
            count += 1
    sums[n, c, s] = total
    if s == 0:
        counts[n, c] = count


@wp.kernel
def view_cost_kernel(sums: wp.array3d(dtype=float), counts: wp.array2d(dtype=wp.int32),
                     view_index: wp.array(dtype=wp.int32), data_counts: wp.array2d(dtype=wp.int32), cap: float,
                     costs: wp.array2d(dtype=float)):
    """Thread (n, s): object + mirror terms of pair n at shift s, (Σ d + cap · max(0, m − k)) /
    max(k, m) with k its contour points and m the data's, 0 for an empty term."""
    n, s = wp.tid()
    v = view_index[n]
    total = float(0.0)
    for c in range(2):
        k = counts[n, c]
        m = data_counts[v, c]
        most = wp.max(k, m)
        if most > 0:
            total += (sums[n, c, s] + cap * float(wp.max(m - k, 0))) / float(most)
    costs[n, s] = total
