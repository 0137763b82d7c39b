"""Metrics on known answers: E_V of offset spheres (the lens volume) and boxes, by mesh booleans
and on the voxel grid; Chamfer-L1 and F-score of concentric spheres; exact point-to-mesh
distances; μ_m and E_mu (eq. 6) and the image metrics (eq. 8–11) in closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from fsswarp.errors import InputError
from fsswarp.metrics import (average_contour_error, average_intensity_error, chamfer, combine, compare, compare_meshes,
                             default_tau, fscore, image_error, inside_grid, intensity_error, normalized_errors, point_mesh_distance,
                             pose_error, view_errors, volume_error, volumes)
from fsswarp.surface import mirror_vectors

R = 0.1


def sphere(radius: float = R, offset=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    mesh.apply_translation(offset)
    return mesh


def lens_error(distance: float) -> float:
    """E_V of two spheres of radius R whose centres lie ``distance`` apart (closed form)."""
    lens = math.pi * (4 * R + distance) * (2 * R - distance) ** 2 / 12 if distance < 2 * R else 0.0
    ball = 4.0 / 3.0 * math.pi * R**3
    return (2 * ball - 2 * lens) / (2 * ball - lens)


@pytest.mark.parametrize("distance", [0.0, 0.03, 0.1, 0.17, 0.25])
@pytest.mark.parametrize("method", ["boolean", "voxels"])
def test_volume_error_of_offset_spheres(distance, method):
    a, b = sphere(), sphere(offset=(distance, 0.0, 0.0))
    va, vb, vab, used = volumes(a, b, method=method)
    assert used == method
    error = (va + vb - 2 * vab) / (va + vb - vab)
    assert error == pytest.approx(lens_error(distance), abs=0.01)
    if method == "boolean":
        assert volume_error(a, b) == pytest.approx(error)


@pytest.mark.parametrize("method", ["boolean", "voxels"])
def test_volume_error_of_offset_boxes(method):
    a = trimesh.creation.box([0.2, 0.1, 0.05])
    b = trimesh.creation.box([0.2, 0.1, 0.05])
    b.apply_translation([0.05, 0.02, 0.01])
    common = 0.15 * 0.08 * 0.04
    single = 0.2 * 0.1 * 0.05
    va, vb, vab, _ = volumes(a, b, method=method)
    assert (va + vb - 2 * vab) / (va + vb - vab) == pytest.approx((2 * single - 2 * common) / (2 * single - common),
                                                                  rel=0.01)


def test_volumes_of_open_meshes_fall_back_to_voxels():
    a = sphere()
    holed = sphere()
    holed.update_faces(np.arange(len(holed.faces)) != 0)  # one triangle missing: not a volume
    assert not holed.is_volume
    va, vb, vab, used = volumes(a, holed)
    assert used == "voxels" and vb == pytest.approx(va, rel=0.01) and vab == pytest.approx(va, rel=0.01)
    with pytest.raises(InputError, match="method"):
        volumes(a, holed, method="boolean")


def test_inside_grid_handles_either_orientation():
    inward = sphere()
    inward.invert()
    step = 0.01
    inside = inside_grid(inward, (-0.105, -0.105, -0.105), step, (22, 22, 22))
    assert inside.sum() * step**3 == pytest.approx(4 / 3 * math.pi * R**3, rel=0.03)


def test_chamfer_and_fscore_of_concentric_spheres():
    delta = 0.005
    a, b = sphere(), sphere(R + delta)
    assert chamfer(a, b) == pytest.approx(delta, rel=0.02)
    assert chamfer(a, a) < 1e-4
    f, precision, recall, tau = fscore(a, b, tau=1.2 * delta)
    assert (f, precision, recall, tau) == (1.0, 1.0, 1.0, 1.2 * delta)
    assert fscore(a, b, tau=0.8 * delta)[0] == 0.0
    assert default_tau(a) == pytest.approx(0.02 * math.sqrt(3) * 2 * R, rel=1e-3)


def test_compare_reports_every_metric():
    a, b = sphere(), sphere(offset=(0.03, 0.0, 0.0))
    report = compare(a, b, samples=2000)
    assert report["E_V"] == pytest.approx(lens_error(0.03), abs=0.01)
    assert report["truth_volume_kept"] == pytest.approx(report["common_volume_m3"] / report["truth_volume_m3"])
    assert report["volume_method"] == "boolean" and 0 < report["fscore"] < 1 and report["chamfer_m"] > 0
    assert compare(a, b, samples=2000) == report  # seeded


def test_a_worker_s_compare_is_the_compare():
    """``compare_meshes`` of the meshes' arrays (a truth worker's job), combined, is
    ``compare``'s dict bit for bit; without distances it gives the volumes alone."""
    a, b = sphere(), sphere(R + 0.004, offset=(0.01, 0.0, 0.0))
    arrays = [(np.asarray(m.vertices), np.asarray(m.faces)) for m in (a, b)]
    volume, distances = compare_meshes(*arrays, distances=True)
    assert combine(b, volume, *distances) == compare(a, b)
    assert compare_meshes(*arrays, distances=False) == (volume, None)
    assert combine(b, volume, distances[0] + 1e-3, distances[1]) != compare(a, b)  # both arrays count


