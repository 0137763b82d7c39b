"""Warp kernels of voxel space carving (kernels/carve.cl documents the rule and the arguments).

``carve_grid`` takes a regular grid of voxels (origin, voxel size, shape), ``carve_points``
explicit (P,) vec3 centres; both write (P,) uint8 seen and rejected counts.
"""

from __future__ import annotations

import warp as wp

from .sonar import MODULE_OPTIONS, KernelSonar, azimuth, beam_coordinate, bin_coordinate, elevation, nearest_index, \
    sonar_range, to_view

wp.set_module_options(MODULE_OPTIONS)


@wp.func
def carve_test(c: wp.vec3, r: wp.mat33, t: wp.vec3, integral: wp.array3d(dtype=wp.int32), v: int,
               beam_table: wp.array2d(dtype=float), sonar: KernelSonar, radius: float):
    """0: view v does not see the voxel at c (wholly); 1: sees and keeps it; 2: sees and rejects
    it (fss_carve_test of kernels/carve.cl, operation for operation)."""
    q = to_view(c, r, t)
    rho = wp.sqrt(q[0] * q[0] + q[1] * q[1])
    if not (radius < rho):
        return 0
    theta = azimuth(q)
    phi = elevation(q)
    rng = sonar_range(q)
    d_phi = wp.asin(radius / rng)
    if not (wp.abs(phi) + d_phi <= sonar.half_elevation):
        return 0
    d_theta = wp.asin(radius / rho)
    b_lo = nearest_index(beam_coordinate(theta - d_theta, sonar, beam_table))
    b_hi = nearest_index(beam_coordinate(theta + d_theta, sonar, beam_table))
    bin_lo = nearest_index(bin_coordinate(rng - radius, sonar))
    bin_hi = nearest_index(bin_coordinate(rng + radius, sonar))
    if b_lo < 0 or b_hi >= sonar.beams or bin_lo < 0 or bin_hi >= sonar.bins:
        return 0
    count = (integral[v, bin_hi + 1, b_hi + 1] - integral[v, bin_lo, b_hi + 1]
             - integral[v, bin_hi + 1, b_lo] + integral[v, bin_lo, b_lo])
    if count == 0:
        return 2
    return 1


@wp.func
def carve_voxel(c: wp.vec3, p: int, rotations: wp.array(dtype=wp.mat33), translations: wp.array(dtype=wp.vec3),
                integral: wp.array3d(dtype=wp.int32), beam_table: wp.array2d(dtype=float), sonar: KernelSonar,
                radius: float, seen_out: wp.array(dtype=wp.uint8), rejected_out: wp.array(dtype=wp.uint8)):
    """Views that see the voxel at c up to the first that rejects it, and whether one does
    (written at p; the loop stops at the first rejection)."""
    seen = int(0)
    rejected = int(0)
    for v in range(rotations.shape[0]):
        test = carve_test(c, rotations[v], translations[v], integral, v, beam_table, sonar, radius)
        if test > 0:
            seen += 1
        if test == 2:
            rejected = 1
            break
    seen_out[p] = wp.uint8(seen)
    rejected_out[p] = wp.uint8(rejected)


@wp.kernel
def carve_grid(origin: wp.vec3, voxel_size: float, ny: int, nz: int, rotations: wp.array(dtype=wp.mat33),
               translations: wp.array(dtype=wp.vec3), integral: wp.array3d(dtype=wp.int32),
               beam_table: wp.array2d(dtype=float), sonar: KernelSonar, radius: float,
               seen_out: wp.array(dtype=wp.uint8),
               rejected_out: wp.array(dtype=wp.uint8)):
    """Thread p = (i·ny + j)·nz + k: the voxel centred at origin + h·(i, j, k)."""
    p = wp.tid()
    k = p % nz
    j = (p // nz) % ny
    i = p // (nz * ny)
    c = wp.vec3(origin[0] + voxel_size * float(i), origin[1] + voxel_size * float(j),
                origin[2] + voxel_size * float(k))
    carve_voxel(c, p, rotations, translations, integral, beam_table, sonar, radius, seen_out, rejected_out)


@wp.kernel
def carve_points(centres: wp.array(dtype=wp.vec3), rotations: wp.array(dtype=wp.mat33),
                 translations: wp.array(dtype=wp.vec3), integral: wp.array3d(dtype=wp.int32),
                 beam_table: wp.array2d(dtype=float), sonar: KernelSonar, radius: float,
                 seen_out: wp.array(dtype=wp.uint8),
                 rejected_out: wp.array(dtype=wp.uint8)):
    """Thread p: the voxel centred at centres[p]."""
    p = wp.tid()
    carve_voxel(centres[p], p, rotations, translations, integral, beam_table, sonar, radius, seen_out,
                rejected_out)
