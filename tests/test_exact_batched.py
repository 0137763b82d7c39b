"""E_mu (fsswarp.compare.ViewComparison.exact, paper eq. 6) batched over views, components and
patches against the method written one view, one contour and one patch at a time (the oracle
below), on the simulated coral-one with its true model, on every backend."""

import math

import numpy as np
import pytest
import trimesh

from fsswarp.compare import ViewComparison, fan_points
from fsswarp.icp import CONTOUR_TOL, icp_many
from fsswarp.motion import image_jacobian, truncated_lstsq
from fsswarp.surface import mirror_points, surface_in_reference

#: (ΔD m, Δβ deg) about the truth: the located estimate itself, and poses the polish visits
#: (views losing contour pairs, patches seen in the mirror alone).
POSES = ((0.0, 0.0), (0.004, 0.25), (-0.012, -0.8), (0.025, 1.2))


@pytest.fixture(scope="module")
def truth_model(coral_one):
    return trimesh.load(coral_one.truth_model_path, process=False)


def loop_requests(comparison, contour, shift):
    """align's ICP requests, one view and component at a time: (component, view, beams,
    source (N, 2), goal (M, 2)) of each contour pair with two points or more in both."""
    data, sonar = comparison.data, comparison.sonar
    theta = sonar.beam_centres
    requests = []
    for c in (0, 1):
        for k in range(len(data.views)):
            beams = np.flatnonzero((contour[k, c] >= 0) & data.masks[k, c])
            target = np.flatnonzero(data.rows[k, c] >= 0)
            if len(beams) >= 2 and len(target) >= 2:
                requests.append((c, k, beams, fan_points(theta[beams], sonar.bin_range(contour[k, c, beams] + shift)),
                                 fan_points(theta[target], sonar.bin_range(data.rows[k, c, target]))))
    return requests


def loop_exact(comparison, depth, tilt):
    """(E_mu, (V,) μ_m, object patches, mirror patches) of eq. 6 one view, contour and patch at
    a time: each contour's frontal faces in a launch of its own, each (component, face, view)
    motion a running sum, each patch's (2 × views, 3) system solved alone, the mirror-only
    patches' object motion the nearest object patch's by brute force, μ_m per view."""
    data, sonar = comparison.data, comparison.sonar
    theta, n_views = sonar.beam_centres, len(data.views)
    contour, shift = comparison.synthetic_contours(depth, tilt)
    rot, t, n, d = (a[0] for a in comparison.view_poses(data.views, np.array([depth]), np.array([tilt])))
    normal, offset = surface_in_reference(comparison.rig, depth, tilt)
    requests = loop_requests(comparison, contour, shift)
    results = icp_many([(source, goal) for *_, source, goal in requests], tol=CONTOUR_TOL,
                       backend=comparison.backend if comparison.backend.has_float64 else None)
    sums, counts = {}, {}  # (component, face) -> {view: sum of 2-D motions, count}
    for (c, k, beams, _, _), result in zip(requests, results):
        faces = comparison.frontal_faces(rot[k:k + 1], t[k:k + 1], n[k:k + 1], d[k:k + 1], [theta[beams]],
                                         mirror=c == 1)[0]
        for face, vector in zip(faces.tolist(), result.motions):
            if face >= 0:
                sums.setdefault((c, face), {})[k] = sums.get((c, face), {}).get(k, 0.0) + vector
                counts.setdefault((c, face), {})[k] = counts.get((c, face), {}).get(k, 0) + 1
    faces = sorted({face for _, face in sums})
    if not any(c == 0 for c, _ in sums):
        return math.nan, np.full(n_views, np.nan), 0, 0
    centre = {z: comparison.vertices[comparison.faces[z]].mean(axis=0) for z in faces}

    def solve(c, z, point):
        rows, values = [], []
        for k in sorted(sums[c, z]):
            p_view = np.einsum("i,ij->j", point - t[k], rot[k])
            jac = image_jacobian(p_view, surface=None if c == 0 else (n[k], d[k]))
            rows.append(np.einsum("aj,ij->ai", jac, rot[k]))
            values.append(sums[c, z][k] / counts[c, z][k])
        return truncated_lstsq(np.concatenate(rows)[None], np.concatenate(values)[None], 1e-2)[0][0]

    solved = {z: solve(0, z, centre[z]) for z in faces if (0, z) in sums}

    def nearest(z):  # the object patch nearest to z (z itself if it is one)
        return min(solved, key=lambda y: float(np.sum((centre[y] - centre[z]) ** 2)))

    obj = {z: solved[nearest(z)] for z in faces}
    mirror = {z: solve(1, z, mirror_points(centre[z], normal, offset)) for z in faces if (1, z) in sums}
    per_view = np.full(n_views, np.nan)
    for k in range(n_views):
        seen = [z for z in faces if k in sums.get((0, z), {})]
        if not seen:
            continue
        per_view[k] = np.mean([np.linalg.norm(obj[z]) for z in seen])
        gaps = [np.linalg.norm(obj[z] - 2.0 * np.dot(obj[z], normal) * normal - mirror[z])
                for z in faces if k in sums.get((1, z), {})]
        per_view[k] += np.mean(gaps) if gaps else 0.0
    finite = per_view[np.isfinite(per_view)]
    return (float(finite.mean()) if finite.size else math.nan, per_view,
            len(solved), len(mirror))


