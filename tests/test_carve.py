"""Space carving: the kernels against the float64 NumPy oracle and each other, the voxel rule's
conservativeness and coarse-to-fine, carving of simulated coral-one, bad input and the CLI.

Tolerance of the kernel tests. Kernels compute in float32, ``carve_reference`` in float64 on
the same float32 voxel centres. A decision can differ only where one of its bounds lies within
float32 rounding of a boundary: a beam or bin coordinate of the footprint box within
``MARGIN`` of a half-index (widened to four float32 ulps of the θ or R behind it), the
elevation bound within ``ELEVATION_MARGIN`` of W_φ, or r within 1e-6 relative of ρ. Voxels
with such a pair are left out, and at least 98% must be compared.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
import warnings

import numpy as np
import pytest
import trimesh

from fsswarp.carving import (MC_LEVEL, UNSEEN_MARGIN, CarveSettings, CarveWarning, MeshJob, VoxelCarving, carve,
                           carve_masks,
                           carve_reference, common_region, held, mesh_workers, voxel_mesh, within, _Carver, _closed,
                           _fill_holes, _step_tolerance)
from fsswarp.errors import InputError
from fsswarp.metrics import inside_grid
from fsswarp.rendering import signed_volume
from fsswarp.rig import rotation_x, rotation_y, rotation_z, to_view
from fsswarp.segment import from_highlight
from fsswarp.sonar import SonarSpec, to_polar
from fsswarp.surface import surface_in_reference

MARGIN = 1e-4  # index units
ULPS = 4.0
ELEVATION_MARGIN = 1e-6  # rad
EPS32 = 2.0**-23
SONARS = {"linear": SonarSpec, "table": lambda: SonarSpec(
    beam_angles=math.radians(14.4) * (0.7 * np.linspace(-1, 1, 96) + 0.3 * np.linspace(-1, 1, 96) ** 3),
    azimuth_fov=math.radians(28.8))}


def carve_scene(seed: int, sonar: SonarSpec, n_views: int = 6):
    """Seeded views looking roughly along +Y (view 0 the identity), feasible masks that start at a
    random bin in 80% of the beams plus scattered feasible pixels, and a grid of 3 cm voxels
    over the fans (27 x 54 x 27)."""
    rng = np.random.default_rng(seed)
    rotations = (rotation_z(rng.uniform(-0.3, 0.3, n_views)) @ rotation_x(rng.uniform(-0.2, 0.2, n_views))
                 @ rotation_y(rng.uniform(-1.6, 1.6, n_views)))
    translations = rng.uniform(-0.2, 0.2, (n_views, 3))
    rotations[0], translations[0] = np.eye(3), 0.0
    first = np.where(rng.random((n_views, sonar.beams)) < 0.8,
                     rng.integers(100, 480, (n_views, sonar.beams)), sonar.bins)
    masks = np.arange(sonar.bins)[None, :, None] >= first[:, None, :]
    for v in range(n_views):
        masks[v, rng.integers(0, sonar.bins, 40), rng.integers(0, sonar.beams, 40)] = True
    grid = dict(origin=(-0.39, 1.11, -0.39), shape=(27, 54, 27))
    return masks, rotations, translations, 0.03, grid


def decidable(points, rotations, translations, sonar: SonarSpec, voxel_size: float) -> np.ndarray:
    """(P,) whether float32 rounding cannot change any view's decision on the voxel."""
    points = np.asarray(points, np.float32).astype(np.float64)
    radius = float(np.float32(voxel_size * math.sqrt(3.0) / 2.0))
    ok = np.ones(len(points), bool)
    for rot, t in zip(rotations, translations):
        q = to_view(points, rot, t)
        rng, theta, phi = to_polar(q)
        rho = np.hypot(q[:, 0], q[:, 1])
        with np.errstate(invalid="ignore", divide="ignore"):
            d_theta = np.arcsin(np.minimum(radius / rho, 1.0))
            d_phi = np.arcsin(np.minimum(radius / rng, 1.0))
        for angle in (theta - d_theta, theta + d_theta):
            h = 1e-7
            slope = np.abs(sonar.beam_coordinate(angle + h) - sonar.beam_coordinate(angle - h)) / (2 * h)
            margin = np.maximum(MARGIN, ULPS * EPS32 * np.maximum(np.abs(angle), 1.0) * slope)
            ok &= _to_boundary(sonar.beam_coordinate(angle)) > margin
        for r in (rng - radius, rng + radius):
            ok &= _to_boundary(sonar.bin_coordinate(r)) > np.maximum(MARGIN, ULPS * EPS32 * rng / sonar.range_step)
        ok &= np.abs(np.abs(phi) + d_phi - sonar.half_elevation) > ELEVATION_MARGIN
        ok &= np.abs(rho - radius) > 1e-6 * rho
    return ok


def _to_boundary(coordinate):
    shifted = coordinate + 0.5
    return np.abs(shifted - np.round(shifted))


def grid_centres(origin, voxel_size, shape) -> np.ndarray:
    """Float32 centres of a grid, formed as the kernels form them."""
    idx = np.stack(np.meshgrid(*(np.arange(n, dtype=np.float32) for n in shape), indexing="ij"), -1)
    return (np.asarray(origin, np.float32) + np.float32(voxel_size) * idx).reshape(-1, 3)


