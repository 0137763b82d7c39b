"""Figures for people, as PNG files: synthetic layers (``layers_figure``), fan images
(``fan_figure``), a mesh over the truth (``carve_figure``), the pose grid levels
(``pose_figure``), frontal contours per view (``contours_figure``), a reconstruction's history
(``history_figure``), ghost removal (``enhance_figure``) and views beside their syntheses as
fan images with range and azimuth axes (``views_figure``, the report's rows; ``comparison_figure``,
the paper's Figures 10–14, draws its rows so).
``FigureDrawer`` draws them in child processes while a command goes on
(``FSSWARP_FIGURE_WORKERS``; the files are the same byte for byte either way).
Every axes title is placed at the axes' top (``y=1.0``): left to place itself, matplotlib
measures the tick labels to lift it over any at the top, which no figure here has (a fifth of a
row's time, bench/notes.md).

Figures read results; nothing in the pipeline imports this module.
"""

from __future__ import annotations

import io
import math
import textwrap
from concurrent.futures import wait
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from .atomic import write_bytes
from .sonar import SonarSpec, scan_convert


def layers_figure(views: dict[str, np.ndarray], sonar: SonarSpec, path: str | Path, *,
                  layers=("object", "ghost", "mirror", "mirror2", "total"), title: str = "",
                  zoom: bool = True) -> Path:
    """Save a PNG grid: one row per view, per layer a beam-bin image and its fan image, with
    one colour bar.

    views : {label: (len(layers), bins, beams) float32}. Intensities on a shared dB scale
    (60 dB below the brightest pixel of all views). With ``zoom`` the axes show the ranges
    and azimuths that hold returns within 40 dB of that peak, plus a margin, instead of the
    whole window; a layer named "data" (noisy) counts for the peak but not for the zoom."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    peak = max(float(np.max(stack)) for stack in views.values()) or 1.0
    clean = [k for k, layer in enumerate(layers) if layer != "data"] or list(range(len(layers)))
    limits = _zoom_limits({label: np.asarray(stack)[clean] for label, stack in views.items()}, sonar, peak) \
        if zoom else None
    rows, cols = len(views), 2 * len(layers)
    fig = plt.figure(figsize=(2.2 * cols, 2.5 * rows + 0.9))
    grid = fixed_grid(fig, rows + 1, cols, top=title_height(fig, title) + 0.3, bottom=0.5, left=0.6, right=0.2,
                      wspace=0.6, hspace=0.65, height_ratios=[1.0] * rows + [0.06])
    axes = np.array([[fig.add_subplot(grid[r, c]) for c in range(cols)] for r in range(rows)])
    extent_bb = (math.degrees(sonar.beam_centres[0]), math.degrees(sonar.beam_centres[-1]),
                 sonar.range_min, sonar.range_max)
    for r, (label, stack) in enumerate(views.items()):
        for k, layer in enumerate(layers):
            db = _decibels(stack[k], peak)
            ax = axes[r, 2 * k]
            shown = ax.imshow(db, origin="lower", aspect="auto", extent=extent_bb, cmap="magma", vmin=-60, vmax=0)
            ax.set_title(f"{label} {layer}, beam-bin", fontsize=8, y=1.0)
            ax.set_xlabel("azimuth (deg)", fontsize=7)
            ax.set_ylabel("range (m)", fontsize=7)
            fan, extent = scan_convert(db, sonar, fill=np.nan)
            ax = axes[r, 2 * k + 1]
            ax.imshow(fan, extent=extent, cmap="magma", vmin=-60, vmax=0)
            ax.set_title(f"{label} {layer}, fan", fontsize=8, y=1.0)
            ax.set_xlabel("x (m)", fontsize=7)
            ax.set_ylabel("y (m)", fontsize=7)
            if limits is not None:
                axes[r, 2 * k].set_xlim(limits["azimuth"])
                axes[r, 2 * k].set_ylim(limits["range"])
                ax.set_xlim(limits["x"])
                ax.set_ylim(limits["y"])
            for a in axes[r, 2 * k: 2 * k + 2]:
                a.tick_params(labelsize=7)
                a.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(4))
                a.yaxis.set_major_locator(matplotlib.ticker.MaxNLocator(5))
    bar = fig.colorbar(shown, cax=fig.add_subplot(grid[-1, cols // 4: cols - cols // 4]), orientation="horizontal")
    bar.set_label("dB below the brightest pixel of all views", fontsize=8)
    bar.ax.tick_params(labelsize=7)
    return write_figure(fig, path)


def _zoom_limits(views: dict[str, np.ndarray], sonar: SonarSpec, peak: float, *, margin_m: float = 0.15):
    """Axis limits around the pixels within 40 dB of ``peak`` (None when there are none):
    {"range", "azimuth" (deg), "x", "y"} as (low, high)."""
    strong = np.zeros((sonar.bins, sonar.beams), bool)
    for stack in views.values():
        strong |= (np.asarray(stack) >= peak * 1e-2).any(axis=0)
    if not strong.any():
        return None
    rows, cols = np.nonzero(strong)
    r_lo = max(sonar.range_min, float(sonar.bin_ranges[rows.min()]) - margin_m)
    r_hi = min(sonar.range_max, float(sonar.bin_ranges[rows.max()]) + margin_m)
    theta = sonar.beam_centres[cols]
    half_width = max(margin_m / r_lo, math.radians(2.0))
    t_lo = max(float(theta.min()) - half_width, float(sonar.beam_centres[0]))
    t_hi = min(float(theta.max()) + half_width, float(sonar.beam_centres[-1]))
    x = [r * math.sin(t) for r in (r_lo, r_hi) for t in (t_lo, t_hi)]
    return {"range": (r_lo, r_hi), "azimuth": (math.degrees(t_lo), math.degrees(t_hi)),
            "x": (min(x), max(x)), "y": (r_lo * math.cos(max(abs(t_lo), abs(t_hi))), r_hi)}


def save_figure(fig, path: str | Path, title: str = "", *, rect=(0, 0, 1, 1)) -> Path:
    """Title (``fig.suptitle``), lay out inside ``rect`` below the title, close and write
    ``fig`` as a PNG, atomically; returns the path."""
    top = min(rect[3], 1 - title_height(fig, title) / fig.get_figheight())
    fig.tight_layout(rect=(rect[0], rect[1], rect[2], top))
    return write_figure(fig, path)


def write_figure(fig, path: str | Path, *, dpi: int = 110, **options) -> Path:
    """Close and write ``fig`` as it is laid out (e.g. on a :func:`fixed_grid`, its title set
    by :func:`title_height`) as a PNG, atomically (``options``: more of ``Figure.savefig``'s);
    returns the path."""
    import matplotlib.pyplot as plt

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi, **options)
    plt.close(fig)
    return write_bytes(path, buffer.getvalue())


def title_height(fig, title: str) -> float:
    """Set ``title`` (lines wrapped to the figure's width) as ``fig``'s 9-point suptitle; returns
    the height (inches) it takes at the top, 0 without a title."""
    if not title:
        return 0.0
    width = max(40, int(fig.get_figwidth() * 15))  # characters of a 9-point line
    text = "\n".join(textwrap.fill(line, width) for line in title.splitlines())
    fig.suptitle(text, fontsize=9, y=1 - 0.06 / fig.get_figheight())
    return 0.17 * (text.count("\n") + 1) + 0.02


def fixed_grid(fig, rows: int, cols: int, *, top: float, bottom: float, left: float, right: float, wspace: float,
               hspace: float, height_ratios=None):
    """A GridSpec of ``fig``: margins and the gaps between axes in inches, for figures of
    panels alike, whose labels need the same room in every panel. Unlike ``tight_layout``, it
    needs no drawing to find: that took about 40% of the enhancement figures' time (bench/notes.md,
    twelfth session)."""
    width, height = fig.get_size_inches()
    axis_width = (width - left - right - (cols - 1) * wspace) / cols
    axis_height = (height - top - bottom - (rows - 1) * hspace) / rows  # the mean, as GridSpec reads hspace
    return fig.add_gridspec(rows, cols, height_ratios=height_ratios, left=left / width, right=1 - right / width,
                            bottom=bottom / height, top=1 - top / height, wspace=wspace / axis_width,
                            hspace=hspace / axis_height)


def _bottom_legend(fig, handles: dict, **options) -> None:
    """One legend row of ``handles`` ({label: artist}) along the figure's bottom, on light grey
    without a frame (``options``: more of ``Figure.legend``'s)."""
    legend = fig.legend(list(handles.values()), list(handles), loc="lower center", ncol=len(handles), fontsize=7,
                        facecolor="lightgrey", **options)
    legend.get_frame().set_edgecolor("none")


def _decibels(image: np.ndarray, peak: float) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return np.maximum(20.0 * np.log10(np.maximum(image, 0) / peak), -60.0).astype(np.float32)


def fan_figure(image: np.ndarray, sonar: SonarSpec, path: str | Path, *, title: str = "") -> Path:
    """Save a PNG of one (bins, beams) image as a fan image (x across, y ahead, metres), in dB
    below its brightest pixel (down to -60 dB)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    image = np.asarray(image, dtype=np.float32)
    db = _decibels(image, float(np.max(image)) or 1.0)
    fan, extent = scan_convert(db, sonar, fill=np.nan)
    aspect = (extent[1] - extent[0]) / (extent[3] - extent[2])
    fig, ax = plt.subplots(figsize=(min(12.0, max(3.5, 6.0 * aspect + 1.6)), 6.6))
    shown = ax.imshow(fan, extent=extent, cmap="magma", vmin=-60, vmax=0)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    fig.colorbar(shown, ax=ax, label="dB below peak", shrink=0.8)
    if title:
        ax.set_title(title, fontsize=9, y=1.0)
    return save_figure(fig, path)


#: The colours of the models in figures and in the report's 3-D view, by label.
MODEL_COLOURS = {"carved": "#d9822b", "final": "#2f6db5", "truth": "#5c5c5c"}


def carve_figure(mesh, path: str | Path, *, truth=None, title: str = "", label: str = "carved") -> Path:
    """Save a PNG of a mesh's XY, XZ and YZ projections (reference frame, metres): the mesh
    shaded as lit from the viewer, in the colour of ``label`` (MODEL_COLOURS; carved orange,
    final blue), and over it, when ``truth`` (a mesh) is given, the truth's outline in black
    (its silhouette and fold edges)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection, PolyCollection
    from matplotlib.colors import to_rgb

    fig = plt.figure(figsize=(12.6, 4.6))
    grid = fixed_grid(fig, 1, 3, top=title_height(fig, title) + 0.35, bottom=0.75, left=0.7, right=0.15, wspace=0.8,
                      hspace=0.0)
    axes = [fig.add_subplot(grid[0, k]) for k in range(3)]
    colour = np.array(to_rgb(MODEL_COLOURS.get(label, MODEL_COLOURS["final"])))
    points = np.concatenate([np.asarray(m.vertices) for m in (mesh, truth) if m is not None])
    pad = 0.05 * float(np.ptp(points, axis=0).max())
    triangles, normals = np.asarray(mesh.triangles), np.asarray(mesh.face_normals)
    for ax, (i, j) in zip(axes, ((0, 1), (0, 2), (1, 2))):
        k = 3 - i - j  # the viewing axis: the viewer looks from +k
        order = np.argsort(triangles[:, :, k].mean(axis=1))  # far faces first
        shade = 0.3 + 0.7 * np.abs(normals[order, k])[:, None]
        faces = np.clip(shade * colour, 0, 1)
        ax.add_collection(PolyCollection(triangles[order][:, :, (i, j)], facecolors=faces, edgecolors="none",
                                         antialiased=False), autolim=False)  # the limits are set below
        if truth is not None:
            ax.add_collection(LineCollection(_outline(truth, k)[:, :, (i, j)], colors=MODEL_COLOURS["truth"],
                                             linewidths=0.9), autolim=False)
        ax.set_xlim(points[:, i].min() - pad, points[:, i].max() + pad)
        ax.set_ylim(points[:, j].min() - pad, points[:, j].max() + pad)
        ax.set_aspect("equal")
        ax.set_xlabel(f"{'xyz'[i]} (m)")
        ax.set_ylabel(f"{'xyz'[j]} (m)")
        ax.set_title(f"{'xyz'[i]}{'xyz'[j]} projection, seen from +{'xyz'[k]}", fontsize=9, y=1.0)
        ax.tick_params(labelsize=7)
    handles = {f"{label} model (shaded)": matplotlib.patches.Patch(color=colour)}
    if truth is not None:
        handles["truth (outline)"] = matplotlib.lines.Line2D([], [], color=MODEL_COLOURS["truth"], lw=1.2)
    _bottom_legend(fig, handles)
    return write_figure(fig, path)


def _outline(mesh, axis: int) -> np.ndarray:
    """(edges, 2, 3) the edges of ``mesh`` between a face turned toward +``axis`` and one
    turned away: its silhouette seen along that axis, and its folds."""
    normals = np.asarray(mesh.face_normals)[:, axis]
    pairs = np.asarray(mesh.face_adjacency)
    turn = np.sign(normals[pairs[:, 0]]) != np.sign(normals[pairs[:, 1]])
    return np.asarray(mesh.vertices)[np.asarray(mesh.face_adjacency_edges)[turn]]


def pose_figure(result, path: str | Path, *, truth: tuple[float, float] | None = None, title: str = "") -> Path:
    """Save a PNG of the (D, β) grid search of ``fsswarp.pose.estimate_pose``: one panel per
    level, the surrogate cost (mm) over depth (m) and tilt (deg), with the level's minimum
    (white ×), and where they fall inside the panel the start (triangle), the estimate (star)
    and, when given, the ``truth`` (depth m, tilt rad; circle)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    levels = result.levels
    fig = plt.figure(figsize=(4.2 * len(levels), 4.3))
    grid = fixed_grid(fig, 1, len(levels), top=title_height(fig, title) + 0.3, bottom=0.95, left=0.7, right=0.15,
                      wspace=0.75, hspace=0.0)
    axes = [[fig.add_subplot(grid[0, k]) for k in range(len(levels))]]
    marks = [((result.depth0, result.tilt0), dict(marker="^", color="tab:orange", markersize=7, ls="none"), "start"),
             ((result.depth, result.tilt), dict(marker="*", color="tab:red", markersize=11, ls="none"), "estimate")]
    if truth is not None:
        marks.append((truth, dict(marker="o", mfc="none", mec="white", markersize=11, mew=1.5, ls="none"), "truth"))
    handles = {}
    for k, (ax, level) in enumerate(zip(axes[0], levels)):
        depths, tilts = level.depths, np.degrees(level.tilts)
        step = (depths[1] - depths[0], tilts[1] - tilts[0])
        extent = (depths[0] - step[0] / 2, depths[-1] + step[0] / 2, tilts[0] - step[1] / 2, tilts[-1] + step[1] / 2)
        shown = ax.imshow(level.costs.T * 1000.0, origin="lower", aspect="auto", extent=extent, cmap="viridis")
        fig.colorbar(shown, ax=ax, label="surrogate (mm)", shrink=0.85)
        i, j = np.unravel_index(int(np.argmin(level.costs)), level.costs.shape)
        handles["grid minimum"], = ax.plot(depths[i], tilts[j], "x", color="white", markersize=9, mew=2)
        for (depth, tilt), style, label in marks:
            if extent[0] <= depth <= extent[1] and extent[2] <= math.degrees(tilt) <= extent[3]:
                handles[label], = ax.plot(depth, math.degrees(tilt), **style)
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(5))
        ax.set_xlabel("depth D (m)")
        ax.set_ylabel("tilt β (deg)")
        ax.set_title(f"level {k + 1}: {len(depths)} x {len(tilts)} cells, "
                     f"{step[0] * 1000:.2f} mm x {step[1]:.3f} deg", fontsize=8, y=1.0)
        ax.tick_params(labelsize=7)
    _bottom_legend(fig, handles)
    return write_figure(fig, path)


def contours_figure(images: dict[str, np.ndarray], contours: dict[str, dict], sonar: SonarSpec, path: str | Path, *,
                    labels=("estimate", "start"), title: str = "") -> Path:
    """Save a PNG of what E_mu compares: per view (up to five per row) the data image in
    beam-bin coordinates (dB below the view's peak, zoomed to the contours' ranges), the data's
    frontal object and mirror contours (dots) and the synthetic ones at each pose (lines,
    the mirror dashed), with μ_m per pose in the panel's title.

    images : {view: (bins, beams)}; contours : ``fsswarp.compare.view_contours``'s dict (its
    views that ``images`` holds); labels : one name per synthetic pose, in its order."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [name for name in contours if name in images]
    cols = min(5, max(1, len(names)))
    rows = max(1, math.ceil(len(names) / cols))
    fig = plt.figure(figsize=(3.0 * cols, 3.1 * rows + 0.4))
    grid = fixed_grid(fig, rows, cols, top=title_height(fig, title) + 0.25, bottom=0.75, left=0.45, right=0.1,
                      wspace=0.45, hspace=0.6)
    axes = np.array([[fig.add_subplot(grid[r, c]) for c in range(cols)] for r in range(rows)])
    azimuth = np.degrees(sonar.beam_centres)
    extent = (azimuth[0], azimuth[-1], sonar.range_min, sonar.range_max)
    colours = ("red", "yellow", "lime", "magenta")
    handles = {}
    for ax, name in zip(axes.ravel(), names):
        entry = contours[name]
        image = np.asarray(images[name], np.float64)
        ax.imshow(_decibels(image, float(image.max()) or 1.0), origin="lower", aspect="auto", extent=extent,
                  cmap="gray", vmin=-40, vmax=0)
        for c, (marker, colour) in enumerate((("o", "white"), ("^", "cyan"))):
            handles[f"data {('object', 'mirror')[c]}"], = ax.plot(azimuth, entry["data"][c], marker, color=colour,
                                                                 markersize=2.2, ls="none")
        for pose, (label, ranges) in reversed(list(enumerate(zip(labels, entry["synthetic"])))):  # the first on top
            colour = colours[pose % len(colours)]
            handles[f"synthetic, {label}"], = ax.plot(azimuth, ranges[0], "-", color=colour, lw=1.0)
            ax.plot(azimuth, ranges[1], "--", color=colour, lw=1.0)
        values = np.stack([entry["data"]] + list(entry["synthetic"]))  # (poses + 1, 2, beams)
        found = np.isfinite(values)
        if found.any():
            ax.set_ylim(max(sonar.range_min, values[found].min() - 0.1),
                        min(sonar.range_max, values[found].max() + 0.1))
            beams = np.flatnonzero(found.any(axis=(0, 1)))
            ax.set_xlim(max(azimuth[0], azimuth[beams[0]] - 3.0), min(azimuth[-1], azimuth[beams[-1]] + 3.0))
        mu = ", ".join(f"{label} {m * 1e3:.1f}" if math.isfinite(m) else f"{label} -"
                       for label, m in zip(labels, entry["mu"]))
        ax.set_title(f"{name}: mu (mm) {mu}", fontsize=7, y=1.0)
        ax.set_xlabel("azimuth (deg)", fontsize=6)
        ax.set_ylabel("range (m)", fontsize=6)
        ax.tick_params(labelsize=5)
    for ax in axes.ravel()[len(names):]:
        ax.axis("off")
    _bottom_legend(fig, handles, markerscale=2.5)
    return write_figure(fig, path)


def history_figure(history: list[dict], path: str | Path, *, truth_depth: float | None = None,
                   truth_tilt_deg: float | None = None, best_iteration: int | None = None,
                   depth_interval_m=None, tilt_interval_deg=None, title: str = "") -> Path:
    """Save a PNG like the paper's Figures 7–8: depth and tilt against iteration (truth dashed),
    E_I and E_mu, and (with a truth model) E_V against iteration, the kept (best) iteration
    marked by a dotted line. ``history``: the entries of ``result.json``; an entry's
    ``depth_interval_m`` and ``tilt_interval_deg`` ([low, high]) are shaded as a band, and
    ``depth_interval_m``, ``tilt_interval_deg`` given here (the result's) as a bar at the kept
    iteration."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    it = np.array([h["iteration"] for h in history])
    panels = 4 if "E_V" in history[0] else 3
    fig = plt.figure(figsize=(3.6 * panels, 3.6))
    grid = fixed_grid(fig, 1, panels, top=title_height(fig, title) + 0.15, bottom=1.0, left=0.75, right=0.1,
                      wspace=0.8, hspace=0.0)
    axes = [fig.add_subplot(grid[0, k]) for k in range(panels)]
    for ax, key, unit, truth, interval in ((axes[0], "depth_m", "depth D (m)", truth_depth, depth_interval_m),
                                           (axes[1], "tilt_deg", "tilt β (deg)", truth_tilt_deg, tilt_interval_deg)):
        band = np.array([h.get(key.replace("_", "_interval_", 1)) or (np.nan, np.nan) for h in history], float)
        if np.isfinite(band).any():
            ax.fill_between(it, band[:, 0], band[:, 1], color="tab:blue", alpha=0.18, lw=0,
                            label="interval per iteration")
        ax.plot(it, [h[key] for h in history], "o-", color="tab:blue", label="estimate")
        if interval is not None and best_iteration is not None:
            ax.plot([best_iteration] * 2, interval, color="tab:red", lw=1.5, marker="_", markersize=10,
                    label="result's interval")
        if truth is not None:
            ax.axhline(truth, color="black", linestyle="--", label="truth")
        ax.set_ylabel(unit)
    axes[0].yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%.3f"))
    axes[1].yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%.2f"))
    ax = axes[2]
    ax.plot(it, [h["E_I"] for h in history], "o-", color="tab:orange", label="E_I")
    ax.plot(it, [h["E_mu"] / history[0]["E_mu"] for h in history], "s-", color="tab:brown", label="E_mu / E_mu(0)")
    ax.set_ylabel("image error (1 = carved model)")
    if panels == 4:
        axes[3].plot(it, [h["E_V"] for h in history], "^-", color="tab:green", label="E_V")
        axes[3].plot(it, [h["fscore"] for h in history], "v-", color="tab:purple", label="F-score")
        axes[3].set_ylabel("E_V, F-score (vs truth)")
    handles = {}
    for a in axes:
        if best_iteration is not None:
            a.axvline(best_iteration, color="grey", linestyle=":", label="kept iteration")
        a.set_xlabel("iteration")
        a.set_xticks(it if len(it) <= 12 else it[::math.ceil(len(it) / 12)])
        a.tick_params(labelsize=7)
        handles.update({label: handle for handle, label in zip(*a.get_legend_handles_labels())})
    _bottom_legend(fig, handles)
    return write_figure(fig, path)


#: The regions of ``enhance_figure``: name and colour, by code (1 object + 2 ghost + 4 mirror).
REGIONS = {0: ("none", "#f2f2f2"), 1: ("object", "#1f77b4"), 2: ("ghost", "#ff7f0e"),
           3: ("object + ghost", "#d62728"), 4: ("mirror", "#9467bd"), 5: ("object + mirror", "#8c564b"),
           6: ("ghost + mirror", "#e377c2"), 7: ("all three", "#2ca02c")}


def enhance_figure(images: dict[str, np.ndarray], results: dict, sonar: SonarSpec, path: str | Path, *,
                   title: str = "") -> Path:
    """Save a PNG grid, one row per view: data | ghost-free (enhanced) | isolated ghost |
    regions (object, ghost, mirror and their overlaps, named in a legend), beam-bin images in
    dB below the data's peak with a colour bar.

    images : {view: (bins, beams) linear data}; results : {view: fsswarp.enhancement.EnhancedView}."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    fig = plt.figure(figsize=(10.0, 2.8 * len(images) + 1.2))
    grid = fixed_grid(fig, len(images) + 1, 4, top=title_height(fig, title) + 0.3, bottom=0.55, left=0.6, right=0.2,
                      wspace=0.2, hspace=0.7, height_ratios=[1.0] * len(images) + [0.05])
    axes = np.array([[fig.add_subplot(grid[r, c]) for c in range(4)] for r in range(len(images))])
    extent = (math.degrees(sonar.beam_centres[0]), math.degrees(sonar.beam_centres[-1]),
              sonar.range_min, sonar.range_max)
    codes = ListedColormap([colour for _, colour in REGIONS.values()])
    for row, (name, image) in enumerate(images.items()):
        result = results[name]
        peak = float(np.max(image)) or 1.0
        regions = (result.object_region.astype(np.int8) + 2 * result.ghost_region + 4 * result.mirror_region)
        panels = [(_decibels(image, peak), "data", "magma", (-60, 0)),
                  (_decibels(result.enhanced, peak), "ghost-free", "magma", (-60, 0)),
                  (_decibels(result.ghost, peak), "isolated ghost", "magma", (-60, 0)),
                  (regions, "regions", codes, (-0.5, 7.5))]
        rows, cols = np.nonzero(result.object_region | result.ghost_region | result.mirror_region)
        for ax, (shown, label, cmap, (low, high)) in zip(axes[row], panels):
            drawn = ax.imshow(shown, origin="lower", aspect="auto", extent=extent, cmap=cmap, vmin=low, vmax=high,
                              interpolation="nearest")
            if label == "data":
                decibels = drawn
            ax.set_title(f"{name} {label}", fontsize=8, y=1.0)
            if rows.size:
                ax.set_ylim(max(sonar.range_min, float(sonar.bin_ranges[rows.min()]) - 0.1),
                            min(sonar.range_max, float(sonar.bin_ranges[rows.max()]) + 0.1))
                ax.set_xlim(max(extent[0], math.degrees(sonar.beam_centres[cols.min()]) - 4.0),
                            min(extent[1], math.degrees(sonar.beam_centres[cols.max()]) + 4.0))
            if ax is axes[row, 0]:  # a row's panels show the same place: its first one has the axes
                ax.set_xlabel("azimuth (deg)", fontsize=7)
                ax.set_ylabel("range (m)", fontsize=7)
                ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(5))
                ax.yaxis.set_major_locator(matplotlib.ticker.MaxNLocator(5))
                ax.tick_params(labelsize=7)
            else:  # no ticks: each costs ~1 ms to make, most of the figure's time
                ax.xaxis.set_major_locator(matplotlib.ticker.NullLocator())
                ax.yaxis.set_major_locator(matplotlib.ticker.NullLocator())
    bar = fig.colorbar(decibels, cax=fig.add_subplot(grid[-1, :2]), orientation="horizontal")
    bar.set_label("dB below the view's data peak", fontsize=8)
    bar.ax.tick_params(labelsize=7)
    key = fig.add_subplot(grid[-1, 2:])
    key.axis("off")
    key.legend([matplotlib.patches.Patch(color=colour) for _, colour in REGIONS.values()],
               [name for name, _ in REGIONS.values()], loc="center", ncol=4, fontsize=7, frameon=False,
               title="regions (the model's, at D and β)", title_fontsize=7)
    return write_figure(fig, path)


