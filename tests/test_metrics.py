"""Model-accuracy metrics on shapes with known answers: E_V of offset spheres (the lens volume)
and boxes, by mesh booleans and on the voxel grid; Chamfer-L1 and F-score of concentric
spheres; exact point-to-mesh distances."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from fsswarp.errors import InputError
from fsswarp.metrics import (chamfer, compare, default_tau, fscore, inside_grid, point_mesh_distance, volume_error,
                             volumes)

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