# --- the kernels ---------------------------------------------------------------------------------
@pytest.mark.parametrize("sonar_kind", SONARS)
def test_carve_kernel_matches_reference(backend, sonar_kind):
    sonar = SONARS[sonar_kind]()
    masks, rot, trans, h, grid = carve_scene(5, sonar)
    seen, rejected = backend.carve(masks, rot, trans, sonar, h, **grid)
    want_seen, want_rejected = carve_reference(masks, rot, trans, sonar, h, **grid)
    ok = decidable(grid_centres(grid["origin"], h, grid["shape"]), rot, trans, sonar, h)
    assert ok.mean() >= 0.98
    assert 0.2 < (want_seen > 0).mean() < 0.95 and 0.1 < (want_rejected > 0).mean() < 0.9  # both outcomes
    assert 0.1 < ((want_seen >= 2) & (want_rejected == 0)).mean() < 0.9
    for what, got, want in (("seen", seen, want_seen), ("rejected", rejected, want_rejected)):
        bad = (got != want) & ok
        assert not bad.any(), f"{what}: {bad.sum()} of {ok.sum()} voxels differ, first {np.flatnonzero(bad)[0]}"

    # explicit centres: the same decisions as the grid, voxel for voxel
    centres = grid_centres(grid["origin"], h, grid["shape"])
    pick = np.random.default_rng(0).choice(len(centres), 5000, replace=False)
    by_points = backend.carve(masks, rot, trans, sonar, h, centres=centres[pick])
    np.testing.assert_array_equal(by_points[0], seen[pick])
    np.testing.assert_array_equal(by_points[1], rejected[pick])


@pytest.mark.parametrize("pair", [
    pytest.param(("warp-cpu", "opencl-cpu"), id="warp-cpu-vs-opencl-cpu"),
    pytest.param(("warp-cuda", "opencl-cpu"), id="warp-cuda-vs-opencl-cpu", marks=pytest.mark.gpu),
    pytest.param(("warp-cpu", "opencl-gpu"), id="warp-cpu-vs-opencl-gpu", marks=pytest.mark.gpu),
])
def test_carve_warp_matches_opencl(backend_for_label, pair):
    warp, opencl = (backend_for_label(label) for label in pair)
    sonar = SONARS["table"]()
    masks, rot, trans, h, grid = carve_scene(9, sonar)
    ok = decidable(grid_centres(grid["origin"], h, grid["shape"]), rot, trans, sonar, h)
    for a, b in zip(warp.carve(masks, rot, trans, sonar, h, **grid), opencl.carve(masks, rot, trans, sonar, h, **grid)):
        assert not ((a != b) & ok).any()


def test_carve_contract(backend):
    sonar = SonarSpec()
    masks, rot, trans, h, grid = carve_scene(2, sonar, n_views=3)
    seen, rejected = backend.carve(masks.astype(np.uint8), rot, trans, sonar, h, **grid)
    for array in (seen, rejected):
        assert array.shape == (27 * 54 * 27,) and array.dtype == np.uint8 and array.flags.c_contiguous
    assert np.all(rejected <= seen) and seen.max() <= 3 and set(np.unique(rejected)) == {0, 1}
    empty = backend.carve(masks, rot, trans, sonar, h, origin=grid["origin"], shape=(4, 0, 2))
    assert empty[0].shape == (0,) and empty[1].dtype == np.uint8
    none = backend.carve(masks[:0], rot[:0], trans[:0], sonar, h, centres=np.zeros((5, 3)))
    assert none[0].tolist() == [0] * 5


@pytest.mark.parametrize("change, error, text", [
    ({"masks": np.zeros((3, 10, 96), bool)}, ValueError, "masks must have shape (V, bins, beams) = (3, 512, 96)"),
    ({"masks": np.zeros((3, 512, 96), np.float32)}, TypeError, "masks must be bool or integer"),
    ({"voxel_size": 0.0}, ValueError, "voxel_size must be a finite number > 0"),
    ({"voxel_size": float("nan")}, ValueError, "voxel_size"),
    ({"shape": (2, 2)}, ValueError, "shape must be three integers >= 0"),
    ({"shape": (2, -1, 2)}, ValueError, "shape must be three integers >= 0"),
    ({"centres": np.zeros((4, 3))}, ValueError, "give either origin and shape (a grid) or centres"),
    ({"origin": None}, ValueError, "give either origin and shape"),
    ({"origin": (0, np.inf, 0)}, ValueError, "origin must be finite"),
    ({"translations": np.zeros((2, 3))}, ValueError, "3 rotations and 2 translations"),
])
def test_carve_rejects_bad_input(backend, change, error, text):
    sonar = SonarSpec()
    call = dict(masks=np.zeros((3, 512, 96), bool), rotations=np.tile(np.eye(3), (3, 1, 1)),
                translations=np.zeros((3, 3)), sonar=sonar, voxel_size=0.01, origin=(0, 1, 0), shape=(2, 2, 2))
    call.update(change)
    with pytest.raises(error) as info:
        backend.carve(**call)
    assert text in str(info.value)


# --- the rule ----------------------------------------------------------------------------------
def sphere_scene(sonar: SonarSpec):
    """A 6 cm sphere 2 m ahead, seen by 8 level views from both sides (four rolls each), with the
    masks its surface points imply (dense samples projected by the float64 rule)."""
    from fsswarp.rig import Rig, View

    views = tuple(View(f"v{k}", position=(0.0, -2.0 if k < 4 else 2.0), heading=0.0 if k < 4 else math.pi,
                       roll=math.radians(-90 + 45 * (k % 4))) for k in range(8))
    rig = Rig(views)
    rot, trans = rig.relative_poses(0.5, 0.0)
    centre = np.array([0.0, 2.0, 0.0])  # the world point (0, 0, -0.5) in the reference frame
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.06)
    sphere.apply_translation(centre)
    points = trimesh.sample.sample_surface_even(sphere, 60_000, seed=1)[0]
    masks = np.zeros((len(views), sonar.bins, sonar.beams), bool)
    for v in range(len(views)):
        rng, theta, phi = to_polar(to_view(points, rot[v], trans[v]))
        b, bb, inside = sonar.beam_bin(theta, rng)
        inside &= sonar.in_elevation(phi)
        highlight = np.zeros((sonar.bins, sonar.beams), bool)
        highlight[bb[inside], b[inside]] = True
        masks[v] = from_highlight(highlight).feasible
    return sphere, masks, rot, trans


