"""Ray casting (Backend.load_mesh / cast_rays) against trimesh's intersector (Embree), on the
built-in targets placed where a scene puts them (~2 m from the origin, so float32 coordinates
carry the scene's rounding), plus watertightness on shared vertices and edges."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import trimesh

from fsswarp.backends import get_backend
from fsswarp.errors import InputError
from fsswarp.rig import world_to_reference
from fsswarp.scenes import builtin_scene, target_world_mesh
from fsswarp.targets import BUILTIN_TARGETS, builtin_mesh

from oracle_render import first_hits, make_intersector, sub_rays

#: Where the targets sit for the casts (m): a scene's standoff, below the sonar.
PLACE = np.array([0.15, 2.0, -0.1])
#: Distance tolerance against Embree (m): both are float32 at ~2 m (ulp 2.4e-7); 1e-4 m is 1/40
#: of a range bin.
TOL = 1e-4
#: Fraction of rays allowed to disagree on hit/miss or distance: rays aimed at random surface
#: points near a silhouette graze the mesh, and two float32 triangle tests can then differ on
#: whether the ray clips the near facet or passes on to a farther one.
GRAZING_FRACTION = 1e-4


@functools.cache
def placed(name: str) -> trimesh.Trimesh:
    mesh = builtin_mesh(name)
    return trimesh.Trimesh(vertices=np.asarray(mesh.vertices) + PLACE, faces=np.asarray(mesh.faces),
                           process=False)


@functools.cache
def random_rays(name: str, count: int = 20000, seed: int = 1):
    """Rays from outside (a sphere of 3× the bounding radius around the target) toward random
    points on the surface, and as many toward random points beside it (near misses)."""
    mesh = placed(name)
    rng = np.random.default_rng(seed)
    targets, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    centre = mesh.bounding_sphere.primitive.center
    radius = 3.0 * mesh.bounding_sphere.primitive.radius
    start = rng.normal(size=(count, 3))
    origins = centre + radius * start / np.linalg.norm(start, axis=1, keepdims=True)
    beside = centre + rng.uniform(-1.2, 1.2, size=(count, 3)) * (0.5 * mesh.extents)
    targets = np.concatenate([targets, beside])
    origins = np.concatenate([origins, origins[rng.permutation(count)]])
    dirs = targets - origins
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return origins, dirs


def compare(dist, face, want_dist, want_face, *, tol=TOL, allowed=GRAZING_FRACTION):
    hit, want_hit = np.isfinite(dist), np.isfinite(want_dist)
    assert np.all(face[~hit] == -1) and np.all(face[hit] >= 0)
    both = hit & want_hit
    bad = (hit != want_hit) | (both & ~(np.abs(np.where(both, dist, 0) - np.where(both, want_dist, 0)) <= tol))
    assert bad.sum() <= max(1, allowed * len(dist)), \
        f"{bad.sum()} of {len(dist)} rays disagree (hit/miss {np.sum(hit != want_hit)}; " \
        f"worst distance {np.max(np.abs(dist[both] - want_dist[both]), initial=0):.3g} m)"
    return bad


@pytest.mark.parametrize("name", BUILTIN_TARGETS)
def test_cast_rays_match_trimesh(backend, name):
    mesh = placed(name)
    origins, dirs = random_rays(name)
    handle = backend.load_mesh(mesh.vertices, mesh.faces)
    dist, face = backend.cast_rays(handle, origins, dirs)
    assert dist.dtype == np.float32 and face.dtype == np.int32 and dist.shape == (len(origins),)
    want_dist, want_face = first_hits(make_intersector(mesh), origins, dirs)
    assert np.isfinite(want_dist[: len(origins) // 2]).all()  # aimed at the surface: all hit
    assert (~np.isfinite(want_dist)).sum() > 1000  # and plenty of misses beside it
    bad = compare(dist, face, want_dist, want_face)
    # the face hit agrees wherever the distances do, up to ties on shared edges
    ok = np.isfinite(dist) & ~bad
    assert np.mean(face[ok] == want_face[ok]) > 0.999


@pytest.mark.parametrize("scene", BUILTIN_TARGETS)
def test_first_hit_per_beam_matches_trimesh(backend, scene):
    """The sonar's own sub-rays from a scene's reference pose: nearest range per beam."""
    manifest = builtin_scene(scene)
    rig, depth, tilt = manifest.rig, manifest.truth.depth, manifest.truth.tilt
    world = target_world_mesh(manifest.target)
    mesh = trimesh.Trimesh(vertices=world_to_reference(world.vertices, rig, depth, tilt),
                           faces=np.asarray(world.faces), process=False)
    rot, trans = rig.relative_poses(depth, tilt)
    view = rig.index("S0")
    u, beam = sub_rays(manifest.sonar, (2, 64))
    dirs = u @ rot[view].T
    origins = np.broadcast_to(trans[view], dirs.shape)
    dist, _ = backend.cast_rays(backend.load_mesh(mesh.vertices, mesh.faces), origins, dirs)
    want, _ = first_hits(make_intersector(mesh), origins, dirs)
    per_beam = np.full(manifest.sonar.beams, np.inf)
    np.minimum.at(per_beam, beam, dist.astype(np.float64))
    want_beam = np.full(manifest.sonar.beams, np.inf)
    np.minimum.at(want_beam, beam, want)
    assert np.isfinite(want_beam).sum() >= 10
    np.testing.assert_array_equal(np.isfinite(per_beam), np.isfinite(want_beam))
    lit = np.isfinite(want_beam)
    np.testing.assert_allclose(per_beam[lit], want_beam[lit], atol=TOL, rtol=0)


def test_watertight_on_vertices_and_edges(backend):
    """Rays aimed exactly at shared vertices and edge midpoints of a closed icosphere, from
    outside, all hit, at the aimed point."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    centre = np.array([0.2, 2.0, -0.3])
    targets = np.concatenate([sphere.vertices, sphere.vertices[sphere.edges_unique].mean(axis=1)])
    rng = np.random.default_rng(5)
    origins, dirs, expected = [], [], []
    for k in range(4):  # radially, then three random directions within 60° of the outward radius
        out = targets / np.linalg.norm(targets, axis=1, keepdims=True)
        if k:
            jitter = rng.normal(size=out.shape)
            jitter -= np.sum(jitter * out, axis=1, keepdims=True) * out
            jitter /= np.linalg.norm(jitter, axis=1, keepdims=True)
            angle = rng.uniform(0.0, np.radians(60.0), size=(len(out), 1))
            out = np.cos(angle) * out + np.sin(angle) * jitter
        length = rng.uniform(0.3, 2.0, size=len(out))
        origins.append(centre + targets + length[:, None] * out)
        dirs.append(-out)
        expected.append(length)
    origins, dirs, expected = (np.concatenate(a) for a in (origins, dirs, expected))
    handle = backend.load_mesh(sphere.vertices + centre, sphere.faces)
    dist, face = backend.cast_rays(handle, origins, dirs)
    missed = ~np.isfinite(dist)
    assert not missed.any(), f"{missed.sum()} of {len(dist)} vertex/edge rays missed the closed mesh"
    assert np.all(face >= 0)
    through = dist > expected + 1e-5
    assert not through.any(), \
        f"{through.sum()} of {len(dist)} rays aimed at a shared vertex/edge leaked through it " \
        f"(first hit {dist[through][:3]} m on the far side, aimed point at {expected[through][:3]} m)"
    # convex: the aimed point is the first hit (float32 at ~2.5 m: ~1e-6 m)
    np.testing.assert_allclose(dist, expected, atol=1e-5, rtol=0)


