"""Exact point-to-surface distances (Backend.load_mesh(..., exact=True) / surface_distances)
against brute force (every triangle, ``fsswarp.metrics._point_triangle_distance``) and against
NumPy's k-d tree search (``fsswarp.metrics.point_mesh_distance``), on every backend; Warp and
OpenCL against each other."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from fsswarp.backends import get_backend
from fsswarp.errors import InputError
from fsswarp.metrics import _point_triangle_distance, point_mesh_distance, surface_points
from fsswarp.targets import builtin_mesh

#: Relative agreement with the float64 oracles: the same closest-point rules, their dot
#: products summed in another order (a point 1 mm from a face: ~1e-14 m apart).
RTOL = 1e-9
#: Where the meshes sit (m): a scene's standoff, so coordinates carry a scene's rounding.
PLACE = np.array([0.15, 2.0, -0.1])


def brute_force(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N,) the least distance from each point to every triangle, one by one."""
    tri = vertices[faces]
    return np.array([_point_triangle_distance(np.repeat(p[None], len(tri), axis=0), tri).min() for p in points])


def awkward_mesh():
    """A coarse sphere with a fan of slivers, a triangle folded onto a line, one with two
    corners in one place and one whose corners coincide (the degenerate ones' distances are
    their nearest corner's), placed."""
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=0.05)
    vertices = np.vstack([sphere.vertices, [[0.07, 0, 0], [0.08, 0, 0], [0.09, 0, 0], [0.07, 0.02, 1e-7],
                                            [0.07, -0.03, 0], [0.09, -0.03, 0.01]]])
    n = len(sphere.vertices)
    faces = np.vstack([sphere.faces, [[n, n + 1, n + 2], [n, n, n], [n, n + 1, n + 3], [n + 1, n + 2, n + 3],
                                     [n + 4, n + 4, n + 5]]])  # the last one's alone: no neighbour stands in
    return vertices + PLACE, faces


def test_distances_are_brute_force_s(backend):
    """Points on, near, inside and far (0.5 m) from an awkward mesh, and at its corners."""
    vertices, faces = awkward_mesh()
    rng = np.random.default_rng(3)
    points = np.vstack([PLACE + rng.normal(0, 0.04, (300, 3)), PLACE + rng.normal(0, 0.5, (50, 3)), vertices,
                        vertices[faces].mean(axis=1), vertices[-1] + rng.normal(0, 0.003, (20, 3))])
    found = backend.surface_distances(backend.load_mesh(vertices, faces, exact=True), points)
    assert found.dtype == np.float64 and found.shape == (len(points),)
    np.testing.assert_allclose(found, brute_force(points, vertices, faces), rtol=RTOL, atol=1e-15)


@pytest.mark.parametrize("name", ["coral-one", "table"])
def test_distances_are_the_k_d_tree_search_s(backend, name):
    """20,000 points sampled on a built-in target, then moved up to 5 mm, against the target
    itself: the metric's own NumPy search."""
    mesh = builtin_mesh(name)
    mesh.vertices = mesh.vertices + PLACE
    points = surface_points(mesh, 20_000, [4, 0]) + np.random.default_rng(4).uniform(-0.005, 0.005, (20_000, 3))
    found = backend.surface_distances(backend.load_mesh(mesh.vertices, mesh.faces, exact=True), points)
    np.testing.assert_allclose(found, point_mesh_distance(points, mesh), rtol=RTOL, atol=1e-15)


def test_surface_distances_validates(backend):
    vertices, faces = awkward_mesh()
    handle = backend.load_mesh(vertices, faces)
    with pytest.raises(ValueError, match="exact=True"):
        backend.surface_distances(handle, np.zeros((2, 3)))
    exact = backend.load_mesh(vertices, faces, exact=True)
    assert backend.surface_distances(exact, np.zeros((0, 3))).shape == (0,)
    with pytest.raises(ValueError, match="points"):
        backend.surface_distances(exact, np.zeros((2, 2)))
    with pytest.raises(ValueError, match="points"):
        backend.surface_distances(exact, [[np.nan, 0, 0]])


def test_exact_meshes_need_float64(backend, monkeypatch):
    monkeypatch.setattr(backend, "has_float64", False)
    vertices, faces = awkward_mesh()
    with pytest.raises(ValueError, match="float64"):
        backend.load_mesh(vertices, faces, exact=True)


def test_warp_and_opencl_agree():
    """The two searches (a growing cube on Warp, nearer child first on OpenCL) on coral-one's
    surface points moved up to 2 cm: the same minimum of the same rules."""
    try:
        warp, opencl = get_backend("warp", "cpu"), get_backend("opencl")
    except InputError as err:  # a missing backend skips
        pytest.skip(f"needs both Warp and OpenCL: {err}")
    mesh = builtin_mesh("coral-one")
    points = surface_points(mesh, 5_000, [5, 0]) + np.random.default_rng(5).uniform(-0.02, 0.02, (5_000, 3))
    a = warp.surface_distances(warp.load_mesh(mesh.vertices, mesh.faces, exact=True), points)
    b = opencl.surface_distances(opencl.load_mesh(mesh.vertices, mesh.faces, exact=True), points)
    np.testing.assert_allclose(a, b, rtol=RTOL, atol=1e-15)