def test_carving_is_conservative_and_coarse_to_fine_is_exact(backend):
    """With masks that mark every surface point, every voxel holding part of the sphere is kept;
    coarse-to-fine keeps exactly what a full grid at the finest level keeps, plus a few interior
    voxels it does not test (never fewer)."""
    sonar = SonarSpec()
    sphere, masks, rot, trans = sphere_scene(sonar)
    carved = carve_masks(masks, rot, trans, sonar, resolution=48, backend=backend)
    full = _Carver(backend, masks, rot, trans, sonar, None, 2).grid(carved.origin, carved.voxel_size,
                                                                    carved.occupancy.shape)
    assert not (full & ~carved.occupancy).any()
    assert (carved.occupancy & ~full).sum() <= 0.01 * full.sum()
    # every voxel whose centre lies in the sphere is kept, and the hull is not far larger
    inside = inside_grid(sphere, carved.origin, carved.voxel_size, carved.occupancy.shape)
    assert inside.sum() > 1000 and not (inside & ~carved.occupancy).any()
    assert carved.kept < 3.0 * inside.sum()
    mesh = voxel_mesh(carved, faces=3000)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0 and len(mesh.faces) <= 3000
    with pytest.warns(CarveWarning, match=r"decimation stopped at \d+ faces, above the 4 asked for"):
        coarse = voxel_mesh(carved, faces=4)  # more than 2 voxels from the surface: not reached
    assert coarse.is_watertight and 4 < len(coarse.faces) < len(mesh.faces)
    assert trimesh.boolean.intersection([mesh, sphere], engine="manifold").volume >= 0.99 * sphere.volume


def test_common_region_of_the_sphere_scene():
    sonar = SonarSpec()
    _, _, rot, trans = sphere_scene(sonar)
    lo, hi = common_region(sonar, rot, trans)
    assert lo[1] < 1.5 and hi[1] > 2.5  # the two positions' windows overlap from y = 1 to 3
    assert common_region(sonar, rot, trans, plane=(np.array([0.0, 0.0, 1.0]), -5.0)) is None  # all above water
    away = rot.copy()
    away[3] = rotation_z(math.pi) @ away[3]  # one view looks the other way
    assert common_region(sonar, away, trans) is None


def test_common_region_holds_every_point_that_every_view_sees():
    """The box bounds the points below the plane that all views see, by brute force over random
    points around it (each tested by every view), and exceeds their box by at most two lattice
    steps: for all eight views, and for two rolled views whose frustums' boxes overlap far more
    widely than the views do."""
    sonar = SonarSpec()
    _, _, rot, trans = sphere_scene(sonar)
    plane = (np.array([0.0, 0.0, 1.0]), 0.2)
    for chosen in (slice(None), [1, 6]):
        lo, hi = common_region(sonar, rot[chosen], trans[chosen], plane=plane, samples=32)
        size = hi - lo
        points = np.random.default_rng(7).uniform(lo - 0.5 * size, hi + 0.5 * size, (400_000, 3))
        seen = points @ plane[0] <= plane[1]
        for r, t in zip(rot[chosen], trans[chosen]):
            rng, az, el = to_polar(to_view(points, r, t))
            seen &= sonar.beam_bin(az, rng)[2] & sonar.in_elevation(el)
        inside = points[seen]
        assert len(inside) > 1000 and np.all(inside >= lo) and np.all(inside <= hi)
        steps = 2 * float(size.max()) / 32
        assert np.all(inside.min(axis=0) - lo <= steps) and np.all(hi - inside.max(axis=0) <= steps)


# --- the mesh ----------------------------------------------------------------------------------
def blob_voxels(seed: int, shape=(44, 40, 34), voxel_size: float = 0.0125) -> VoxelCarving:
    """Seeded voxels: five random balls (one through the grid's edge) with a hollow in the first
    (binary_fill_holes fills it) and a lone voxel apart (under 1% of the largest component:
    dropped), at an origin and voxel size that round."""
    rng = np.random.default_rng(seed)
    idx = np.stack(np.meshgrid(*(np.arange(n) for n in shape), indexing="ij"), -1).astype(float)
    occupancy = np.zeros(shape, bool)
    centres = rng.uniform(10, np.array(shape) - 10, (5, 3))
    centres[4, 0] = shape[0] - 3
    radii = rng.uniform(5, 9, 5)
    for centre, radius in zip(centres, radii):
        occupancy |= np.linalg.norm(idx - centre, axis=-1) <= radius
    occupancy &= np.linalg.norm(idx - centres[0], axis=-1) > 0.4 * radii[0]
    occupancy[1, 1, 1] = True
    return VoxelCarving(occupancy=occupancy, origin=rng.uniform(-1, 1, 3), voxel_size=voxel_size,
                        domain=np.zeros((2, 3)), tested=0)


