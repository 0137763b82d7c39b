"""Warp kernel of ``Backend.icp_runs``: IRLS-ICP runs of 2-D contours, one thread each, float64.

fsswarp/icp.py states the algorithm; kernels/icp.cl is the same, line by line.
"""

from __future__ import annotations

import math

import warp as wp

from .sonar import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

_RAYLEIGH_MEDIAN = wp.constant(wp.float64(math.sqrt(2.0 * math.log(2.0))))  # fsswarp.icp.RAYLEIGH_MEDIAN
_TIE = wp.constant(wp.float64(1e-9))  # a second nearest within this share is a tie (fsswarp.icp)


@wp.func
def icp_match(r: int, p: int, tx: wp.array(dtype=wp.float64), ty: wp.array(dtype=wp.float64),
              runs: wp.array2d(dtype=wp.int32), moved_x: wp.array(dtype=wp.float64),
              moved_y: wp.array(dtype=wp.float64), anchor_x: wp.array(dtype=wp.float64),
              anchor_y: wp.array(dtype=wp.float64), room2: wp.array(dtype=wp.float64),
              nearest: wp.array(dtype=wp.int32)):
    """Distance of run r's moved point p to its nearest target. The point keeps the target of
    its last search while it stays within its room (half the gap to the second nearest, less
    1e-9 of it, of where it searched); else all the run's targets are searched again."""
    x = moved_x[p]
    y = moved_y[p]
    ax = x - anchor_x[p]
    ay = y - anchor_y[p]
    if ax * ax + ay * ay >= room2[p]:
        best = wp.float64(-1.0)
        second = wp.float64(-1.0)
        found = int(-1)
        for j in range(runs[r, 1], runs[r, 1] + runs[r, 2]):
            dx = x - tx[j]
            dy = y - ty[j]
            d2 = dx * dx + dy * dy
            if found < 0 or d2 < best:
                second = best
                best = d2
                found = j
            elif second < wp.float64(0.0) or d2 < second:
                second = d2
        room = wp.float64(-1.0)
        if second >= wp.float64(0.0):
            room = (wp.sqrt(second) * (wp.float64(1.0) - _TIE) - wp.sqrt(best)) / wp.float64(2.0)
        nearest[p] = found
        anchor_x[p] = x
        anchor_y[p] = y
        if room > wp.float64(0.0):
            room2[p] = room * room
        else:
            room2[p] = wp.float64(-1.0)
    k = nearest[p]
    dx = x - tx[k]
    dy = y - ty[k]
    return wp.sqrt(dx * dx + dy * dy)


@wp.func
def icp_select(a: wp.array(dtype=wp.float64), lo: int, hi: int, k: int):
    """The value of rank k of a[lo..hi] (inclusive), moved to a[k], with no larger value
    before it and no smaller one after it (Wirth's selection)."""
    left = lo
    right = hi
    while left < right:
        pivot = a[k]
        i = left
        j = right
        while i <= j:
            while a[i] < pivot:
                i += 1
            while pivot < a[j]:
                j -= 1
            if i <= j:
                swap = a[i]
                a[i] = a[j]
                a[j] = swap
                i += 1
                j -= 1
        if j < k:
            left = i
        if k < i:
            right = j
    return a[k]


@wp.func
def icp_weight(d: wp.float64, tuning: wp.float64, sigma: wp.float64):
    """Cauchy weight of a pair at distance d (-1: not usable, weight 0)."""
    if d < wp.float64(0.0):
        return wp.float64(0.0)
    u = d / (tuning * sigma)
    return wp.float64(1.0) / (wp.float64(1.0) + u * u)


