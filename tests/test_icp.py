"""IRLS-ICP of 2-D contours (fsswarp.icp; paper §2.4, eq. 5) on seeded synthetic curves."""

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from fsswarp.backends.constants import GPU_ICP_LANES
from fsswarp.icp import _Active, _medians, _Runs, contour_error, icp, icp_many

finite = dict(allow_nan=False, allow_infinity=False)
#: Misalignments of the kind contour alignment meets: up to 2.9° about the contour and 2 cm.
#: ICP is local: it needs the misalignment well below the distance from the contour to the
#: outliers (at ±4.6° and 3 cm, outliers 5 cm off drew a few seeds into wrong minima).
angles = st.floats(-0.05, 0.05, **finite)
shifts = st.floats(-0.02, 0.02, **finite)
seeds = st.integers(0, 2**16)
CENTRE = np.array([0.0, 1.9])  # fan-plane point (m) the misalignment rotates about


def curve(n, s0=-1.2, s1=1.2):
    """(n, 2) frontal-contour-like curve in the fan plane (m): an elliptic arc 2 m ahead with
    bumps, so that no rigid motion slides it onto itself (a circular arc would)."""
    s = np.linspace(s0, s1, n)
    return np.stack([0.35 * np.sin(s), 2.0 - 0.15 * np.cos(s) + 0.06 * np.sin(4 * s)], axis=1)


def rigid(angle, shift):
    """The true transform, rotation by ``angle`` about CENTRE then ``shift``, as (R, t)."""
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    return rot, CENTRE + np.asarray(shift) - rot @ CENTRE


def misplace(points, rot, trans):
    """Points that the transform (rot, trans) moves onto ``points``."""
    return (points - trans) @ rot


def false_highlights(points, rng):
    """Outliers of a frontal contour: each point pulled 5–30 cm toward the sonar along its beam
    (a spurious highlight in front of the object)."""
    rng_m = np.linalg.norm(points, axis=1, keepdims=True)
    return points * (1.0 - rng.uniform(0.05, 0.3, (len(points), 1)) / rng_m)


def clutter(clean, count, rng):
    """``count`` outlier points at least 5 cm from every point of ``clean``, within 0.3 m of it."""
    lo, hi = clean.min(axis=0) - 0.3, clean.max(axis=0) + 0.3
    out = np.empty((0, 2))
    while len(out) < count:
        cand = rng.uniform(lo, hi, (4 * count, 2))
        dist = np.min(np.linalg.norm(cand[:, None, :] - clean[None, :, :], axis=2), axis=1)
        out = np.concatenate([out, cand[(dist >= 0.05) & (dist <= 0.3)]])
    return out[:count]


def transform_error(result, rot, trans, points):
    """RMS distance (m) between where the estimate and the truth put ``points``."""
    return float(np.sqrt(np.mean(np.sum((result.apply(points) - (points @ rot.T + trans)) ** 2, axis=1))))


# --- exact cases -------------------------------------------------------------------------------

@given(seed=seeds, n=st.integers(2, 300))
@settings(derandomize=True, max_examples=30, deadline=None)
def test_identical_sets_give_identity_and_zero_error(seed, n):
    points = curve(n) + np.random.default_rng(seed).normal(0.0, 0.005, (n, 2))
    res = icp(points, points)  # identity to rounding
    np.testing.assert_allclose(res.rotation, np.eye(2), rtol=0, atol=1e-15)
    np.testing.assert_allclose(res.translation, np.zeros(2), rtol=0, atol=1e-14)
    np.testing.assert_allclose(res.motions, np.zeros((n, 2)), rtol=0, atol=1e-14)
    np.testing.assert_array_equal(res.pairs, np.stack([np.arange(n), np.arange(n)], axis=1))
    assert res.error <= 1e-14 and abs(res.angle) <= 1e-15
    assert res.converged and res.iterations <= 2


@given(angle=st.floats(-0.01, 0.01, **finite), sx=st.floats(-5e-4, 5e-4, **finite),
       sy=st.floats(-5e-4, 5e-4, **finite))