def bisection_tolerances(max_tolerance: float) -> dict[int, float]:
    """Step k (1..256) -> the tolerance that the former bisection (0.5 (low + high) from
    [0, max_tolerance], 8 halvings) tries at k/256 of max_tolerance, every path walked."""
    found = {256: max_tolerance}

    def walk(low, high, lo, hi):
        if high - low > 1:
            middle, value = (low + high) // 2, 0.5 * (lo + hi)
            found[middle] = value
            walk(low, middle, lo, value)
            walk(middle, high, value, hi)

    walk(0, 256, 0.0, max_tolerance)
    return found


def former_surface(voxels: VoxelCarving, smooth: int):
    """The former voxel_mesh up to decimation, written with the libraries' own functions
    (scipy's binary_fill_holes and label, scikit-image's marching cubes at spacing h, trimesh's
    process, invert, is_watertight and filter_taubin)."""
    from scipy import ndimage
    from skimage.measure import marching_cubes

    filled = ndimage.binary_fill_holes(voxels.occupancy)
    labels, _ = ndimage.label(filled, structure=np.ones((3, 3, 3), bool))
    sizes = np.bincount(labels.ravel())[1:]
    solid = np.isin(labels, 1 + np.flatnonzero(sizes >= 0.01 * sizes.max()))
    h = voxels.voxel_size
    vertices, triangles, _, _ = marching_cubes(np.pad(solid, 1).astype(np.float32), level=MC_LEVEL,
                                               spacing=(h, h, h), method="lewiner", allow_degenerate=False)
    mesh = trimesh.Trimesh(vertices + (voxels.origin - h), triangles, process=True)
    if signed_volume(mesh.triangles) < 0:
        mesh.invert()
    assert mesh.is_watertight and mesh.is_winding_consistent
    if smooth:
        trimesh.smoothing.filter_taubin(mesh, iterations=smooth)
    return mesh


def former_decimation(mesh, faces: int, max_tolerance: float):
    """(the former decimation of ``mesh``: manifold3d's simplify at the tolerance that
    bisection of [0, max_tolerance] finds in 8 halvings, the Manifold it simplified)."""
    import manifold3d

    manifold = manifold3d.Manifold(manifold3d.Mesh(vert_properties=np.asarray(mesh.vertices, np.float32),
                                                   tri_verts=np.asarray(mesh.faces, np.uint32)))
    low, high = 0.0, max_tolerance
    best = manifold.simplify(high)
    assert best.num_tri() <= faces
    for _ in range(8):
        middle = 0.5 * (low + high)
        trial = manifold.simplify(middle)
        if trial.num_tri() <= faces:
            high, best = middle, trial
        else:
            low = middle
    out = best.to_mesh()
    return trimesh.Trimesh(np.asarray(out.vert_properties[:, :3], np.float64), out.tri_verts, process=False), manifold