def comparison_figure(images: dict[str, np.ndarray], enhanced: dict[str, np.ndarray],
                      synthetic: dict[str, np.ndarray], sonar: SonarSpec, path: str | Path, *,
                      initial: dict[str, np.ndarray] | None = None, floor_db: float = -40.0,
                      title: str = "") -> Path:
    """Save a PNG like the paper's Figures 10–14, one row per view: data | ghost-free data |
    initial synthetic (only when ``initial`` is given) | optimized synthetic, drawn as
    :func:`views_figure` draws the report's rows (fans zoomed on the synthetic returns, one
    colour scale per row: dB below the row's data peak, down to ``floor_db``).

    Every dict is {view: (bins, beams) linear image}, keyed like ``images``; the synthetic
    images should already be scaled to the data's level (fsswarp.enhancement.match_level)."""
    rows = {name: {"data": images[name], "ghost-free data": enhanced[name]}
            | ({} if initial is None else {"initial synthetic": initial[name]})
            | {"optimized synthetic": synthetic[name]} for name in images}
    return views_figure(rows, sonar, path, floor_db=floor_db, title=title)


def views_figure(rows: dict[str, dict[str, np.ndarray]], sonar: SonarSpec, path: str | Path, *,
                 floor_db: float = -40.0, title: str = "") -> Path:
    """Save a PNG like the paper's Figures 10–14: per row, its images side by side as fan
    images with range arcs (m) and azimuth rays (deg), zoomed on the returns of the images
    after the second (the synthetic ones), and one colour bar.

    rows : {row label: {column label: (bins, beams) linear image}}, the first column the data;
    each row on its own scale, dB below its data's peak down to ``floor_db``. Synthetic images
    should already be scaled to the data's level (fsswarp.enhancement.match_level)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    first = next(iter(rows.values()))
    limits = {label: _zoom_limits({label: np.stack(list(images.values())[2:] or list(images.values()))}, sonar,
                                  max(float(np.max(m)) for m in list(images.values())[2:] or images.values()) or 1.0)
              or _window(sonar) for label, images in rows.items()}
    aspect = max((lim["x"][1] - lim["x"][0]) / (lim["y"][1] - lim["y"][0]) for lim in limits.values())
    width, height = 2.2, min(2.2, max(1.0, 2.2 / aspect))  # a panel's, inches
    # fixed margins (no tight bounding box: its second drawing was a third of the figure's time):
    # above each row its titles, below it the azimuth labels, right of each panel its range labels
    columns, gap_below, gap_right = len(first), 0.5, 0.5
    fig = plt.figure(figsize=(0.1 + columns * width + columns * gap_right,
                              0.3 + len(rows) * (height + gap_below) + 0.12 + 0.35))
    title_room = title_height(fig, title)
    fig.set_figheight(fig.get_figheight() + title_room)
    grid = fixed_grid(fig, len(rows) + 1, columns, top=title_room + 0.3, bottom=0.35, left=0.1, right=gap_right,
                      wspace=gap_right, hspace=gap_below, height_ratios=[height] * len(rows) + [0.12])
    for row, (label, images) in enumerate(rows.items()):
        peak = float(np.max(next(iter(images.values())))) or 1.0
        for col, (column, image) in enumerate(images.items()):
            ax = fig.add_subplot(grid[row, col])
            with np.errstate(divide="ignore"):
                db = np.maximum(20.0 * np.log10(np.maximum(np.asarray(image, np.float64), 0) / peak), floor_db)
            shown = draw_fan(ax, db, sonar, limits[label], vmin=floor_db)
            ax.set_title(f"{label}: {column}" if len(rows) > 1 else column, fontsize=8, y=1.0)
    bar = fig.colorbar(shown, cax=fig.add_subplot(grid[-1, 1:-1] if columns > 2 else grid[-1, :]),
                       orientation="horizontal")
    bar.set_label("dB below the data's peak", fontsize=7)
    bar.ax.tick_params(labelsize=7)
    return write_figure(fig, path, dpi=100)


def _window(sonar: SonarSpec) -> dict:
    """``_zoom_limits``'s dict for the whole window of ``sonar``."""
    t_lo, t_hi = float(sonar.beam_centres[0]), float(sonar.beam_centres[-1])
    x = [r * math.sin(t) for r in (sonar.range_min, sonar.range_max) for t in (t_lo, t_hi)]
    return {"range": (sonar.range_min, sonar.range_max), "azimuth": (math.degrees(t_lo), math.degrees(t_hi)),
            "x": (min(x), max(x)), "y": (sonar.range_min * math.cos(max(abs(t_lo), abs(t_hi))), sonar.range_max)}


