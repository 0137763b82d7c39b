"""Segmentation of beam-bin images against the truth layers of simulated coral-one, and on bad
input.

Numbers on coral-one (seed 1, noise: Gamma speckle of 4 looks and an exponential background at
5% of the 99th-percentile echo), printed by ``test_segmentation_of_coral_one``: highlight
precision against every echo layer, recall of the object layer (pixels and echo energy), the
share of object pixels inside the feasible region, and the frontal contour's offset from the
true one (bins; negative = in front).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from fsswarp.errors import InputError
from fsswarp.rendering import add_noise
from fsswarp.compare import detection_threshold
from fsswarp.segment import (SPIKE_RATIO, SegmentSettings, SegmentWarning, clip_spikes, from_highlight, segment,
                             segment_views)
from fsswarp.surface import COMPONENTS


def test_segmentation_of_coral_one(coral_one):
    precision, recall, energy, covered, front = [], [], [], [], []
    for name in coral_one.rig.names:
        seg = segment(coral_one.images[name], name=name)
        obj = coral_one.truth_layer(name, "object")
        echo = sum(coral_one.truth_layer(name, c) for c in COMPONENTS)
        precision.append((seg.highlight & (echo > 0)).sum() / seg.highlight.sum())
        recall.append((seg.highlight & (obj > 0)).sum() / (obj > 0).sum())
        energy.append(obj[seg.highlight].sum() / obj.sum())
        covered.append((seg.feasible & (obj > 0)).sum() / (obj > 0).sum())
        true_front = from_highlight(obj > 0).contour
        both = (true_front >= 0) & (seg.contour >= 0)
        front.append(np.mean(seg.contour[both] - true_front[both]))
        assert np.array_equal(seg.shadow, seg.feasible & ~seg.highlight)
    print(f"highlight precision {np.mean(precision):.3f} (min {np.min(precision):.3f}), object recall "
          f"{np.mean(recall):.3f} of pixels, {np.mean(energy):.3f} of echo energy; feasible holds "
          f"{np.mean(covered):.4f} (min {np.min(covered):.4f}) of object pixels; contour offset "
          f"{np.mean(front):+.2f} bins")
    assert np.mean(precision) >= 0.8 and np.min(precision) >= 0.6
    assert np.mean(energy) >= 0.95 and np.mean(recall) >= 0.75
    assert np.mean(covered) >= 0.98 and np.min(covered) >= 0.9
    assert -3.0 <= np.mean(front) <= 0.5


def test_a_hot_pixel_leaves_the_segmentation_as_it_was(coral_one):
    """One pixel at 5 to 1000 times a view's peak, in its background: the highlight equals the
    clean view's and the detection threshold is within 0.1% of it (before step 0, 5x shrank the
    object's highlight and 20x lost it); every noisy view of the scene is left as it is."""
    for name in coral_one.rig.names:
        image = coral_one.images[name].astype(np.float64)
        assert np.array_equal(clip_spikes(image), image), name
    clean = coral_one.images["Sm22p5"].astype(np.float64)
    base = segment(clean)
    assert base.highlight.sum() > 100 and not base.highlight[:60, :10].any()
    for factor in (5, 20, 1000):
        hot = clean.copy()
        hot[30, 5] = factor * clean.max()
        assert np.array_equal(segment(hot).highlight, base.highlight), factor
        # the clipped pixel takes its neighbours' value, not its own: the spread moves by 0.04%
        np.testing.assert_allclose(detection_threshold(hot), detection_threshold(clean), rtol=1e-3)


def test_clip_spikes():
    """A pixel above SPIKE_RATIO times its largest neighbour takes that neighbour's value (at
    the border too); a pair of bright pixels, a pixel at the ratio and images without a noise
    floor (median 0) are kept."""
    image = np.full((6, 5), 1.0)
    image[2, 2] = 2.0
    image[0, 4] = 10 * SPIKE_RATIO
    image[2, 1] = SPIKE_RATIO * 2.0  # exactly at the ratio: kept
    image[5, 0] = image[5, 1] = 1e6  # two pixels: an echo, not a spike
    image[4, 3] = 1e3
    clipped = clip_spikes(image)
    want = image.copy()
    want[0, 4] = 1.0
    want[4, 3] = 1.0
    assert np.array_equal(clipped, want)
    sparse = np.zeros((6, 5))
    sparse[3, 3] = 5.0
    sparse[3, 4] = 0.01  # a noise-free facet's echo beside a faint one
    assert clip_spikes(sparse) is sparse


def test_noise_alone_has_no_highlight():
    """The simulator's background alone: at most one of ten images shows a (false) blob, and an
    image without highlight warns and has an empty feasible region."""
    images = [add_noise(np.zeros((512, 96), np.float32), np.random.default_rng(seed)) for seed in range(10)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SegmentWarning)
        empty = [segment(image).empty for image in images]
    assert sum(empty) >= 9
    with pytest.warns(SegmentWarning, match="S9: no object highlight"):
        seg = segment(images[empty.index(True)], name="S9")
    assert seg.empty and not seg.feasible.any() and (seg.contour == -1).all()
    with pytest.warns(SegmentWarning):
        assert segment(np.zeros((512, 96), np.float32)).empty


