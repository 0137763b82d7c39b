"""Built-in target meshes (fsswarp.targets), checked against independent geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from trimesh.ray.ray_triangle import RayMeshIntersector

from fsswarp.errors import InputError
from fsswarp.targets import (BUILTIN_TARGETS, CORAL_ONE, CORAL_TWO, LEG_OVERLAP_M, builtin_mesh,
                             coral_mesh, table_mesh)

CORALS = {"coral-one": CORAL_ONE, "coral-two": CORAL_TWO}
TABLE_TOP = (0.24, 0.16, 0.02)  # table_mesh's defaults
TABLE_LEG = (0.025, 0.025, 0.14)
TABLE_INSET = 0.015


@pytest.fixture(scope="module", params=BUILTIN_TARGETS)
def builtin(request):
    return request.param, builtin_mesh(request.param)


@pytest.fixture(scope="module")
def table():
    return builtin_mesh("table")


# --- independent checks -------------------------------------------------------------------

def _signed_volume(mesh: trimesh.Trimesh) -> float:
    """Divergence theorem: Σ det(v0, v1, v2) / 6 over the faces."""
    tri = mesh.vertices[mesh.faces]
    return float(np.sum(np.linalg.det(tri)) / 6.0)


def _hits(mesh: trimesh.Trimesh, origin, direction) -> np.ndarray:
    """Sorted distinct distances (m) along one ray to where it crosses the surface."""
    origin = np.asarray(origin, np.float64)[None]
    direction = np.asarray(direction, np.float64)[None]
    locations, _, _ = RayMeshIntersector(mesh).intersects_location(origin, direction,
                                                                   multiple_hits=True)
    distances = np.sort((locations - origin) @ direction[0])
    keep = np.concatenate([[True], np.diff(distances) > 1e-9])  # a hit on a shared edge
    return distances[keep]


def _crossing_pairs(mesh: trimesh.Trimesh, eps: float = 1e-9) -> int:
    """How many pairs of faces sharing no edge cross: an edge of one pierces the other.

    Candidate pairs are faces whose centroids lie within two circumradii; each of the six
    edges of a pair is tested against the other triangle (Möller–Trumbore, strict interior).
    """
    tri = mesh.vertices[mesh.faces]  # (F, 3, 3)
    centre = tri.mean(axis=1)
    reach = np.max(np.linalg.norm(tri - centre[:, None], axis=2))
    pairs = np.array(sorted(cKDTree(centre).query_pairs(2.0 * reach + eps)), dtype=np.int64)
    faces = np.sort(mesh.faces, axis=1)
    shared = (faces[pairs[:, 0], :, None] == faces[pairs[:, 1], None, :]).sum(axis=(1, 2))
    pairs = pairs[shared < 2]
    crossed = np.zeros(len(pairs), dtype=bool)
    for a, b in ((0, 1), (1, 0)):
        edges_of, target = tri[pairs[:, a]], tri[pairs[:, b]]
        for i in range(3):
            start, end = edges_of[:, i], edges_of[:, (i + 1) % 3]
            crossed |= _segment_hits_triangle(start, end, target, eps)
    return int(crossed.sum())


def _segment_hits_triangle(start, end, tri, eps) -> np.ndarray:
    """(N,) whether segments start→end (N, 3) pass through the interiors of tri (N, 3, 3)."""
    d = end - start
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > eps**2
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = start - tri[:, 0]
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = np.einsum("ij,ij->i", d, q) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    return ok & (u > eps) & (v > eps) & (u + v < 1 - eps) & (t > eps) & (t < 1 - eps)


def test_crossing_check_finds_overlapping_boxes():
    """The self-intersection check itself can fail: two boxes merged without a union."""
    a = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    b = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    b.apply_translation((0.05, 0.03, 0.02))
    assert _crossing_pairs(trimesh.util.concatenate([a, b])) > 0
    assert _crossing_pairs(a) == 0


# --- every built-in -----------------------------------------------------------------------

def test_closed_outward_two_manifold(builtin):
    _, mesh = builtin
    edges = mesh.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    directed = {tuple(e) for e in edges.tolist()}
    assert len(directed) == len(edges)  # each directed edge once: consistent winding
    assert all((b, a) in directed for a, b in directed)  # each edge has its twin: closed
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.is_volume
    assert _signed_volume(mesh) > 0
    assert mesh.volume == pytest.approx(_signed_volume(mesh), rel=1e-9)
    assert len(mesh.vertices) - len(edges) // 2 + len(mesh.faces) == 2  # genus 0


def test_well_formed_arrays(builtin):
    _, mesh = builtin
    assert mesh.vertices.dtype == np.float64 and mesh.vertices.shape[1] == 3
    assert 0 < len(mesh.faces) <= 10_000
    tri = mesh.vertices[mesh.faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    longest = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1)
    assert np.all(area > 1e-4 * longest**2)  # no degenerate (needle or zero-area) faces
    assert len(np.unique(mesh.vertices, axis=0)) == len(mesh.vertices)
    np.testing.assert_allclose(mesh.bounds[0], -mesh.bounds[1], atol=1e-12)  # bbox centred


def test_no_self_intersections(builtin):
    _, mesh = builtin
    assert _crossing_pairs(mesh) == 0


def test_builtin_returns_a_new_mesh():
    first = builtin_mesh("coral-one")
    first.apply_translation((1.0, 0.0, 0.0))
    np.testing.assert_array_equal(builtin_mesh("coral-one").vertices,
                                  coral_mesh(CORAL_ONE.seed, size_m=CORAL_ONE.size_m).vertices)


# --- corals --------------------------------------------------------------------------------

@pytest.mark.parametrize("name", CORALS)
def test_coral_size(name):
    mesh = builtin_mesh(name)
    np.testing.assert_allclose(mesh.extents, CORALS[name].size_m, rtol=0, atol=1e-9)
    assert np.all((mesh.extents >= 0.15) & (mesh.extents <= 0.25))


@pytest.mark.parametrize("name", CORALS)
def test_coral_star_shaped_about_origin(name):
    """Every face sees the origin on its inner side and the faces tile the sphere of
    directions once (solid angles sum to 4π): so rays from the origin cross the surface
    exactly once and the surface cannot intersect itself."""
    mesh = builtin_mesh(name)
    a, b, c = np.moveaxis(mesh.vertices[mesh.faces], 1, 0)
    triple = np.einsum("ij,ij->i", a, np.cross(b, c))
    assert np.all(triple > 0)
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
    denominator = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc
                   + np.einsum("ij,ij->i", a, c) * lb + np.einsum("ij,ij->i", b, c) * la)
    solid_angle = 2.0 * np.arctan2(triple, denominator)  # Van Oosterom–Strackee
    assert np.sum(solid_angle) == pytest.approx(4.0 * math.pi, rel=1e-9)
    centroid = mesh.triangles_center
    assert np.all(np.einsum("ij,ij->i", mesh.face_normals, centroid) > 0)

    directions = np.random.default_rng(0).normal(size=(24, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    for direction in directions:
        assert len(_hits(mesh, (0.0, 0.0, 0.0), direction)) == 1


@pytest.mark.parametrize("name", CORALS)
def test_coral_dominantly_convex_with_mild_concavities(name):
    mesh = builtin_mesh(name)
    assert 0.85 < mesh.volume / mesh.convex_hull.volume < 0.995


@pytest.mark.parametrize("seed", range(6))
def test_any_seed_gives_a_mild_rock(seed):
    mesh = coral_mesh(seed, subdivisions=3)
    assert mesh.is_volume
    assert 0.85 < mesh.volume / mesh.convex_hull.volume < 0.995
    np.testing.assert_allclose(mesh.extents, (0.22, 0.18, 0.16), rtol=0, atol=1e-9)


def test_coral_deterministic():
    first, again = coral_mesh(5, subdivisions=3), coral_mesh(np.int64(5), subdivisions=3)
    np.testing.assert_array_equal(first.vertices, again.vertices)
    np.testing.assert_array_equal(first.faces, again.faces)
    other = coral_mesh(6, subdivisions=3)
    assert np.max(np.abs(first.vertices - other.vertices)) > 0.01


def test_builtin_corals_differ():
    one, two = builtin_mesh("coral-one"), builtin_mesh("coral-two")
    assert CORAL_ONE.seed != CORAL_TWO.seed
    # the same shape would scale into the other box; compare in unit boxes
    unit_one = one.vertices / one.extents
    unit_two = two.vertices / two.extents
    assert np.mean(np.linalg.norm(unit_one - unit_two, axis=1)) > 0.05


@pytest.mark.parametrize("subdivisions, faces", [(1, 80), (2, 320), (5, 20480)])
def test_coral_resolution(subdivisions, faces):
    """A finer icosphere meshes the same rock: the field does not depend on the resolution."""
    mesh = coral_mesh(3, subdivisions=subdivisions)
    assert len(mesh.faces) == faces and mesh.is_volume
    reference = coral_mesh(3)
    tolerance = {1: 0.2, 2: 0.05, 5: 0.005}[subdivisions]
    assert mesh.volume == pytest.approx(reference.volume, rel=tolerance)


# --- table ---------------------------------------------------------------------------------

def test_table_size_and_volume(table):
    height = TABLE_TOP[2] + TABLE_LEG[2] - LEG_OVERLAP_M
    np.testing.assert_allclose(table.extents, (TABLE_TOP[0], TABLE_TOP[1], height),
                               rtol=0, atol=1e-12)
    legs = 4 * TABLE_LEG[0] * TABLE_LEG[1] * (TABLE_LEG[2] - LEG_OVERLAP_M)
    assert table.volume == pytest.approx(np.prod(TABLE_TOP) + legs, rel=1e-9)


def test_table_thin_top_overlap():
    """Legs reach half of a top thinner than twice the overlap."""
    mesh = table_mesh(top=(0.2, 0.1, 0.003), leg=(0.02, 0.02, 0.1), inset=0.0)
    assert mesh.is_volume and _crossing_pairs(mesh) == 0
    np.testing.assert_allclose(mesh.extents, (0.2, 0.1, 0.003 + 0.1 - 0.0015), atol=1e-12)


def test_table_deep_concavity(table):
    assert table.volume / table.convex_hull.volume < 0.6


def test_table_open_between_legs(table):
    """A ray up the middle passes between the legs to the underside of the top."""
    bottom, top = table.bounds[0, 2], table.bounds[1, 2]
    hits = _hits(table, (0.0, 0.0, bottom - 0.1), (0.0, 0.0, 1.0))
    np.testing.assert_allclose(hits + bottom - 0.1, [top - TABLE_TOP[2], top], atol=1e-12)
    side = _hits(table, (0.0, TABLE_TOP[1] / 2 - TABLE_INSET - TABLE_LEG[1] / 2, bottom - 0.1),
                 (0.0, 0.0, 1.0))
    np.testing.assert_allclose(side + bottom - 0.1, [top - TABLE_TOP[2], top], atol=1e-12)


@pytest.mark.parametrize("sx, sy", [(1, 1), (-1, 1), (-1, -1), (1, -1)])
def test_table_legs(table, sx, sy):
    """A ray up a leg's axis enters at the foot and leaves at the top: no inner faces."""
    bottom, top = table.bounds[0, 2], table.bounds[1, 2]
    x = sx * (TABLE_TOP[0] / 2 - TABLE_INSET - TABLE_LEG[0] / 2)
    y = sy * (TABLE_TOP[1] / 2 - TABLE_INSET - TABLE_LEG[1] / 2)
    hits = _hits(table, (x, y, bottom - 0.1), (0.0, 0.0, 1.0))
    np.testing.assert_allclose(hits + bottom - 0.1, [bottom, top], atol=1e-12)
    beside = _hits(table, (x + sx * (TABLE_LEG[0] / 2 + 0.002), y, bottom - 0.1), (0.0, 0.0, 1.0))
    assert beside[0] + bottom - 0.1 == pytest.approx(top - TABLE_TOP[2], abs=1e-12)


