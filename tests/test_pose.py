"""Depth and tilt estimation (fsswarp.pose; paper §2.4, DESIGN §7) on the simulated coral-one
(noisy images, the true model)."""

import dataclasses
import json
import math
import warnings

import numpy as np
import pytest
import trimesh
from hypothesis import given
from hypothesis import strategies as st
from scipy.ndimage import distance_transform_edt
from figure_checks import assert_laid_out, captured_figures

from fsswarp.backends import get_backend
from fsswarp.cli import main
from fsswarp.dataset import Dataset
from fsswarp.errors import InputError
from fsswarp.figures import contours_figure, pose_figure
from fsswarp.icp import icp_many
from fsswarp.compare import (PoseSettings, PoseWarning, ViewComparison, _parabola_minimum, _view_cost,
                             contour_distance, detection_threshold, view_contours)
from fsswarp.pose import Prior, estimate_pose, pose_objective
from fsswarp.rig import Rig
from fsswarp.surface import COMPONENTS


@pytest.fixture(scope="module")
def truth_model(coral_one):
    return trimesh.load(coral_one.truth_model_path, process=False)


@pytest.fixture(scope="module")
def opencl():
    return get_backend("opencl")


@pytest.fixture(scope="module")
def truth_comparison(coral_one, truth_model, opencl):
    truth = coral_one.manifest.truth
    return ViewComparison(coral_one, backend=opencl).use(truth_model, truth.depth, truth.tilt)


#: No prior: the images alone (σ → ∞), the plain E_mu estimate.
FLAT = dict(depth_sigma=math.inf, tilt_sigma=math.inf)


@pytest.fixture(scope="module")
def estimate(coral_one, truth_model, opencl):
    """estimate_pose with no prior from initial errors of +4 cm in D and -1.5° in β, over a
    box of ± 6 cm and ± 2.4°."""
    truth = coral_one.manifest.truth
    lines = []
    result = estimate_pose(truth_model, coral_one, depth0=truth.depth + 0.04, tilt0=truth.tilt - math.radians(1.5),
                           bounds=(0.06, math.radians(2.4)), prior=Prior(truth.depth, truth.tilt, **FLAT),
                           backend=opencl, progress=lines.append)
    return result, lines


def test_recovers_depth_and_tilt(coral_one, estimate):
    result, lines = estimate
    truth = coral_one.manifest.truth
    assert abs(result.depth - truth.depth) <= 0.005
    assert abs(math.degrees(result.tilt - truth.tilt)) <= 0.2
    assert result.accepted and result.error_after < 0.2 * result.error_before
    assert (result.depth, result.tilt) == result.candidate
    # the grid spans the given box, halving per level
    assert [level.costs.shape for level in result.levels] == [(9, 9)] * 3
    first = result.levels[0]
    assert first.depths[-1] - first.depths[0] == pytest.approx(0.12)
    assert math.degrees(first.tilts[-1] - first.tilts[0]) == pytest.approx(4.8)
    spacing = [level.depths[1] - level.depths[0] for level in result.levels]
    assert spacing == pytest.approx([0.015, 0.0075, 0.00375])
    # three levels and the posterior's grid of 11 x 11 cells, refitted at most twice
    assert result.evaluations["grid_cells"] in (243 + 121, 243 + 242, 243 + 363) and 3 <= result.evaluations["exact"] <= 32
    assert result.anchors == ("Sm90", "Sm67p5", "Sm45", "Sp45", "Sp67p5") and 0.5 < result.shift < 1.5
    assert len(lines) == 6 and lines[0].startswith("start:") and "accepted" in lines[-1]
    assert result.views == tuple(v.name for v in coral_one.rig.views if v.optimize)


def test_mirror_term_only_where_the_mirror_is_distinct(coral_one, truth_model, opencl):
    # every view optimized: at roll 0 the mirror falls on the object and ghost, so those views
    # keep the object term only; at |roll| >= 45 deg it stands apart
    rig = coral_one.rig
    every = Rig(tuple(dataclasses.replace(v, optimize=True) for v in rig.views), rig.reference)
    dataset = Dataset(dataclasses.replace(coral_one.manifest, rig=every), coral_one.images, coral_one.root)
    truth = coral_one.manifest.truth
    comparison = ViewComparison(dataset, backend=opencl).use(truth_model, truth.depth + 0.03,
                                                          truth.tilt + math.radians(1.0))
    mirror = set(comparison.data.mirror_views)
    assert not mirror & {"S0", "N0"}
    assert {v.name for v in rig.views if abs(math.degrees(v.roll)) >= 45} <= mirror
    counts = dict(zip(comparison.data.names, comparison.data.counts.tolist()))
    assert all(counts[name][0] >= 10 for name in counts)  # every view has its object contour


def test_synthetic_contours_meet_the_data_contours(coral_one, truth_comparison):
    # the true noise-free layers' detection contours against the noisy data's first highlight
    # rows: on average 0.5 row (the data's whole rows) plus a small detection bias
    data = truth_comparison.data
    layers = np.stack([np.stack([coral_one.truth_layer(n, c) for c in COMPONENTS]) for n in data.names])
    contours, _, _ = truth_comparison.backend.contour_cost(layers, np.arange(len(layers)), data.threshold, data.windows,
                                                        data.masks, data.distances, [0.0], truth_comparison.smoothing)
    both = (contours >= 0) & (data.rows >= 0)
    offset = (data.rows - contours)[both]
    assert both[:, 0].sum() >= 150 and both[:, 1].sum() >= 100
    assert 0.5 <= np.median(offset) <= 1.25
    assert np.mean(np.abs(offset - np.median(offset)) <= 2.0) >= 0.9


def test_surrogate_and_exact_minima_agree(coral_one, truth_comparison):
    # a 5 x 5 grid around the truth at 5 mm x 0.2 deg: both objectives are smallest at the truth
    truth = coral_one.manifest.truth
    depths, tilts = np.meshgrid(truth.depth + np.linspace(-0.01, 0.01, 5),
                                truth.tilt + np.radians(np.linspace(-0.4, 0.4, 5)), indexing="ij")
    surrogate = truth_comparison.surrogate(depths, tilts)
    exact = np.vectorize(lambda d, t: truth_comparison.exact(d, t).value)(depths, tilts)
    assert np.unravel_index(np.argmin(surrogate), surrogate.shape) == (2, 2)
    assert np.unravel_index(np.argmin(exact), exact.shape) == (2, 2)
    assert exact[2, 2] < 0.004 and surrogate[2, 2] < 0.013  # metres
    assert np.all(np.isfinite(surrogate)) and np.all(np.isfinite(exact))


def test_pose_objective_is_e_mu(coral_one, truth_model, opencl):
    truth = coral_one.manifest.truth
    value = pose_objective(truth_model, coral_one, truth.depth, truth.tilt, backend=opencl)
    comparison = ViewComparison(coral_one, backend=opencl).use(truth_model, truth.depth, truth.tilt)
    detail = comparison.exact(truth.depth, truth.tilt)
    assert value == detail.value
    assert detail.per_view.shape == (10,) and np.all(np.isfinite(detail.per_view))
    assert detail.value == pytest.approx(np.mean(detail.per_view))
    assert detail.object_patches >= 50 and detail.mirror_patches >= 50