def test_views_segmented_side_by_side_are_each_segmented_alone(coral_one, monkeypatch):
    """``segment_views`` in threads (nothing kept from before) gives each view's ``segment``, mask
    for mask; an image without highlight warns in its place in the order, and a bad image is
    refused by its label."""
    import concurrent.futures

    import fsswarp.segment as module

    names = list(coral_one.rig.names)
    images = {names[0]: coral_one.images[names[0]], "blank": np.zeros((512, 96), np.float32)}
    images |= {name: coral_one.images[name] for name in names[1:]} | {"zeros": np.zeros((64, 8))}
    pools, made = [], concurrent.futures.ThreadPoolExecutor

    def counted(workers, **kwargs):
        pools.append(workers)
        return made(workers, **kwargs)

    monkeypatch.setattr(concurrent.futures, "ThreadPoolExecutor", counted)
    monkeypatch.setattr("fsswarp.system.usable_cpus", lambda: 4)
    module._memo.clear()
    with pytest.warns(SegmentWarning) as caught:
        together = segment_views(images, label="images/{}")
    assert pools == [4] and list(together) == list(images)
    assert [str(w.message).split(":")[0] for w in caught] == ["images/blank", "images/zeros"]
    module._memo.clear()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SegmentWarning)
        for name, image in images.items():
            alone = segment(image, name=name)
            for field in ("highlight", "feasible", "shadow", "contour"):
                assert np.array_equal(getattr(together[name], field), getattr(alone, field)), (name, field)
    with pytest.raises(InputError, match="images/bad"):
        segment_views({names[0]: images[names[0]], "bad": np.full((4, 4), -1.0)}, label="images/{}")


def test_noise_free_image_and_range_gain():
    """A noise-free image (exact zeros around the echo) thresholds at a fraction of its peak; a
    background that grows with range is normalised away."""
    image = np.zeros((512, 96), np.float32)
    image[200:206, 40:50] = 1.0
    image[206:230, 40:50] = 0.02  # faint tail, under 3% of the peak after smoothing
    seg = segment(image)
    assert ((seg.contour[40:50] >= 197) & (seg.contour[40:50] <= 200)).all()
    assert (seg.contour[:38] == -1).all() and (seg.contour[52:] == -1).all()

    rng = np.random.default_rng(5)
    gain = np.linspace(1.0, 20.0, 512)[:, None]
    noisy = (rng.exponential(0.004, (512, 96)) * gain).astype(np.float32)
    noisy[300:304, 30:40] += 0.8
    seg = segment(noisy)
    assert set(np.flatnonzero(seg.contour >= 0)) <= set(range(28, 42)) and (seg.contour[31:39] >= 298).all()


def test_from_highlight():
    mask = np.zeros((10, 5), bool)
    mask[4, 1] = mask[7, 1] = mask[2, 3] = True
    seg = from_highlight(mask)
    assert seg.contour.tolist() == [-1, 4, -1, 2, -1]
    assert seg.feasible[:, 1].tolist() == [False] * 4 + [True] * 6
    assert not seg.feasible[:, 0].any() and seg.shadow.sum() == (6 - 2) + (8 - 1)
    wide = from_highlight(mask, dilate_beams=1)
    assert [int(np.argmax(c)) if c.any() else -1 for c in wide.feasible.T] == [4, 4, 2, 2, 2]
    assert wide.contour.tolist() == seg.contour.tolist()


@pytest.mark.parametrize("image, text", [
    (np.zeros(10, np.float32), "(bins, beams) image"),
    (np.full((8, 8), np.nan, np.float32), "non-finite"),
    (-np.ones((8, 8), np.float32), "linear intensity >= 0"),
    (np.full((8, 8), "a"), "real numbers"),
])
def test_segment_bad_input(image, text):
    with pytest.raises(InputError, match=text.replace("(", r"\(").replace(")", r"\)")):
        segment(image, name="images/S0.tiff")


@pytest.mark.parametrize("field, value", [("low", 0.0), ("min_pixels", 0), ("sigma_bins", -1.0),
                                          ("dilate_beams", 1.5)])
def test_segment_settings_are_checked(field, value):
    with pytest.raises(InputError, match=f"segment.{field}" if field != "low" else "segment.low"):
        SegmentSettings(**{field: value})


def test_the_memo_keys_on_content_and_settings_and_keeps_results_read_only(monkeypatch):
    """A second call on an equal image returns the kept result without segmenting again; a
    changed pixel, other settings or a full memo segment afresh; kept arrays cannot be changed;
    an empty result warns on every call."""
    import fsswarp.segment as seg

    calls = []
    real = seg._highlight
    monkeypatch.setattr(seg, "_highlight", lambda image, settings: calls.append(1) or real(image, settings))
    monkeypatch.setattr(seg, "_memo", type(seg._memo)(seg.MEMO_SIZE))
    rng = np.random.default_rng(3)
    image = rng.exponential(1.0, (64, 24)).astype(np.float32)
    image[30:34, 8:14] += 200.0
    first = segment(image)
    again = segment(image.copy())
    assert again is first and len(calls) == 1
    assert np.array_equal(first.highlight, real(image.astype(np.float64), SegmentSettings()))
    with pytest.raises(ValueError):
        first.highlight[0, 0] = True
    changed = image.copy()
    changed[10, 3] += 1e-3
    assert segment(changed) is not first and len(calls) == 2
    assert segment(image, SegmentSettings(low=3.0)) is not first and len(calls) == 3
    for k in range(seg.MEMO_SIZE):
        segment(image + np.float32(k + 1))
    assert len(seg._memo) == seg.MEMO_SIZE
    segment(image)
    assert len(calls) == 3 + seg.MEMO_SIZE + 1  # the first result had been dropped
    flat = np.ones((64, 24), np.float32)
    for _ in range(2):
        with pytest.warns(SegmentWarning, match="no object highlight"):
            segment(flat, name="flat")
