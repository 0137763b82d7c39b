"""Ghost removal by the LUT method and ghost isolation (paper §2.6, Figure 5; DESIGN §10).

:func:`enhance` renders a model at (depth m, tilt rad) and runs :func:`enhance_view` on every
view: ``{view name: EnhancedView}`` with the ghost-free image ``enhanced``, the isolated
``ghost`` (both (bins, beams) float32, the data's linear units), the synthetic total layer,
the (bins, beams) bool object, ghost and mirror regions, and the LUT, (2, levels) float64 dB.

Per view, with data image I (linear) and the layers rendered at (D, β):

1. L_0 = 10 log10(object layer), the synthetic log object image (dB).
2. Regions: where a layer reaches ``threshold`` of the synthetic peak, dilated by ``dilate``
   pixels: object O, ghost G, mirror M (mirror + mirror2).
3. O splits into the overlap O ∩ (G ∪ M) and the rest, N; L_0 is normalized over N.
4. Rescaled to the data's dB mean and spread over N: L, the object in the data's log scale.
5. The LUT maps L to the data's dB values by matching their ``levels``-quantile histograms over N.
6. Over the overlap the LUT's output replaces the data; ghost- and mirror-only pixels take the
   data's background level; elsewhere the data stays.

Ghost: over G, max(I − enhanced, 0) times the synthetic ghost's share of the synthetic
multipath, optionally despeckled (``ghost_sigma``, pixels). Views where the model does not
project, or leaves too few object pixels for the LUT, are skipped with a warning.
:func:`comparison_views` picks the views of figures like the paper's Figures 10–14;
:func:`match_level` scales a synthetic image to the data's level; :func:`score` compares with
the truth layers of simulated data. docs/method.md has our reading of §2.6 in full.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from .errors import InputError, is_number
from .rendering import LAYERS, RenderSettings, RenderWarning, render

_DB_FLOOR = 1e-30
#: Largest despeckle σ (pixels) of the isolated ghost (``--ghost-sigma``).
MAX_GHOST_SIGMA = 20.0


@dataclass(frozen=True)
class EnhancedView:
    """One view's result. Images are (bins, beams) float32 in the data's linear units but
    ``synthetic``, the model's total layer (render's units); masks (bins, beams) bool. ``lut``
    is (2, levels) float64: source dB (scaled synthetic) and target dB (data) values of the
    table."""

    enhanced: np.ndarray
    ghost: np.ndarray
    synthetic: np.ndarray
    object_region: np.ndarray
    ghost_region: np.ndarray
    mirror_region: np.ndarray
    overlap: np.ndarray
    lut: np.ndarray
    background: float

    def summary(self) -> dict:
        """Pixel counts, background and LUT ends, for enhance.json."""
        return {"object_pixels": int(self.object_region.sum()), "ghost_pixels": int(self.ghost_region.sum()),
                "mirror_pixels": int(self.mirror_region.sum()), "overlap_pixels": int(self.overlap.sum()),
                "background": self.background,
                "lut_db": {"source": [float(self.lut[0, 0]), float(self.lut[0, -1])],
                           "target": [float(self.lut[1, 0]), float(self.lut[1, -1])]}}


def enhance_view(image, layers, *, threshold: float = 1e-3, dilate: int = 1, levels: int = 256,
                 ghost_sigma: tuple[float, float] = (0.0, 0.0), name: str = "image") -> EnhancedView:
    """Ghost-free object image and isolated ghost of one view (module docstring, steps 1–6).

    image : (bins, beams) linear data; layers : (5, bins, beams) synthetic layers in the order
    of ``render.LAYERS``. ``ghost_sigma`` (bins, beams): Gaussian σ of a despeckle of the
    isolated ghost inside the ghost region (normalized convolution; (0, 0), the default, keeps
    the recorded, speckled ghost; (1, 0.7), segment's smoothing, estimates the noise-free
    one). InputError when the shapes differ or the synthetic object leaves too few
    non-overlapping pixels (fewer than 16) to learn the LUT from."""
    from scipy import ndimage

    check_ghost_sigma(ghost_sigma)
    image = np.asarray(image, np.float64)
    layers = np.asarray(layers, np.float64)
    if image.ndim != 2 or layers.shape != (len(LAYERS),) + image.shape:
        raise InputError(f"layers must be ({len(LAYERS)}, bins, beams) matching the image",
                         field=name, value=f"image {image.shape}, layers {layers.shape}")
    layer = dict(zip(LAYERS, layers))
    cut = threshold * float(layer["total"].max())
    if not cut > 0:
        raise InputError("the model does not project into this view (its synthetic image is empty)",
                         field=name, value="model")
    grow = (lambda m: ndimage.binary_dilation(m, iterations=dilate)) if dilate > 0 else (lambda m: m)
    obj = grow(layer["object"] >= cut)
    ghost = grow(layer["ghost"] >= cut)
    mirror = grow(np.maximum(layer["mirror"], layer["mirror2"]) >= cut)
    overlap = obj & (ghost | mirror)
    # inside the dilation margin the synthetic object may be zero: those pixels keep the data
    core = layer["object"] > 0
    non_overlap = obj & ~overlap & core
    if non_overlap.sum() < 16:
        raise InputError("the model's object image leaves fewer than 16 pixels free of ghost and "
                         "mirror to learn the look-up table from", field=name,
                         value=f"{int(non_overlap.sum())} pixels")
    data_db = 10.0 * np.log10(np.maximum(image, _DB_FLOOR))
    synth_db = 10.0 * np.log10(np.maximum(layer["object"], _DB_FLOOR))
    mean_n, std_n = synth_db[non_overlap].mean(), synth_db[non_overlap].std()
    mean_i, std_i = data_db[non_overlap].mean(), data_db[non_overlap].std()
    scaled = std_i * (synth_db - mean_n) / max(std_n, 1e-12) + mean_i
    q = (np.arange(levels) + 0.5) / levels
    lut = np.stack([np.quantile(scaled[non_overlap], q), np.quantile(data_db[non_overlap], q)])
    fill = overlap & core
    source = scaled[fill]
    estimate = np.interp(source, lut[0], lut[1])
    estimate = np.where(source < lut[0, 0], lut[1, 0] + source - lut[0, 0], estimate)
    estimate = np.where(source > lut[0, -1], lut[1, -1] + source - lut[0, -1], estimate)
    background = float(np.median(image[~(obj | ghost | mirror)])) if (~(obj | ghost | mirror)).any() else 0.0
    enhanced = image.copy()
    enhanced[(ghost | mirror) & ~core] = background
    enhanced[fill] = 10.0 ** (estimate / 10.0)
    multipath = layer["ghost"] + layer["mirror"] + layer["mirror2"]
    share = np.divide(layer["ghost"], multipath, out=(~mirror).astype(np.float64), where=multipath > 0)
    isolated = np.where(ghost, np.maximum(image - enhanced, 0.0) * share, 0.0)
    if any(ghost_sigma):
        weight = ndimage.gaussian_filter(ghost.astype(np.float64), ghost_sigma)
        isolated = np.where(ghost, ndimage.gaussian_filter(isolated, ghost_sigma) / np.maximum(weight, 1e-12), 0.0)
    return EnhancedView(enhanced.astype(np.float32), isolated.astype(np.float32),
                        layer["total"].astype(np.float32), obj, ghost, mirror, overlap, lut, background)


def check_ghost_sigma(sigma) -> None:
    """InputError (field --ghost-sigma) unless ``sigma`` is two numbers in [0, MAX_GHOST_SIGMA]
    (pixels): a larger σ blurs the ghost over more than the region it fills, and a huge one
    would run for minutes."""
    values = tuple(sigma) if isinstance(sigma, (tuple, list)) else ()
    if len(values) != 2 or not all(is_number(v) and 0.0 <= v <= MAX_GHOST_SIGMA for v in values):  # NaN fails too
        raise InputError(f"must be two sigmas (bins, beams) in [0, {MAX_GHOST_SIGMA:g}] pixels", field="--ghost-sigma",
                         value=sigma)


def enhance(dataset, model, depth: float, tilt: float, *, views=None, settings: RenderSettings = RenderSettings(),
            backend=None, model_name: str = "model", **options) -> dict[str, EnhancedView]:
    """Enhanced views of ``dataset`` (fsswarp.dataset.Dataset) with the mesh ``model`` (reference
    frame) rendered at (depth m, tilt rad). views : names (default: all). ``options`` go to
    ``enhance_view``.

    Views that cannot be enhanced, where the model does not project (an empty synthetic object
    layer) or leaves too few object pixels free of ghost and mirror (``enhance_view``), are
    skipped with a RenderWarning naming them and are absent from the result. InputError naming
    a view the dataset lacks, or when no view is left: naming ``model_name`` when it projects
    into none, else the first view's reason."""
    names = list(dataset.rig.names if views is None else views)
    if not names:
        raise InputError("no views to enhance", field="views", value=names)
    if "ghost_sigma" in options:
        check_ghost_sigma(options["ghost_sigma"])
    check_views(dataset, names)
    rendered = render_model(model, dataset, depth, tilt, names, settings=settings, backend=backend,
                            model_name=model_name)
    results, failures = {}, []
    for name, layers in rendered.items():
        try:
            results[name] = enhance_view(dataset.images[name], layers, name=f"view {name}", **options)
        except InputError as err:
            failures.append(err)
    if not results:
        raise failures[0]
    for err in failures:
        warnings.warn(f"{model_name}: {err}: skipped", RenderWarning, stacklevel=2)
    return results