def test_e_mu_aligns_on_the_device_where_it_has_float64(coral_one, truth_comparison, opencl, monkeypatch):
    """ViewComparison.align runs ICP on the backend's device when it has float64 (one thread per
    run), else on the host (k-d tree); E_mu is the same either way, up to rounding."""
    import fsswarp.compare

    used = []

    def spy(*args, **kwargs):
        used.append(kwargs["backend"])
        return icp_many(*args, **kwargs)

    monkeypatch.setattr(fsswarp.compare, "icp_many", spy)
    truth = coral_one.manifest.truth
    on_device = truth_comparison.exact(truth.depth, truth.tilt)
    monkeypatch.setattr(opencl, "has_float64", False)
    on_host = truth_comparison.exact(truth.depth, truth.tilt)
    assert used == [opencl, None]
    assert on_device.value == pytest.approx(on_host.value, rel=1e-9)
    np.testing.assert_allclose(on_device.per_view, on_host.per_view, rtol=1e-9)


def _oracle_frontal_faces(mesh, sonar, rot, t, n, d, theta, rays: int, mirror: bool) -> np.ndarray:
    """ViewComparison.frontal_faces of one view by float64 trimesh ray casts: per beam the face
    hit at the shortest range (object) or mirror range (|P| + |Q| + |P - Q|)/2 over the beam's
    elevation rays (mirror: the ray meets the surface at Q first, is reflected to P, and P is in
    the fan and visible from the sonar)."""
    from oracle_render import first_hits, make_intersector

    from fsswarp.backends import RAY_EPSILON as EPSILON, FRONTAL_VISIBLE as VISIBLE

    hits = make_intersector(mesh)
    phi = -sonar.half_elevation + (np.arange(rays) + 0.5) / rays * sonar.elevation_fov
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    u = np.stack([np.cos(ph) * np.sin(th), np.cos(ph) * np.cos(th), np.sin(ph)], axis=-1).reshape(-1, 3)
    up = u @ n
    surface = np.where(up > 0, d / np.where(up > 0, up, 1.0), np.inf)
    dist, face = first_hits(hits, np.tile(t, (len(u), 1)), u @ rot.T)
    rng = np.where(dist < surface, dist, np.inf)
    if mirror:
        rng, face = np.full(len(u), np.inf), np.full(len(u), -1)
        i = np.flatnonzero(np.isfinite(surface) & (surface < dist))
        q = u[i] * surface[i, None]
        w = u[i] - 2.0 * up[i, None] * n
        r2, hit = first_hits(hits, (q + EPSILON * w) @ rot.T + t, w @ rot.T)
        ok = np.isfinite(r2)
        i, q, w, r2, hit = i[ok], q[ok], w[ok], r2[ok] + EPSILON, hit[ok]
        p = q + r2[:, None] * w
        length = np.linalg.norm(p, axis=1)
        back, _ = first_hits(hits, np.tile(t, (len(p), 1)), (p / length[:, None]) @ rot.T)
        seen = (np.abs(np.arcsin(p[:, 2] / length)) <= sonar.half_elevation) \
            & (np.abs(np.arctan2(p[:, 0], p[:, 1])) <= sonar.half_azimuth) & (back >= length - VISIBLE)
        rng[i[seen]] = 0.5 * (length[seen] + surface[i[seen]] + r2[seen])
        face[i[seen]] = hit[seen]
    rng, face = rng.reshape(len(theta), rays), face.reshape(len(theta), rays)
    best = np.argmin(rng, axis=1)
    rows = np.arange(len(theta))
    return np.where(np.isfinite(rng[rows, best]), face[rows, best], -1)


@pytest.mark.parametrize("mirror", [False, True], ids=["object", "mirror"])
def test_frontal_faces_match_a_ray_casting_oracle_and_do_not_depend_on_the_batch(coral_one, truth_model, backend,
                                                                                mirror):
    """Every optimized view in one call (some with a subset of the beams): per beam the same
    face as the float64 trimesh oracle, bar near-ties between neighbouring rays, and exactly
    what each view gives alone."""
    truth = coral_one.manifest.truth
    comparison = ViewComparison(coral_one, settings=PoseSettings(patch_rays=16),
                             backend=backend).use(truth_model, truth.depth, truth.tilt)
    rot, t, n, d = (a[0] for a in comparison.view_poses(comparison.data.views, [truth.depth], [truth.tilt]))
    sonar = coral_one.sonar
    thetas = [sonar.beam_centres] * len(rot)
    thetas[1], thetas[2] = sonar.beam_centres[::2], sonar.beam_centres[30:70]
    together = comparison.frontal_faces(rot, t, n, d, thetas, mirror=mirror)
    for k in (0, 1, 2, len(rot) - 1):
        alone = comparison.frontal_faces(rot[k:k + 1], t[k:k + 1], n[k:k + 1], d[k:k + 1], [thetas[k]], mirror=mirror)
        np.testing.assert_array_equal(together[k], alone[0])
    found = np.concatenate(together)
    want = np.concatenate([_oracle_frontal_faces(truth_model, sonar, rot[k], t[k], n[k], float(d[k]), theta, 16,
                                                 mirror) for k, theta in enumerate(thetas)])
    assert (want >= 0).sum() >= 100
    assert np.mean(found == want) >= 0.98
    assert comparison.frontal_faces(rot[:0], t[:0], n[:0], d[:0], [], mirror=mirror) == []
    mixed = np.arange(len(rot)) % 2 == 0  # object beams and mirror beams in one launch
    other = comparison.frontal_faces(rot, t, n, d, thetas, mirror=not mirror)
    both = comparison.frontal_faces(rot, t, n, d, thetas, mirror=np.where(mixed, mirror, not mirror))
    for k in range(len(rot)):
        np.testing.assert_array_equal(both[k], together[k] if mixed[k] else other[k])


def test_costs_at_the_estimate_read_the_located_layers(coral_one, truth_model, backend):
    """One cell at the located estimate with the exact samples reads ``predicted`` instead of
    rendering: bit for bit what rendering the cell gives (a batch of two renders), also after
    ``locate`` moves the estimate."""
    truth = coral_one.manifest.truth
    comparison = ViewComparison(coral_one, backend=backend).use(truth_model, truth.depth + 0.01, truth.tilt)
    exact = comparison.settings.exact_samples
    for depth in (truth.depth + 0.01, truth.depth):
        comparison.locate(depth, truth.tilt)
        one = comparison.view_costs(np.array([depth]), np.array([truth.tilt]), exact, 0.02)
        two = comparison.view_costs(np.array([depth] * 2), np.array([truth.tilt] * 2), exact, 0.02)
        for alone, rendered in zip(one, two):
            np.testing.assert_array_equal(alone[0], rendered[0])
            np.testing.assert_array_equal(rendered[0], rendered[1])
        assert (one[1] >= 0).sum() > 100