@wp.kernel
def icp_runs_kernel(sx: wp.array(dtype=wp.float64), sy: wp.array(dtype=wp.float64),
                    tx: wp.array(dtype=wp.float64), ty: wp.array(dtype=wp.float64),
                    runs: wp.array2d(dtype=wp.int32), floors: wp.array(dtype=wp.float64),
                    step_tols: wp.array(dtype=wp.float64), max_iterations: int, max_distance: wp.float64,
                    tuning: wp.float64, angles: wp.array(dtype=wp.float64), trans: wp.array2d(dtype=wp.float64),
                    iterations: wp.array(dtype=wp.int32), converged: wp.array(dtype=wp.int32),
                    moved_x: wp.array(dtype=wp.float64), moved_y: wp.array(dtype=wp.float64),
                    nearest: wp.array(dtype=wp.int32), dist: wp.array(dtype=wp.float64),
                    anchor_x: wp.array(dtype=wp.float64), anchor_y: wp.array(dtype=wp.float64),
                    room2: wp.array(dtype=wp.float64), scratch: wp.array(dtype=wp.float64), lanes: int):
    """Thread r · lanes: IRLS-ICP run r (Backend.icp_runs; the run's other lanes - 1 threads
    return, ``GPU_ICP_LANES``). runs[r] = (first source point, first target, targets, source
    points); angles, trans hold the start and receive the result; dist receives the distances
    after the last move, -1 where a pair is not usable."""
    thread = wp.tid()
    r = thread // lanes
    if thread - r * lanes != 0:
        return
    first = runs[r, 0]
    end = first + runs[r, 3]
    c = wp.cos(angles[r])
    s = wp.sin(angles[r])
    for p in range(first, end):
        moved_x[p] = c * sx[p] - s * sy[p] + trans[r, 0]
        moved_y[p] = s * sx[p] + c * sy[p] + trans[r, 1]
        anchor_x[p] = wp.float64(0.0)
        anchor_y[p] = wp.float64(0.0)
        room2[p] = wp.float64(-1.0)  # search at once
    done = int(0)
    iteration = int(0)
    while iteration <= max_iterations:
        # match: distances, -1 where not usable; sigma from their median
        count = int(0)
        for p in range(first, end):
            d = icp_match(r, p, tx, ty, runs, moved_x, moved_y, anchor_x, anchor_y, room2, nearest)
            if d <= max_distance:
                dist[p] = d
                scratch[first + count] = d
                count += 1
            else:
                dist[p] = wp.float64(-1.0)
        if iteration == max_iterations or done != 0:
            break  # the final match after the last move
        iteration += 1
        iterations[r] = iteration
        sigma = floors[r]
        if count > 0:
            low = first + (count - 1) // 2
            a = icp_select(scratch, first, first + count - 1, low)
            b = a
            if count % 2 == 0:
                b = scratch[low + 1]
                for q in range(low + 2, first + count):
                    b = wp.min(b, scratch[q])
            sigma = wp.max((a + b) / wp.float64(2.0) / _RAYLEIGH_MEDIAN, floors[r])
        total = wp.float64(0.0)
        for p in range(first, end):  # the weights, in scratch (the median is taken)
            scratch[p] = icp_weight(dist[p], tuning, sigma)
            total += scratch[p]
        if total <= wp.float64(0.0):
            done = 1  # no weight left
        else:
            # weighted Procrustes from the original points, with the weights divided by their total
            cx = wp.float64(0.0)
            cy = wp.float64(0.0)
            gx = wp.float64(0.0)
            gy = wp.float64(0.0)
            for p in range(first, end):
                w = scratch[p] / total
                scratch[p] = w
                k = nearest[p]
                cx += sx[p] * w
                cy += sy[p] * w
                gx += tx[k] * w
                gy += ty[k] * w
            h00 = wp.float64(0.0)
            h01 = wp.float64(0.0)
            h10 = wp.float64(0.0)
            h11 = wp.float64(0.0)
            for p in range(first, end):
                w = scratch[p]
                k = nearest[p]
                bx = (tx[k] - gx) * w
                by = (ty[k] - gy) * w
                h00 += (sx[p] - cx) * bx
                h01 += (sx[p] - cx) * by
                h10 += (sy[p] - cy) * bx
                h11 += (sy[p] - cy) * by
            angle = wp.atan2(h01 - h10, h00 + h11)
            ca = wp.cos(angle)
            sa = wp.sin(angle)
            angles[r] = angle
            trans[r, 0] = gx - (ca * cx - sa * cy)
            trans[r, 1] = gy - (sa * cx + ca * cy)
            step2 = wp.float64(0.0)
            for p in range(first, end):
                x = ca * sx[p] - sa * sy[p] + trans[r, 0]
                y = sa * sx[p] + ca * sy[p] + trans[r, 1]
                dx = x - moved_x[p]
                dy = y - moved_y[p]
                step2 = wp.max(step2, dx * dx + dy * dy)
                moved_x[p] = x
                moved_y[p] = y
            if wp.sqrt(step2) <= step_tols[r]:
                converged[r] = 1
                done = 1
