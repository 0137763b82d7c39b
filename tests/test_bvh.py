"""The host BVH (fsswarp/backends/bvh.py) and the OpenCL ray caster (kernels/raycast.cl)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from fsswarp.backends.bvh import LEAF_SIZE, build_bvh, decode_leaf, triangle_bounds

from conftest import backend_for


def _check_structure(vertices, faces):
    bvh = build_bvh(np.asarray(vertices, np.float32), np.asarray(faces, np.int32))
    nf = faces.shape[0]
    assert bvh.node_bounds.shape == (bvh.n_nodes, 2, 2, 4) and bvh.node_bounds.dtype == np.float32
    assert bvh.node_children.shape == (bvh.n_nodes, 2) and bvh.node_children.dtype == np.int32
    assert bvh.triangles.shape == (nf, 9) and bvh.face_index.shape == (nf,)
    assert np.array_equal(np.sort(bvh.face_index), np.arange(nf))
    tri = bvh.triangles.reshape(nf, 3, 3)
    assert np.array_equal(tri, np.asarray(vertices, np.float32)[faces[bvh.face_index]])
    ch = bvh.node_children.astype(np.int64)
    box_lo = bvh.node_bounds[:, :, 0, :3]
    box_hi = bvh.node_bounds[:, :, 1, :3]
    leaf = ch < 0
    first, count = decode_leaf(ch[leaf])
    assert count.max() <= LEAF_SIZE
    # every triangle in exactly one leaf
    covered = np.zeros(nf, np.int64)
    for f, c in zip(first, count):
        covered[f:f + c] += 1
    assert np.all(covered == 1)
    # every inner node referenced exactly once, never the root, and never upward
    inner = ch[~leaf]
    assert np.array_equal(np.sort(inner), np.arange(1, bvh.n_nodes))
    parent = np.broadcast_to(np.arange(bvh.n_nodes)[:, None], ch.shape)[~leaf]
    assert np.all(inner > parent)
    # a child box is the tightest box of the child's node boxes or of its leaf triangles
    child_lo = box_lo[inner].min(axis=1)
    child_hi = box_hi[inner].max(axis=1)
    assert np.array_equal(box_lo[~leaf], child_lo) and np.array_equal(box_hi[~leaf], child_hi)
    tlo, thi = tri.min(axis=1), tri.max(axis=1)
    for lo, hi, f, c in zip(box_lo[leaf], box_hi[leaf], first, count):
        if c:
            assert np.array_equal(lo, tlo[f:f + c].min(axis=0)) and np.array_equal(hi, thi[f:f + c].max(axis=0))
    return bvh


@pytest.mark.parametrize("subdivisions", [0, 3])
def test_bvh_structure_icosphere(subdivisions):
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    _check_structure(m.vertices, m.faces)


def test_triangle_bounds_are_the_corners_extremes():
    rng = np.random.default_rng(3)
    vertices = rng.normal(size=(50, 3)).astype(np.float32)
    faces = rng.integers(0, 50, (200, 3))
    faces[:5] = faces[:5, :1]  # degenerate triangles: a point
    lo, hi = triangle_bounds(vertices, faces)
    tri = vertices[faces]
    assert np.array_equal(lo, tri.min(axis=1)) and np.array_equal(hi, tri.max(axis=1))


def test_bvh_structure_small_and_degenerate():
    rng = np.random.default_rng(1)
    one = _check_structure(np.eye(3), np.array([[0, 1, 2]]))
    assert one.n_nodes == 1
    # degenerate triangles: repeated vertices, all centroids equal, collinear points
    v = np.concatenate([np.zeros((3, 3)), rng.normal(size=(30, 3))])
    faces = np.concatenate([np.zeros((50, 3), int), rng.integers(0, 33, size=(200, 3))])
    _check_structure(v, faces)
    _check_structure(np.zeros((3, 3)), np.zeros((9, 3), int))


def test_bvh_structure_random_soup():
    rng = np.random.default_rng(2)
    v = rng.uniform(-5, 5, size=(3000, 3))
    _check_structure(v, np.arange(3000).reshape(-1, 3))


@pytest.fixture(scope="module")
def opencl():
    return backend_for("opencl-cpu")


def _embree_or_trimesh(mesh):
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector
        return RayMeshIntersector(mesh)
    except Exception:  # noqa: BLE001 - embree missing: trimesh's own intersector
        return trimesh.ray.ray_triangle.RayMeshIntersector(mesh)


def _compare(backend, mesh, org, d):
    handle = backend.load_mesh(mesh.vertices, mesh.faces)
    dist, face = backend.cast_rays(handle, org, d)
    loc, ray_idx, _ = _embree_or_trimesh(mesh).intersects_location(org, d, multiple_hits=False)
    ref = np.full(len(org), np.inf)
    ref[ray_idx] = np.linalg.norm(loc - org[ray_idx], axis=1)
    assert np.array_equal(np.isfinite(dist), np.isfinite(ref))
    assert np.array_equal(face >= 0, np.isfinite(dist))
    hit = np.isfinite(ref)
    np.testing.assert_allclose(dist[hit], ref[hit], atol=1e-4, rtol=0)
    # the reported face lies at the reported distance
    tri = mesh.triangles[face[hit]]
    p = org[hit] + dist[hit, None] * d[hit]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    assert np.abs(np.einsum("ij,ij->i", p - tri[:, 0], nrm)).max() < 1e-4
    return dist, face


def _unit(x):
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def test_cast_rays_icosphere_against_reference(opencl):
    rng = np.random.default_rng(3)
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=1.5)
    org = _unit(rng.normal(size=(20000, 3))) * 4.0
    d = _unit(rng.uniform(-1.6, 1.6, size=(20000, 3)) - org)
    dist, _ = _compare(opencl, mesh, org, d)
    assert 0.3 < np.isfinite(dist).mean() < 0.95


def test_cast_rays_random_rays_and_soup(opencl):
    rng = np.random.default_rng(4)
    mesh = trimesh.Trimesh(rng.uniform(-2, 2, size=(1500, 3)), np.arange(1500).reshape(-1, 3),
                           process=False)
    org = rng.uniform(-3, 3, size=(5000, 3))
    d = _unit(rng.normal(size=(5000, 3)))
    _compare(opencl, mesh, org, d)


def test_cast_rays_max_distance_and_one_triangle(opencl):
    handle = opencl.load_mesh(np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1]]), np.array([[0, 1, 2]]))
    org = np.zeros((3, 3))
    d = np.array([[0.1, 0.1, 1.0], [0.0, 0.0, -1.0], [0.1, 0.1, 1.0]])
    d = _unit(d)
    dist, face = opencl.cast_rays(handle, org, d)
    assert face.tolist() == [0, -1, 0] and np.isinf(dist[1])
    dist, face = opencl.cast_rays(handle, org[:1], d[:1], max_distance=0.5)
    assert face.tolist() == [-1] and np.isinf(dist[0])


@pytest.mark.parametrize("subdivisions", [2, 4])
def test_cast_rays_watertight_at_vertices_and_edges(opencl, subdivisions):
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions)
    v32 = mesh.vertices.astype(np.float32).astype(np.float64)
    edges = mesh.edges_unique
    targets = np.concatenate([v32, 0.5 * (v32[edges[:, 0]] + v32[edges[:, 1]])])
    rng = np.random.default_rng(5)
    # from outside, toward each target: along the outward axis, and obliquely
    org_axis = 3.0 * _unit(targets)
    org_oblique = targets + 3.0 * _unit(_unit(targets) + 0.6 * _unit(rng.normal(size=targets.shape)))
    org = np.concatenate([org_axis, org_oblique]).astype(np.float32).astype(np.float64)
    tgt = np.concatenate([targets, targets])
    d = _unit(tgt - org)
    handle = opencl.load_mesh(mesh.vertices, mesh.faces)
    dist, face = opencl.cast_rays(handle, org, d)
    assert np.all(face >= 0), f"{np.sum(face < 0)} of {len(face)} rays leaked"
    np.testing.assert_allclose(dist, np.linalg.norm(tgt - org, axis=1), atol=1e-4)
    # and from inside, out through the same points: none escapes either
    dist, face = opencl.cast_rays(handle, np.zeros_like(tgt), _unit(tgt))
    assert np.all(face >= 0)