def test_surrogate_views_combine_the_costs_on_the_device_as_the_host_did(coral_one, truth_model, backend):
    """``surrogate_views`` reads only the device's view costs (``Backend.view_costs``): the per-view
    costs of the host's float64 combination of the contour sums (``view_costs(contours=True)``,
    the former path) at the same best shift, within float32 rounding; with the detection shift,
    without one (each cell's best of every candidate shift), and for the located cell."""
    truth = coral_one.manifest.truth
    comparison = ViewComparison(coral_one, backend=backend).use(truth_model, truth.depth, truth.tilt)
    depths, tilts = np.meshgrid(truth.depth + np.array([-0.02, 0.0, 0.03]), truth.tilt + np.radians([-1.0, 0.5]),
                                indexing="ij")
    samples, cap = (1, 32), 0.03
    assert comparison.shift is not None
    for shift in (comparison.shift, None):
        comparison.shift = shift
        for d, t, sam in ((depths, tilts, samples), (np.array([truth.depth]), np.array([truth.tilt]),
                                                     comparison.settings.exact_samples)):
            costs, contours = comparison.view_costs(d.ravel(), t.ravel(), sam, cap, contours=True)
            best = np.argmin(costs.mean(axis=1), axis=-1)
            want = costs[np.arange(len(best)), :, best].reshape(d.shape + (costs.shape[1],))
            got = comparison.surrogate_views(d, t, cap=cap, samples=sam)
            assert got.shape == want.shape and got.dtype == np.float64
            assert np.all(want > 0) and (contours >= 0).sum() > 100
            np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-7)
        assert costs.shape[-1] == (1 if shift is not None else len(comparison.shifts))


def test_planning_ahead_keeps_the_order_and_plans_the_next_while_this_one_is_used():
    """``_planned``: each item's plan in order; with ``ahead`` the next item's plan is made in
    another thread before this one is handed over, and a failing plan raises at its own item."""
    import threading

    from fsswarp.compare import _planned

    events, started = [], {item: threading.Event() for item in "abc"}

    def plan(item):
        if item == "bad":
            raise InputError("no plan", field="item", value=item)
        events.append(("planned", item, threading.current_thread() is threading.main_thread()))
        started[item].set()
        return item * 2

    for item, made in zip("abc", _planned(plan, "abc", ahead=True)):
        assert made == item * 2
        if item != "c":  # the next plan is made while this item is in use
            assert started[chr(ord(item) + 1)].wait(timeout=10)
    assert events == [("planned", x, False) for x in "abc"]
    assert list(_planned(plan, "ab", ahead=False)) == ["aa", "bb"]
    used = []
    with pytest.raises(InputError, match="no plan"):
        for made in _planned(plan, ["a", "bad", "c"], ahead=True):
            used.append(made)
    assert used == ["aa"]


def test_view_costs_planned_ahead_are_those_planned_in_turn(coral_one, truth_model, opencl, monkeypatch):
    """Over several launches, the costs and contours with each launch's host work done in a
    thread while the one before renders, and a short first launch (as on a GPU), are those made
    one after another, bit for bit."""
    import fsswarp.compare as compare

    truth = coral_one.manifest.truth
    comparison = ViewComparison(coral_one, settings=PoseSettings(launch_bytes=1 << 21), backend=opencl).use(
        truth_model, truth.depth, truth.tilt)
    depths, tilts = np.meshgrid(truth.depth + np.linspace(-0.02, 0.02, 3), truth.tilt + np.radians([-1.0, 0.0, 1.0]),
                                indexing="ij")
    assert comparison.grid_launches()[3] < depths.size / 2  # several launches
    want = comparison.view_costs(depths.ravel(), tilts.ravel(), (1, 32), 0.03)
    original = compare._planned
    ahead = []
    monkeypatch.setattr(compare, "_planned", lambda plan, items, ahead: original(plan, items, ahead=True))
    monkeypatch.setattr(compare, "FIRST_LAUNCH_SHARE", 0.25)
    monkeypatch.setattr(compare, "FIRST_LAUNCH_CELLS", 1)  # a first launch of one cell, then twice that, up to 4
    assert compare._launches(9, 4, True) == [slice(0, 1), slice(1, 3), slice(3, 7), slice(7, 9)]
    assert compare._launches(9, 4, False) == [slice(0, 4), slice(4, 8), slice(8, 9)]
    monkeypatch.setattr(comparison, "plan_pairs", lambda *a, **k: ahead.append(1) or ViewComparison.plan_pairs(
        comparison, *a, **k))
    got = comparison.view_costs(depths.ravel(), tilts.ravel(), (1, 32), 0.03)
    assert len(ahead) > 2
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)


def test_queued_launches_read_after_the_last_give_the_same_costs(coral_one, truth_model, backend, monkeypatch):
    """On a GPU the grid's launches are queued and their costs read after the last
    (``view_costs(contours=False)``; ``render_planned(wait=False)``): bit for bit the costs of
    launches waited for one by one. With a one-slot queue of hits every render overflows: Warp
    then renders each launch again, waiting, once all are queued (OpenCL waits in the render and
    renders again there), and the costs are still the same."""
    truth = coral_one.manifest.truth
    comparison = ViewComparison(coral_one, settings=PoseSettings(launch_bytes=1 << 21), backend=backend).use(
        truth_model, truth.depth, truth.tilt)
    depths, tilts = np.meshgrid(truth.depth + np.linspace(-0.02, 0.02, 3), truth.tilt + np.radians([-1.0, 0.0, 1.0]),
                                indexing="ij")
    launches = len(range(0, depths.size, comparison.grid_launches()[3]))
    assert launches > 2
    monkeypatch.setattr(backend, "is_gpu", False)
    want = comparison.view_costs(depths.ravel(), tilts.ravel(), (1, 32), 0.03, contours=False)[0]
    monkeypatch.setattr(backend, "is_gpu", True)
    waits = []
    render = comparison._render_planned
    monkeypatch.setattr(comparison, "_render_planned", lambda plan, wait=True: waits.append(wait) or render(plan, wait))
    for share in (None, 1e-12):
        if share is not None:
            monkeypatch.setattr(type(backend), "hit_queue", property(lambda self: share))
        waits.clear()
        got = comparison.view_costs(depths.ravel(), tilts.ravel(), (1, 32), 0.03, contours=False)[0]
        np.testing.assert_array_equal(got, want)
        queued = waits.count(False)
        assert queued >= launches and waits[:queued] == [False] * queued
        made_again = share is not None and backend.name == "warp"
        assert waits[queued:] == [True] * (queued if made_again else 0)