def test_point_mesh_distance_is_exact():
    rng = np.random.default_rng(2)
    mesh = trimesh.creation.box([0.2, 0.1, 0.05])
    mesh = mesh.subdivide()  # triangles of two sizes
    points = rng.uniform(-0.3, 0.3, (500, 3))
    _, want, _ = trimesh.proximity.closest_point(mesh, points)
    np.testing.assert_allclose(point_mesh_distance(points, mesh), want, atol=1e-9)


def test_point_mesh_distance_is_exact_over_many_chunks_and_mixed_triangles():
    """Fine and coarse triangles together (the coarse ones get a site grid), points inside,
    near and far, split over many chunks of the thread pool."""
    rng = np.random.default_rng(5)
    fine = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    coarse = trimesh.creation.box([0.3, 0.02, 0.2])
    coarse.apply_translation([0.0, 0.12, 0.0])
    mesh = trimesh.util.concatenate([fine, coarse])
    points = np.concatenate([rng.uniform(-0.25, 0.25, (600, 3)), rng.normal(0.0, 0.03, (600, 3))])
    want = np.array([_brute_distance(p, mesh.triangles) for p in points])  # trimesh's is off inside the sphere
    got = point_mesh_distance(points, mesh, chunk=97)
    np.testing.assert_allclose(got, want, atol=1e-9)
    np.testing.assert_array_equal(point_mesh_distance(points, mesh, chunk=len(points)), got)