@settings(derandomize=True, max_examples=30, deadline=None)
def test_small_motion_of_matched_points_is_exact(angle, sx, sy):
    # 2 cm spacing, sub-mm motion: the nearest neighbours are the true pairs from the start,
    # and weighted Procrustes solves the rigid motion exactly.
    target = curve(60)
    rot, trans = rigid(angle, (sx, sy))
    res = icp(misplace(target, rot, trans), target)
    assert res.converged
    np.testing.assert_allclose(res.rotation, rot, atol=1e-12)
    np.testing.assert_allclose(res.translation, trans, atol=1e-11)
    assert res.angle == pytest.approx(angle, abs=1e-12)
    assert res.error == pytest.approx(0.0, abs=1e-11)
    np.testing.assert_array_equal(res.pairs[:, 0], res.pairs[:, 1])


# --- recovery of a known transform ------------------------------------------------------------

# name: (noise σ per axis on both sets (m), outlier fraction of the target, angle tol (rad),
#        RMS point tol (m))
CASES = {
    "clean": (0.0, 0.0, 1e-3, 5e-4),
    "noise": (0.001, 0.0, 0.01, 4e-3),
    "outliers": (0.0, 0.2, 2e-3, 1.5e-3),
    "noise+outliers": (0.001, 0.2, 0.01, 4e-3),
}


@pytest.mark.parametrize("case", list(CASES))
@given(angle=angles, sx=shifts, sy=shifts, seed=seeds)
# a wrong minimum 0.064 rad away holds ICP started at the true angle (fixed by the extra starts)
@example(angle=0.0, sx=0.015625, sy=0.01953125, seed=27)
@settings(derandomize=True, max_examples=15, deadline=None)
def test_recovers_known_transform(case, angle, sx, sy, seed):
    # Unequal counts (300 data vs 170 synthetic points) and partial overlap: each contour
    # covers a stretch that the other lacks.
    noise, outliers, angle_tol, point_tol = CASES[case]
    rng = np.random.default_rng(seed)
    clean_target = curve(300, -1.2, 0.9)
    target = clean_target + rng.normal(0.0, noise, clean_target.shape)
    n_out = int(round(outliers * len(target)))
    if n_out:
        bad = rng.choice(len(target), n_out, replace=False)
        target[bad] = false_highlights(target[bad], rng)
    truth_source = curve(170, -0.9, 1.1)
    rot, trans = rigid(angle, (sx, sy))
    source = misplace(truth_source + rng.normal(0.0, noise, truth_source.shape), rot, trans)
    res = icp(source, target)
    assert abs(res.angle - angle) <= angle_tol
    overlap = truth_source[:, 0] <= clean_target[-1, 0]
    assert transform_error(res, rot, trans, source[overlap]) <= point_tol
    np.testing.assert_allclose(res.motions, res.apply(source) - source, atol=1e-15)
    # CE (eq. 5) over the inlier pairs: the noise level of the residuals, never the outliers
    moved = res.apply(source)
    assert res.error == pytest.approx(contour_error(target[res.pairs[:, 1]], moved[res.pairs[:, 0]]))
    assert res.error <= 2.0 * math.sqrt(2.0) * noise + 1e-3
    # the stretch of the source beyond the data's end is no inlier
    assert not np.any(truth_source[res.pairs[:, 0], 0] > clean_target[-1, 0] + 0.02)


def test_clutter_is_never_an_inlier():
    rng = np.random.default_rng(7)
    clean = curve(250)
    target = clean.copy()
    bad = rng.choice(len(target), 50, replace=False)
    target[bad] = clutter(clean, 50, rng)
    rot, trans = rigid(0.04, (0.015, -0.015))
    source = misplace(curve(140, -1.0, 1.0), rot, trans)
    res = icp(source, target)
    assert transform_error(res, rot, trans, source) <= 1e-3
    assert not np.isin(res.pairs[:, 1], bad).any()
    dist = np.linalg.norm(target[res.pairs[:, 1]] - res.apply(source)[res.pairs[:, 0]], axis=1)
    assert np.all(dist <= 3.0 * res.scale)  # the stated gate
    assert res.weights.shape == (140,) and np.all((res.weights > 0) & (res.weights <= 1))