def test_grid_launches_hold_at_most_the_launch_bytes_and_2_31_values(coral_one, truth_model, opencl):
    """Cells per launch: the components' sums' 8 B per pixel within ``launch_bytes``, and never
    past one launch's 2^31 values (a render refuses more), however many bytes are allowed."""
    truth = coral_one.manifest.truth
    for size, binds in ((1 << 30, "bytes"), (1 << 40, "values")):
        comparison = ViewComparison(coral_one, settings=PoseSettings(launch_bytes=size), backend=opencl).use(
            truth_model, truth.depth, truth.tilt)
        _, rows, _, per = comparison.grid_launches()
        values = 2 * rows * coral_one.sonar.beams * len(comparison.data.views)
        assert 4 * values * per <= size and per * values < 2**31
        assert (4 * values * (per + 1) > size) if binds == "bytes" else ((per + 1) * values >= 2**31)


def test_grid_launches_hold_below_2_31_sub_rays(truth_comparison, monkeypatch):
    """With many sub-rays per beam the grid's launches hold fewer cells: one launch's views ×
    beams × K_θ × K_φ stay below 2^31 (a render refuses more), at least one cell a launch."""
    from fsswarp import compare

    class Planned(Exception):
        pass

    seen = []

    def launches(cells, per, ahead):
        seen.append(per)
        raise Planned

    monkeypatch.setattr(compare, "_launches", launches)
    truth = truth_comparison.data
    views = len(truth.views)
    for samples in ((2, 64), (256, 256)):
        with pytest.raises(Planned):
            truth_comparison.view_costs(np.array([0.43, 0.44]), np.array([0.18, 0.18]), samples, 0.03)
    beams = truth_comparison.sonar.beams
    assert seen[0] == truth_comparison.grid_launches()[3] == truth_comparison.grid_launches((2, 64))[3]
    assert seen[0] * views * beams * 2 * 64 < 2**31
    assert seen[1] * views * beams * 2**16 < 2**31 <= (seen[1] + 1) * views * beams * 2**16


def test_a_gpu_locates_without_the_host_copy(coral_one, truth_model, opencl, monkeypatch):
    """On a GPU, locating scans the predicted views from row 0 and leaves their host copy
    unread until ``predicted`` is read: the same data contours, anchors, shift, layers and
    E_mu as the CPU's scan from ``scan_start`` with the copy read at once."""
    truth = coral_one.manifest.truth
    depth, tilt = truth.depth + 0.01, truth.tilt
    cpu = ViewComparison(coral_one, backend=opencl).use(truth_model, depth, tilt)
    monkeypatch.setattr(opencl, "is_gpu", True)
    gpu = ViewComparison(coral_one, backend=opencl).use(truth_model, depth, tilt)
    assert cpu._predicted is not None and gpu._predicted is None
    for name in (f.name for f in dataclasses.fields(cpu.data)):
        np.testing.assert_array_equal(getattr(gpu.data, name), getattr(cpu.data, name), err_msg=name)
    assert (gpu.anchors, gpu.shift) == (cpu.anchors, cpu.shift) and gpu.anchors
    np.testing.assert_array_equal(gpu.exact(depth, tilt).per_view, cpu.exact(depth, tilt).per_view)
    assert gpu._predicted is None  # E_mu at the estimate costs the device layers
    np.testing.assert_array_equal(gpu.predicted, cpu.predicted)


def test_a_relocated_comparison_reads_its_new_data_contours(coral_one, truth_model, opencl):
    """After ``locate`` moves a used comparison, its surrogate and E_mu are a fresh comparison's there,
    bit for bit (nothing of the old data contours, e.g. their capped distances, stays)."""
    truth = coral_one.manifest.truth
    depth, tilt = truth.depth, truth.tilt
    moved = ViewComparison(coral_one, backend=opencl).use(truth_model, depth + 0.05, tilt + math.radians(1.0))
    moved.surrogate(depth, tilt)
    moved.exact(depth, tilt)
    moved.locate(depth, tilt)
    fresh = ViewComparison(coral_one, backend=opencl).use(truth_model, depth, tilt)
    away = ViewComparison(coral_one, backend=opencl).use(truth_model, depth + 0.05, tilt + math.radians(1.0))
    assert not np.array_equal(away.data.distances, fresh.data.distances)
    cells = (np.array([depth, depth + 0.01]), np.array([tilt, tilt]))
    np.testing.assert_array_equal(moved.surrogate(*cells), fresh.surrogate(*cells))
    np.testing.assert_array_equal(moved.exact(depth, tilt).per_view, fresh.exact(depth, tilt).per_view)


def test_frontal_faces_warp_and_opencl_agree(coral_one, truth_model, backend_for_label):
    """Both backends' kernels, every beam of every view 1 cm and 0.3 deg off the truth: the same
    faces bar float32 near-ties between a beam's rays."""
    warp, opencl = backend_for_label("warp-cpu"), backend_for_label("opencl-cpu")
    truth = coral_one.manifest.truth
    comparison = ViewComparison(coral_one, backend=opencl).use(truth_model, truth.depth, truth.tilt)
    poses = comparison.view_poses(comparison.data.views, [truth.depth + 0.01], [truth.tilt + np.radians(0.3)])
    rot, t, n, d = (a[0] for a in poses)
    beams = coral_one.sonar.beam_centres
    views, azimuths = np.repeat(np.arange(len(rot)), len(beams)), np.tile(beams, len(rot))
    for mirror in (False, True):
        found = [b.frontal_faces(b.load_mesh(truth_model.vertices, truth_model.faces), coral_one.sonar, rot, t, n, d,
                                 views, azimuths, 16, mirror=mirror) for b in (warp, opencl)]
        assert found[0].dtype == np.int32 and found[0].shape == views.shape
        assert (found[0] >= 0).sum() >= 100
        assert np.mean(found[0] == found[1]) >= 0.999


def test_frontal_faces_validates(coral_one, truth_model, backend):
    handle = backend.load_mesh(truth_model.vertices, truth_model.faces)
    rot, t, n, d = np.eye(3)[None], np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), np.array([0.5])
    sonar = coral_one.sonar
    assert backend.frontal_faces(handle, sonar, rot, t, n, d, np.zeros(0, int), np.zeros(0), 4,
                                 mirror=True).shape == (0,)
    for views, azimuths, rays, match in (([0, 0], [0.1], 4, "views must be .* like azimuths"),
                                         ([1], [0.1], 4, "views must be a 1-D integer array of views 0..0"),
                                         ([0.0], [0.1], 4, "views must be"), ([0], [0.1], 0, "rays"),
                                         ([0], [np.nan], 4, "azimuths")):
        with pytest.raises(ValueError, match=match):
            backend.frontal_faces(handle, sonar, rot, t, n, d, views, azimuths, rays, mirror=False)
    with pytest.raises(ValueError, match="same views"):
        backend.frontal_faces(handle, sonar, rot, t, n, np.array([0.5, 0.5]), [0], [0.1], 4, mirror=False)
    for mirror in ([True, False], 1, np.array([1], np.uint8)):
        with pytest.raises(ValueError, match="mirror must be a bool"):
            backend.frontal_faces(handle, sonar, rot, t, n, d, [0], [0.1], 4, mirror=mirror)


