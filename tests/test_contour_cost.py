"""Backend.contour_cost (kernels/pose.cl and its Warp twin) against a float64 NumPy oracle,
and Warp against OpenCL on rendered views."""

import numpy as np
import pytest
import trimesh

from fsswarp.backends import HostLayers, beams_read
from fsswarp.backends.base import mask_items
from fsswarp.compare import _gaussian
from fsswarp.rig import Rig, View
from fsswarp.sonar import SonarSpec
from fsswarp.surface import surface_in_views


def contour_cost_reference(layers, view_index, thresholds, windows, masks, distances, shifts, smoothing):
    """The rule of kernels/pose.cl in float64: (contours (N, 2, beams), sums (N, 2, S), counts (N, 2))."""
    from scipy.ndimage import correlate1d

    layers = np.asarray(layers, np.float64)
    n_pairs, _, bins, beams = layers.shape
    w_range, w_beam = (np.asarray(w, np.float64) for w in smoothing)
    contours = np.full((n_pairs, 2, beams), -1.0)
    for n, v in enumerate(view_index):
        for c in (0, 1):
            image = layers[n, 2 * c] + layers[n, 2 * c + 1]
            smooth = correlate1d(correlate1d(image, w_beam, axis=1, mode="nearest"), w_range, axis=0,
                                 mode="nearest")
            lo, hi = windows[v]
            f = smooth[lo:hi] - np.asarray(thresholds[v], np.float64)[lo:hi, None]
            for b in np.flatnonzero(masks[v, c]):
                above = np.flatnonzero(f[:, b] > 0)
                if above.size:
                    i = above[0]
                    contours[n, c, b] = lo if i == 0 else lo + i - 1 + f[i - 1, b] / (f[i - 1, b] - f[i, b])
    sums = np.zeros((n_pairs, 2, len(shifts)))
    for s, shift in enumerate(shifts):
        y = np.clip(contours + shift, 0, bins - 1)
        b0 = np.floor(y).astype(int)
        b1 = np.minimum(b0 + 1, bins - 1)
        t = y - b0
        cols = np.arange(beams)
        for n, v in enumerate(view_index):
            for c in (0, 1):
                d = np.asarray(distances[v, c], np.float64)
                value = (1 - t[n, c]) * d[b0[n, c], cols] + t[n, c] * d[b1[n, c], cols]
                sums[n, c, s] = value[contours[n, c] >= 0].sum()
    return contours, sums, (contours >= 0).sum(axis=-1)