def same_mesh(a, b) -> bool:
    return (a.vertices.dtype == b.vertices.dtype and a.faces.dtype == b.faces.dtype
            and np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_voxel_mesh_is_the_former_pipelines_bit_for_bit(seed):
    """Holes filled, specks dropped, marching cubes, orientation and Taubin smoothing give the
    former pipeline's vertices and faces bit for bit; decimation gives the mesh of a step k
    where the face count reaches the budget (at most it at k, more at k - 1), and where the
    count crosses the budget once (counted at all 256 steps) the former bisection's mesh."""
    voxels = blob_voxels(seed)
    smoothed = former_surface(voxels, 10)
    assert same_mesh(voxel_mesh(voxels, faces=0), smoothed)
    assert same_mesh(voxel_mesh(voxels, smooth=0, faces=0), former_surface(voxels, 0))
    budget = len(smoothed.faces) // 3
    decimated, manifold = former_decimation(smoothed, budget, 2.0 * voxels.voxel_size)
    mesh = voxel_mesh(voxels, faces=budget)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0 and len(mesh.faces) <= budget
    tolerances = bisection_tolerances(2.0 * voxels.voxel_size)
    counts = {k: manifold.simplify(tolerances[k]).num_tri() for k in range(1, 257)}
    counts[0] = len(smoothed.faces)
    crossings = [k for k in range(1, 257) if counts[k] <= budget < counts[k - 1]]
    print(f"seed {seed}: {len(smoothed.faces)} faces -> {len(mesh.faces)} (budget {budget}), crossings {crossings}")
    assert len(mesh.faces) in {counts[k] for k in crossings}
    if len(crossings) == 1:
        assert same_mesh(mesh, decimated)


def test_step_tolerance_is_the_bisections():
    for max_tolerance in (2 * 0.0024093313731700836, 0.1, 3.0e-3 / 7):
        tolerances = bisection_tolerances(max_tolerance)
        assert sorted(tolerances) == list(range(1, 257))
        assert all(_step_tolerance(k, max_tolerance) == tolerances[k] for k in range(1, 257))


def test_fill_holes_and_closed_agree_with_scipy_and_trimesh():
    """_fill_holes is scipy's binary_fill_holes (seeded random solids with cavities, some at
    the grid's edge); _closed is trimesh's is_watertight and is_winding_consistent on closed
    meshes and on ones with a face flipped, removed or doubled."""
    from scipy import ndimage

    rng = np.random.default_rng(5)
    for _ in range(20):
        occupancy = ndimage.binary_dilation(rng.random((17, 13, 11)) < 0.08, iterations=int(rng.integers(1, 3)))
        occupancy &= rng.random(occupancy.shape) > 0.05
        assert np.array_equal(_fill_holes(occupancy), ndimage.binary_fill_holes(occupancy))
    for mesh in (trimesh.creation.icosphere(2), trimesh.creation.box(), trimesh.creation.torus(1.0, 0.3)):
        flipped, removed, doubled = (np.array(mesh.faces) for _ in range(3))
        flipped[3] = flipped[3, ::-1]
        for faces in (mesh.faces, flipped, removed[1:], np.concatenate([doubled, doubled[:2]])):
            other = trimesh.Trimesh(mesh.vertices, faces, process=False)
            assert _closed(np.asarray(faces)) == (other.is_watertight and other.is_winding_consistent)
        assert _closed(np.asarray(mesh.faces)) and not _closed(flipped)


def test_voxel_mesh_of_a_ball_and_a_box():
    """Against the analytic solids that the voxels sample (centres inside): a ball of radius
    17.3 voxels and the 21 x 14 x 9 cubes of a box of voxels. Marching cubes puts the surface
    ½ voxel past the kept centres; Taubin smoothing and decimation move it a little: every
    vertex within 3/4 voxel of the solid's surface, the volume within 2%, the area within 7%
    (marching cubes cuts the box's edges and corners)."""
    h = 0.01
    idx = np.stack(np.meshgrid(*(np.arange(n) for n in (44, 42, 40)), indexing="ij"), -1).astype(float)
    centre, radius = np.array([21.3, 20.6, 19.8]), 17.3
    ball = np.linalg.norm(idx - centre, axis=-1) <= radius
    low, high = np.array([5, 9, 12]), np.array([25, 22, 20])  # kept centres 5..25, 9..22, 12..20
    box = np.all((idx >= low) & (idx <= high), axis=-1)
    origin = np.array([0.3, -1.2, 0.7])
    for occupancy, faces in ((ball, 3000), (box, 600)):
        mesh = voxel_mesh(VoxelCarving(occupancy, origin, h, np.zeros((2, 3)), 0), faces=faces)
        assert mesh.is_watertight and mesh.is_winding_consistent and len(mesh.faces) <= faces
        p = (mesh.vertices - origin) / h  # voxel index units
        if occupancy is ball:
            gap = np.abs(np.linalg.norm(p - centre, axis=-1) - radius)
            volume, area = 4 / 3 * math.pi * radius**3, 4 * math.pi * radius**2
        else:
            lo, hi = low - 0.5, high + 0.5  # the box of the kept voxels' cubes
            inside = np.all((p > lo) & (p < hi), axis=1)
            gap = np.where(inside, np.min(np.concatenate([p - lo, hi - p], axis=1), axis=1),
                           np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0.0), axis=1))
            volume, area = np.prod(hi - lo), 2 * (np.prod(hi - lo) * np.sum(1 / (hi - lo)))
        print(f"{'ball' if occupancy is ball else 'box'}: {len(mesh.faces)} faces, largest gap {gap.max():.2f} "
              f"voxels, volume {mesh.volume / h**3 / volume:.4f}, area {mesh.area / h**2 / area:.4f} x the solid's")
        assert gap.max() <= 0.75
        assert abs(mesh.volume / h**3 / volume - 1) <= 0.02 and abs(mesh.area / h**2 / area - 1) <= 0.07


def ball_voxels(radius: int = 10, side: int = 30) -> VoxelCarving:
    z = np.indices((side,) * 3) - side // 2
    return VoxelCarving(occupancy=(z ** 2).sum(axis=0) < radius ** 2, origin=np.full(3, -0.1), voxel_size=0.01,
                        domain=np.array([[-0.1] * 3, [0.2] * 3]), tested=0)


@pytest.mark.parametrize("workers", ["0", "2"])
def test_a_mesh_job_is_the_voxel_mesh_wherever_it_is_made(monkeypatch, workers):
    """In a mesh process (2) or here when asked for (0): the same vertices and faces bit for bit,
    the warnings that voxel_mesh issued issued here, once, and its errors raised here."""
    monkeypatch.setenv("FSSWARP_MESH_WORKERS", workers)
    voxels = ball_voxels()
    for faces in (400, 40):  # 40: decimation stops above it, with a CarveWarning
        with warnings.catch_warnings(record=True) as expected:
            warnings.simplefilter("always")
            here = voxel_mesh(voxels, smooth=4, faces=faces)
        job = MeshJob(voxels, smooth=4, faces=faces)
        assert (job.future is not None) == (workers == "2")
        with warnings.catch_warnings(record=True) as issued:
            warnings.simplefilter("always")
            made = job.result()
            assert job.result() is made
        assert [(str(w.message), w.category) for w in issued] == [(str(w.message), w.category) for w in expected]
        assert len(issued) == (faces == 40)
        assert made.vertices.dtype == here.vertices.dtype and np.array_equal(made.vertices, here.vertices)
        assert np.array_equal(made.faces, here.faces)
    empty = dataclasses.replace(voxels, occupancy=np.zeros_like(voxels.occupancy))
    with pytest.raises(ValueError, match="Surface level must be within volume data range"):
        MeshJob(empty).result()


def test_mesh_workers_setting(monkeypatch):
    import fsswarp.carving as carving

    monkeypatch.setattr(carving, "_MESH_PROCESSES", {})
    for cpus, expected in ((2, 0), (4, 0), (7, 0), (8, 1), (12, 2), (16, 3), (128, 3)):
        monkeypatch.setattr("fsswarp.system.usable_cpus", lambda cpus=cpus: cpus)
        assert mesh_workers() == expected
    monkeypatch.setenv("FSSWARP_MESH_WORKERS", " 5 ")
    assert mesh_workers() == 5
    monkeypatch.setenv("FSSWARP_MESH_WORKERS", "0")
    assert carving.start_mesh_workers() is None and MeshJob(ball_voxels()).future is None
    for bad in ("-1", "two", "65"):
        monkeypatch.setenv("FSSWARP_MESH_WORKERS", bad)
        with pytest.raises(InputError, match=f"FSSWARP_MESH_WORKERS = '{bad}': must be an integer from 0 to 64"):
            mesh_workers()