def test_nearest_of_many_stacked_sheets(backend):
    """60 square sheets stacked along +y in shuffled face order, every ray crossing all of them:
    the first hit is the nearest sheet's, from origins before, between and past the sheets (a
    walk that skips a subtree it must enter, or keeps a farther hit, lands on another sheet)."""
    rng = np.random.default_rng(11)
    ys = 2.0 + 0.01 * np.arange(60)
    square = np.array([[-0.5, 0.0, -0.5], [0.5, 0.0, -0.5], [0.5, 0.0, 0.5], [-0.5, 0.0, 0.5]])
    vertices = np.concatenate([square + [0.1, y, -0.2] for y in ys])
    faces = np.concatenate([[[4 * k, 4 * k + 1, 4 * k + 2], [4 * k, 4 * k + 2, 4 * k + 3]] for k in range(60)])
    faces = faces[rng.permutation(len(faces))]
    handle = backend.load_mesh(vertices, faces)
    starts = 2.005 + 0.01 * rng.integers(-10, 70, size=500)  # midway between sheets
    origins = np.column_stack([rng.uniform(-0.2, 0.4, 500), starts, rng.uniform(-0.5, 0.1, 500)])
    dirs = np.column_stack([rng.uniform(-0.05, 0.05, 500), np.ones(500), rng.uniform(-0.05, 0.05, 500)])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dist, face = backend.cast_rays(handle, origins, dirs)
    ahead = ys[None, :] > starts[:, None]
    nearest = np.where(ahead.any(axis=1), np.where(ahead, ys[None, :], np.inf).min(axis=1), np.inf)
    want = (nearest - starts) / dirs[:, 1]
    np.testing.assert_array_equal(np.isfinite(dist), np.isfinite(want))
    hit = np.isfinite(want)
    assert 300 < hit.sum() < 500
    np.testing.assert_allclose(dist[hit], want[hit], atol=1e-5, rtol=0)
    sheet = vertices[faces[face[hit], 0], 1]
    np.testing.assert_array_equal(sheet, nearest[hit])