def random_case(seed, n_pairs=7, n_views=3, bins=48, beams=14):
    rng = np.random.default_rng(seed)
    layers = rng.exponential(1.0, (n_pairs, 4, bins, beams)).astype(np.float32)
    layers *= (rng.uniform(0, 1, (n_pairs, 4, bins, 1)) ** 3).astype(np.float32)  # rows of weak and strong echo
    thresholds = rng.uniform(0.3, 1.5, (n_views, bins)).astype(np.float32)
    lo = rng.integers(0, bins // 2, n_views)
    windows = np.stack([lo, lo + rng.integers(1, bins - lo + 1)], axis=1)
    masks = rng.uniform(size=(n_views, 2, beams)) < 0.7
    distances = rng.uniform(0, 0.05, (n_views, 2, bins, beams)).astype(np.float32)
    view_index = rng.integers(0, n_views, n_pairs)
    shifts = np.array([-1.0, 0.0, 0.25, 0.5, 3.5])
    return layers, view_index, thresholds, windows, masks, distances, shifts, (_gaussian(1.0), _gaussian(0.7))


@pytest.mark.parametrize("seed, sigma_bins", [(0, 1.0), (1, 1.0), (2, 1.0), (3, 3.9), (4, 6.0)])
def test_matches_numpy_oracle(backend, seed, sigma_bins):
    """Also a range smoothing of 33 taps (as many as the kernels' ring of rows holds) and of 49
    (summed afresh per tap)."""
    case = random_case(seed)
    case = (*case[:7], (_gaussian(sigma_bins), case[7][1]))
    contours, sums, counts = backend.contour_cost(*case)
    ref_contours, ref_sums, ref_counts = contour_cost_reference(*case)
    np.testing.assert_array_equal(contours >= 0, ref_contours >= 0)
    np.testing.assert_allclose(contours, ref_contours, rtol=0, atol=2e-4)
    np.testing.assert_array_equal(counts, ref_counts)
    np.testing.assert_allclose(sums, ref_sums, rtol=1e-5, atol=1e-6)
    assert contours.dtype == np.float32 and sums.dtype == np.float32 and counts.dtype == np.int32


def view_cost_reference(sums, counts, view_index, data_counts, cap):
    """(N, S) float64 object + mirror terms (Σ d + cap · max(0, m − k)) / max(k, m), 0 for an
    empty term, from the oracle's sums (N, 2, S) and counts (N, 2) and the data's (V, 2) counts."""
    out = np.zeros((sums.shape[0], sums.shape[2]))
    for n, v in enumerate(view_index):
        for c in (0, 1):
            k, m = int(counts[n, c]), int(data_counts[v, c])
            if max(k, m) > 0:
                out[n] += (sums[n, c] + cap * max(m - k, 0)) / max(k, m)
    return out


def view_cost_case(seed):
    """random_case with one empty object term (no mask, no data point), data counts above,
    equal to and below the synthetic ones, and a cap among the distances."""
    case = list(random_case(seed))
    case[4][0, 1] = False  # view 0: no mirror beams
    case[1][:2] = 0  # pairs 0 and 1 compare with view 0
    rng = np.random.default_rng(seed + 100)
    data_counts = rng.integers(0, case[4].shape[2] + 3, (case[4].shape[0], 2))
    data_counts[0, 1] = 0
    return case, data_counts, 0.03


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_view_costs_match_numpy_oracle(backend, seed):
    """``view_costs`` combines the contour sums on the device as the float64 oracle does, with
    the cap read into the distances and the missing points."""
    case, data_counts, cap = view_cost_case(seed)
    got = backend.view_costs(*case, data_counts, cap)
    _, sums, counts = contour_cost_reference(*case[:5], np.minimum(case[5], np.float32(cap)), *case[6:])
    want = view_cost_reference(sums, counts, case[1], data_counts, cap)
    assert got.dtype == np.float32 and got.shape == (len(case[1]), len(case[6]))
    assert np.all(want[:2] >= 0) and np.any(want > 0)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("seed", [0, 1])
def test_view_costs_are_the_host_combination_of_contour_cost(backend, seed):
    """The device's view costs equal the host's float64 combination (``compare._view_cost``,
    the grid's former path) of the same backend's ``contour_cost``, within float32 rounding."""
    from fsswarp.compare import _view_cost

    case, data_counts, cap = view_cost_case(seed)
    uploaded = backend.device_distances(case[5])
    _, sums, counts = backend.contour_cost(*case[:5], uploaded, *case[6:], cap=cap)
    n_views, n = data_counts.shape[0], len(case[1])
    # one pair per "cell" of V views: pair p of view v sits at cell p, view v (other views empty)
    full_sums = np.zeros((n, n_views, 2, len(case[6])))
    full_counts = np.zeros((n, n_views, 2), np.int64)
    full_sums[np.arange(n), case[1]] = sums
    full_counts[np.arange(n), case[1]] = counts
    want = _view_cost(full_sums, full_counts, data_counts, cap)[np.arange(n), case[1]]
    got = backend.view_costs(*case[:5], uploaded, *case[6:], data_counts, cap)
    np.testing.assert_allclose(got, want, rtol=2e-6, atol=1e-7)


def test_crossing_rules(backend):
    # one beam, ramp 0, 0, 1, 3 (rows 0..3) against threshold 2: crossing at row 2.5; a window
    # starting above the threshold gives its first row; no crossing gives -1
    layers = np.zeros((3, 4, 4, 1), np.float32)
    layers[:, 0, :, 0] = [0.0, 0.0, 1.0, 3.0]
    thresholds = np.full((3, 4), 2.0, np.float32)
    windows = np.array([[0, 4], [3, 4], [0, 3]])
    masks = np.ones((3, 2, 1), bool)
    distances = np.zeros((3, 2, 4, 1), np.float32)
    distances[:, 0, :, 0] = [0.0, 1.0, 2.0, 3.0]
    contours, sums, counts = backend.contour_cost(layers, [0, 1, 2], thresholds, windows, masks, distances,
                                                  [0.0, 0.25, 9.0], ([1.0], [1.0]))
    np.testing.assert_allclose(contours[:, 0, 0], [2.5, 3.0, -1.0], atol=1e-6)
    np.testing.assert_array_equal(contours[:, 1, 0], [-1, -1, -1])  # the mirror layers are empty
    np.testing.assert_allclose(sums[0, 0], [2.5, 2.75, 3.0], atol=1e-6)  # read at 2.5, 2.75, clamped to 3
    np.testing.assert_array_equal(counts, [[1, 0], [1, 0], [0, 0]])


def sphere_views():
    """A sphere 2 cm below the surface seen by 5 rolled views at 3 (D, β): (sonar, mesh, the 15
    pairs' rotations, translations, plane normals and offsets, flat), detection thresholds and
    windows (at the image's borders too) of the 5 views."""
    sonar = SonarSpec(beams=64, bins=160, range_min=1.5, range_max=2.5)
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    mesh.vertices += (0.0, 2.0, -0.12)
    rig = Rig(tuple(View(f"r{k}", roll=np.radians(r)) for k, r in enumerate((-90, -45, 0, 45, 90))))
    depths, tilts = np.array([0.28, 0.3, 0.32]), np.radians([9.0, 10.0, 11.0])
    rot, t = rig.relative_poses(depths, tilts)
    n, d = surface_in_views(rig, depths, tilts)
    poses = (rot.reshape(-1, 3, 3), t.reshape(-1, 3), n.reshape(-1, 3), d.reshape(-1))
    windows = np.array([[20, 150], [0, 140], [30, 160], [20, 150], [10, 155]])
    return sonar, mesh, poses, np.full((5, sonar.bins), 2e-3, np.float32), windows


def test_warp_and_opencl_agree_on_rendered_views(backend_for_label):
    warp, opencl = backend_for_label("warp-cpu"), backend_for_label("opencl-cpu")
    sonar, mesh, poses, thresholds, windows = sphere_views()
    masks = np.ones((5, 2, sonar.beams), bool)
    distances = np.random.default_rng(0).uniform(0, 0.05, (5, 2, sonar.bins, sonar.beams))
    view_index = np.tile(np.arange(5), 3)
    data_counts = np.array([[40, 10], [64, 0], [20, 30], [0, 0], [50, 50]])
    first, count = tight_bands(view_index, windows, (len(_gaussian(1.0)) - 1) // 2, sonar.bins)
    out = {}
    for b in (warp, opencl):
        handle = b.load_mesh(mesh.vertices, mesh.faces)
        for rows, components in ((None, False), ((first, count), False), ((first, count), True)):
            layers = b.render_device(handle, sonar, *poses, (1, 32), gamma=1.0, surface_reflection=0.9, rows=rows,
                                     components=components)
            args = (layers, view_index, thresholds, windows, masks, distances, [0.0, 0.5],
                    (_gaussian(1.0), _gaussian(0.7)))
            key = rows is None if not components else "components"
            out[b.name, key] = b.contour_cost(*args)
            out[b.name, "view costs", key] = b.view_costs(*args, data_counts, 0.04)
        # banded layers and the components' sums: bit for bit the full layers' results
        for a, f, c in zip(out[b.name, False], out[b.name, True], out[b.name, "components"]):
            np.testing.assert_array_equal(a, f)
            np.testing.assert_array_equal(c, f)
        np.testing.assert_array_equal(out[b.name, "view costs", "components"], out[b.name, "view costs", True])
    for full in (True, False):
        (c_w, s_w, n_w), (c_o, s_o, n_o) = out["warp", full], out["opencl", full]
        assert (c_w[:, 0] >= 0).sum() >= 60 and (c_w[:, 1] >= 0).sum() >= 60  # object and mirror contours
        np.testing.assert_array_equal(c_w >= 0, c_o >= 0)
        np.testing.assert_allclose(c_w, c_o, rtol=0, atol=1e-4)  # fractional rows
        np.testing.assert_array_equal(n_w, n_o)
        np.testing.assert_allclose(s_w, s_o, rtol=1e-5, atol=1e-6)  # metres
        np.testing.assert_array_equal(out["warp", "view costs", full], out["warp", "view costs", not full])
        np.testing.assert_allclose(out["warp", "view costs", full], out["opencl", "view costs", full],
                                   rtol=1e-5, atol=1e-6)


def test_device_layers_give_their_host_floats_results(backend):
    """Device layers hold the render's fixed-point accumulator, which the contour kernels read
    as it is: contours, sums, counts and view costs bit for bit those of the same layers handed
    over as host floats (``numpy``), full and in bands; and ``numpy`` is the accumulator / 2^24."""
    sonar, mesh, poses, thresholds, windows = sphere_views()
    masks = np.ones((5, 2, sonar.beams), bool)
    distances = np.random.default_rng(1).uniform(0, 0.05, (5, 2, sonar.bins, sonar.beams))
    view_index = np.tile(np.arange(5), 3)
    smoothing = (_gaussian(1.0), _gaussian(0.7))
    handle = backend.load_mesh(mesh.vertices, mesh.faces)
    for rows in (None, tight_bands(view_index, windows, (len(smoothing[0]) - 1) // 2, sonar.bins)):
        layers = backend.render_device(handle, sonar, *poses, (1, 32), gamma=1.0, surface_reflection=0.9, rows=rows)
        floats = layers.numpy()
        fixed = layers.array.numpy() if backend.name == "warp" else _buffer_ints(layers)
        assert fixed.dtype == np.int32 and np.count_nonzero(fixed) > 1000
        np.testing.assert_array_equal(floats, fixed.astype(np.float32) * np.float32(2.0 ** -24))
        results = []
        for given in (layers, HostLayers(floats, layers.first_rows)):
            args = (given, view_index, thresholds, windows, masks, distances, [0.0, 0.5], smoothing)
            results.append((*backend.contour_cost(*args), backend.view_costs(*args, np.full((5, 2), 20), 0.04)))
        assert (results[0][0] >= 0).sum() >= 100
        for device, host in zip(*results):
            np.testing.assert_array_equal(device, host)


def _buffer_ints(layers) -> np.ndarray:
    """The int32 accumulator of OpenCLLayers, copied as it is."""
    import pyopencl as cl

    ints = np.empty(layers.shape, np.int32)
    cl.enqueue_copy(layers.backend.queue, ints, layers.buffer, is_blocking=True)
    return ints


@pytest.mark.parametrize("taps", [1, 3, 5, 9])
def test_beams_read_are_the_beams_the_smoothing_reaches(taps):
    """beams_read: every beam that the contour of a masked beam reads, clamp(b + k, 0, beams − 1)
    for |k| <= radius (frontal_contour's rule, brute force), and no other."""
    masks = np.random.default_rng(taps).random((6, 2, 40)) < 0.15
    masks[0] = False
    masks[1, :, 0] = masks[1, :, -1] = True  # at both borders
    radius = (taps - 1) // 2
    want = np.zeros_like(masks)
    for n, c, b in zip(*np.nonzero(masks)):
        for k in range(-radius, radius + 1):
            want[n, c, min(max(b + k, 0), 39)] = True
    np.testing.assert_array_equal(beams_read(masks, taps), want)


@pytest.mark.parametrize("seed", [0, 1])
def test_mask_items_list_each_views_masked_beams_in_order(seed):
    """mask_items: per view, c · beams + b of every masked (component, beam) in that order, then
    -1 up to the most of any view (a loop over the masks), at least one column."""
    masks = np.random.default_rng(seed).random((5, 2, 30)) < 0.3
    masks[0] = False
    masks[2] = True
    want = [[c * 30 + b for c in range(2) for b in range(30) if masks[v, c, b]] for v in range(5)]
    items = mask_items(masks)
    assert items.dtype == np.int32 and items.shape == (5, max(map(len, want)))
    for v in range(5):
        np.testing.assert_array_equal(items[v], want[v] + [-1] * (items.shape[1] - len(want[v])))
    assert mask_items(np.zeros((3, 2, 4), bool)).tolist() == [[-1]] * 3


def test_layers_of_the_beams_read_give_the_full_layers_results(backend):
    """Pairs rendered with only the beams their masks read (``beams_read``; per pair, or once for
    the views of each cell, as ViewComparison.view_costs renders them), full or in bands, as four
    layers or the components' sums: contours, sums, counts and view costs bit for bit those of
    every beam rendered, with masks that leave out a side, a component and a view's mirror."""
    sonar, mesh, poses, thresholds, windows = sphere_views()
    masks = np.zeros((5, 2, sonar.beams), bool)
    masks[:, 0, 16:36] = True  # the object's contour lies at beams 19-44, the mirror's at 23-40
    masks[:, 1, 28:50] = True
    masks[1, 1] = False  # no mirror contour in view 1
    masks[3, 1, 28:50], masks[3, 1, 10:28] = False, True  # the mirror on the other side
    distances = np.random.default_rng(0).uniform(0, 0.05, (5, 2, sonar.bins, sonar.beams))
    view_index = np.tile(np.arange(5), 3)
    smoothing = (_gaussian(1.0), _gaussian(2.0))
    per_view = beams_read(masks, len(smoothing[1]))  # pair n = 5 g + v reads row v: n % 5
    read = per_view[view_index]
    handle = backend.load_mesh(mesh.vertices, mesh.faces)
    for rows in (None, tight_bands(view_index, windows, (len(smoothing[0]) - 1) // 2, sonar.bins)):
        results = []
        for beams, components in ((None, False), (read, False), (per_view, False), (per_view, True), (None, True)):
            layers = backend.render_device(handle, sonar, *poses, (1, 32), gamma=1.0, surface_reflection=0.9,
                                           rows=rows, beams=beams, components=components)
            assert layers.shape[1] == (2 if components else 4)
            args = (layers, view_index, thresholds, windows, masks, distances, [0.0, 0.5], smoothing)
            results.append((*backend.contour_cost(*args), backend.view_costs(*args, np.full((5, 2), 20), 0.04)))
            if beams is not None:
                assert 0 < layers.numpy().sum() < 0.99 * full_sum
            else:
                full_sum = layers.numpy().sum()
        assert (results[0][0][:, 0] >= 0).sum() >= 40 and (results[0][0][:, 1] >= 0).sum() >= 20
        for result in results[1:]:
            for every, other in zip(results[0], result):
                np.testing.assert_array_equal(other, every)


def tight_bands(view_index, windows, radius, bins):
    """(first (N,), R): the rows each pair's window reads, [max(lo − r, 0), min(hi + r, bins)),
    R the widest, bands started lower where they would pass the last row (as ViewComparison.view_costs)."""
    need_lo = np.maximum(windows[:, 0] - radius, 0)
    count = int(np.max(np.minimum(windows[:, 1] + radius, bins) - need_lo))
    return np.minimum(need_lo, bins - count)[view_index], count


def banded(layers, first, count):
    return HostLayers(np.stack([layers[n, :, f:f + count] for n, f in enumerate(first)]), first)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_banded_layers_match_full(backend, seed):
    """contour_cost on each pair's band of rows (image row B at row B − first[n]) gives the full
    layers' contours, sums and counts bit for bit, with windows at both image borders (the
    smoothing clamps to the image, not to the band)."""
    layers, view_index, thresholds, _, masks, distances, shifts, smoothing = random_case(seed, n_pairs=9, n_views=4)
    bins, radius = layers.shape[2], (len(smoothing[0]) - 1) // 2
    windows = np.array([[0, 9], [bins - 7, bins], [20, 31], [12, 36]])  # at the top and bottom rows, inside
    view_index = np.array([0, 1, 2, 3, 0, 1, 2, 2, 1])
    full = backend.contour_cost(layers, view_index, thresholds, windows, masks, distances, shifts, smoothing)
    assert (full[0] >= 0).sum() > 20 and (full[0] == -1).sum() > 5
    tight = tight_bands(view_index, windows, radius, bins)
    for first, count in (tight, (tight[0] * 0, bins), (np.clip(tight[0] - 3, 0, bins - tight[1] - 3), tight[1] + 3)):
        got = backend.contour_cost(banded(layers, first, count), view_index, thresholds, windows, masks, distances,
                                   shifts, smoothing)
        for a, b in zip(got, full):
            np.testing.assert_array_equal(a, b)
    # a band one row short at either end of what the window reads: refused
    first, count = tight
    short_top = np.array(first)
    short_top[0] += 1  # pair 0 (window [0, 9)) no longer holds row 0
    short_bottom = np.array(first)
    short_bottom[1] = bins - count + 1  # pair 1 (window [bins - 7, bins)) would need rows past the image
    for bad_first, bad_count in ((short_top, count), (first, count - 1)):
        with pytest.raises(ValueError, match="band"):
            backend.contour_cost(banded(layers, bad_first, bad_count), view_index, thresholds, windows, masks,
                                 distances, shifts, smoothing)
    with pytest.raises(ValueError, match="rows"):
        backend.contour_cost(HostLayers(np.zeros((9, 4, count, layers.shape[3]), np.float32), short_bottom),
                             view_index, thresholds, windows, masks, distances, shifts, smoothing)
    with pytest.raises(ValueError, match="banded layers"):  # a band for another number of beams
        backend.contour_cost(HostLayers(np.zeros((9, 4, count, 3), np.float32), first), view_index, thresholds,
                             windows, masks, distances, shifts, smoothing)


@pytest.mark.parametrize("seed", [0, 1])
def test_device_distances_give_the_host_arrays_results(backend, seed):
    """Distances uploaded once (``device_distances``) give contour_cost the results of the
    host array, bit for bit, in any number of calls."""
    case = random_case(seed)
    want = backend.contour_cost(*case)
    uploaded = backend.device_distances(case[5])
    assert uploaded.shape == case[5].shape
    for _ in range(2):
        got = backend.contour_cost(*case[:5], uploaded, *case[6:])
        for a, b in zip(got, want):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_cap_reads_the_distances_as_if_capped_on_the_host(backend, seed):
    """``cap`` reads each distance as min(distance, cap): the results of the maps capped in
    float32 on the host, bit for bit, at caps below, among and above the distances; and the
    oracle's at one of them."""
    case = random_case(seed)
    uploaded = backend.device_distances(case[5])
    for cap in (0.004, 0.02, 0.05, 1.0):
        capped = np.minimum(case[5], np.float32(cap))
        want = backend.contour_cost(*case[:5], capped, *case[6:])
        got = backend.contour_cost(*case[:5], uploaded, *case[6:], cap=cap)
        for a, b in zip(got, want):
            np.testing.assert_array_equal(a, b)
    reference = contour_cost_reference(*case[:5], np.minimum(case[5], np.float32(0.02)), *case[6:])
    got = backend.contour_cost(*case, cap=0.02)
    np.testing.assert_allclose(got[1], reference[1], rtol=0, atol=2e-4 * case[5].shape[3])
    assert not np.allclose(got[1], backend.contour_cost(*case)[1])  # the cap is read


def test_device_distances_are_checked_once_and_stay_with_their_backend(backend_for_label):
    opencl, warp = backend_for_label("opencl-cpu"), backend_for_label("warp-cpu")
    with pytest.raises(ValueError, match=">= 0"):
        opencl.device_distances(-np.ones((3, 2, 8, 4)))
    with pytest.raises(ValueError, match="distances must have shape"):
        opencl.device_distances(np.zeros((3, 8, 4)))
    case = random_case(0)
    with pytest.raises(ValueError, match="uploaded by <WarpBackend"):
        opencl.contour_cost(*case[:5], warp.device_distances(case[5]), *case[6:])
    with pytest.raises(ValueError, match="like thresholds"):  # maps of another image size
        opencl.contour_cost(*case[:5], opencl.device_distances(case[5][:, :, :-1]), *case[6:])


@pytest.mark.parametrize("change, message", [
    (dict(view_index=[0, 5]), "view_index"),
    (dict(windows=np.array([[5, 5], [0, 8], [0, 8]])), "windows"),
    (dict(masks=np.ones((3, 2, 4), np.uint8)), "masks"),
    (dict(distances=-np.ones((3, 2, 8, 4))), ">= 0"),
    (dict(shifts=[]), "shifts"),
    (dict(cap=0.0), "cap"),
    (dict(cap=float("nan")), "cap"),
    (dict(smoothing=([0.5, 0.5], [1.0])), "odd"),
    (dict(layers=np.zeros((2, 4, 8, 5))), "layers"),
])
def test_bad_inputs_raise(backend_for_label, change, message):
    backend = backend_for_label("opencl-cpu")
    args = dict(layers=np.zeros((2, 4, 8, 4)), view_index=[0, 2], thresholds=np.ones((3, 8)),
                windows=np.tile([0, 8], (3, 1)), masks=np.ones((3, 2, 4), bool), distances=np.zeros((3, 2, 8, 4)),
                shifts=[0.0], smoothing=([1.0], [1.0]))
    args.update(change)
    with pytest.raises(ValueError, match=message):
        backend.contour_cost(**args)


@pytest.mark.parametrize("change, message", [
    (dict(data_counts=np.zeros((3, 3), int)), "data_counts"),
    (dict(data_counts=-np.ones((3, 2), int)), "data_counts"),
    (dict(data_counts=np.zeros((3, 2))), "data_counts"),
    (dict(cap=float("inf")), "finite"),
    (dict(cap=0.0), "cap"),
    (dict(view_index=[0, 5]), "view_index"),
])
def test_view_costs_bad_inputs_raise(backend_for_label, change, message):
    backend = backend_for_label("opencl-cpu")
    args = dict(layers=np.zeros((2, 4, 8, 4)), view_index=[0, 2], thresholds=np.ones((3, 8)),
                windows=np.tile([0, 8], (3, 1)), masks=np.ones((3, 2, 4), bool), distances=np.zeros((3, 2, 8, 4)),
                shifts=[0.0], smoothing=([1.0], [1.0]), data_counts=np.ones((3, 2), int), cap=0.02)
    args.update(change)
    with pytest.raises(ValueError, match=message):
        backend.view_costs(**args)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_scan_from_scan_start_finds_the_contours_of_a_scan_from_row_0(backend, seed):
    """The pose step scans its predicted views from ``scan_start`` (the row before the
    smoothing first reaches a return): the contours equal a scan of the whole image, also for
    echoes at the top rows and views with none; and ``scan_start`` is that row."""
    from fsswarp.compare import scan_start

    layers, view_index, thresholds, _, _, distances, shifts, smoothing = random_case(seed)
    n_pairs, _, bins, beams = layers.shape
    rng = np.random.default_rng(seed)
    first = rng.integers(0, bins, n_pairs)
    first[0], first[1] = 0, bins  # an echo in the first row, a view without any
    layers *= (np.arange(bins)[None, :] >= first[:, None])[:, None, :, None]  # 0 above the first echo row
    taps = len(smoothing[0])
    np.testing.assert_array_equal(scan_start(layers, taps),
                                  np.clip(first - (taps - 1) // 2 - 1, 0, bins - 1))
    index = np.arange(n_pairs)
    views = thresholds[view_index], np.ones((n_pairs, 2, beams), bool), distances[view_index]
    whole = np.stack([np.zeros(n_pairs, int), np.full(n_pairs, bins)], axis=1)
    scan = np.stack([scan_start(layers, taps), np.full(n_pairs, bins)], axis=1)
    full = backend.contour_cost(layers, index, views[0], whole, *views[1:], shifts, smoothing)
    started = backend.contour_cost(layers, index, views[0], scan, *views[1:], shifts, smoothing)
    for a, b in zip(full, started):
        np.testing.assert_array_equal(a, b)
    assert (full[0] >= 0).any()
