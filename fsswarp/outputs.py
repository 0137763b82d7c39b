"""The files of ``fsswarp carve``, ``reconstruct``, ``pose`` and ``enhance`` besides their
figures (DESIGN §12; docs/formats.md lists every field).

Each ``*_record`` function builds a command's JSON record from its results; each ``write_*``
function writes the record and the command's meshes or images into a folder, every file
atomically (``fsswarp.atomic``), byte for byte as the command line writes them:

- ``write_carve``: carved.ply and carve.json
- ``write_reconstruction``: model.ply, carved.ply and result.json
- ``write_pose``: pose.json
- ``write_enhancement``: <view>_enhanced.tiff, <view>_ghost.tiff (float32, (bins, beams),
  the data's linear units) and enhance.json

Lengths are in m, angles in degrees, times in s. The command line writes into the temporary
folder of ``fsswarp.atomic.output_folder``, so a command's output appears whole or not at all.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

from .atomic import json_number, write_bytes, write_text

#: The comparison figures of ``fsswarp enhance``: file name and group of
#: ``fsswarp.enhancement.comparison_views``.
COMPARISON_FIGURES = {"views_optimized.png": "optimized", "views_heldout.png": "held-out"}


def _write_json(path: Path, record: dict) -> Path:
    return write_text(path, json.dumps(record, indent=2))


def _write_mesh(path: Path, mesh) -> Path:
    return write_bytes(path, mesh.export(file_type="ply"))


# --- carve -----------------------------------------------------------------------------------

def carve_record(dataset_dir, dataset, result, *, resolution: int, given: bool, load_s: float,
                 truth=None) -> dict:
    """carve.json of ``result`` (a ``fsswarp.carving.CarveResult`` of ``dataset``, read from
    ``dataset_dir`` in ``load_s`` seconds) at ``resolution``; ``given``: the depth and tilt came
    from the user; ``truth``: the truth mesh, scored against (``fsswarp.metrics.compare``)."""
    from .metrics import compare

    voxels, mesh = result.voxels, result.mesh
    timings = {"load_s": load_s, **result.timings}
    metrics = None
    if truth is not None:
        begin = time.perf_counter()
        metrics = compare(mesh, truth)
        timings["metrics_s"] = time.perf_counter() - begin
    return {
        "dataset": str(dataset_dir), "depth_m": result.depth, "tilt_deg": math.degrees(result.tilt),
        "depth_tilt_source": "given" if given else "measured", "views": list(result.views),
        "views_left_out": [n for n in dataset.rig.names if n not in result.views],
        "resolution": resolution,
        "grid": {"origin_m": voxels.origin.tolist(), "voxel_size_m": voxels.voxel_size,
                 "shape": list(voxels.occupancy.shape), "domain_m": voxels.domain.tolist(),
                 "origin_is": "centre of voxel (0, 0, 0)"},
        "voxels_kept": voxels.kept, "voxels_tested": voxels.tested,
        "mesh": {"faces": len(mesh.faces), "vertices": len(mesh.vertices), "volume_m3": float(mesh.volume),
                 "watertight": bool(mesh.is_watertight)},
        "backend": result.backend, "device": result.device, "timings_s": timings, "metrics": metrics,
    }


def write_carve(out, result, record: dict) -> Path:
    """OUT/carved.ply (``result.mesh``, reference frame) and OUT/carve.json (``record``, from
    :func:`carve_record`); returns OUT."""
    out = Path(out)
    _write_mesh(out / "carved.ply", result.mesh)
    _write_json(out / "carve.json", record)
    return out


# --- reconstruct -----------------------------------------------------------------------------

def write_reconstruction(out, result) -> Path:
    """OUT/model.ply, OUT/carved.ply and OUT/result.json of ``result`` (a
    ``fsswarp.reconstruction.ReconstructResult``); returns OUT."""
    out = Path(out)
    _write_mesh(out / "model.ply", result.model)
    _write_mesh(out / "carved.ply", result.carved)
    _write_json(out / "result.json", result.summary())
    return out


# --- pose ------------------------------------------------------------------------------------

def pose_record(dataset_dir, model_path, dataset, result, contours: dict, *, given: bool, backend) -> dict:
    """pose.json of ``result`` (a ``fsswarp.pose.PoseResult`` of the mesh read from
    ``model_path`` and ``dataset``, read from ``dataset_dir``); ``contours``: the
    ``fsswarp.compare.view_contours`` at the estimate and at the start; ``given``: the start came
    from the user; ``backend``: the backend that ran it."""
    left_out = [v.name for v in dataset.rig.views if v.optimize and v.name not in result.views]
    record = {"dataset": str(dataset_dir), "model": str(model_path), **result.summary(),
              "start_source": "given" if given else "measured", "views_left_out": left_out,
              "view_mu_m": {name: dict(zip(("estimate", "start"), map(json_number, c["mu"])))
                            for name, c in contours.items()},
              "backend": backend.name, "device": backend.device}
    truth = dataset.manifest.truth
    if truth is not None:
        record["truth"] = {"depth_m": truth.depth, "tilt_deg": math.degrees(truth.tilt),
                           "depth_error_m": result.depth - truth.depth,
                           "tilt_error_deg": math.degrees(result.tilt - truth.tilt)}
    return record


def write_pose(out, record: dict) -> Path:
    """OUT/pose.json (``record``, from :func:`pose_record`); returns OUT."""
    out = Path(out)
    _write_json(out / "pose.json", record)
    return out


# --- enhance ---------------------------------------------------------------------------------

def enhancement_scores(dataset, results: dict) -> dict | None:
    """``fsswarp.enhancement.score`` of ``results`` where every view has its truth object layer
    (a simulated dataset), else None."""
    from .enhancement import score

    has_truth = dataset.root is not None and all((dataset.root / "truth" / f"{n}_object.tiff").is_file()
                                                 for n in results)
    return score(dataset, results) if has_truth else None


def comparison_figures(groups: dict[str, list[str]], *, initial: bool) -> dict:
    """enhance.json's "figures": per file of COMPARISON_FIGURES whose group (of
    ``fsswarp.enhancement.comparison_views``) has views, its views and columns; ``initial``:
    the figures show an initial model's column."""
    columns = ["data", "ghost-free data"] + (["initial synthetic"] if initial else []) + ["optimized synthetic"]
    return {file: {"views": groups[group], "columns": columns}
            for file, group in COMPARISON_FIGURES.items() if groups[group]}


