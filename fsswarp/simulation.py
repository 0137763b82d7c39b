"""Simulate a dataset from a scene: render the truth layers, add seeded noise, save (DESIGN §12).

Views are rendered in batches (``rendering.stream_views``); each batch's noise is drawn on a
worker thread while the next batch renders. The dataset is written whole at the end
(``save_dataset``: all or nothing).
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np

from .atomic import check_output_folder
from .dataset import TRUTH_MODEL, Dataset, Manifest, Truth, deep_water_pose, load_dataset, load_scene, save_dataset
from .errors import InputError, check_integer
from .rendering import LAYERS, RenderSettings, RenderWarning, add_noise, rig_poses, stream_views, warn_outside_window
from .rig import world_to_reference
from .scenes import builtin_scene, target_world_mesh
from .targets import BUILTIN_TARGETS

#: Views rendered per batch: the noise of one batch is drawn while the next renders.
BATCH = 8


def resolve_scene(scene: str | Path) -> tuple[Manifest, Path | None]:
    """A built-in scene name or a scene file → (manifest, the scene file or None)."""
    if str(scene) in BUILTIN_TARGETS:
        return builtin_scene(str(scene)), None
    path = Path(scene)
    if not path.is_file():
        raise InputError(f"neither a scene file nor a built-in scene ({', '.join(BUILTIN_TARGETS)})",
                         field="SCENE", value=str(scene))
    return load_scene(path), path


def check_scene(scene: str | Path | Manifest) -> tuple[Manifest, trimesh.Trimesh]:
    """The manifest of ``scene`` (a built-in name, a scene file or a scene Manifest) and its
    target mesh placed in the world frame, or InputError."""
    manifest, file = (scene, None) if isinstance(scene, Manifest) else resolve_scene(scene)
    if manifest.target is None or (manifest.truth is None and not manifest.deep_water):
        raise InputError("a scene needs [target] and [truth]", field="scene", value=str(scene))
    return manifest, target_world_mesh(manifest.target, base=file.parent if file else None, file=file)


def simulate(scene: str | Path | Manifest, out: str | Path, *, seed: int = 0,
             settings: RenderSettings = RenderSettings(), noise: bool = True, backend=None) -> Dataset:
    """Synthesize the dataset of ``scene`` (a built-in name, a scene file or a scene Manifest)
    into the folder ``out``: noisy images, the noise-free layers and the truth model (in the
    reference frame of the true depth and tilt). A deep-water scene (no [surface]) is placed at
    its known [rig] depth and tilt and rendered at ``deep_water_pose``: its images hold the
    object alone, and truth/ its object layers alone. Returns the saved Dataset."""
    import trimesh

    check_integer("--seed", seed, 0)
    check_output_folder(out, marker=TRUTH_MODEL)  # before the rendering; a recording is never replaced
    manifest, world = check_scene(scene)
    deep = manifest.deep_water
    placed = manifest.known_pose if deep else manifest.truth  # the sonar's true depth and tilt
    model = trimesh.Trimesh(world_to_reference(world.vertices, manifest.rig, placed.depth, placed.tilt),
                            world.faces, process=False)
    depth, tilt = deep_water_pose(manifest) if deep else (placed.depth, placed.tilt)
    names = manifest.rig.names
    poses = rig_poses(manifest.rig, depth, tilt, names)
    with warnings.catch_warnings():
        if deep:  # the surface lies beyond every window on purpose (deep_water_pose)
            warnings.filterwarnings("ignore", "view .*: ghost returns reach", RenderWarning)
        warn_outside_window(model, manifest.sonar, *poses, names)
    kept = ("object",) if deep else tuple(layer for layer in LAYERS if layer != "total")
    images, layers = {}, {}

    def keep(index: int, stack: np.ndarray) -> None:  # on stream_views' worker, beside the next batch
        total = stack[LAYERS.index("total")]
        images[names[index]] = add_noise(total, np.random.default_rng([seed, index])) if noise else total
        layers[names[index]] = {layer: stack[LAYERS.index(layer)] for layer in kept}

    stream_views(model, manifest.sonar, *poses, keep, settings=settings, backend=backend, batch=BATCH)
    dataset_manifest = dataclasses.replace(manifest, target=None, truth=Truth(depth=None, tilt=None) if deep else
                                           Truth(depth=placed.depth, tilt=placed.tilt))
    dataset = Dataset(dataset_manifest, images)
    save_dataset(dataset, out, truth_layers=layers, truth_mesh=model, marker=TRUTH_MODEL)
    return load_dataset(out)
