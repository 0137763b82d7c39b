"""Image Jacobians and 3-D patch motions from 2-D motions (fsswarp.motion) against finite
differences, the coral-one rig and closed forms; E_mu (fsswarp.metrics) of reflected motions."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fsswarp.metrics import pose_error
from fsswarp.motion import image_jacobian, patch_motions, truncated_lstsq
from fsswarp.rig import world_to_reference
from fsswarp.scenes import builtin_scene
from fsswarp.sonar import fan_xy, from_polar, to_polar
from fsswarp.surface import (apparent_returns, mirror_points, mirror_vectors, surface_in_reference,
                             surface_in_views)

finite = dict(allow_nan=False, allow_infinity=False)
fast = settings(derandomize=True, max_examples=40, deadline=None)


def image_coordinates(points, plane, surface=None):
    """(..., 2) image coordinates of the object return of ``points`` or, with ``surface``, the
    mirror return of the virtual points ``points`` (through surface.apparent_returns)."""
    if surface is None:
        rng, theta, _ = to_polar(points)
    else:
        theta, rng = apparent_returns(mirror_points(points, *surface), *surface)["mirror"]
    if plane == "polar":
        return np.stack([theta, rng], axis=-1)
    return np.stack(fan_xy(theta, rng), axis=-1)


def central_difference(points, plane, surface=None, h=1e-6):
    """(..., 2, 3) Jacobian by central differences."""
    cols = []
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        cols.append((image_coordinates(points + e, plane, surface) -
                     image_coordinates(points - e, plane, surface)) / (2 * h))
    return np.stack(cols, axis=-1)


# --- Jacobians -----------------------------------------------------------------------------------

@pytest.mark.parametrize("plane", ["fan", "polar"])
@given(rng=st.floats(0.5, 5.0, **finite), theta=st.floats(-0.8, 0.8, **finite),
       phi=st.floats(-0.4, 0.4, **finite))
@fast
def test_jacobian_matches_central_differences(plane, rng, theta, phi):
    p = from_polar(rng, theta, phi)
    np.testing.assert_allclose(image_jacobian(p, plane=plane), central_difference(p, plane), atol=1e-8)


@pytest.mark.parametrize("plane", ["fan", "polar"])
@given(rng=st.floats(0.5, 4.0, **finite), theta=st.floats(-0.4, 0.4, **finite),
       phi=st.floats(-0.2, 0.2, **finite), tilt=st.floats(-0.3, 0.3, **finite),
       depth=st.floats(0.2, 1.0, **finite))
@fast
def test_mirror_jacobian_matches_central_differences(plane, rng, theta, phi, tilt, depth):
    normal = np.array([0.0, math.sin(tilt), math.cos(tilt)])
    q = mirror_points(from_polar(rng, theta, phi), normal, depth)  # a virtual mirror point
    surface = (normal, depth)
    np.testing.assert_allclose(image_jacobian(q, plane=plane, surface=surface),
                               central_difference(q, plane, surface), atol=1e-7)


def test_jacobian_closed_form_on_the_axis():
    j_polar = image_jacobian([0.0, 2.0, 0.0], plane="polar")
    np.testing.assert_allclose(j_polar, [[0.5, 0.0, 0.0], [0.0, 1.0, 0.0]], atol=1e-15)
    j_fan = image_jacobian([0.0, 2.0, 0.0])
    np.testing.assert_allclose(j_fan, [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], atol=1e-15)


@given(rng=st.floats(0.5, 5.0, **finite), theta=st.floats(-0.8, 0.8, **finite),
       phi=st.floats(-0.4, 0.4, **finite))
@fast
def test_elevation_direction_is_the_null_space(rng, theta, phi):
    tangent = np.array([-math.sin(phi) * math.sin(theta), -math.sin(phi) * math.cos(theta), math.cos(phi)])
    for plane in ("fan", "polar"):
        np.testing.assert_allclose(image_jacobian(from_polar(rng, theta, phi), plane=plane) @ tangent,
                                   0.0, atol=1e-14)


def test_jacobian_rejects_bad_points():
    with pytest.raises(ValueError, match="plane"):
        image_jacobian([0.0, 1.0, 0.0], plane="xy")
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        image_jacobian([0.0, 1.0])
    with pytest.raises(ValueError, match="non-finite"):
        image_jacobian([np.nan, 1.0, 0.0])
    with pytest.raises(ValueError, match="vertical axis"):
        image_jacobian([0.0, 0.0, 1.0])


# --- 3-D patch motions on the coral-one rig -------------------------------------------------

@pytest.fixture(scope="module")
def rig_case():
    """Patch centres around the coral-one target, small known 3-D motions, and the rig's true
    relative poses and surface (reference frame)."""
    scene = builtin_scene("coral-one")
    depth, tilt = scene.truth.depth, scene.truth.tilt
    rot, trans = scene.rig.relative_poses(depth, tilt)
    rng = np.random.default_rng(11)
    centre = world_to_reference(np.array(scene.target.position), scene.rig, depth, tilt)
    centres = centre + rng.normal(0.0, 0.06, (40, 3))
    delta = rng.normal(0.0, 0.003, (40, 3))
    return dict(scene=scene, depth=depth, tilt=tilt, rot=rot, trans=trans, centres=centres, delta=delta,
                surface=surface_in_reference(scene.rig, depth, tilt))


def in_view(points, sonar):
    """(...,) whether view-frame points lie inside the sonar's window."""
    rng, theta, phi = to_polar(points)
    return ((np.abs(theta) <= sonar.half_azimuth) & sonar.in_elevation(phi) &
            (rng >= sonar.range_min) & (rng <= sonar.range_max))