def test_max_distance_gates_pairs():
    target = curve(200)
    source = np.concatenate([curve(100, -1.0, 1.0), [[5.0, 5.0], [-5.0, 6.0]]])
    res = icp(source, target, max_distance=0.1)
    assert set(res.pairs[:, 0].tolist()) == set(range(100))
    assert res.weights[100:].tolist() == [0.0, 0.0]
    far = icp(source + 10.0, target, max_distance=0.1)
    assert len(far.pairs) == 0 and math.isnan(far.error) and not far.converged
    np.testing.assert_array_equal(far.rotation, np.eye(2))


def test_deterministic():
    rng = np.random.default_rng(3)
    target = curve(300) + rng.normal(0, 0.003, (300, 2))
    rot, trans = rigid(-0.04, (0.01, 0.02))
    source = misplace(curve(123, -0.7, 1.2), rot, trans)
    a, b = icp(source, target), icp(source.copy(), target.copy())
    for field in ("rotation", "translation", "pairs", "motions", "weights"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert (a.error, a.iterations, a.scale) == (b.error, b.iterations, b.scale)


# --- CE and validation ---------------------------------------------------------------------------

def test_contour_error_closed_form():
    # eq. (5): distances 0, 5 and 1 -> mean 2
    data = [[0.0, 0.0], [3.0, 4.0], [1.0, 1.0]]
    synthetic = [[0.0, 0.0], [0.0, 0.0], [1.0, 2.0]]
    assert contour_error(data, synthetic) == pytest.approx(2.0)
    assert math.isnan(contour_error(np.empty((0, 2)), np.empty((0, 2))))
    with pytest.raises(ValueError, match="must match"):
        contour_error(data, synthetic[:2])


@pytest.mark.parametrize("source, target, kwargs, message", [
    (np.zeros((5, 3)), np.zeros((5, 2)), {}, r"shape \(N, 2\)"),
    (np.zeros(10), np.zeros((5, 2)), {}, r"shape \(N, 2\)"),
    (np.zeros((1, 2)), np.zeros((5, 2)), {}, "at least 2"),
    (np.zeros((5, 2)), np.zeros((1, 2)), {}, "at least 2"),
    (np.array([[0.0, np.nan], [1.0, 1.0]]), np.zeros((5, 2)), {}, "non-finite"),
    (np.zeros((5, 2)), np.array([[0.0, np.inf], [1.0, 1.0]]), {}, "non-finite"),
    (np.zeros((5, 2)), np.zeros((5, 2)), {"max_iterations": 0}, "max_iterations"),
    (np.zeros((5, 2)), np.zeros((5, 2)), {"gate": -1.0}, "gate"),
    (np.zeros((5, 2)), np.zeros((5, 2)), {"tol": math.nan}, "tol"),
    (np.zeros((5, 2)), np.zeros((5, 2)), {"max_distance": 0.0}, "max_distance"),
])
def test_bad_inputs_raise(source, target, kwargs, message):
    with pytest.raises(ValueError, match=message):
        icp(source, target, **kwargs)


@pytest.mark.parametrize("side", ["source", "target"])
def test_a_non_finite_point_of_any_pair_raises(side):
    """icp_many checks the pairs' points together: a NaN in the last pair's source or target."""
    good = curve(12)
    bad = good.copy()
    bad[7, 1] = np.nan
    last = (bad, good) if side == "source" else (good, bad)
    with pytest.raises(ValueError, match=f"{side} holds non-finite values"):
        icp_many([(good, good), (good + 0.01, good), last])


@settings(deadline=None, max_examples=50)
@given(st.lists(st.lists(st.floats(0.0, 1.0, allow_nan=False), max_size=40), min_size=1, max_size=5))
def test_the_robust_scale_medians_are_numpys(rows):
    """ICP's row-wise median of the distances that count (+inf elsewhere; called every
    iteration) equals np.median of each row, odd and even lengths, NaN for an empty row."""
    values = np.full((len(rows), max(1, max(map(len, rows)))), np.inf)
    for i, row in enumerate(rows):
        values[i, :len(row)] = row
    for row, median in zip(rows, _medians(values, np.array([len(row) for row in rows]))):
        assert median == float(np.median(row)) if row else math.isnan(median)


def test_many_pairs_at_once_give_each_pair_its_own_result():
    """icp_many runs the pairs in lockstep over padded arrays: every pair gets what icp gives it
    alone (up to rounding), whatever the other pairs' sizes, iterations or gating."""
    rng = np.random.default_rng(11)
    problems = []
    for n, angle, shift in ((60, 0.03, (0.01, -0.005)), (123, -0.04, (0.0, 0.02)), (7, 0.0, (0.0, 0.0)),
                            (200, 0.045, (-0.015, 0.01))):
        target = curve(300) + rng.normal(0, 0.002, (300, 2))
        rot, trans = rigid(angle, shift)
        problems.append((misplace(curve(n, -0.8, 0.9), rot, trans), target))
    problems.append((problems[0][0] + 10.0, problems[0][1]))  # every pair gated off: no iteration moves it
    together = icp_many(problems, max_distance=0.1)
    assert len(together) == len(problems) and icp_many([]) == []
    for (source, target), many in zip(problems, together):
        one = icp(source, target, max_distance=0.1)
        np.testing.assert_allclose(many.rotation, one.rotation, rtol=0, atol=1e-12)
        np.testing.assert_allclose(many.translation, one.translation, rtol=0, atol=1e-11)
        np.testing.assert_allclose(many.motions, one.motions, rtol=0, atol=1e-11)
        np.testing.assert_array_equal(many.pairs, one.pairs)
        assert (many.iterations, many.converged) == (one.iterations, one.converged)
        assert many.error == pytest.approx(one.error, rel=1e-9, abs=0, nan_ok=True)
    assert [r.iterations for r in together[:4]] != [together[0].iterations] * 4  # the runs stop at different times
    assert len(together[-1].pairs) == 0 and not together[-1].converged


def test_the_kept_nearest_targets_are_the_k_d_tree_s():
    """The matching reuses a point's last k-d tree answer while the point stays within its room:
    after every move the nearest targets and their distances are a fresh query's, to the bit,
    ties included (points of a binary grid halfway between two targets)."""
    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(np.arange(8), np.arange(5)), axis=-1).reshape(-1, 2) / 64.0
    pairs = [(grid[rng.choice(40, n, replace=False)] + [0.5 / 64, 0.0], grid[rng.choice(40, m, replace=False)])
             for n, m in ((30, 25), (12, 40), (40, 2))]
    runs = _Runs(pairs, None, 1e-10)
    active, ties = _Active(runs, np.arange(9)), 0
    for step in range(40):
        if step % 10 == 0:  # onto the grid, where the ties are
            active.moved_x, active.moved_y = active.x.copy(), active.y.copy()
        else:
            scale = 10.0 ** rng.uniform(-5, -2, len(active.points))
            active.moved_x = active.moved_x + scale * rng.normal(size=len(active.points))
            active.moved_y = active.moved_y + scale * rng.normal(size=len(active.points))
        dist = active.distances()
        lift = runs.lift * (active.rows // 3)[active.rank]
        want_dist, want = runs.tree.query(np.column_stack([active.moved_x, active.moved_y, lift]), k=1)
        np.testing.assert_array_equal(active.nearest, want)
        np.testing.assert_array_equal(dist, want_dist)
        ties += np.count_nonzero(active.room2 < 0)
    assert ties > 0


# --- on a backend's device (Backend.icp_runs, one thread per run, float64) ---------------------

def contour_problems(seed):
    """Pairs of the pose step's kind: misplaced noisy curves of 2–200 points against data with
    false highlights, and one pair whose every point lies 10 m off (gated off by a hard gate)."""
    rng = np.random.default_rng(seed)
    problems = []
    for n, m, angle, shift in ((60, 300, 0.03, (0.01, -0.005)), (123, 80, -0.04, (0.0, 0.02)),
                               (2, 2, 0.0, (0.0, 0.0)), (7, 40, 0.01, (0.002, 0.0)),
                               (200, 150, 0.045, (-0.015, 0.01))):
        target = curve(m) + rng.normal(0.0, 0.002, (m, 2))
        source = misplace(curve(n, -0.8, 0.9), *rigid(angle, shift)) + rng.normal(0.0, 0.002, (n, 2))
        problems.append((source, np.concatenate([target, false_highlights(target[: m // 5], rng)])))
    problems.append((problems[0][0] + 10.0, problems[0][1]))
    return problems


def assert_same_results(got, want, atol, iterations=0):
    """Pair by pair: transforms and motions to ``atol``, the same pairs, CE and σ to 1e-9, and
    iteration counts within ``iterations`` (rounding decides the last step of a slow run)."""
    for a, b in zip(got, want, strict=True):
        np.testing.assert_allclose(a.rotation, b.rotation, rtol=0, atol=atol)
        np.testing.assert_allclose(a.translation, b.translation, rtol=0, atol=atol)
        np.testing.assert_allclose(a.motions, b.motions, rtol=0, atol=atol)
        np.testing.assert_allclose(a.weights, b.weights, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(a.pairs, b.pairs)
        assert abs(a.iterations - b.iterations) <= iterations and a.converged == b.converged
        assert a.error == pytest.approx(b.error, rel=1e-9, abs=0, nan_ok=True)
        assert a.scale == pytest.approx(b.scale, rel=1e-9, abs=0)


@pytest.mark.parametrize("max_distance", [None, 0.05])
def test_device_runs_give_the_host_s_results(backend, max_distance):
    """The kernel's brute-force matching and selection median give the host's k-d tree and
    np.median results up to rounding: the same pairs, transforms to 1e-10 m, and the same
    iterations but where rounding decides a slow run's last step (tol 1e-10)."""
    problems = contour_problems(5)
    host = icp_many(problems, max_distance=max_distance)
    device = icp_many(problems, max_distance=max_distance, backend=backend)
    assert_same_results(device, host, 1e-10, iterations=1)
    assert len({r.iterations for r in host}) > 2  # the runs stop at different times
    if max_distance is not None:
        assert len(device[-1].pairs) == 0 and not device[-1].converged  # no weight: stops unconverged


def test_device_runs_with_a_warp_each_give_the_same_bits(backend, monkeypatch):
    """A GPU gives each run ``GPU_ICP_LANES`` threads, of which one works, a CPU one: with the
    other count forced on this device, every run's result is the same, bit for bit."""
    problems = contour_problems(7)
    own = icp_many(problems, max_distance=0.05, backend=backend)
    assert backend.icp_lanes == (GPU_ICP_LANES if backend.is_gpu else 1)
    other = 1 if backend.is_gpu else GPU_ICP_LANES
    monkeypatch.setattr(type(backend), "icp_lanes", property(lambda self: other))
    forced = icp_many(problems, max_distance=0.05, backend=backend)
    for a, b in zip(forced, own, strict=True):
        for field in ("rotation", "translation", "motions", "weights", "pairs", "iterations", "converged",
                      "error", "scale"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert len({r.iterations for r in own}) > 2


@given(angle=st.floats(-0.01, 0.01, **finite), sx=st.floats(-5e-4, 5e-4, **finite),
       sy=st.floats(-5e-4, 5e-4, **finite))
@settings(derandomize=True, max_examples=10, deadline=None)
def test_device_runs_solve_a_small_motion_of_matched_points_exactly(backend, angle, sx, sy):
    """Closed form, as on the host: matched points moved by a sub-mm rigid motion come back
    exactly, with every point paired with its own target."""
    target = curve(60)
    rot, trans = rigid(angle, (sx, sy))
    res = icp_many([(misplace(target, rot, trans), target)], backend=backend)[0]
    assert res.converged
    np.testing.assert_allclose(res.rotation, rot, atol=1e-12)
    np.testing.assert_allclose(res.translation, trans, atol=1e-11)
    assert res.error == pytest.approx(0.0, abs=1e-11)
    np.testing.assert_array_equal(res.pairs[:, 0], res.pairs[:, 1])


def test_device_runs_take_medians_of_equal_distances(backend):
    """Sources a few fixed offsets off the targets' binary grid: the first match's distances
    take four values, many times each, which the selection median must order like np.median
    (odd and even counts; a gate that drops the largest), and σ then weighs the pairs."""
    grid = np.stack(np.meshgrid(np.arange(9), np.arange(6)), axis=-1).reshape(-1, 2) / 64.0
    offsets = np.array([[0.125, 0.0], [0.25, 0.0], [0.375, 0.125], [0.125, 0.125]]) / 64.0
    pick = np.random.default_rng(4).integers(0, 4, 54)
    problems = [(grid[:n] + offsets[pick[:n]], grid) for n in (5, 6, 17, 54)]
    for max_distance in (None, 0.3 / 64.0):
        for iterations in (1, 3):
            host = icp_many(problems, max_distance=max_distance, max_iterations=iterations)
            device = icp_many(problems, max_distance=max_distance, max_iterations=iterations, backend=backend)
            assert_same_results(device, host, 1e-14)


def test_warp_and_opencl_icp_runs_agree(backend_for_label):
    """The two kernels, line by line the same: the same pairs, transforms to 1e-13 (their
    sin, cos and atan2 may round differently, and so a slow run's last step)."""
    warp, opencl = backend_for_label("warp-cpu"), backend_for_label("opencl-cpu")
    problems = contour_problems(9)
    assert_same_results(icp_many(problems, backend=warp), icp_many(problems, backend=opencl), 1e-13, iterations=1)


@pytest.mark.parametrize("change, message", [
    (dict(runs=np.zeros((2, 2), int)), "runs must be an"),
    (dict(runs=[[0, 3, 4], [0, 3, 0]]), "count >= 1"),
    (dict(runs=[[0, 9, 4], [0, 3, 4]]), "within 0..3"),
    (dict(runs=[[0, 3, 4], [0, 3, 3]]), "sum to 7"),
    (dict(floors=[1e-9, 0.0]), "floors must be > 0"),
    (dict(angles=[0.0, math.nan]), "angles must be finite"),
    (dict(translations=np.zeros(2)), "translations must have shape"),
    (dict(max_iterations=0), "max_iterations"),
    (dict(max_distance=-1.0), "max_distance and tuning"),
])
def test_icp_runs_rejects_bad_input(backend, change, message):
    args = dict(source_x=np.arange(8.0), source_y=np.zeros(8), target_x=np.arange(3.0), target_y=np.zeros(3),
                runs=[[0, 3, 4], [0, 3, 4]], angles=[0.0, 0.0], translations=np.zeros((2, 2)),
                floors=[1e-9, 1e-9], step_tols=[1e-9, 1e-9], max_iterations=5, max_distance=math.inf,
                tuning=2.0)
    args.update(change)
    positional = [args.pop(k) for k in ("source_x", "source_y", "target_x", "target_y", "runs", "angles",
                                        "translations", "floors", "step_tols")]
    with pytest.raises(ValueError, match=message):
        backend.icp_runs(*positional, **args)


def test_the_opencl_kernel_s_constant_is_python_s():
    from fsswarp.backends.opencl import kernel_source
    from fsswarp.icp import RAYLEIGH_MEDIAN

    assert f"#define RAYLEIGH_MEDIAN {RAYLEIGH_MEDIAN!r} " in kernel_source("icp.cl")