def test_figure(tmp_path, coral_one, estimate, monkeypatch):
    truth = coral_one.manifest.truth
    kept = captured_figures(monkeypatch)
    path = pose_figure(estimate[0], tmp_path / "pose.png", truth=(truth.depth, truth.tilt), title="coral-one")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert_laid_out(kept[0])


def test_bad_input(coral_one, truth_model, opencl):
    truth = coral_one.manifest.truth
    rig = coral_one.rig
    none = Rig(tuple(dataclasses.replace(v, optimize=False) for v in rig.views), rig.reference)
    held_out = Dataset(dataclasses.replace(coral_one.manifest, rig=none), coral_one.images, coral_one.root)
    with pytest.raises(InputError, match="views.optimize = False: no view takes part"):
        estimate_pose(truth_model, held_out, backend=opencl)
    far = truth_model.copy()
    far.vertices += (0.0, 10.0, 0.0)
    with pytest.raises(InputError, match="model = .*: the model is seen in none of the views"):
        pose_objective(far, coral_one, truth.depth, truth.tilt, backend=opencl)
    with pytest.raises(InputError, match="holds no triangles"):
        pose_objective(trimesh.Trimesh(), coral_one, truth.depth, truth.tilt, backend=opencl)
    with pytest.raises(InputError, match="bounds"):
        estimate_pose(truth_model, coral_one, bounds=(0.0, 0.01), backend=opencl)
    with pytest.raises(InputError, match="levels"):
        estimate_pose(truth_model, coral_one, levels=0, backend=opencl)
    with pytest.raises(InputError, match="tilt"):
        estimate_pose(truth_model, coral_one, tilt0=math.radians(95.0), backend=opencl)
    with pytest.raises(InputError, match="pose.grid"):
        PoseSettings(grid=(2, 9))
    with pytest.raises(InputError, match="pose.coarse_samples"):
        PoseSettings(coarse_samples=(0, 16))
    comparison = ViewComparison(coral_one, backend=opencl).use(truth_model, truth.depth, truth.tilt)
    with pytest.raises(InputError, match="cap = 0.06: must be a distance in"):
        comparison.surrogate(truth.depth, truth.tilt, cap=0.06)  # beyond the distances kept (5 cm)


def test_detection_threshold_is_kept_per_image_content():
    """The memo of fsswarp.segment: an equal image gets the kept (read-only) threshold, a
    changed one its own."""
    rng = np.random.default_rng(4)
    image = rng.exponential(1.0, (64, 24)).astype(np.float32)
    image[20:25, 5:9] += 50.0
    first = detection_threshold(image)
    assert detection_threshold(image.copy()) is first and not first.flags.writeable
    brighter = image.copy()
    brighter[:, 0] += 10.0
    assert detection_threshold(brighter) is not first


class _SamplesSpy:
    """A backend that records the sub-ray samples and view count of every render launch."""

    def __init__(self, backend):
        self.backend, self.launches = backend, []

    def __getattr__(self, name):
        return getattr(self.backend, name)

    def render_planned(self, mesh, sonar, plan, **kwargs):
        self.launches.append(((plan.k_theta, plan.k_phi), len(plan.rotations)))
        return self.backend.render_planned(mesh, sonar, plan, **kwargs)


def test_grid_levels_before_the_finest_use_the_coarse_samples(coral_one, truth_model, opencl):
    truth = coral_one.manifest.truth
    spy = _SamplesSpy(opencl)
    settings = PoseSettings(grid=(3, 3), coarse_samples=(1, 8), samples=(2, 16), exact_samples=(2, 32), polish=0)
    result = estimate_pose(truth_model, coral_one, depth0=truth.depth, tilt0=truth.tilt, levels=3,
                           settings=settings, backend=spy)
    views = len(result.views)
    grid_launches = [samples for samples, n in spy.launches if n == 9 * views]
    assert grid_launches == [(1, 8), (1, 8), (2, 16)]
    posterior = [samples for samples, n in spy.launches if n == 121 * views]  # fitted coarsely, then finest
    assert posterior[-1] == (2, 16) and set(posterior[:-1]) <= {(1, 8)} and 2 <= len(posterior) <= 3
    assert {samples for samples, n in spy.launches if n not in (9 * views, 121 * views)} == {(2, 32)}  # E_mu


@given(st.lists(st.integers(-1, 40), min_size=1, max_size=12), st.integers(41, 48),
       st.floats(0.002, 0.02), st.floats(0.001, 0.01), st.floats(0.005, 0.08))
def test_contour_distance_is_the_euclidean_distance_transform_saturated(rows, bins, range_step, arc, reach):
    rows = np.array(rows)
    pixels = np.ones((bins, len(rows)), bool)
    beams = np.flatnonzero(rows >= 0)
    pixels[rows[beams], beams] = False
    expected = distance_transform_edt(pixels, sampling=(range_step, arc)) if beams.size \
        else np.full(pixels.shape, np.inf)
    got = contour_distance(rows, bins, range_step, arc, reach)
    assert got.dtype == np.float32 and got.shape == (bins, len(rows))
    np.testing.assert_allclose(got, np.minimum(expected, reach), rtol=1e-6, atol=0)


def test_located_comparisons_share_their_data_distance_maps(coral_one, truth_comparison):
    """A located comparison's data distances are contour_distance's maps of its data contours;
    a comparison located on the same contours reuses them (read-only, one copy per map)."""
    from fsswarp.compare import _remembered_distance

    sonar, data = coral_one.sonar, truth_comparison.data
    rows = data.rows[0, 0]
    arc = float(np.median(sonar.bin_range(rows[rows >= 0]))) * float(np.mean(np.diff(sonar.beam_centres)))
    np.testing.assert_array_equal(data.distances[0, 0],
                                  contour_distance(rows, sonar.bins, sonar.range_step, arc, truth_comparison.reach))
    first = truth_comparison._distance(rows)
    assert truth_comparison._distance(rows.copy()) is first and not first.flags.writeable
    assert _remembered_distance.cache_info().hits >= 1


def test_relocating_on_the_same_data_contours_keeps_their_maps_and_device_copy(coral_one, truth_model, opencl):
    """Locating again where the data contours do not change (a nearby estimate) keeps the same
    read-only distance maps and their device copy; where they change, new maps are made, each
    the map of its contour."""
    truth = coral_one.manifest.truth
    comparison = ViewComparison(coral_one, backend=opencl).use(truth_model, truth.depth, truth.tilt)
    maps, device, goals = comparison.data.distances, comparison._distances, comparison._goals
    comparison.use(truth_model, truth.depth + 1e-5, truth.tilt)
    assert comparison.estimate[0] != truth.depth  # located again
    assert comparison.data.distances is maps and comparison._distances is device and comparison._goals is goals
    assert not maps.flags.writeable
    rows = comparison.data.rows.copy()
    rows[0, 0, rows[0, 0] >= 0] += 3  # a moved contour
    moved = comparison._data_distances_of(comparison.data.views, rows)
    assert moved is not maps and np.array_equal(moved[1:], maps[1:])
    np.testing.assert_array_equal(moved[0, 0], comparison._distance(rows[0, 0]))
    assert not np.array_equal(moved[0, 0], maps[0, 0])