def draw_fan(ax, db: np.ndarray, sonar: SonarSpec, limits: dict, *, vmin: float = -40.0, cmap: str = "magma"):
    """Draw the (bins, beams) image ``db`` (dB, 0 at the top of the scale) on ``ax`` as a fan
    (x across, y ahead, true shape), the part within ``limits`` (``_zoom_limits``'s "range" m
    and "azimuth" deg), with range arcs labelled in m and azimuth rays in deg; returns the mesh."""
    import matplotlib
    from matplotlib.collections import LineCollection

    centres = np.asarray(sonar.beam_centres, np.float64)
    ranges = np.asarray(sonar.bin_ranges, np.float64)
    theta = np.concatenate([[1.5 * centres[0] - 0.5 * centres[1]], 0.5 * (centres[1:] + centres[:-1]),
                            [1.5 * centres[-1] - 0.5 * centres[-2]]])
    radius = np.concatenate([ranges - 0.5 * sonar.range_step, [ranges[-1] + 0.5 * sonar.range_step]])
    (r_lo, r_hi), (t_lo, t_hi) = limits["range"], np.radians(limits["azimuth"])
    rows = np.flatnonzero((radius[1:] > r_lo) & (radius[:-1] < r_hi))
    cols = np.flatnonzero((theta[1:] > t_lo) & (theta[:-1] < t_hi))
    t, r = np.meshgrid(theta[cols[0]:cols[-1] + 2], radius[rows[0]:rows[-1] + 2])
    shown = ax.pcolormesh(r * np.sin(t), r * np.cos(t), db[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1], cmap=cmap,
                          vmin=vmin, vmax=0, shading="flat", rasterized=True)
    r_lo, r_hi = float(r[0, 0]), float(r[-1, 0])
    t_lo, t_hi = float(t[0, 0]), float(t[0, -1])
    arc = np.linspace(t_lo, t_hi, 64)
    grid = []  # the range arcs and azimuth rays, drawn as one collection
    for value in matplotlib.ticker.MaxNLocator(4).tick_values(r_lo, r_hi):
        if r_lo <= value <= r_hi:
            grid.append(np.column_stack([value * np.sin(arc), value * np.cos(arc)]))
            ax.annotate(f"{value:.2f} m", (value * math.sin(t_hi), value * math.cos(t_hi)), xytext=(3, 0),
                        textcoords="offset points", fontsize=7, va="center", ha="left")
    for value in matplotlib.ticker.MaxNLocator(5).tick_values(math.degrees(t_lo), math.degrees(t_hi)):
        angle = math.radians(value)
        if t_lo <= angle <= t_hi:
            grid.append([(r * math.sin(angle), r * math.cos(angle)) for r in (r_lo, r_hi)])
            ax.annotate(f"{value:g}°", (r_lo * math.sin(angle), r_lo * math.cos(angle)), xytext=(0, -3),
                        textcoords="offset points", fontsize=7, ha="center", va="top")
    ax.add_collection(LineCollection(grid, colors="white", linewidths=0.5, alpha=0.45, zorder=2))
    ax.plot(np.r_[r_lo * np.sin(arc), r_hi * np.sin(arc[::-1]), r_lo * math.sin(t_lo)],
            np.r_[r_lo * np.cos(arc), r_hi * np.cos(arc[::-1]), r_lo * math.cos(t_lo)], color="black", lw=0.8)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.annotate("azimuth (deg)", (0.5, -0.02), xycoords="axes fraction", xytext=(0, -11), textcoords="offset points",
                fontsize=7, ha="center", va="top", color="#444444")
    return shown


