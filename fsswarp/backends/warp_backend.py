"""NVIDIA Warp kernels ("cpu" and "cuda:N") behind the Backend interface.

Kernels and their helper functions first, compiled once per process and device (Warp keeps
the build in its kernel cache, ~/.cache/warp); the wrapper class below. The ``@wp.func``
helpers mirror ``kernels/sonar.h`` operation for operation, so that this backend and the
OpenCL one round alike; change them together.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from . import Backend, SonarConstants, _warp

_INDEX_LIMIT = wp.constant(1073741824.0)  # ±2^30: far-away points cannot overflow int32


# --- shared geometry (kernels/sonar.h) -------------------------------------------------------
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


@wp.func
def beam_coordinate(theta: float, use_table: int, table: wp.array2d(dtype=float), beams: int,
                    half_azimuth: float, beam_scale: float):
    """Fractional column of azimuth theta: linear, or interpolated in the angle table (row 0
    the centres, row 1 the inverse spacings) and extrapolated with the outer spacing."""
    if use_table == 0:
        return (theta + half_azimuth) * beam_scale
    last = beams - 1
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
def bin_coordinate(r: float, range_min: float, inv_range_step: float):
    return (r - range_min) * inv_range_step


@wp.func
def nearest_index(c: float):
    """floor(c + 0.5), clamped to ±2^30."""
    f = wp.floor(c + 0.5)
    return int(wp.clamp(f, -_INDEX_LIMIT, _INDEX_LIMIT))


# --- kernels ---------------------------------------------------------------------------------
@wp.kernel
def project_points(points: wp.array(dtype=wp.vec3), rotations: wp.array(dtype=wp.mat33),
                   translations: wp.array(dtype=wp.vec3), beam_table: wp.array2d(dtype=float),
                   use_table: int, beams: int, bins: int, half_azimuth: float, beam_scale: float,
                   range_min: float, inv_range_step: float, half_elevation: float,
                   beam_out: wp.array2d(dtype=wp.int32), bin_out: wp.array2d(dtype=wp.int32),
                   inside_out: wp.array2d(dtype=wp.uint8)):
    """Thread (v, p): nearest beam and bin of point p in view v, and whether it lands in the
    image with |elevation| <= W_φ (kernels/project.cl documents the arguments)."""
    v, p = wp.tid()
    q = to_view(points[p], rotations[v], translations[v])
    theta = azimuth(q)
    phi = elevation(q)
    r = sonar_range(q)
    b = nearest_index(beam_coordinate(theta, use_table, beam_table, beams, half_azimuth, beam_scale))
    bb = nearest_index(bin_coordinate(r, range_min, inv_range_step))
    beam_out[v, p] = b
    bin_out[v, p] = bb
    if b >= 0 and b < beams and bb >= 0 and bb < bins and wp.abs(phi) <= half_elevation:
        inside_out[v, p] = wp.uint8(1)
    else:
        inside_out[v, p] = wp.uint8(0)


# --- the backend -----------------------------------------------------------------------------
class WarpBackend(Backend):
    """Warp on one device ("cpu", "cuda:N"). Create through ``get_backend("warp", device)``."""

    name = "warp"

    def __init__(self, device: str):
        _warp()  # initialized quietly
        self._device = wp.get_device(device)
        self.device = str(self._device.alias)
        self.is_gpu = bool(self._device.is_cuda)

    def _array(self, data: np.ndarray, dtype) -> wp.array:
        return wp.array(data, dtype=dtype, device=self._device)

    def _project(self, points, rotations, translations, sonar: SonarConstants):
        n_views, n_points = rotations.shape[0], points.shape[0]
        with wp.ScopedDevice(self._device):
            beam = wp.empty((n_views, n_points), dtype=wp.int32)
            bin_ = wp.empty((n_views, n_points), dtype=wp.int32)
            inside = wp.empty((n_views, n_points), dtype=wp.uint8)
            wp.launch(project_points, dim=(n_views, n_points),
                      inputs=[self._array(points, wp.vec3), self._array(rotations, wp.mat33),
                              self._array(translations, wp.vec3), self._array(sonar.beam_table, float),
                              sonar.use_table, sonar.beams, sonar.bins, sonar.half_azimuth,
                              sonar.beam_scale, sonar.range_min, sonar.inv_range_step,
                              sonar.half_elevation],
                      outputs=[beam, bin_, inside])
            wp.synchronize_device(self._device)
            return beam.numpy(), bin_.numpy(), inside.numpy()