def test_an_equal_model_keeps_the_loaded_mesh_and_its_location(coral_one, truth_model, opencl):
    """A new model object with the same vertices and faces (as refinement makes of the model it
    is given) is neither loaded nor located again; one that moved, or whose vertices the caller
    changed in place after using it, is."""
    truth = coral_one.manifest.truth
    model = truth_model.copy()
    comparison = ViewComparison(coral_one, backend=opencl).use(model, truth.depth, truth.tilt)
    mesh, data = comparison.mesh, comparison.data
    comparison.use(truth_model.copy(), truth.depth, truth.tilt)
    assert comparison.mesh is mesh and comparison.data is data
    moved = truth_model.copy()
    moved.vertices += (0.0, 0.0, 0.002)
    comparison.use(moved, truth.depth, truth.tilt)
    assert comparison.mesh is not mesh and comparison.data is not data
    mesh = comparison.mesh
    moved.vertices -= (0.0, 0.0, 0.002)  # back where the model was, in place
    comparison.use(truth_model.copy(), truth.depth, truth.tilt)
    assert comparison.mesh is not mesh
    np.testing.assert_array_equal(comparison.vertices, truth_model.vertices)


def test_contour_errors_at_the_estimate_are_found_once_per_location(coral_one, truth_model, opencl, monkeypatch):
    """CE at the located estimate is computed once (refinement's last CE, then E_I's) and handed
    out as a copy; elsewhere, or once located again, it is computed anew: the same values."""
    truth = coral_one.manifest.truth
    comparison = ViewComparison(coral_one, backend=opencl).use(truth_model, truth.depth, truth.tilt)
    aligned = []
    align = ViewComparison.align
    monkeypatch.setattr(ViewComparison, "align", lambda self, *a, **k: aligned.append(1) or align(self, *a, **k))
    first = comparison.contour_errors(truth.depth, truth.tilt)
    first[:] = 1.0  # the caller's copy
    again = comparison.contour_errors(truth.depth, truth.tilt)
    assert len(aligned) == 1 and not np.any(again == 1.0)
    elsewhere = comparison.contour_errors(truth.depth + 0.002, truth.tilt)
    assert len(aligned) == 2 and not np.array_equal(elsewhere, again, equal_nan=True)
    comparison.use(truth_model, truth.depth + 0.002, truth.tilt)
    np.testing.assert_array_equal(comparison.contour_errors(truth.depth + 0.002, truth.tilt), elsewhere)
    assert len(aligned) == 3


def test_an_open_model_is_judged_once_for_its_faces(coral_one, truth_model, opencl):
    """An open model warns when it is loaded; a moved copy of it (the faces in use) is not
    judged again; a model of other faces is, and the open one again after it."""
    from fsswarp.rendering import RenderWarning

    truth = coral_one.manifest.truth
    holed = trimesh.Trimesh(truth_model.vertices, truth_model.faces[1:], process=False)
    moved = trimesh.Trimesh(truth_model.vertices + 0.001, truth_model.faces[1:], process=False)
    comparison = ViewComparison(coral_one, backend=opencl)
    for model, warns in ((holed, True), (moved, False), (truth_model, False), (holed, True)):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            comparison.use(model, truth.depth, truth.tilt)
        assert any(issubclass(w.category, RenderWarning) for w in caught) == warns


def _data_windows_one_view_at_a_time(contour, highlight, pad, margin, min_mirror):
    """_data_windows written view by view (the oracle): each view's window slice of its highlights."""
    beams, bins = contour.shape[2], highlight.shape[1]
    index = np.arange(beams)
    windows, masks, rows = [], [], []
    for k in range(contour.shape[0]):
        points = contour[k][contour[k] >= 0]
        lo, hi = int(math.floor(points.min())) - pad, int(math.ceil(points.max())) + pad + 1
        lo, hi = max(lo, 0), min(hi, bins)
        span = np.flatnonzero(contour[k, 0] >= 0)
        obj = (index >= span.min() - margin) & (index <= span.max() + margin)
        lit = highlight[k][lo:hi]
        first_row = np.where(lit.any(axis=0), lit.argmax(axis=0) + lo, -1)
        left, right = index < span.min() - margin, index > span.max() + margin
        found = first_row >= 0
        mirror = left if np.sum(found & left) > np.sum(found & right) else right
        if np.sum(found & mirror) < min_mirror:
            mirror = np.zeros_like(obj)
        windows.append((lo, hi))
        masks.append(np.stack([obj, mirror]))
        rows.append(np.stack([np.where(obj, first_row, -1), np.where(mirror, first_row, -1)]))
    return np.asarray(windows, np.int64), np.asarray(masks), np.asarray(rows)


@pytest.mark.parametrize("seed", range(6))
def test_data_windows_of_all_views_at_once_are_each_view_s_own(seed):
    """The windows, masks and data rows of many views at once equal those found view by view,
    also with views near the image's edges, mirrors short of the fewest beams and ties of sides."""
    from fsswarp.compare import _data_windows

    rng = np.random.default_rng(seed)
    views, bins, beams = 9, 128, 40
    contour = np.full((views, 2, beams), -1.0, np.float32)
    for k in range(views):
        first, width = rng.integers(0, beams - 3), rng.integers(1, 12)
        near = rng.choice([2.0, 60.0, 125.0])
        contour[k, 0, first:first + width] = near + rng.uniform(-2, 2, min(width, beams - first))
        side = rng.integers(0, beams, rng.integers(0, 6))
        contour[k, 1, side] = rng.uniform(0, bins - 1, side.size)
    contour = np.clip(contour, -1.0, bins - 1.0)
    highlight = rng.random((views, bins, beams)) < rng.choice([0.002, 0.02, 0.2])
    for pad, margin, min_mirror in ((5, 2, 4), (0, 0, 2), (40, 3, 2)):
        got = _data_windows(contour, highlight, pad, margin, min_mirror)
        want = _data_windows_one_view_at_a_time(contour, highlight, pad, margin, min_mirror)
        for g, w in zip(got, want):
            assert g.dtype == w.dtype
            np.testing.assert_array_equal(g, w)


