"""Figures for people: layers of synthetic views as beam-bin and fan images.

Figures read results; nothing in the pipeline imports this module.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np

from .atomic import write_bytes
from .sonar import SonarSpec, scan_convert


def layers_figure(views: dict[str, np.ndarray], sonar: SonarSpec, path: str | Path, *,
                  layers=("object", "ghost", "mirror", "mirror2", "total"), title: str = "",
                  zoom: bool = True) -> Path:
    """Save a PNG grid: one row per view, per layer a beam-bin image and its fan image.

    views : {label: (len(layers), bins, beams) float32}. Intensities on a shared dB scale
    (60 dB below the brightest pixel of all views). With ``zoom`` the axes show the ranges
    and azimuths that hold returns within 40 dB of that peak, plus a margin, instead of the
    whole window."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    peak = max(float(np.max(stack)) for stack in views.values()) or 1.0
    limits = _zoom_limits(views, sonar, peak) if zoom else None
    rows, cols = len(views), 2 * len(layers)
    fig, axes = plt.subplots(rows, cols, figsize=(2.1 * cols, 2.6 * rows), squeeze=False)
    extent_bb = (math.degrees(sonar.beam_centres[0]), math.degrees(sonar.beam_centres[-1]),
                 sonar.range_min, sonar.range_max)
    for r, (label, stack) in enumerate(views.items()):
        for k, layer in enumerate(layers):
            db = _decibels(stack[k], peak)
            ax = axes[r, 2 * k]
            ax.imshow(db, origin="lower", aspect="auto", extent=extent_bb, cmap="magma", vmin=-60, vmax=0)
            ax.set_title(f"{label} {layer}\nbeam-bin", fontsize=7)
            ax.set_xlabel("azimuth (deg)", fontsize=6)
            ax.set_ylabel("range (m)", fontsize=6)
            fan, extent = scan_convert(db, sonar, fill=np.nan)
            ax = axes[r, 2 * k + 1]
            ax.imshow(fan, extent=extent, cmap="magma", vmin=-60, vmax=0)
            ax.set_title(f"{label} {layer}\nfan", fontsize=7)
            ax.set_xlabel("x (m)", fontsize=6)
            if limits is not None:
                axes[r, 2 * k].set_xlim(limits["azimuth"])
                axes[r, 2 * k].set_ylim(limits["range"])
                ax.set_xlim(limits["x"])
                ax.set_ylim(limits["y"])
            for a in axes[r, 2 * k: 2 * k + 2]:
                a.tick_params(labelsize=5)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    return write_bytes(path, buffer.getvalue())


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
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    return write_bytes(path, buffer.getvalue())


def carve_figure(mesh, path: str | Path, *, truth=None, title: str = "") -> Path:
    """Save a PNG of a mesh's XY, XZ and YZ projections (reference frame, metres), over the
    truth's projections when ``truth`` (a mesh) is given: filled triangles, carved in blue,
    truth in black."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    fig, axes = plt.subplots(1, 3, figsize=(12.6, 4.4))
    meshes = [(m, colour, alpha, label) for m, colour, alpha, label in
              ((truth, "black", 0.35, "truth"), (mesh, "tab:blue", 0.35, "carved")) if m is not None]
    points = np.concatenate([np.asarray(m.vertices) for m, *_ in meshes])
    pad = 0.05 * float(np.ptp(points, axis=0).max())
    for ax, (i, j) in zip(axes, ((0, 1), (0, 2), (1, 2))):
        for m, colour, alpha, label in meshes:
            tri = np.asarray(m.triangles)[:, :, (i, j)]
            ax.add_collection(PolyCollection(tri, facecolors=colour, edgecolors="none", alpha=alpha, label=label))
        ax.set_xlim(points[:, i].min() - pad, points[:, i].max() + pad)
        ax.set_ylim(points[:, j].min() - pad, points[:, j].max() + pad)
        ax.set_aspect("equal")
        ax.set_xlabel(f"{'xyz'[i]} (m)")
        ax.set_ylabel(f"{'xyz'[j]} (m)")
        ax.set_title(f"{'xyz'[i]}{'xyz'[j]} projection", fontsize=9)
        ax.tick_params(labelsize=7)
    if truth is not None:
        axes[0].legend(handles=[matplotlib.patches.Patch(color=c, alpha=0.5, label=lab) for _, c, _, lab in meshes],
                       fontsize=7, loc="upper right")
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    return write_bytes(path, buffer.getvalue())
