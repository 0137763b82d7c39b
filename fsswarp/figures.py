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
                  layers=("object", "ghost", "mirror", "mirror2", "total"), title: str = "") -> Path:
    """Save a PNG grid: one row per view, per layer a beam-bin image and its fan image.

    views : {label: (len(layers), bins, beams) float32}. Intensities on a shared dB scale
    (60 dB below the brightest pixel of all views)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    peak = max(float(np.max(stack)) for stack in views.values()) or 1.0
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
            for a in axes[r, 2 * k: 2 * k + 2]:
                a.tick_params(labelsize=5)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    return write_bytes(path, buffer.getvalue())


def _decibels(image: np.ndarray, peak: float) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return np.maximum(20.0 * np.log10(np.maximum(image, 0) / peak), -60.0).astype(np.float32)
