"""Warp kernel of ``Backend.project``: nearest beam and bin of points in views (kernels/project.cl).
"""

from __future__ import annotations

import warp as wp

from .sonar import MODULE_OPTIONS, KernelSonar, azimuth, beam_coordinate, bin_coordinate, elevation, nearest_index, \
    sonar_range, to_view

wp.set_module_options(MODULE_OPTIONS)


@wp.kernel
def project_points(points: wp.array(dtype=wp.vec3), rotations: wp.array(dtype=wp.mat33),
                   translations: wp.array(dtype=wp.vec3), beam_table: wp.array2d(dtype=float),
                   sonar: KernelSonar, beam_out: wp.array2d(dtype=wp.int32), bin_out: wp.array2d(dtype=wp.int32),
                   inside_out: wp.array2d(dtype=wp.uint8)):
    """Thread (v, p): nearest beam and bin of point p in view v, and whether it lands in the
    image with |elevation| <= W_φ (kernels/project.cl documents the arguments)."""
    v, p = wp.tid()
    q = to_view(points[p], rotations[v], translations[v])
    theta = azimuth(q)
    phi = elevation(q)
    r = sonar_range(q)
    b = nearest_index(beam_coordinate(theta, sonar, beam_table))
    bb = nearest_index(bin_coordinate(r, sonar))
    beam_out[v, p] = b
    bin_out[v, p] = bb
    if b >= 0 and b < sonar.beams and bb >= 0 and bb < sonar.bins and wp.abs(phi) <= sonar.half_elevation:
        inside_out[v, p] = wp.uint8(1)
    else:
        inside_out[v, p] = wp.uint8(0)