def test_meshes_are_made_here_where_processes_cannot_start(monkeypatch):
    """A system without the pool's semaphores (an OSError): one CarveWarning, and every mesh
    job is made in this process."""
    import concurrent.futures

    import fsswarp.carving as carving

    def refuse(*args, **kwargs):
        raise OSError(38, "Function not implemented")

    monkeypatch.setattr(concurrent.futures, "ProcessPoolExecutor", refuse)
    monkeypatch.setattr(carving, "_MESH_PROCESSES", {})
    monkeypatch.setenv("FSSWARP_MESH_WORKERS", "2")
    with pytest.warns(CarveWarning, match=r"mesh processes could not start \(\[Errno 38\] Function not "
                                          r"implemented\); making carvings' meshes in this process"):
        assert carving.start_mesh_workers() is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # warned once
        job = MeshJob(ball_voxels(), faces=400)
    assert job.future is None and np.array_equal(job.result().faces, voxel_mesh(ball_voxels(), faces=400).faces)


def test_a_mesh_process_that_dies_leaves_the_mesh_to_this_process(monkeypatch):
    """A mesh process killed (out of memory, say) while its job waits: one CarveWarning, the
    same mesh made here, and no mesh process from then on."""
    import signal

    import fsswarp.carving as carving

    monkeypatch.setattr(carving, "_MESH_PROCESSES", {})
    monkeypatch.setenv("FSSWARP_MESH_WORKERS", "2")
    processes = carving.start_mesh_workers()
    for child in list(processes.pool._processes.values()):
        os.kill(child.pid, signal.SIGKILL)
    voxels = ball_voxels()
    with pytest.warns(CarveWarning, match="a mesh process ended unexpectedly"):
        made = MeshJob(voxels, faces=400).result()
    assert np.array_equal(made.faces, voxel_mesh(voxels, faces=400).faces)
    assert carving.start_mesh_workers() is None and MeshJob(voxels).future is None


def test_within_keeps_the_kept_voxels_whose_centres_lie_inside_the_mesh():
    """Against trimesh's ray-parity ``contains`` on the voxel centres: a box of kept voxels
    with a hole, held to an icosphere that cuts it (centres within 1e-6 m of the sphere left
    out); the other fields are unchanged and the input is not modified."""
    h = 0.01
    occupancy = np.ones((30, 26, 22), bool)
    occupancy[12:16, 10:14, :] = False  # a shaft through it: stays empty
    origin = np.array([0.1, -0.2, -0.15])
    voxels = VoxelCarving(occupancy.copy(), origin, h, np.array([[0.0, 0, 0], [1, 1, 1]]), 1234)
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.13)
    sphere.apply_translation([0.25, -0.06, -0.04])
    held = within(voxels, sphere)
    centres = origin + h * np.argwhere(np.ones(occupancy.shape, bool))
    inside = sphere.contains(centres).reshape(occupancy.shape)
    clear = np.abs(trimesh.proximity.signed_distance(sphere, centres)).reshape(occupancy.shape) > 1e-6
    assert np.array_equal((held.occupancy == (occupancy & inside))[clear], np.ones(clear.sum(), bool))
    assert 0 < held.kept < voxels.kept and not held.occupancy[12:16, 10:14, :].any()
    assert np.array_equal(voxels.occupancy, occupancy)
    assert held.voxel_size == h and held.tested == 1234 and np.array_equal(held.origin, origin)
    assert np.array_equal(held.domain, voxels.domain)


def test_held_adds_to_the_voxels_inside_the_mesh_those_that_no_view_sees_past_it(backend):
    """Against an oracle written out here: trimesh's first hit along each line from a view's origin
    to a voxel centre, and the window of a linear sonar (nearest beam and bin in the image,
    elevation within W_φ). A box of 2 cm voxels around an icosphere, a view from the front and one
    from the side: the voxels inside the sphere are kept, those behind it from both views or
    outside both windows (the box reaches above and below the side view's aperture) are added,
    no other voxel is; decisions within 0.1 mm of the hiding distance are left out."""
    sonar = SonarSpec()
    h = 0.02
    origin = np.array([-0.24, 1.76, -0.36])
    occupancy = np.ones((25, 25, 37), bool)
    occupancy[:, :, :2] = False  # voxels the carving did not keep are never added
    voxels = VoxelCarving(occupancy.copy(), origin, h, np.array([[0.0, 0, 0], [1, 1, 1]]), 99)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.15)
    sphere.apply_translation([0.013, 2.007, -0.011])
    rotations = np.stack([np.eye(3), rotation_z(math.pi / 2)])  # ahead along +y; from +x, ahead along -x
    translations = np.array([[0.0, 0.0, 0.0], [1.8, 2.0, 0.0]])
    result = held(voxels, sphere, rotations, translations, sonar, backend)

    inside = within(voxels, sphere).occupancy
    outside = np.argwhere(occupancy & ~inside)
    centres = origin + h * outside
    seen = np.zeros(len(centres), bool)
    doubtful = np.zeros(len(centres), bool)
    step = sonar.azimuth_fov / (sonar.beams - 1)
    for rotation, translation in zip(rotations, translations):
        q = (centres - translation) @ rotation
        rng = np.linalg.norm(q, axis=1)
        beam = np.floor((np.arctan2(q[:, 0], q[:, 1]) + sonar.azimuth_fov / 2) / step + 0.5)
        row = np.floor((rng - sonar.range_min) / sonar.range_step + 0.5)
        elevation = np.arctan2(q[:, 2], np.hypot(q[:, 0], q[:, 1]))
        window = (beam >= 0) & (beam < sonar.beams) & (row >= 0) & (row < sonar.bins) & (
            np.abs(elevation) <= sonar.elevation_fov / 2)
        directions = (centres - translation) / rng[:, None]
        hits, rays, _ = sphere.ray.intersects_location(np.repeat(translation[None], len(centres), 0), directions,
                                                       multiple_hits=False)
        first = np.full(len(centres), np.inf)
        first[rays] = np.linalg.norm(hits - translation, axis=1)
        limit = rng - UNSEEN_MARGIN * h
        seen |= window & ~(first < limit)
        doubtful |= window & (np.abs(first - limit) < 1e-4)
    added = np.zeros(occupancy.shape, bool)
    added[tuple(outside[~seen].T)] = True
    expected = inside | added
    clear = np.ones(occupancy.shape, bool)
    clear[tuple(outside[doubtful].T)] = False
    assert np.array_equal(result.occupancy[clear], expected[clear])
    assert not (result.occupancy & ~occupancy).any() and np.array_equal(voxels.occupancy, occupancy)
    behind = outside[~seen] @ [0, 0, 1] * h + origin[2]
    assert np.abs(behind).min() < 0.2 < np.abs(behind).max()  # some added behind the sphere, some above or below
    assert 0 < (~seen).sum() < 0.5 * len(outside) and inside.sum() > 0
    assert result.voxel_size == h and result.tested == 99 and np.array_equal(result.origin, origin)