def observe(case, centres, delta, plane="fan", mirror=False):
    """True 2-D motions (K, V, 2) of P -> P + δ projected in every view, and visibility (K, V).
    ``mirror``: the motions of the mirror returns (the patch seen from the mirrored sonar)."""
    rot, trans = case["rot"], case["trans"]

    def view_points(p):
        return np.einsum("kvi,vij->kvj", p[:, None, :] - trans[None], rot)

    before, after = view_points(centres), view_points(centres + delta)
    sonar = case["scene"].sonar
    if not mirror:
        seen = in_view(before, sonar) & in_view(after, sonar)
        return image_coordinates(after, plane) - image_coordinates(before, plane), seen
    n, d = surface_in_views(case["scene"].rig, case["depth"], case["tilt"])
    q0, q1 = mirror_points(before, n, d), mirror_points(after, n, d)
    seen = in_view(before, sonar) & in_view(q0, sonar) & in_view(q1, sonar)
    return image_coordinates(q1, plane, (n, d)) - image_coordinates(q0, plane, (n, d)), seen


@pytest.mark.parametrize("plane", ["fan", "polar"])
def test_least_squares_recovers_3d_motion(rig_case, plane):
    motions, seen = observe(rig_case, rig_case["centres"], rig_case["delta"], plane)
    assert seen.sum(axis=1).min() >= 8
    res = patch_motions(rig_case["centres"], motions, seen, rig_case["rot"], rig_case["trans"], plane=plane)
    delta = rig_case["delta"]
    err = np.linalg.norm(res.motion - delta, axis=1) / np.linalg.norm(delta, axis=1)
    assert err.max() < 0.01  # first-order model: the error is O(|δ|/R) ~ 1e-3
    assert res.rank.tolist() == [3] * 40
    np.testing.assert_array_equal(res.views, seen.sum(axis=1))
    assert res.residual.max() < 1e-4


def test_mirror_motion_is_the_reflected_object_motion(rig_case):
    # The paper's "consistent manner": with the true surface, the 3-D motion recovered from the
    # mirror returns is the object motion reflected across the surface, V^M = H V^O.
    n, d = rig_case["surface"]
    q = mirror_points(rig_case["centres"], n, d)
    motions, seen = observe(rig_case, rig_case["centres"], rig_case["delta"], mirror=True)
    res = patch_motions(q, motions, seen, rig_case["rot"], rig_case["trans"], surface=(n, d))
    full = res.rank == 3
    assert full.sum() >= 30
    expected = mirror_vectors(rig_case["delta"], n)
    err = np.linalg.norm(res.motion - expected, axis=1) / np.linalg.norm(rig_case["delta"], axis=1)
    assert err[full].max() < 0.01
    # so E_mu's mirror term vanishes and E_mu is the mean object-motion norm
    frontal = np.ones((1, 40), dtype=bool)
    e_mu = pose_error(rig_case["delta"], frontal, mirror_motion=res.motion,
                      mirror_frontal=full[None], normal=n)
    assert float(e_mu) == pytest.approx(np.linalg.norm(rig_case["delta"], axis=1).mean(), rel=0.01)