@pytest.mark.parametrize("offset", POSES)
def test_exact_is_the_per_view_loop(coral_one, truth_model, backend, offset):
    truth = coral_one.manifest.truth
    comparison = ViewComparison(coral_one, backend=backend).use(truth_model, truth.depth, truth.tilt)
    depth, tilt = truth.depth + offset[0], truth.tilt + math.radians(offset[1])
    found = comparison.exact(depth, tilt)
    value, per_view, object_patches, mirror_patches = loop_exact(comparison, depth, tilt)
    assert (found.object_patches, found.mirror_patches) == (object_patches, mirror_patches)
    assert object_patches > 0 and mirror_patches > 0
    np.testing.assert_allclose(found.per_view, per_view, rtol=1e-12, atol=0)
    assert found.value == pytest.approx(value, rel=1e-12, abs=0)
    assert found.value == comparison.exact(depth, tilt).value  # nothing carried between calls


def test_align_and_frontal_motions_are_the_per_view_loop(coral_one, truth_model, backend):
    truth = coral_one.manifest.truth
    depth, tilt = truth.depth - 0.012, truth.tilt - math.radians(0.8)
    comparison = ViewComparison(coral_one, backend=backend).use(truth_model, truth.depth, truth.tilt)
    contour, shift = comparison.synthetic_contours(depth, tilt)
    contour = contour.copy()  # contours too short for ICP: view 3's object (one point), view 5's mirror (none)
    contour[3, 0, np.flatnonzero(contour[3, 0] >= 0)[1:]] = -1
    contour[5, 1] = -1
    aligned = comparison.align(contour, shift)
    requests = loop_requests(comparison, contour, shift)
    assert [(c, k) for c, k, *_ in aligned] == [(c, k) for c, k, *_ in requests]
    assert {c for c, *_ in requests} == {0, 1} and (0, 3) not in [(c, k) for c, k, *_ in requests]
    assert 10 < len(requests) < 2 * len(comparison.data.views) - 1
    for got, want in zip(aligned, requests):
        for a, b in zip(got[2:5], want[2:]):
            np.testing.assert_array_equal(a, b)
    objects = comparison.align(contour, shift, (0,))
    assert [(c, k) for c, k, *_ in objects] == [(c, k) for c, k, *_ in requests if c == 0]
    # frontal motions: each contour's faces found alone, its beams' 2-D motions where one is found
    rot, t, n, d = (a[0] for a in comparison.view_poses(comparison.data.views, np.array([depth]), np.array([tilt])))
    motions = [(c, k, beams, result.motions) for c, k, beams, _, _, result in aligned]
    component, view, face, vectors = comparison.frontal_motions(rot, t, n, d, motions[::-1])
    want = []
    for c in (0, 1):
        for _, k, beams, vec in [m for m in motions[::-1] if m[0] == c]:
            faces = comparison.frontal_faces(rot[k:k + 1], t[k:k + 1], n[k:k + 1], d[k:k + 1],
                                             [comparison.sonar.beam_centres[beams]], mirror=c == 1)[0]
            want += [(c, k, f, tuple(v)) for f, v in zip(faces.tolist(), vec.tolist()) if f >= 0]
    assert list(zip(component.tolist(), view.tolist(), face.tolist(), map(tuple, vectors.tolist()))) == want
    assert component.dtype == view.dtype == face.dtype == np.int64 and vectors.dtype == np.float64