# --- simulated coral-one -------------------------------------------------------------------------
def truth_volume_kept(carving, truth) -> float:
    """Share of the truth's voxel-centre samples (at the carving's grid) inside kept voxels."""
    inside = inside_grid(truth, carving.origin, carving.voxel_size, carving.occupancy.shape)
    return float((inside & carving.occupancy).sum() / inside.sum())


def test_carving_with_true_masks_keeps_the_true_volume(coral_one):
    """The carving rule with the true feasible masks (object layer > 0) keeps >= 99% of the truth."""
    truth = trimesh.load(coral_one.truth_model_path)
    masks = {v: from_highlight(coral_one.truth_layer(v, "object") > 0).feasible for v in coral_one.rig.names}
    t = coral_one.manifest.truth
    result = carve(coral_one, t.depth, t.tilt, resolution=64, masks=masks, settings=CarveSettings(faces=4000))
    kept = truth_volume_kept(result.voxels, truth)
    print(f"true masks, true D/tilt: {kept:.4f} of the true volume kept")
    assert kept >= 0.99


def test_carve_coral_one(coral_one):
    """Segmented noisy data: with the true (D, tilt) the carved mesh holds >= 95% of the true
    volume; with the measured (D0, tilt0) it loses a little more (printed)."""
    truth = trimesh.load(coral_one.truth_model_path)
    t = coral_one.manifest.truth
    kept = {}
    for label, depth, tilt in (("true", t.depth, t.tilt), ("measured", None, None)):
        result = carve(coral_one, depth, tilt, resolution=64, settings=CarveSettings(faces=4000))
        mesh = result.mesh
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
        kept[label] = trimesh.boolean.intersection([mesh, truth], engine="manifold").volume / truth.volume
        print(f"{label} D/tilt: {kept[label]:.4f} of the true volume inside the carved mesh, carved volume "
              f"{mesh.volume / truth.volume:.2f} x the truth")
    assert kept["true"] >= 0.95
    assert kept["measured"] >= 0.90


def test_a_view_without_highlight_is_left_out(coral_one):
    images = dict(coral_one.images)
    images["Np45"] = np.full_like(images["Np45"], 0.004)
    from fsswarp.dataset import Dataset

    broken = Dataset(coral_one.manifest, images, coral_one.root)
    with pytest.warns(CarveWarning, match="views Np45: no object highlight"):
        result = carve(broken, resolution=32, settings=CarveSettings(smooth=0, faces=0))
    assert "Np45" not in result.views and len(result.views) == 15


def test_carve_bad_input(coral_one):
    t = coral_one.manifest.truth
    with pytest.raises(InputError, match="--box.*outside the region"):
        carve(coral_one, t.depth, t.tilt, resolution=32, box=[[1, 1, 1], [2, 2, 2]])
    with pytest.raises(InputError, match="--box.*x0 < x1"):
        carve(coral_one, t.depth, t.tilt, resolution=32, box=[[0, 2, 0], [-1, 3, 1]])
    with pytest.raises(InputError, match="--resolution"):
        carve(coral_one, resolution=4)
    with pytest.raises(InputError, match="--depth"):
        carve(coral_one, -0.4)
    with pytest.raises(InputError, match="at least 2 views"):
        carve(coral_one, views=["S0"])
    empty = {v: np.zeros((512, 96), bool) for v in coral_one.rig.names}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CarveWarning)
        with pytest.raises(InputError, match="views"):
            carve(coral_one, masks=empty)
    # views that see nothing in common: every N view turned to look away from the target
    from dataclasses import replace

    from fsswarp.dataset import Dataset
    from fsswarp.rig import Rig

    rig = coral_one.rig
    turned = Rig(tuple(replace(v, heading=0.0) if v.name.startswith("N") else v for v in rig.views), rig.reference)
    away = Dataset(replace(coral_one.manifest, rig=turned), coral_one.images, coral_one.root)
    with pytest.raises(InputError, match="no region in common"):
        carve(away, resolution=32)
    # everything carved away: masks that are feasible only far from the object
    far = {v: np.zeros((512, 96), bool) for v in coral_one.rig.names}
    for m in far.values():
        m[500:, :5] = True
    with pytest.raises(InputError, match="every voxel was carved away"):
        carve(coral_one, masks=far, resolution=32)


