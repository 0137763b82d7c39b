"""Sonar geometry shared by the Warp kernels: ``fss_*`` of kernels/sonar.h, operation for operation.

The ``@wp.func`` helpers mirror ``kernels/sonar.h`` so that both backends round alike (same
order of operations, no contraction into fma: ``MODULE_OPTIONS``, which every Warp kernel
module sets); change them together. ``KernelSonar`` is the struct of a sonar's scalars that
the kernels take as one argument (``fss_sonar``). Angles in radians, lengths in metres.
"""

from __future__ import annotations

import warp as wp

from ..base import SonarConstants
from ..constants import INDEX_LIMIT

#: Options of every Warp kernel module: no contraction of a*b + c into fma (the watertight
#: ray-triangle test needs a shared edge to give the same float expression in both triangles;
#: kernels/*.cl build with FP_CONTRACT OFF too) and no adjoint code (nothing is differentiated).
MODULE_OPTIONS = {"fuse_fp": False, "enable_backward": False}

wp.set_module_options(MODULE_OPTIONS)

_INDEX_LIMIT = wp.constant(INDEX_LIMIT)


@wp.func
def to_view(p: wp.vec3, r: wp.mat33, t: wp.vec3):
    """P_view = Rᵀ (p − t)."""
    d0 = p[0] - t[0]
    d1 = p[1] - t[1]
    d2 = p[2] - t[2]
    x = r[0, 0] * d0 + r[1, 0] * d1 + r[2, 0] * d2
    y = r[0, 1] * d0 + r[1, 1] * d1 + r[2, 1] * d2
    z = r[0, 2] * d0 + r[1, 2] * d1 + r[2, 2] * d2
    return wp.vec3(x, y, z)


@wp.func
def sonar_range(q: wp.vec3):
    return wp.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2])


@wp.func
def azimuth(q: wp.vec3):
    return wp.atan2(q[0], q[1])


@wp.func
def elevation(q: wp.vec3):
    return wp.atan2(q[2], wp.sqrt(q[0] * q[0] + q[1] * q[1]))


@wp.struct
class KernelSonar:
    """``SonarConstants`` without the beam table, as one kernel argument (``fss_sonar`` of
    kernels/sonar.h, the same fields in the same order)."""

    use_table: int
    beams: int
    bins: int
    half_azimuth: float
    beam_scale: float
    range_min: float
    inv_range_step: float
    half_elevation: float


def kernel_sonar(sonar: SonarConstants) -> KernelSonar:
    """The Warp struct of ``sonar``'s scalars (float32 fields: the float32 values)."""
    packed = KernelSonar()
    for name in KernelSonar.vars:
        setattr(packed, name, getattr(sonar, name))
    return packed


@wp.func
def beam_coordinate(theta: float, sonar: KernelSonar, table: wp.array2d(dtype=float)):
    """Fractional column of azimuth theta: linear, or interpolated in the angle table (row 0
    the centres, row 1 the inverse spacings) and extrapolated with the outer spacing."""
    if sonar.use_table == 0:
        return (theta + sonar.half_azimuth) * sonar.beam_scale
    last = sonar.beams - 1
    if theta < table[0, 0]:
        return (theta - table[0, 0]) * table[1, 0]
    if theta > table[0, last]:
        return float(last) + (theta - table[0, last]) * table[1, last]
    lo = int(0)  # invariant: table[0, lo] <= theta <= table[0, hi]
    hi = int(last)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if table[0, mid] <= theta:
            lo = mid
        else:
            hi = mid
    return float(lo) + (theta - table[0, lo]) * table[1, lo]


@wp.func
def bin_coordinate(r: float, sonar: KernelSonar):
    return (r - sonar.range_min) * sonar.inv_range_step


@wp.func
def nearest_index(c: float):
    """floor(c + 0.5), clamped to ±2^30."""
    f = wp.floor(c + 0.5)
    return int(wp.clamp(f, -_INDEX_LIMIT, _INDEX_LIMIT))
