"""Segmentation of beam-bin images: object highlight, feasible region, shadow, frontal contour.

:func:`segment` takes a (bins, beams) linear image and returns a :class:`Segmentation` of
(bins, beams) bool masks (highlight, feasible, shadow) and the frontal contour, (beams,) int:
per beam the first highlight bin, -1 where the beam holds none. The highlight is every echo
that stands out of the water's noise: object, ghost and mirror alike.

Steps (``SegmentSettings`` holds every constant):

0. :func:`clip_spikes`: in an image with a noise floor (median > 0), a pixel above
   ``SPIKE_RATIO`` times the largest of its 8 neighbours takes that value.
1. :func:`normalized`: the image divided by its background level per range row (the row's
   median over the beams / ln 2, smoothed along range over ``background_rows`` rows).
2. A Gaussian of (``sigma_bins``, ``sigma_beams``) pixels; hysteresis at median + ``high``
   (seeds) and + ``low`` (growth) robust standard deviations (1.4826 · MAD, floored at 1% of
   the peak above the median).
3. Blobs under ``min_pixels`` pixels are dropped.

Feasible region (DESIGN §6): along each beam, every bin from the first highlight to the end of
the window, started no later than that of any beam within ``dilate_beams``. Shadow: the
feasible pixels that are not highlight. :func:`memoized` keeps the last ``MEMO_SIZE`` results
by image content, read-only (Memo). Why these thresholds: docs/decisions.md ("Segmentation").
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, fields
from typing import Callable

import numpy as np
import xxhash

from .caching import Remembered
from .errors import InputError, check_integer, is_finite_number


class SegmentWarning(UserWarning):
    """A view whose segmentation is suspect (no highlight at all)."""


@dataclass(frozen=True)
class SegmentSettings:
    """Options of :func:`segment` (the module docstring explains each step).

    sigma_bins, sigma_beams : Gaussian smoothing (pixels) along range and across beams
    low, high : hysteresis thresholds, in robust standard deviations of the smoothed image
    min_pixels : smallest highlight blob kept (8-connected pixels)
    background_rows : running-median length (rows) of the background level along range
    dilate_beams : the feasible region of a beam starts no later than its neighbours' within
        this many beams (0: no margin)
    """

    sigma_bins: float = 1.0
    sigma_beams: float = 0.7
    low: float = 2.0
    high: float = 10.0
    min_pixels: int = 15
    background_rows: int = 31
    dilate_beams: int = 0

    def __post_init__(self) -> None:
        for name in ("sigma_bins", "sigma_beams"):
            value = getattr(self, name)
            if not (is_finite_number(value) and 0 <= value <= 50):
                raise InputError("must be a number in [0, 50] (pixels)", field=f"segment.{name}", value=value)
        if not (is_finite_number(self.low) and is_finite_number(self.high) and 0 < self.low <= self.high):
            raise InputError("thresholds must satisfy 0 < low <= high", field="segment.low",
                             value=(self.low, self.high))
        for name, lowest in (("min_pixels", 1), ("background_rows", 1), ("dilate_beams", 0)):
            check_integer(f"segment.{name}", getattr(self, name), lowest)


@dataclass(frozen=True)
class Segmentation:
    """One view's segmentation; every mask is (bins, beams) bool.

    highlight : echo above the noise (object, ghost and mirror)
    feasible : the carving region: per beam from the (beam-dilated) first highlight to the end
    shadow : feasible and not highlight
    contour : (beams,) int32 frontal contour: first highlight bin per beam, -1 where none
    """

    highlight: np.ndarray
    feasible: np.ndarray
    shadow: np.ndarray
    contour: np.ndarray

    @property
    def empty(self) -> bool:
        """Whether the view holds no highlight at all."""
        return not bool(self.highlight.any())


def segment(image, settings: SegmentSettings = SegmentSettings(), *, name: str = "image") -> Segmentation:
    """Segment one (bins, beams) linear beam-bin image (float, finite, >= 0).

    ``name`` labels errors and the warning (SegmentWarning) given when nothing stands out of
    the noise; the result is then empty (no feasible pixel)."""
    result = _segmentation(_checked(image, name), settings)
    _warn_if_empty(result, name)
    return result


def segment_views(images: dict, settings: SegmentSettings = SegmentSettings(), *,
                  label: str = "{}") -> dict[str, Segmentation]:
    """:func:`segment` of every image of ``images`` ({name: (bins, beams) image}), worked out side
    by side in threads (``fsswarp.system.map_on_threads``, at most ``SEGMENT_THREADS``: the
    filters and the labelling release the interpreter's lock): {name: Segmentation}, the same
    ones, with the same errors and warnings in the order of ``images``. ``label``: an image's
    name in them, formatted with its key (e.g. "images/{}")."""
    from .system import map_on_threads

    arrays = {key: _checked(image, label.format(key)) for key, image in images.items()}
    results = map_on_threads(lambda array: _segmentation(array, settings), arrays.values(), most=SEGMENT_THREADS,
                             name="fsswarp-segment")
    for key, result in zip(arrays, results):
        _warn_if_empty(result, label.format(key))
    return dict(zip(arrays, results))


#: Threads of :func:`segment_views`: coral-one's 16 views took 0.146 s one after another and
#: 0.084 s in two threads on this project's 2-CPU machine (bench/notes.md, forty-second session).
SEGMENT_THREADS = 8


def _checked(image, name: str) -> np.ndarray:
    """``image`` as a float64 (bins, beams) array; InputError naming ``name`` where it is no such
    image, holds non-finite values or negative ones."""
    array = np.asarray(image)
    if array.ndim != 2 or min(array.shape) < 2:
        raise InputError("must be a (bins, beams) image with at least 2 rows and columns", field=name,
                         value=array.shape)
    if array.dtype.kind not in "fiu":
        raise InputError("must hold real numbers", field=name, value=str(array.dtype))
    array = array.astype(np.float64)
    if not np.all(np.isfinite(array)):
        raise InputError("holds non-finite values", field=name, value=int((~np.isfinite(array)).sum()))
    if array.min() < 0:
        raise InputError("must be linear intensity >= 0", field=name, value=float(array.min()))
    return array


def _segmentation(array: np.ndarray, settings: SegmentSettings) -> Segmentation:
    """The Segmentation of a checked image (:func:`_checked`), kept by :func:`memoized`."""
    return memoized("segment", array, settings,
                    lambda: from_highlight(_highlight(array, settings), dilate_beams=settings.dilate_beams))


def _warn_if_empty(result: Segmentation, name: str) -> None:
    """SegmentWarning, from the caller of :func:`segment` or :func:`segment_views`, where nothing
    stands out of the noise in the image ``name``."""
    if result.empty:
        warnings.warn(f"{name}: no object highlight stands out of the noise; its feasible region is empty",
                      SegmentWarning, stacklevel=3)


#: A pixel above this many times the largest of its 8 neighbours is an isolated spike (module
#: docstring, step 0).
SPIKE_RATIO = 40.0


def clip_spikes(image: np.ndarray) -> np.ndarray:
    """The (bins, beams) float64 ``image`` with its isolated spikes clipped to the largest of
    their 8 neighbours (module docstring, step 0); ``image`` itself where there is none, or no
    noise floor."""
    from scipy import ndimage

    if not (image.size and np.median(image) > 0):
        return image
    footprint = np.ones((3, 3), bool)
    footprint[1, 1] = False
    neighbours = ndimage.maximum_filter(image, footprint=footprint, mode="constant", cval=0.0)
    spikes = image > SPIKE_RATIO * neighbours
    return np.where(spikes, neighbours, image) if spikes.any() else image


def normalized(image: np.ndarray, settings: SegmentSettings):
    """Steps 0–2 of the module docstring for a clean (bins, beams) float64 image: (level (bins,),
    smooth (bins, beams), m, s), the background level per row, the smoothed image in units of
    it, and that image's median and robust spread."""
    from scipy import ndimage

    image = clip_spikes(image)
    peak = float(image.max()) if image.size else 0.0
    level = ndimage.median_filter(np.median(image, axis=1) / math.log(2.0), settings.background_rows,
                                  mode="nearest")
    level = np.maximum(level, 1e-6 * peak if peak > 0 else 1e-30)  # noise-free rows hold exact zeros
    smooth = ndimage.gaussian_filter(image / level[:, None], (settings.sigma_bins, settings.sigma_beams),
                                     mode="nearest")
    centre = float(np.median(smooth))
    spread = max(1.4826 * float(np.median(np.abs(smooth - centre))), 0.01 * (float(smooth.max()) - centre))
    return level, smooth, centre, spread


#: Results :func:`memoized` keeps (module docstring, "Memo").
MEMO_SIZE = 128
_memo = Remembered(MEMO_SIZE)


def memoized(kind: str, image: np.ndarray, settings, compute: Callable):
    """``compute()`` (an array or a dataclass of arrays), or the result kept for an image of
    the same content and the same ``kind`` and settings; the result's arrays are read-only."""
    image = np.ascontiguousarray(image)
    key = (kind, xxhash.xxh3_128_digest(image), image.shape, image.dtype.str, settings)

    def read_only():
        result = compute()
        for array in [result] if isinstance(result, np.ndarray) else [getattr(result, f.name) for f in fields(result)]:
            array.setflags(write=False)
        return result
    return _memo.get(key, read_only)


def from_highlight(highlight, *, dilate_beams: int = 0) -> Segmentation:
    """The segmentation that a (bins, beams) highlight mask implies: contour, feasible region
    (from the first highlight of the beam, or of a beam within ``dilate_beams``, to the end of
    the window) and shadow. Also builds the true segmentation from a truth layer (``> 0``)."""
    mask = np.asarray(highlight, bool)
    bins, beams = mask.shape
    any_hit = mask.any(axis=0)
    contour = np.where(any_hit, mask.argmax(axis=0), -1).astype(np.int32)
    start = np.where(any_hit, contour, bins).astype(np.int64)
    shifted = start.copy()
    for step in range(1, dilate_beams + 1):
        shifted[step:] = np.minimum(shifted[step:], start[:-step])
        shifted[:-step] = np.minimum(shifted[:-step], start[step:])
    feasible = np.arange(bins)[:, None] >= shifted[None, :]
    return Segmentation(highlight=mask, feasible=feasible, shadow=feasible & ~mask, contour=contour)


def _highlight(image: np.ndarray, settings: SegmentSettings) -> np.ndarray:
    """(bins, beams) bool highlight of a clean float64 image (steps 0-3 of the module docstring)."""
    from skimage.filters import apply_hysteresis_threshold
    from skimage.measure import label

    _, smooth, centre, spread = normalized(image, settings)
    if not float(smooth.max()) > centre:
        return np.zeros(image.shape, bool)
    mask = apply_hysteresis_threshold(smooth - centre, settings.low * spread, settings.high * spread)
    labels = label(mask, connectivity=2)
    sizes = np.bincount(labels.ravel())
    keep = sizes >= settings.min_pixels
    keep[0] = False
    return keep[labels]