def test_surface_clip_removes_the_mirror_world(coral_one):
    """Without the sea-surface rule a mirror copy of the object survives above the surface."""
    t = coral_one.manifest.truth
    normal, offset = surface_in_reference(coral_one.rig, t.depth, t.tilt)
    result = carve(coral_one, t.depth, t.tilt, resolution=32, settings=CarveSettings(surface_margin=1.0, faces=0,
                                                                                    smooth=0))
    above = result.voxels.centres() @ normal > offset + 0.02
    clipped = carve(coral_one, t.depth, t.tilt, resolution=32, settings=CarveSettings(faces=0, smooth=0))
    print(f"voxels above the surface without the rule: {above.mean():.2f}")
    assert above.mean() > 0.2
    assert not (clipped.voxels.centres() @ normal > offset + clipped.voxels.voxel_size).any()


# --- the command line ------------------------------------------------------------------------------
def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "fsswarp", "--backend", "opencl", *args], capture_output=True,
                          text=True)


def test_cli_carve(coral_one, tmp_path):
    out = tmp_path / "carved"
    done = run_cli("carve", str(coral_one.root), "--out", str(out), "--resolution", "48", "--faces", "3000")
    assert done.returncode == 0, done.stderr
    assert "E_V" in done.stdout and "wrote" in done.stdout
    assert sorted(p.name for p in out.iterdir()) == ["carve.json", "carve.png", "carved.ply"]
    record = json.loads((out / "carve.json").read_text())
    assert record["depth_tilt_source"] == "measured" and record["depth_m"] == coral_one.manifest.surface.depth
    assert record["voxels_kept"] > 0 and len(record["grid"]["shape"]) == 3 and record["mesh"]["watertight"]
    assert set(record["timings_s"]) >= {"segment_s", "carve_s", "mesh_s", "metrics_s"}
    assert 0 < record["metrics"]["E_V"] < 1 and record["metrics"]["truth_volume_kept"] > 0.9
    mesh = trimesh.load(out / "carved.ply")
    assert mesh.is_watertight and len(mesh.faces) <= 3000

    quiet = subprocess.run([sys.executable, "-m", "fsswarp", "--backend", "opencl", "--quiet", "carve",
                            str(coral_one.root), "--out", str(out), "--resolution", "32", "--tilt", "10.3",
                            "--depth", "0.43"], capture_output=True, text=True)
    assert quiet.returncode == 0 and quiet.stdout == ""
    assert json.loads((out / "carve.json").read_text())["depth_tilt_source"] == "given"


def test_cli_carve_with_a_hot_pixel_in_every_view(coral_one, tmp_path):
    """A pixel at 1000 times its view's peak, in the background of every view, is clipped
    (fsswarp.segment step 0): the carving keeps the same voxels as without it. Before, every
    view lost its object and the carving failed."""
    import shutil

    import tifffile

    hot = tmp_path / "hot"
    shutil.copytree(coral_one.root, hot)
    for name in coral_one.rig.names:
        image = coral_one.images[name].copy()
        image[30, 5] = 1000 * image.max()
        tifffile.imwrite(hot / "images" / f"{name}.tiff", image)
    records = []
    for folder in (coral_one.root, hot):
        done = run_cli("--quiet", "carve", str(folder), "--out", str(tmp_path / folder.name / "out"), "--resolution", "32")
        assert done.returncode == 0, done.stderr
        records.append(json.loads((tmp_path / folder.name / "out" / "carve.json").read_text()))
    assert records[1]["voxels_kept"] == records[0]["voxels_kept"] > 0
    assert records[1]["mesh"] == records[0]["mesh"]


def test_cli_carve_bad_input_writes_nothing(coral_one, tmp_path):
    out = tmp_path / "nothing"
    done = run_cli("carve", str(coral_one.root), "--out", str(out), "--box", "1", "1", "1", "2", "2", "2")
    assert done.returncode == 2
    assert done.stderr.startswith("fsswarp: error: --box = ") and len(done.stderr.strip().splitlines()) == 1
    assert not out.exists()
    done = run_cli("carve", str(tmp_path / "missing"), "--out", str(out))
    assert done.returncode == 2 and "no such folder" in done.stderr and not out.exists()


def test_summed_area_tables_count_the_masks_and_are_remembered_by_their_content():
    """Each table entry counts the nonzero pixels above and left of it (brute force); equal
    masks, even in another array, give the one read-only table; other masks their own."""
    from fsswarp.backends.base import _summed_area

    class Sonar:
        bins, beams = 7, 5

    rng = np.random.default_rng(3)
    masks = (rng.random((2, 7, 5)) > 0.4).astype(np.uint8)
    table = _summed_area(masks, Sonar)
    want = np.zeros((2, 8, 6), np.int64)
    for v, B, b in np.ndindex(want.shape):
        want[v, B, b] = np.count_nonzero(masks[v, :B, :b])
    np.testing.assert_array_equal(table, want)
    assert _summed_area(masks.copy() * 3, Sonar) is table and not table.flags.writeable
    other = masks.copy()
    other[1, 6, 4] ^= 1
    assert _summed_area(other, Sonar) is not table and _summed_area(other, Sonar)[1, 7, 5] != table[1, 7, 5]