def test_detection_shift_with_views_left_out_is_that_of_the_anchors_layers_alone(coral_one, truth_model, opencl):
    """Locating costs every rendered pair where it lies, views left out included (against
    data view 0, then dropped): the anchors' costs, and so the shift, equal those of the
    anchors' predicted layers uploaded alone."""
    truth = coral_one.manifest.truth
    aside = truth_model.copy()
    aside.vertices += (0.4, 0.0, 0.0)  # out of the elevation aperture of the views rolled 67.5-90 deg
    settings = PoseSettings(exact_samples=(1, 16))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoseWarning)
        comparison = ViewComparison(coral_one, settings=settings, backend=opencl).use(aside, truth.depth, truth.tilt)
    data = comparison.data
    assert len(data.views) < len(comparison.views) and comparison.anchors  # views left out, anchors kept
    fixed = [data.names.index(name) for name in comparison.anchors]
    _, sums, counts = opencl.contour_cost(comparison.predicted[fixed], np.asarray(fixed), data.threshold, data.windows,
                                          data.masks, np.minimum(data.distances, np.float32(settings.min_cap)),
                                          comparison.shifts, comparison.smoothing)
    sums[:, 1], counts[:, 1] = 0.0, 0
    counts_data = data.counts[fixed]
    counts_data[:, 1] = 0
    cost = _view_cost(sums[None], counts[None], counts_data, settings.min_cap)[0].mean(axis=0)
    assert comparison.shift == _parabola_minimum(comparison.shifts, cost)


def test_a_given_comparison_gives_the_same_estimate_and_warnings(coral_one, truth_model, opencl):
    """estimate_pose going on with a ViewComparison already used for CE and E_mu (as the
    reconstruction loop hands it its record's) gives the estimate it gets alone, and warns
    about the same unseen views; a comparison located at another start, or holding another
    model, is put to the model at the start and gives that estimate too."""
    truth = coral_one.manifest.truth
    aside = truth_model.copy()
    aside.vertices += (0.4, 0.0, 0.0)  # out of the elevation aperture of the views rolled 67.5-90 deg
    settings = PoseSettings(grid=(3, 3), coarse_samples=(1, 8), samples=(1, 8), exact_samples=(1, 16), polish=4)
    start = dict(depth0=truth.depth + 0.01, tilt0=truth.tilt, bounds=(0.01, math.radians(0.4)))

    def estimate(comparison=None):
        given = dict(settings=settings, backend=opencl) if comparison is None else dict(comparison=comparison)
        with pytest.warns(PoseWarning) as caught:
            result = estimate_pose(aside, coral_one, **start, levels=2, **given)
        return result, sorted(str(w.message).split(":")[0] for w in caught)

    def same(result, alone):
        assert (result.depth, result.tilt, result.candidate) == (alone.depth, alone.tilt, alone.candidate)
        assert [level.costs.tolist() for level in result.levels] == [level.costs.tolist() for level in alone.levels]
        assert result.evaluations == alone.evaluations

    alone, warned = estimate()
    assert "views Nm67p5, Nm90, Np67p5, Sm67p5, Sm90, Sp67p5" in warned
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoseWarning)
        used = ViewComparison(coral_one, settings=settings, backend=opencl).use(aside, start["depth0"], start["tilt0"])
    assert used.data.names == ("Sm45", "Sp45", "Nm45", "Np45")
    used.contour_errors(start["depth0"], start["tilt0"])
    used.exact(start["depth0"], start["tilt0"])
    handed, warned_handed = estimate(used)
    assert warned_handed == warned
    same(handed, alone)
    # E_mu at the candidate is the polish's own evaluation there: the comparison, left located
    # where the last level put it, gives the same value again
    assert used.exact(*handed.candidate).value == handed.polish_error
    assert handed.error_after == (handed.polish_error if handed.accepted else handed.error_before)
    relocated, warned_relocated = estimate(used)  # located at the last level's best cell, not at the start
    assert warned_relocated == warned
    same(relocated, alone)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoseWarning)
        used.use(truth_model, start["depth0"], start["tilt0"])
    reloaded, _ = estimate(used)
    same(reloaded, alone)
    with pytest.raises(ValueError, match="settings and backend come with the comparison"):
        estimate_pose(aside, coral_one, **start, settings=settings, comparison=used)


def _cli(capsys, *args):
    """Run the command line; returns (exit status, stderr lines)."""
    capsys.readouterr()
    status = main(list(args))
    return status, capsys.readouterr().err.splitlines()