# --- bad input -----------------------------------------------------------------------------

@pytest.mark.parametrize("call, field", [
    (lambda: builtin_mesh("rock"), "target.builtin"),
    (lambda: coral_mesh(1, size_m=(-0.1, 0.2, 0.2)), "size_m"),
    (lambda: coral_mesh(1, size_m=(0.1, 0.2)), "size_m"),
    (lambda: coral_mesh(1, size_m=(0.1, float("nan"), 0.2)), "size_m"),
    (lambda: coral_mesh(1, size_m="big"), "size_m"),
    (lambda: coral_mesh(1.5), "seed"),
    (lambda: coral_mesh(-1), "seed"),
    (lambda: coral_mesh(True), "seed"),
    (lambda: coral_mesh(1, subdivisions=0), "subdivisions"),
    (lambda: coral_mesh(1, subdivisions=7), "subdivisions"),
    (lambda: table_mesh(top=(0.24, 0.16, -0.02)), "top"),
    (lambda: table_mesh(leg=(0.025, 0.0, 0.14)), "leg"),
    (lambda: table_mesh(leg=(0.2, 0.025, 0.14)), "leg"),
    (lambda: table_mesh(inset=-0.01), "inset"),
    (lambda: table_mesh(inset=float("inf")), "inset"),
])
def test_bad_arguments(call, field):
    with pytest.raises(InputError) as caught:
        call()
    assert caught.value.field == field
    text = str(caught.value)
    assert "\n" not in text and text.startswith(field)


def test_unknown_builtin_names_the_choices():
    with pytest.raises(InputError) as caught:
        builtin_mesh("rock")
    text = str(caught.value)
    assert "'rock'" in text and all(name in text for name in BUILTIN_TARGETS)