def check_views(dataset, names) -> None:
    """InputError (field ``view``) naming the first of ``names`` that ``dataset`` lacks."""
    for name in names:
        if name not in dataset.images:
            raise InputError(f"no such view in the dataset (views: {', '.join(dataset.rig.names)})",
                             field="view", value=name)


def render_model(model, dataset, depth: float, tilt: float, names, *, settings: RenderSettings = RenderSettings(),
                 backend=None, model_name: str = "model") -> dict[str, np.ndarray]:
    """``render`` of the mesh ``model`` at (depth m, tilt rad) for the views ``names`` of
    ``dataset``, less the views it does not project into (an empty object layer), which are
    named in one RenderWarning: {view: (5, bins, beams) float32}. InputError naming
    ``model_name`` when it projects into none of them."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RenderWarning)
        rendered = render(model, dataset.sonar, dataset.rig, depth, tilt, views=names, settings=settings,
                          backend=backend)
    missed = [name for name in names if not rendered[name][LAYERS.index("object")].any()]
    if len(missed) == len(names):
        raise InputError(f"projects into none of the views ({_listed(names)}) at D = {depth:.4g} m, "
                         f"tilt = {np.degrees(tilt):.4g} deg: is the model in the dataset's reference frame, "
                         "and are the depth and tilt right?", file=model_name)
    if missed:
        warnings.warn(f"{model_name}: does not project into view(s) {_listed(missed)}: skipped",
                      RenderWarning, stacklevel=3)
    for warning in caught:  # pass on what render said about the views that are kept
        if not any(str(warning.message).startswith(f"view {name}:") for name in missed):
            warnings.warn(warning.message, warning.category, stacklevel=3)
    return {name: stack for name, stack in rendered.items() if name not in missed}


def _listed(names, most: int = 6) -> str:
    return ", ".join(names[:most]) + (f" and {len(names) - most} more" if len(names) > most else "")


def comparison_views(rig, names, *, most: int = 4) -> dict[str, list[str]]:
    """The views to show in comparison figures (paper Figures 10–14), grouped by the
    manifest's ``optimize`` flags: {"optimized": [...], "held-out": [...]}, each at most
    ``most`` of ``names`` (views of ``rig``, fsswarp.rig.Rig). Held-out views come in order of
    |roll| (the roll-0 ones first), then rig order; optimized ones are spread evenly over
    rig order (first and last included)."""
    order = [v for v in rig.views if v.name in set(names)]
    held = sorted((v for v in order if not v.optimize), key=lambda v: abs(v.roll))[:most]
    used = [v for v in order if v.optimize]
    if len(used) > most:
        used = [used[i] for i in np.unique(np.round(np.linspace(0, len(used) - 1, most)).astype(int))]
    return {"optimized": [v.name for v in used], "held-out": [v.name for v in held]}


def match_level(synthetic, image, *, threshold: float = 1e-3) -> np.ndarray:
    """``synthetic`` (bins, beams, render's units) scaled to the data ``image`` (bins, beams,
    linear) so that their means match over the synthetic's returns (pixels at least
    ``threshold`` × its peak), the data's background level (median elsewhere) taken off first.
    Returns float32 (bins, beams); all zeros for an empty synthetic."""
    synthetic = np.asarray(synthetic, np.float64)
    image = np.asarray(image, np.float64)
    if not synthetic.max() > 0:
        return np.zeros(synthetic.shape, np.float32)
    region = synthetic >= threshold * float(synthetic.max())
    background = float(np.median(image[~region])) if (~region).any() else 0.0
    gain = max(float(image[region].mean()) - background, 0.0) / float(synthetic[region].mean())
    return (gain * synthetic).astype(np.float32)


def score(dataset, results: dict[str, EnhancedView], *, threshold: float = 1e-3, background: float = 0.05) -> dict:
    """Per-view scores against the truth layers of a simulated dataset (InputError without them).

    Overlap: pixels where the true object and the true ghost both reach ``threshold`` × the
    true total's peak. Like with like: the data carry speckle of mean 1 and an additive
    exponential floor of mean ``background`` × the 99th percentile of the non-zero true total
    (fsswarp.rendering.add_noise), so the reference is the object-only data's expectation, true
    object + floor mean. Returns {view: {"overlap_pixels", "mae_raw", "mae_enhanced",
    "mae_reduction", "ghost_corr"}}; the MAE entries are None for views without overlap;
    ``ghost_corr`` is Pearson's r of the isolated and the true ghost over the true ghost region."""
    scores = {}
    for name, result in results.items():
        truth = {c: dataset.truth_layer(name, c).astype(np.float64) for c in LAYERS[:-1]}
        total = sum(truth.values())
        cut = threshold * float(total.max())
        floor = background * float(np.percentile(total[total > 0], 99)) if (total > 0).any() else 0.0
        ghost_region = truth["ghost"] >= cut
        overlap = (truth["object"] >= cut) & ghost_region
        row = {"overlap_pixels": int(overlap.sum()), "mae_raw": None, "mae_enhanced": None, "mae_reduction": None,
               "ghost_corr": None}
        if overlap.any():
            reference = truth["object"][overlap] + floor
            raw = float(np.abs(dataset.images[name][overlap] - reference).mean())
            enhanced = float(np.abs(result.enhanced[overlap] - reference).mean())
            row.update(mae_raw=raw, mae_enhanced=enhanced, mae_reduction=1.0 - enhanced / raw)
        if ghost_region.sum() > 2 and result.ghost[ghost_region].std() > 0:
            row["ghost_corr"] = float(np.corrcoef(result.ghost[ghost_region], truth["ghost"][ghost_region])[0, 1])
        scores[name] = row
    return scores