def _brute_distance(p, triangles) -> float:
    """Distance from p to the nearest of the triangles (T, 3, 3): the nearest of each triangle's
    three edges and, where p's projection falls inside it, its plane."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    squared = np.full(len(triangles), np.inf)
    for u, v in ((a, b), (b, c), (c, a)):
        e = v - u
        t = np.clip(np.sum((p - u) * e, axis=1) / np.sum(e * e, axis=1), 0.0, 1.0)
        squared = np.minimum(squared, np.sum((p - u - t[:, None] * e) ** 2, axis=1))
    n = np.cross(b - a, c - a)
    inside = np.all([np.sum(np.cross(v - u, p - u) * n, axis=1) >= 0 for u, v in ((a, b), (b, c), (c, a))], axis=0)
    plane = np.sum((p - a) * n, axis=1) ** 2 / np.sum(n * n, axis=1)
    return float(np.sqrt(np.where(inside, np.minimum(plane, squared), squared).min()))


def test_metrics_reject_empty_meshes():
    with pytest.raises(InputError, match="no triangles"):
        chamfer(sphere(), trimesh.Trimesh())


def test_view_errors_closed_form():
    # 3 patches, 2 views, surface normal +Z (H flips z).
    vo = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 2.0], [1.0, 0.0, 0.0]])
    vm = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 1.0], [np.nan, np.nan, np.nan]])
    object_frontal = np.array([[True, True, False], [False, True, True]])
    mirror_frontal = np.array([[True, True, False], [False, False, False]])
    mu = view_errors(vo, object_frontal, mirror_motion=vm, mirror_frontal=mirror_frontal,
                     normal=[0.0, 0.0, 1.0])
    # view 0: object (5 + 2)/2; mirror |H vo - vm| = 0 and |(0,0,-2) - (0,0,1)| = 3 -> 3/2
    # view 1: object (2 + 1)/2; no distinct mirror -> 0
    np.testing.assert_allclose(mu, [3.5 + 1.5, 1.5])
    assert float(pose_error(vo, object_frontal, mirror_motion=vm, mirror_frontal=mirror_frontal,
                            normal=[0.0, 0.0, 1.0])) == pytest.approx(3.25)
    # object term alone
    np.testing.assert_allclose(view_errors(vo, object_frontal), [3.5, 1.5])


def test_same_frontal_sets_read_as_eq6():
    # With one frontal set for both terms, μ^m = (1/Z_m) Σ_z (‖V^O‖ + ‖H V^O - Ṽ^M‖).
    rng = np.random.default_rng(2)
    vo, vm = rng.normal(size=(7, 3)), rng.normal(size=(7, 3))
    n = np.array([0.0, math.sin(0.2), math.cos(0.2)])
    frontal = rng.random((4, 7)) < 0.6
    frontal[:, 0] = True
    mu = view_errors(vo, frontal, mirror_motion=vm, mirror_frontal=frontal, normal=n)
    terms = np.linalg.norm(vo, axis=1) + np.linalg.norm(mirror_vectors(vo, n) - vm, axis=1)
    np.testing.assert_allclose(mu, (frontal * terms).sum(axis=1) / frontal.sum(axis=1), rtol=1e-12)


def test_pose_error_skips_views_without_patches_and_batches():
    vo = np.array([[[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]], [[0.0, 0.0, 0.0], [0.0, 0.0, 4.0]]])  # (G=2, K=2, 3)
    frontal = np.array([[True, False], [False, False], [True, True]])  # view 1 sees nothing
    mu = view_errors(vo, frontal)
    assert mu.shape == (2, 3) and np.isnan(mu[:, 1]).all()
    np.testing.assert_allclose(pose_error(vo, frontal), [(1.0 + 1.5) / 2, (0.0 + 2.0) / 2])
    assert np.isnan(pose_error(vo, np.zeros((3, 2), dtype=bool))).all()


def test_pose_error_rejects_bad_inputs():
    vo = np.zeros((3, 3))
    with pytest.raises(ValueError, match="go together"):
        view_errors(vo, np.ones((2, 3), dtype=bool), mirror_motion=vo)
    with pytest.raises(ValueError, match="bool"):
        view_errors(vo, np.ones((2, 3)))
    with pytest.raises(ValueError, match="object_frontal"):
        view_errors(vo, np.ones((2, 4), dtype=bool))
    bad = vo.copy()
    bad[1, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        view_errors(bad, np.ones((2, 3), dtype=bool))
    # a NaN motion of a patch no view uses is fine
    assert view_errors(bad, np.array([[True, False, True]])).tolist() == [0.0]


# --- image metrics (eq. 8–11) ----------------------------------------------------------------------

def test_intensity_errors_closed_form():
    synthetic = np.array([[[1.0, 2.0], [3.0, 4.0]], [[0.0, 0.0], [0.0, 0.0]], [[5.0, 5.0], [5.0, 5.0]]])
    data = np.array([[[2.0, 2.0], [0.0, np.nan]], [[1.0, 1.0], [1.0, 1.0]], [[5.0, 5.0], [5.0, 5.0]]])
    regions = np.array([[[True, True], [True, False]], [[False, False], [False, False]],
                        [[True, False], [False, True]]])
    ie = intensity_error(synthetic, data, regions)
    # view 0: (1 + 0 + 3)/3; view 1: empty Ω -> NaN; view 2: 0
    np.testing.assert_allclose(ie, [4.0 / 3.0, np.nan, 0.0])
    assert average_intensity_error(synthetic, data, regions) == pytest.approx(2.0 / 3.0)
    assert float(intensity_error(synthetic[0], data[0], regions[0])) == pytest.approx(4.0 / 3.0)
    with pytest.raises(ValueError, match="non-finite"):
        intensity_error(synthetic, data, np.ones_like(regions))
    with pytest.raises(ValueError, match="bool"):
        intensity_error(synthetic, data, regions.astype(float))
    with pytest.raises(ValueError, match="one shape"):
        intensity_error(synthetic, data[:2], regions)


def test_contour_and_image_errors_closed_form():
    assert average_contour_error([1.0, 2.0, np.nan, 3.0]) == pytest.approx(2.0)  # eq. 9
    assert math.isnan(average_contour_error([np.nan]))
    assert normalized_errors(2.0, 3.0, 4.0, 12.0) == pytest.approx((0.5, 0.25))  # eq. 10
    assert image_error(2.0, 3.0, 4.0, 12.0) == pytest.approx(0.375)  # eq. 11
    assert image_error(4.0, 12.0, 4.0, 12.0) == 1.0  # iteration 0
    with pytest.raises(ValueError, match="> 0"):
        image_error(1.0, 1.0, 0.0, 1.0)
    with pytest.raises(ValueError, match=">= 0"):
        normalized_errors(-1.0, 1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="1-D"):
        average_contour_error([[1.0]])


def test_image_error_is_the_mean_of_the_two_ratios_and_passes_nan_on():
    """E_I as the reconstruction loop records it: ``0.5 * (AIE / AIE⁰ + ACE / ACE⁰)`` to the bit;
    an error without a value (NaN) gives NaN."""
    rng = np.random.default_rng(3)
    for aie, ace, aie0, ace0 in (rng.random((50, 4)) + 0.01).tolist():
        assert image_error(aie, ace, aie0, ace0) == 0.5 * (aie / aie0 + ace / ace0)
    assert math.isnan(image_error(math.nan, 1.0, 1.0, 1.0)) and math.isnan(image_error(1.0, 1.0, math.nan, 1.0))