def test_one_view_leaves_elevation_at_zero(rig_case):
    # One view cannot see motion along its elevation direction ∂P/∂φ: the minimum-norm
    # solution recovers δ less its elevation component, with rank 2.
    motions, seen = observe(rig_case, rig_case["centres"], rig_case["delta"])
    view = 3
    only = np.zeros_like(seen)
    only[:, view] = seen[:, view]
    assert only.sum() == 40
    res = patch_motions(rig_case["centres"], motions, only, rig_case["rot"], rig_case["trans"])
    rot, trans = rig_case["rot"][view], rig_case["trans"][view]
    _, theta, phi = to_polar((rig_case["centres"] - trans) @ rot)
    tangent = np.stack([-np.sin(phi) * np.sin(theta), -np.sin(phi) * np.cos(theta), np.cos(phi)], axis=1)
    elevation = tangent @ rot.T  # into the reference frame
    delta = rig_case["delta"]
    expected = delta - np.sum(delta * elevation, axis=1, keepdims=True) * elevation
    np.testing.assert_allclose(res.motion, expected, atol=0.01 * np.abs(delta).max())
    assert np.abs(np.sum(res.motion * elevation, axis=1)).max() < 1e-12
    assert res.rank.tolist() == [2] * 40 and res.views.tolist() == [1] * 40