def enhancement_record(dataset, results: dict, *, model_name: str, depth: float, tilt: float, source: str,
                       requested, initial_name: str | None, ghost_sigma, scores: dict | None, figures: dict,
                       backend, seconds: float, dataset_label=None) -> dict:
    """enhance.json of ``results`` ({view: ``fsswarp.enhancement.EnhancedView``}) of the mesh
    ``model_name`` at (depth m, tilt rad) from ``source`` ("given", "measured" or "estimated").
    ``requested``: the views asked for; ``initial_name``: the initial model's name (None: none);
    ``scores``: :func:`enhancement_scores`; ``figures``: :func:`comparison_figures`;
    ``dataset_label``: the dataset folder's name when ``dataset.root`` is a temporary folder."""
    surface = dataset.manifest.surface
    return {"dataset": str(dataset_label or dataset.root), "model": model_name, "depth_m": depth,
            "tilt_deg": math.degrees(tilt),
            "depth_tilt_source": source,
            "initial_model": None if initial_name is None else {"model": initial_name, "depth_m": surface.depth,
                                                                "tilt_deg": math.degrees(surface.tilt)},
            "views": {name: result.summary() for name, result in results.items()},
            "ghost_sigma": list(ghost_sigma), "views_skipped": [n for n in requested if n not in results],
            "figures": figures,
            "scores": scores, "backend": backend.name, "device": backend.device,
            "seconds": seconds}


def write_enhancement(out, results: dict, record: dict) -> Path:
    """OUT/<view>_enhanced.tiff and OUT/<view>_ghost.tiff of each of ``results`` and
    OUT/enhance.json (``record``, from :func:`enhancement_record`); returns OUT."""
    from .dataset import tiff_bytes

    out = Path(out)
    images = {f"{name}_{kind}.tiff": getattr(result, kind) for name, result in results.items()
              for kind in ("enhanced", "ghost")}
    for file, data in tiff_bytes(images).items():
        write_bytes(out / file, data)
    _write_json(out / "enhance.json", record)
    return out