def test_misses_give_inf_and_minus_one(backend):
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    handle = backend.load_mesh(sphere.vertices + [0, 2, 0], sphere.faces)
    origins = np.zeros((4, 3))
    dirs = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1], [0.3, 0.954, 0]])  # away, beside, up, past
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dist, face = backend.cast_rays(handle, origins, dirs)
    assert np.all(np.isinf(dist)) and np.all(dist > 0) and np.all(face == -1)
    # a hit beyond max_distance is no hit
    dist, face = backend.cast_rays(handle, [[0, 0, 0]] * 2, [[0, 1, 0]] * 2, max_distance=1.5)
    assert np.all(np.isinf(dist)) and np.all(face == -1)
    dist, face = backend.cast_rays(handle, [[0, 0, 0]], [[0, 1, 0]], max_distance=2.0)
    assert dist[0] == pytest.approx(1.8, abs=1e-5) and face[0] >= 0
    # no rays: empty results
    dist, face = backend.cast_rays(handle, np.zeros((0, 3)), np.zeros((0, 3)))
    assert dist.shape == (0,) and face.shape == (0,)


def test_cast_rays_validates(backend):
    sphere = trimesh.creation.icosphere(subdivisions=1)
    handle = backend.load_mesh(sphere.vertices, sphere.faces)
    with pytest.raises(ValueError):
        backend.cast_rays(handle, np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError):
        backend.cast_rays(handle, [[np.nan, 0, 0]], [[0, 1, 0]])


def test_warp_and_opencl_agree():
    """Same rays, same float32 geometry: identical hit/miss, distances within 1e-5 m."""
    try:
        warp, opencl = get_backend("warp", "cpu"), get_backend("opencl")
    except InputError as err:  # a missing backend skips
        pytest.skip(f"needs both Warp and OpenCL: {err}")
    for name in BUILTIN_TARGETS:
        mesh = placed(name)
        origins, dirs = random_rays(name)
        a = warp.cast_rays(warp.load_mesh(mesh.vertices, mesh.faces), origins, dirs)
        b = opencl.cast_rays(opencl.load_mesh(mesh.vertices, mesh.faces), origins, dirs)
        np.testing.assert_array_equal(np.isfinite(a[0]), np.isfinite(b[0]), err_msg=name)
        hit = np.isfinite(a[0])
        np.testing.assert_allclose(a[0][hit], b[0][hit], atol=1e-5, rtol=0, err_msg=name)
        assert np.mean(a[1][hit] == b[1][hit]) > 0.999, name


def test_warp_mesh_corners_and_boxes_are_the_host_s_bit_for_bit(wp_device):
    """``load_mesh`` on Warp gathers the corners and pads the boxes on the device: the float32
    corners (np.take), boxes (``triangle_bounds``) and pad (1e-6 × the largest |coordinate| +
    1e-6 × the box's longest side, float32) of NumPy, bit for bit, on a coral, a mesh far from
    the origin with axis-aligned triangles, and one of random triangles."""
    from fsswarp.backends.bvh import triangle_bounds

    backend = get_backend("warp", wp_device)
    rng = np.random.default_rng(3)
    box = trimesh.creation.box(extents=(0.3, 0.2, 0.1))
    meshes = [builtin_mesh("coral-one"), (box.vertices + (120.0, -40.0, 7.5), box.faces),
              (rng.normal(0.0, 2.0, (300, 3)), rng.integers(0, 300, (500, 3)))]
    for mesh in meshes:
        vertices, faces = (mesh.vertices, mesh.faces) if hasattr(mesh, "faces") else mesh
        handle = backend.load_mesh(vertices, faces)
        points = np.asarray(vertices, np.float32)
        lo, hi = triangle_bounds(points, np.asarray(faces, np.int64))
        pad = np.float32(1.0e-6 * max(float(np.max(np.abs(vertices))), 1.0e-12)) \
            + 1.0e-6 * (hi - lo).max(axis=1, keepdims=True)
        np.testing.assert_array_equal(handle.corners.numpy(), np.take(points, np.ravel(faces), axis=0))
        np.testing.assert_array_equal(handle.lowers.numpy(), lo - pad)
        np.testing.assert_array_equal(handle.uppers.numpy(), hi + pad)
        assert handle.lowers.numpy().dtype == np.float32 and (handle.uppers.numpy() > handle.lowers.numpy()).all()