def test_cli_pose_recovers_the_truth_from_the_measured_start(coral_one, tmp_path, capsys):
    """``fsswarp pose`` with the true model, from the manifest's measured (D0, β0) (4 cm and
    0.8° off): within 5 mm and 0.2° of the simulation's truth, pose.json strict JSON."""
    truth, surface = coral_one.manifest.truth, coral_one.manifest.surface
    out = tmp_path / "pose"
    status, err = _cli(capsys, "pose", str(coral_one.root), "--model", str(coral_one.truth_model_path),
                       "--out", str(out))
    assert status == 0 and err == []
    record = json.loads((out / "pose.json").read_text(), parse_constant=lambda name: pytest.fail(name))
    assert abs(record["depth_m"] - truth.depth) <= 0.005
    assert abs(record["tilt_deg"] - math.degrees(truth.tilt)) <= 0.2
    assert record["start"] == {"depth_m": surface.depth, "tilt_deg": pytest.approx(math.degrees(surface.tilt))}
    assert record["start_source"] == "measured" and record["accepted"]
    assert record["E_mu_m"] < 0.2 * record["E_mu_start_m"]
    assert record["truth"]["depth_error_m"] == pytest.approx(record["depth_m"] - truth.depth)
    assert record["truth"]["tilt_error_deg"] == pytest.approx(record["tilt_deg"] - math.degrees(truth.tilt))
    assert [np.shape(level["costs_m"]) for level in record["levels"]] == [(9, 9)] * 3
    assert record["views"] == [v.name for v in coral_one.rig.views if v.optimize]
    assert record["views_left_out"] == [] and record["backend"] == get_backend().name
    assert record["search_box_edges"] == []
    assert (out / "pose.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "contours.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    mu = record["view_mu_m"]
    assert list(mu) == record["views"]
    assert np.mean([m["estimate"] for m in mu.values()]) == pytest.approx(record["E_mu_m"], rel=0.1)
    assert np.mean([m["start"] for m in mu.values()]) > 3 * record["E_mu_m"]


def test_cli_pose_bad_input(coral_one, tmp_path, capsys):
    """Each mistake: one line naming the option and value, exit 2, nothing written (a wrong
    --out: tests/test_reconstruct.py)."""
    model = str(coral_one.truth_model_path)
    far = tmp_path / "far.ply"
    trimesh.load_mesh(model, process=False).apply_translation([0.0, 10.0, 0.0]).export(far)
    bad = tmp_path / "bad"
    cases = [(["--model", str(tmp_path / "nope.ply")], ["--model", "nope.ply", "no such mesh file"]),
             (["--model", str(far)], ["--model", "far.ply", "seen in none of the views"]),
             (["--model", model, "--tilt", "95"], ["--tilt = 95"]),
             (["--model", model, "--levels", "0"], ["--levels", "0"]),
             (["--model", model, "--depth-range", "0.5"], ["--depth-range = 0.5", "below the start depth 0.432 m"]),
             (["--model", model, "--depth", "47"], ["--depth = 47.0", "sigma from the measured 0.432 m"]),
             (["--model", model, "--tilt-range", "nan"], ["--tilt-range = nan"])]
    for args, words in cases:
        status, err = _cli(capsys, "pose", str(coral_one.root), *args, "--out", str(bad))
        assert status == 2 and len(err) == 1 and err[0].startswith("fsswarp: error: "), (args, err)
        assert all(w in err[0] for w in words), err
        assert not bad.exists() and not list(tmp_path.glob(".bad.*"))


def test_view_contours_are_what_e_mu_compares(coral_one, truth_model, opencl, tmp_path, monkeypatch):
    """At the truth the mean μ_m is E_mu (``pose_objective``) and the synthetic object
    contours of the true model lie on the data's (median within a range bin); 4 cm and 0.8°
    off, the views away from the reference position see them move, and μ_m grows."""
    truth, sonar = coral_one.manifest.truth, coral_one.sonar
    off = (truth.depth + 0.04, truth.tilt + math.radians(0.8))
    contours = view_contours(truth_model, coral_one, truth.depth, truth.tilt, at=[off], backend=opencl)
    assert list(contours) == [v.name for v in coral_one.rig.views if v.optimize]
    mu = np.array([c["mu"] for c in contours.values()])  # (views, 2 poses)
    assert np.mean(mu[:, 0]) == pytest.approx(pose_objective(truth_model, coral_one, truth.depth, truth.tilt,
                                                             backend=opencl), rel=1e-12)
    assert np.all(mu[:, 1] > mu[:, 0])
    for name, entry in contours.items():
        data, (at_truth, at_off) = entry["data"][0], entry["synthetic"]
        both = np.isfinite(data) & np.isfinite(at_truth[0])
        assert both.sum() >= 5 and np.median(np.abs(at_truth[0][both] - data[both])) <= sonar.range_step, name
        if name.startswith("N"):  # the far position: the tilt error moves its object contours
            moved = np.isfinite(at_off[0]) & both
            assert np.median(np.abs(at_off[0][moved] - data[moved])) > 2 * sonar.range_step, name
    images = {name: coral_one.images[name] for name in contours}
    blank = dict(next(iter(contours.values())), data=np.full((2, sonar.beams), np.nan))
    blank["synthetic"] = [np.full((2, sonar.beams), np.nan)] * 2
    kept = captured_figures(monkeypatch)
    path = contours_figure(images, dict(contours, Sm90=blank), sonar, tmp_path / "c.png", title="coral-one")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert_laid_out(kept[0])


@pytest.mark.filterwarnings("always::fsswarp.compare.PoseWarning")  # main prints it
def test_cli_pose_lists_the_views_that_do_not_see_the_model(coral_one, tmp_path, capsys):
    """A model the views rolled 67.5-90° do not see (0.4 m aside): they are left out and listed
    in pose.json, and the rest are used."""
    aside = tmp_path / "aside.ply"
    trimesh.load_mesh(coral_one.truth_model_path, process=False).apply_translation([0.4, 0.0, 0.0]).export(aside)
    out = tmp_path / "pose"
    status, err = _cli(capsys, "pose", str(coral_one.root), "--model", str(aside), "--out", str(out), "--levels", "1")
    assert status == 0 and all(line.startswith("fsswarp: warning: the grid search ended on") for line in err), err
    record = json.loads((out / "pose.json").read_text())
    optimized = [v.name for v in coral_one.rig.views if v.optimize]
    assert record["views_left_out"] and set(record["views_left_out"]) | set(record["views"]) == set(optimized)
    assert not set(record["views_left_out"]) & set(record["views"]) and list(record["view_mu_m"]) == record["views"]
    assert len(record["levels"]) == 1


@pytest.mark.filterwarnings("always::fsswarp.compare.PoseWarning")  # main prints it
def test_cli_pose_warns_when_the_estimate_lies_on_the_search_box_edge(coral_one, tmp_path, capsys):
    """From 12 mm too deep (4 sigma of the depth sensor) the truth lies outside the box (D0 ±
    9 mm): the grid search ends on its lowest depth, and the command says so (exit 0) and
    records it; with --depth-range 0.03 the box holds the truth, and the estimate meets the
    pose aim, its intervals holding the truth."""
    out = tmp_path / "pose"
    start = coral_one.manifest.surface.depth + 0.012
    status, err = _cli(capsys, "pose", str(coral_one.root), "--model", str(coral_one.truth_model_path),
                       "--out", str(out), "--depth", str(start), "--levels", "1")
    assert status == 0 and len(err) == 1 and "ended on the lowest depth edge of its box" in err[0], err
    record = json.loads((out / "pose.json").read_text())
    assert record["search_box_edges"] == ["lowest depth"]
    assert record["levels"][0]["best"]["depth_m"] == pytest.approx(start - 0.009)
    status, err = _cli(capsys, "pose", str(coral_one.root), "--model", str(coral_one.truth_model_path),
                       "--out", str(out), "--depth", str(start), "--depth-range", "0.03")
    assert status == 0 and err == []
    record = json.loads((out / "pose.json").read_text())
    assert record["search_box_edges"] == [] and record["levels"][0]["depths_m"][0] == pytest.approx(start - 0.03)
    assert abs(record["truth"]["depth_error_m"]) <= 0.003 and abs(record["truth"]["tilt_error_deg"]) <= 0.15
    truth = coral_one.manifest.truth
    (d0, d1), (t0, t1) = record["depth_interval_m"], record["tilt_interval_deg"]
    assert d0 <= truth.depth <= d1 and t0 <= math.degrees(truth.tilt) <= t1


def test_box_edges_name_the_edges_the_estimate_lies_on(coral_one, estimate):
    result = estimate[0]
    assert result.box_edges() == ()
    first, last = result.levels[0], result.levels[-1]
    corner = dataclasses.replace(last, best=(float(first.depths[-1]), float(first.tilts[0]) + 1e-6))
    assert dataclasses.replace(result, levels=result.levels[:-1] + (corner,)).box_edges() == ("highest depth",
                                                                                              "lowest tilt")


def test_grid_plans_group_the_pairs_by_tilt_and_view(truth_comparison, monkeypatch):
    """plan_pairs hands the render its pairs' pose groups (a tilt and a view): one group per
    tilt and view of the cells, every pair of a group the same pose bit for bit (so the shared
    poses are hashed once per group, not once per pair)."""
    from fsswarp.backends import base

    seen = []
    original = base.shared_poses
    monkeypatch.setattr(base, "shared_poses", lambda *args: seen.append(args) or original(*args))
    truth = truth_comparison.data
    depths, tilts = np.meshgrid([0.42, 0.43, 0.44], np.radians([10.0, 10.5]), indexing="ij")
    truth_comparison.plan_pairs(truth.views, depths.ravel(), tilts.ravel(), (1, 8))
    rotations, translations, _, _, groups = seen[-1]
    views = len(truth.views)
    assert groups.shape == (6 * views,) and len(np.unique(groups)) == 2 * views
    rows = np.concatenate([rotations.reshape(-1, 9), translations], axis=1)
    for group in np.unique(groups):
        members = rows[groups == group]
        assert len(members) == 3 and (members == members[0]).all()