def test_unseen_patches_and_ignored_entries(rig_case):
    motions, seen = observe(rig_case, rig_case["centres"], rig_case["delta"])
    seen = seen.copy()
    seen[:5] = False
    motions = np.where(seen[..., None], motions, np.nan)  # invisible entries are ignored
    res = patch_motions(rig_case["centres"], motions, seen, rig_case["rot"], rig_case["trans"])
    np.testing.assert_array_equal(res.motion[:5], 0.0)
    assert res.rank[:5].tolist() == [0] * 5 and res.views[:5].tolist() == [0] * 5
    assert res.residual[:5].tolist() == [0.0] * 5
    assert np.all(np.isfinite(res.motion)) and np.all(res.rank[5:] == 3)
    seen[5, 0] = True
    motions[5, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        patch_motions(rig_case["centres"], motions, seen, rig_case["rot"], rig_case["trans"])


def test_grid_of_candidates_broadcasts(rig_case):
    # A (D, β) grid: poses and surface gain a leading axis; each cell solves like a lone call.
    scene = rig_case["scene"]
    depth = np.array([0.40, 0.47])
    tilt = np.radians([9.5, 11.1])
    rot, trans = scene.rig.relative_poses(depth, tilt)  # (2, V, 3, 3), (2, V, 3)
    n, d = surface_in_reference(scene.rig, depth, tilt)  # (2, 3), (2,)
    centres = rig_case["centres"][:6]
    q = mirror_points(centres[None], n[:, None, :], d[:, None])  # (2, 6, 3)
    motions = np.random.default_rng(5).normal(0.0, 0.002, (2, 6, 16, 2))
    seen = np.random.default_rng(6).random((6, 16)) < 0.7
    batch = patch_motions(q, motions, seen, rot, trans, surface=(n, d))
    assert batch.motion.shape == (2, 6, 3) and batch.rank.shape == (2, 6)
    for g in range(2):
        one = patch_motions(q[g], motions[g], seen, rot[g], trans[g], surface=(n[g], d[g]))
        np.testing.assert_allclose(batch.motion[g], one.motion, rtol=1e-10, atol=1e-15)
        np.testing.assert_array_equal(batch.rank[g], one.rank)


def dense_patch_motions(centres, motions, visible, rot, trans, plane="fan", surface=None, rcond=1e-2):
    """patch_motions' systems written out whole: every patch's 2V rows, those of the views
    that do not see it zero, solved by ``truncated_lstsq``; (motion, rank, views, residual)."""
    p_view = np.einsum("...kvi,...vij->...kvj", centres[..., :, None, :] - trans[..., None, :, :], rot)
    view_surface = None
    if surface is not None:
        n_view = np.einsum("...vij,...i->...vj", rot, surface[0])
        d_view = surface[1][..., None] - np.einsum("...vi,...i->...v", trans, surface[0])
        view_surface = (n_view[..., None, :, :], d_view[..., None, :])
    shape = np.broadcast_shapes(p_view.shape[:-1], motions.shape[:-1], visible.shape)
    seen = np.broadcast_to(visible, shape)
    p_view = np.where(seen[..., None], p_view, (0.0, 1.0, 0.0))  # a stand-in where not seen
    jac = np.einsum("...kvaj,...vij->...kvai", image_jacobian(p_view, plane=plane, surface=view_surface), rot)
    a = np.where(seen[..., None, None], jac, 0.0).reshape(shape[:-1] + (-1, 3))
    b = np.where(seen[..., None], motions, 0.0).reshape(shape[:-1] + (-1,))
    delta, rank = truncated_lstsq(a, b, rcond)
    views = seen.sum(axis=-1)
    misfit = np.einsum("...ri,...i->...r", a, delta) - b
    residual = np.sqrt(np.divide(np.sum(misfit * misfit, axis=-1), 2 * views, out=np.zeros(views.shape),
                                 where=views > 0))
    return delta, rank, views, residual


@pytest.mark.parametrize("seed", range(12))
def test_patch_motions_solve_the_dense_systems_bit_for_bit(rig_case, seed):
    """Only the (patch, view) pairs that count are computed, and each patch's rows are packed:
    the dense systems' results exactly (their sums run over the same rows in the same order,
    the zero rows adding nothing), lone and on a grid of two, object and mirror, both planes,
    from no pair seen to every pair."""
    rng = np.random.default_rng(seed)
    scene = rig_case["scene"]
    depth = rig_case["depth"] + rng.uniform(-0.05, 0.05, 2)
    tilt = rig_case["tilt"] + rng.uniform(-0.05, 0.05, 2)
    rot, trans = scene.rig.relative_poses(depth, tilt)  # (2, V, 3, 3)
    n, d = surface_in_reference(scene.rig, depth, tilt)
    share = (0.0, 0.03, 0.1, 0.3, 0.7, 1.0)[seed % 6]
    k = int(rng.integers(1, 40))
    centres = rig_case["centres"][:k] + rng.normal(0.0, 0.01, (k, 3))
    motions = rng.normal(0.0, 0.003, (2, k, rot.shape[1], 2))
    seen = rng.random((k, rot.shape[1])) < share
    plane = ("fan", "polar")[seed % 2]
    for g, surface in ((0, None), (1, (n[1], d[1])), (slice(None), None),
                       (slice(None), (n, d))):
        points = centres if surface is None else mirror_points(centres, surface[0][..., None, :],
                                                               np.asarray(surface[1])[..., None])
        got = patch_motions(points, motions[g], seen, rot[g], trans[g], plane=plane, surface=surface)
        want = dense_patch_motions(points, motions[g], seen, rot[g], trans[g], plane=plane, surface=surface)
        for name, value in zip(("motion", "rank", "views", "residual"), want):
            assert getattr(got, name).shape == value.shape, name
            np.testing.assert_array_equal(getattr(got, name), value, err_msg=name)


@pytest.mark.parametrize("kwargs, message", [
    (dict(motions=np.zeros((4, 16, 3))), r"motions \(\.\.\., K, V, 2\)"),
    (dict(visible=np.ones((4, 15), dtype=bool)), "shapes disagree"),
    (dict(visible=np.ones((4, 16))), "bool"),
    (dict(centres=np.full((4, 3), np.nan)), "non-finite"),
    (dict(rcond=0.0), "rcond"),
    (dict(surface=(np.array([0.0, 0.0, 2.0]), 0.4)), "unit"),
    (dict(surface=(np.array([0.0, 0.0, 1.0]), np.nan)), "offset"),
])
def test_patch_motions_rejects_bad_inputs(rig_case, kwargs, message):
    args = dict(centres=rig_case["centres"][:4], motions=np.zeros((4, 16, 2)),
                visible=np.ones((4, 16), dtype=bool), rotations=rig_case["rot"],
                translations=rig_case["trans"])
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        patch_motions(**args)


# --- E_mu (eq. 6) ------------------------------------------------------------------------------

def test_truncated_lstsq_is_numpy_lstsq_with_its_rcond():
    """NumPy's lstsq (SVD; singular values at or below rcond × the largest dropped) is the
    oracle: full-rank, rank-2, rank-1 and all-zero systems, solutions and ranks, and a
    direction just above the cut-off is kept while one just below is dropped."""
    rng = np.random.default_rng(5)
    a = rng.normal(size=(40, 12, 3))
    a[10:20, :, 2] = a[10:20, :, 0] - a[10:20, :, 1]  # rank 2
    a[20:30] = rng.normal(size=(10, 12, 1)) * rng.normal(size=(10, 1, 3))  # rank 1
    a[30:32] = 0.0
    for k, smallest in zip(range(32, 36), (0.008, 0.012, 0.005, 0.02)):  # singular values 1, 0.5, smallest
        u, _ = np.linalg.qr(rng.normal(size=(12, 3)))
        v, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        a[k] = u @ np.diag([1.0, 0.5, smallest]) @ v.T
    b = rng.normal(size=(40, 12))
    rcond = 1e-2
    delta, rank = truncated_lstsq(a, b, rcond)
    for k in range(len(a)):
        want, _, want_rank, _ = np.linalg.lstsq(a[k], b[k], rcond=rcond)
        np.testing.assert_allclose(delta[k], want, rtol=1e-9, atol=1e-12)
        assert rank[k] == want_rank
    assert rank[:10].tolist() == [3] * 10 and rank[10:20].tolist() == [2] * 10
    assert rank[20:30].tolist() == [1] * 10 and rank[30:32].tolist() == [0, 0]
    assert delta[30:32].tolist() == [[0.0] * 3] * 2 and rank[32:36].tolist() == [2, 3, 2, 3]