def draw_here(function, *args, **kwargs):
    """Draw a figure in this process: ``function(*args, **kwargs)`` (the ``draw`` of a
    command without figure processes)."""
    return function(*args, **kwargs)


#: Most figure processes by default: the demo's 26 figures are about 23 s of matplotlib work
#: (coral-one, this project's 2-core CI-class CPU); on a 16-core GPU server eight draw them while
#: the demo goes on where four left 3.9 s to wait for at its end (bench/notes.md, eleventh session).
MAX_FIGURE_WORKERS = 8


def figure_workers() -> int:
    """Processes that draw a command's figures: the environment variable
    FSSWARP_FIGURE_WORKERS (0: draw in the command's own process), else one per CPU that this
    process may use, at most ``MAX_FIGURE_WORKERS``."""
    from .processes import worker_count
    from .system import usable_cpus

    return worker_count("FSSWARP_FIGURE_WORKERS", min(MAX_FIGURE_WORKERS, usable_cpus()))


class FigureWarning(UserWarning):
    """Figures are drawn in the command's own process because figure processes could not start."""


class FigureDrawer:
    """Draws figures in child processes while the command goes on (``workers``, default
    :func:`figure_workers`; 0 draws each at once in this process).

    A figure is 0.3–2.6 s of matplotlib work (coral-one on the 2-core CI-class machine) and
    the demo draws nine, 11 s of its 81 s there; on a GPU server, whose kernels are done in a
    fraction of that, they were most of the demo's wall time. The processes start (and import
    matplotlib, about 0.9 s) when the drawer is made, at the start of the command, so they
    are ready when its first figure comes. Each figure's arguments are pickled to its process,
    and its file is written there, atomically (``write_figure``).

    Use: per output folder ``with drawer.batch() as draw:`` and ``draw(figure_function, *args,
    **kwargs)``. Leaving a batch waits for its figures and raises the first failure; leaving it
    by an error waits only for the figures being drawn, so none is written into a folder that
    is being removed. ``close`` stops the processes (the command line's ``State.figure_drawer``
    calls it when the command ends)."""

    def __init__(self, workers: int | None = None):
        self.workers = figure_workers() if workers is None else workers
        self.pool = None
        if self.workers > 0:
            import warnings

            from .processes import WorkerProcesses

            try:
                self.pool = WorkerProcesses(self.workers, _start_figure_process)
            except OSError as err:  # e.g. no /dev/shm for the pool's semaphores in some containers
                warnings.warn(f"figure processes could not start ({err}); drawing the figures in this process "
                              "(FSSWARP_FIGURE_WORKERS=0 does so without this warning)", FigureWarning, stacklevel=2)

    def close(self) -> None:
        """Stop the processes (a figure being drawn is finished first)."""
        if self.pool is not None:
            self.pool.close()

    @contextmanager
    def batch(self):
        """Yield ``draw(function, *args, **kwargs)``; wait for what it drew on leaving."""
        if self.pool is None:
            yield draw_here
            return
        futures = []
        try:
            yield lambda function, *args, **kwargs: futures.append(self.pool.submit(function, *args, **kwargs))
        except BaseException:
            for future in futures:
                future.cancel()
            wait(futures)
            raise
        wait(futures)
        for future in futures:
            future.result()


def _start_figure_process() -> None:
    """Set up a figure process: the modules that every figure needs are imported before the
    first comes."""
    import importlib

    import matplotlib

    matplotlib.use("Agg")
    for module in ("matplotlib.pyplot", "trimesh"):  # trimesh: meshes arrive pickled
        importlib.import_module(module)
