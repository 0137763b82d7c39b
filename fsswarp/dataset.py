"""The dataset folder and the scene file (DESIGN §2, §12).

A dataset folder::

    DIR/dataset.toml         the manifest
    DIR/images/<view>.tiff   float32 beam-bin image, shape (bins, beams)
    DIR/truth/               simulated data only: model.ply and the noise-free layers
                             <view>_{object,ghost,mirror,mirror2}.tiff

A scene file is the same manifest with a ``[target]`` and a ``[truth]`` table and no images.
A manifest without ``[surface]`` is deep water (no sea surface in view): ``[rig] depth_m`` and
``tilt_deg`` give the known shared depth and tilt, and a scene of it has no ``[truth]`` table.

Files hold metres and degrees; the objects here hold metres and radians. Every field that is
read is validated, and unknown keys are mistakes too (a misspelt key must not fall back to a
default). A mistake raises :class:`InputError` whose text is one line naming the file, the
field as a dotted path (``views[3].roll_deg``; view indices count from 0, in file order) and
the value.

Angles round-trip exactly through a file: :func:`manifest_to_toml` writes, for an angle x,
the shortest degree value d with ``math.radians(d) == x``. Every angle that came from degrees
has one; any other radian value moves by at most one ulp on its first trip and then stays.
"""

from __future__ import annotations

import io
import math
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np
import tifffile
import tomli_w

from .atomic import output_folder, write_text
from .errors import InputError, check_number, is_number
from .rig import Rig, View
from .sonar import SonarSpec
from .surface import COMPONENTS
from .system import map_on_threads
from .targets import BUILTIN_TARGETS

#: The manifest's file name inside a dataset folder.
MANIFEST_NAME = "dataset.toml"
#: Where ``save_dataset`` writes the truth mesh, relative to the dataset folder.
TRUTH_MODEL = "truth/model.ply"

_REQUIRED = object()
_HEADER = "# fsswarp manifest (DESIGN §12): lengths in metres, angles in degrees\n"

# the keys each table may hold, in the order they are written
_TOP_KEYS = ("sonar", "surface", "truth", "target", "rig", "views")
_SONAR_KEYS = ("beams", "bins", "azimuth_fov_deg", "elevation_fov_deg", "range_min_m", "range_max_m",
               "beam_angles_deg")
_SURFACE_KEYS = ("depth_m", "tilt_deg", "depth_sigma_m", "tilt_sigma_deg")
_TRUTH_KEYS = ("depth_m", "tilt_deg", "model")
_TARGET_KEYS = ("mesh", "builtin", "scale_m", "position_m", "rotation_deg")
_RIG_KEYS = ("reference_view", "depth_m", "tilt_deg")
_VIEW_KEYS = ("name", "image", "position_m", "heading_deg", "roll_deg", "depth_offset_m",
              "tilt_offset_deg", "optimize")


# --- the manifest ------------------------------------------------------------------------

@dataclass(frozen=True)
class SurfaceEstimate:
    """The sensors' depth D0 (m) and tilt β0 (rad) and their uncertainties (1 sigma)."""

    depth: float
    tilt: float
    depth_sigma: float = 0.05
    tilt_sigma: float = math.radians(2.0)

    def __post_init__(self) -> None:
        _check_depth("surface.depth_m", self.depth)
        _check_tilt("surface.tilt_deg", self.tilt)
        check_number("surface.depth_sigma_m", self.depth_sigma, lambda v: v >= 0, "must be >= 0")
        check_number("surface.tilt_sigma_deg", self.tilt_sigma, lambda v: v >= 0, "must be >= 0",
                      degrees=True)


@dataclass(frozen=True)
class KnownPose:
    """The shared sonar depth D (m, below the surface z = 0) and tilt β (rad) of a deep-water
    dataset (no ``[surface]`` table: no sea surface in view to estimate them from), known and
    not estimated; the manifest's ``[rig] depth_m`` and ``tilt_deg``."""

    depth: float
    tilt: float

    def __post_init__(self) -> None:
        _check_depth("rig.depth_m", self.depth)
        _check_tilt("rig.tilt_deg", self.tilt)


@dataclass(frozen=True)
class Truth:
    """The true depth (m) and tilt (rad) of simulated data, and the true model's file
    (relative to the manifest's folder), if any. A deep-water dataset's truth has no depth
    and tilt (None): its poses are known ([rig])."""

    depth: float | None
    tilt: float | None
    model: str | None = None

    def __post_init__(self) -> None:
        if (self.depth is None) != (self.tilt is None):
            raise InputError("give depth_m and tilt_deg together", field="truth.depth_m", value=self.depth)
        if self.depth is not None:
            _check_depth("truth.depth_m", self.depth)
            _check_tilt("truth.tilt_deg", self.tilt)
        if self.model is not None:
            _check_inner_path("truth.model", self.model, (".ply",))


@dataclass(frozen=True)
class Target:
    """The object of a scene: a mesh file or a built-in shape, placed in the world frame.

    position : (x, y, z) of the mesh origin in the world frame (m); z < 0 is below the surface
    mesh : a mesh file, relative to the scene file's folder (or absolute); or
    builtin : one of ``BUILTIN_TARGETS``
    scale : factor applied to the mesh (its units become metres)
    rotation : (rx, ry, rz) about the mesh origin (rad), applied x, then y, then z
    """

    position: tuple[float, float, float]
    mesh: str | None = None
    builtin: str | None = None
    scale: float = 1.0
    rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.mesh is not None and self.builtin is not None:
            raise InputError(f"give mesh or builtin, not both (builtin = {self.builtin!r})",
                             field="target.mesh", value=self.mesh)
        if self.mesh is None and self.builtin is None:
            raise InputError("is required (or target.builtin)", field="target.mesh")
        if self.mesh is not None and (not isinstance(self.mesh, str) or not self.mesh.strip()):
            raise InputError("must be a mesh file name", field="target.mesh", value=self.mesh)
        if self.builtin is not None and self.builtin not in BUILTIN_TARGETS:
            raise InputError(f"unknown built-in target; choose one of {', '.join(BUILTIN_TARGETS)}",
                             field="target.builtin", value=self.builtin)
        check_number("target.scale_m", self.scale, lambda v: v > 0, "must be > 0")
        _check_vector("target.position_m", self.position, 3)
        if not self.position[2] < 0:
            raise InputError("z must be < 0: the mesh origin lies below the surface (z = 0)",
                             field="target.position_m", value=list(self.position))
        _check_vector("target.rotation_deg", self.rotation, 3, degrees=True)

    def mesh_path(self, base: str | Path) -> Path | None:
        """The mesh file resolved against ``base`` (the scene file's folder); None if builtin."""
        return None if self.mesh is None else Path(base) / self.mesh


@dataclass(frozen=True)
class Manifest:
    """Everything a ``dataset.toml`` or a scene file says, in metres and radians.

    surface : the measured D0 and β0; None for deep water (no sea surface in view), whose
        shared depth and tilt are then ``known_pose`` instead (exactly one of the two is set)
    Equality also compares the sonar's beam-angle table (``SonarSpec`` itself does not).
    """

    sonar: SonarSpec
    surface: SurfaceEstimate | None
    rig: Rig
    truth: Truth | None = None
    target: Target | None = None
    known_pose: KnownPose | None = None

    def __post_init__(self) -> None:
        if (self.surface is None) == (self.known_pose is None):
            raise InputError("give a [surface] table or, for deep water (no sea surface in view), [rig] depth_m "
                             "and tilt_deg, not both", field="surface")
        if self.truth is not None and (self.truth.depth is None) != (self.surface is None):
            raise InputError("a [truth] table gives depth_m and tilt_deg with a [surface] table and not without one "
                             "(deep water: the depth and tilt are known, [rig] depth_m and tilt_deg)",
                             field="truth.depth_m", value=self.truth.depth)

    @property
    def deep_water(self) -> bool:
        """No sea surface in view: no [surface] table, known depth and tilt, no multipath."""
        return self.surface is None

    def __eq__(self, other: object) -> bool:
        if other.__class__ is not self.__class__:
            return NotImplemented
        mine = (self.sonar, self.surface, self.rig, self.truth, self.target, self.known_pose)
        theirs = (other.sonar, other.surface, other.rig, other.truth, other.target, other.known_pose)
        a, b = self.sonar.beam_angles, other.sonar.beam_angles
        same_angles = (a is None and b is None) or (a is not None and b is not None and np.array_equal(a, b))
        return mine == theirs and same_angles


#: Metres between a deep-water dataset's range window and the surface plane where
#: :func:`deep_water_pose` puts it.
SURFACE_CLEARANCE_M = 1.0


def deep_water_pose(manifest: Manifest) -> tuple[float, float]:
    """(D m, β rad) at which the steps synthesize, carve and refine a deep-water dataset: the
    known tilt, and the known depth or, where the surface z = 0 would then lie within
    ``SURFACE_CLEARANCE_M`` of some view's range window, the depth that puts it there. An echo by
    way of the surface has an apparent range of at least the sonar's distance to it, so it falls
    beyond range_max_m: the synthetic views hold the object alone. The views' relative poses, and
    so the models' reference frame, do not depend on D."""
    if manifest.known_pose is None:
        raise InputError("has a [surface] table: its depth and tilt are estimated, not known", field="surface")
    reach = manifest.sonar.range_max + SURFACE_CLEARANCE_M
    lowest = max(reach - view.depth_offset for view in manifest.rig.views)
    return max(manifest.known_pose.depth, lowest), manifest.known_pose.tilt


def image_file(view: View) -> str:
    """The image of ``view``, relative to the dataset folder (default ``images/<name>.tiff``)."""
    return view.image if view.image is not None else f"images/{view.name}.tiff"


# --- the dataset -------------------------------------------------------------------------

@dataclass(eq=False)
class Dataset:
    """A manifest and its images.

    images : view name -> (bins, beams) float32 image, in rig order; made read-only, since
        results derived from them are kept (:meth:`derived`)
    root : the folder it was loaded from (truth layers and the truth model are read from it)
    """

    manifest: Manifest
    images: dict[str, np.ndarray]
    root: Path | None = None
    _derived: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        for image in self.images.values():
            image.setflags(write=False)

    def derived(self, key, compute):
        """``compute()``, computed once per ``key`` (hashable) for this dataset and then kept:
        for results that depend only on the images and ``key`` (the reconstruction loop
        segments the same images for every pose and shape step)."""
        if key not in self._derived:
            self._derived[key] = compute()
        return self._derived[key]

    @property
    def sonar(self) -> SonarSpec:
        return self.manifest.sonar

    @property
    def rig(self) -> Rig:
        return self.manifest.rig

    @property
    def truth_model_path(self) -> Path | None:
        """The truth mesh file, if the manifest names one and the dataset has a folder."""
        truth = self.manifest.truth
        if truth is None or truth.model is None or self.root is None:
            return None
        return self.root / truth.model

    def truth_mesh(self):
        """The truth mesh (trimesh.Trimesh, reference frame; a new one per call), or None
        without one; InputError naming dataset.toml's ``truth.model`` when it is unreadable."""
        path = self.truth_model_path
        if path is None:
            return None
        return read_mesh(path, file=self.root / MANIFEST_NAME, field="truth.model")

    def check_truth_layers(self) -> int:
        """Read and validate every truth layer file the folder holds (``truth_layer``); returns
        how many there are (0 without a folder)."""
        if self.root is None:
            return 0
        present = [(view, component) for view in self.rig.names for component in COMPONENTS
                   if (self.root / _truth_layer_file(view, component)).exists()]
        for view, component in present:
            self.truth_layer(view, component)
        return len(present)

    def truth_layer(self, view: str, component: str) -> np.ndarray:
        """The noise-free ``component`` layer (object, ghost, mirror, mirror2) of ``view``:
        ``root/truth/<view>_<component>.tiff``, validated; InputError if absent."""
        if component not in COMPONENTS:
            raise InputError(f"must be one of {', '.join(COMPONENTS)}", field="component", value=component)
        if view not in self.rig.names:
            raise InputError("no view of that name", field="view", value=view)
        if self.root is None:
            raise InputError("the dataset was not loaded from a folder; it has no truth layers",
                             field="truth", value=f"{view}_{component}")
        path = self.root / _truth_layer_file(view, component)
        if not path.is_file():
            raise InputError("file not found (truth layers exist for simulated data only)",
                             file=path, field="truth", value=f"{view}_{component}")
        return _read_image(path, self.sonar, field=f"truth.{view}_{component}")


# --- reading -----------------------------------------------------------------------------

def parse_manifest(table: dict, *, file) -> Manifest:
    """Validate a parsed TOML table (``tomllib.load``) as a manifest; ``file`` names it in
    errors. Touches no files: image and mesh files are checked by the loaders."""
    top = _Table(table, "", file, _TOP_KEYS)
    sonar = _parse_sonar(top.table("sonar"), file)
    surface = _parse_surface(top.table("surface", required=False), file)
    truth = _parse_truth(top.table("truth", required=False), file, deep_water=surface is None)
    target = _parse_target(top.table("target", required=False), file)
    views = _parse_views(top, file)
    rig, known = _parse_rig(top.table("rig", required=False), views, file, deep_water=surface is None)
    shared = (surface.depth, "surface.depth_m") if surface is not None else (known.depth, "rig.depth_m")
    for depth, what in (shared, (truth.depth if truth and truth.depth is not None else math.inf, "truth.depth_m")):
        for view in views:
            if depth + view.depth_offset <= 0:
                raise InputError(f"puts the sonar above the surface at {what} = {depth:g} m (it must lie below: "
                                 "depth + offset > 0)", file=file, field=f"views[{view.name}].depth_offset_m",
                                 value=view.depth_offset)
    return Manifest(sonar=sonar, surface=surface, rig=rig, truth=truth, target=target, known_pose=known)


def read_mesh(path: Path, *, field: str, file: Path | None = None, value: str | None = None):
    """A triangle mesh (trimesh.Trimesh, processed) from the file ``path``, or InputError
    naming ``field`` (and ``file``, where the path was given) and ``value``, the path as the
    user wrote it (default ``path``)."""
    import trimesh

    value = str(path) if value is None else value
    if not path.is_file():
        raise InputError("no such mesh file", file=file, field=field, value=value)
    try:
        mesh = trimesh.load_mesh(path, process=False)  # processing would drop non-finite vertices unseen
    except Exception as err:  # trimesh raises many kinds for unreadable files
        raise InputError(f"cannot read mesh ({' '.join(str(err).split())})", file=file, field=field,
                         value=value) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError("holds no triangles", file=file, field=field, value=value)
    bad = vertices_beyond_float32(mesh.vertices)
    if bad:
        raise InputError(f"has {bad} vertices that are not finite numbers within float32's range (the kernels')",
                         file=file, field=field, value=value)
    mesh.process()  # as trimesh.load_mesh(..., process=True): duplicate vertices merged
    return mesh


def vertices_beyond_float32(vertices) -> int:
    """How many of the (N, 3) ``vertices`` are not finite numbers within float32's range (the
    kernels' precision)."""
    with np.errstate(invalid="ignore"):
        return int(np.sum(~(np.abs(np.asarray(vertices)) < np.finfo(np.float32).max).all(axis=1)))


def load_manifest(path) -> Manifest:
    """Read and validate a ``dataset.toml`` or a scene file (or a dataset folder's manifest)."""
    path = Path(path)
    if path.is_dir():
        path = path / MANIFEST_NAME
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("file not found", file=path) from None
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"cannot read the file ({err})", file=path) from None
    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise InputError(f"not valid TOML: {err}", file=path) from None
    return parse_manifest(table, file=path)


def load_dataset(folder) -> Dataset:
    """A dataset folder: ``dataset.toml`` and every view's image, all validated."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("no such folder" if not folder.exists() else "is not a folder", file=folder)
    path = folder / MANIFEST_NAME
    if not path.is_file():
        raise InputError(f"not a dataset folder: it holds no {MANIFEST_NAME}", file=folder)
    manifest = load_manifest(path)
    truth = manifest.truth
    if truth is not None and truth.model is not None and not (folder / truth.model).is_file():
        raise InputError(f"file not found: {folder / truth.model}", file=path, field="truth.model",
                         value=truth.model)
    images = {}
    for i, view in enumerate(manifest.rig.views):
        rel = image_file(view)
        image_path = folder / rel
        if not image_path.is_file():
            raise InputError(f"file not found: {image_path}", file=path, field=f"views[{i}].image", value=rel)
        images[view.name] = _read_image(image_path, manifest.sonar, field=f"views[{i}].image")
    return Dataset(manifest=manifest, images=images, root=folder)


def load_scene(path) -> Manifest:
    """A scene file: a manifest with ``[target]`` and ``[truth]`` and no images. A mesh
    target's file must exist (relative to the scene file's folder)."""
    path = Path(path)
    if path.is_dir():
        raise InputError("is a folder; a scene file is a .toml file", file=path)
    manifest = load_manifest(path)
    _check_scene(manifest, path)
    mesh = manifest.target.mesh_path(path.parent)
    if mesh is not None and not mesh.is_file():
        raise InputError(f"file not found: {mesh}", file=path, field="target.mesh", value=manifest.target.mesh)
    return manifest


# --- writing -----------------------------------------------------------------------------

def manifest_to_toml(manifest: Manifest) -> str:
    """The manifest as TOML text (degrees); ``parse_manifest`` reads it back equal."""
    sonar = manifest.sonar
    sonar_table = {"beams": int(sonar.beams), "bins": int(sonar.bins),
                   "azimuth_fov_deg": _degrees(sonar.azimuth_fov),
                   "elevation_fov_deg": _degrees(sonar.elevation_fov),
                   "range_min_m": float(sonar.range_min), "range_max_m": float(sonar.range_max)}
    if sonar.beam_angles is not None:
        sonar_table["beam_angles_deg"] = [_degrees(a) for a in sonar.beam_angles]
    s = manifest.surface
    sections = [("sonar", sonar_table)]
    if s is not None:
        sections.append(("surface", {"depth_m": float(s.depth), "tilt_deg": _degrees(s.tilt),
                                     "depth_sigma_m": float(s.depth_sigma), "tilt_sigma_deg": _degrees(s.tilt_sigma)}))
    if manifest.truth is not None:
        t = manifest.truth
        table = {} if t.depth is None else {"depth_m": float(t.depth), "tilt_deg": _degrees(t.tilt)}
        if t.model is not None:
            table["model"] = t.model
        sections.append(("truth", table))
    if manifest.target is not None:
        g = manifest.target
        table = {"mesh": g.mesh} if g.mesh is not None else {"builtin": g.builtin}
        table.update(scale_m=float(g.scale), position_m=[float(v) for v in g.position],
                     rotation_deg=[_degrees(a) for a in g.rotation])
        sections.append(("target", table))
    rig = manifest.rig
    rig_table = {"reference_view": rig.views[rig.reference].name}
    if manifest.known_pose is not None:
        rig_table.update(depth_m=float(manifest.known_pose.depth), tilt_deg=_degrees(manifest.known_pose.tilt))
    sections.append(("rig", rig_table))
    for view in rig.views:
        table = {"name": view.name}
        if view.image is not None:
            table["image"] = view.image
        table.update(position_m=[float(v) for v in view.position], heading_deg=_degrees(view.heading),
                     roll_deg=_degrees(view.roll), depth_offset_m=float(view.depth_offset),
                     tilt_offset_deg=_degrees(view.tilt_offset), optimize=bool(view.optimize))
        sections.append(("[views]", table))
    lines = [_HEADER.rstrip("\n")]
    for name, table in sections:
        lines += ["", f"[{name}]"]
        lines += [f"{key} = {_toml_value(value)}" for key, value in table.items()]
    return "\n".join(lines) + "\n"


def save_scene(manifest: Manifest, path) -> Path:
    """Write ``manifest`` as a scene file (target and truth, no images), atomically.

    The mesh of a mesh target is not checked here (``load_scene`` checks it)."""
    path = Path(path)
    _check_scene(manifest, path)
    if path.is_file() and not _is_scene_file(path):
        raise InputError("exists and is not a scene file (no [target] table); choose another file", file=path)
    text = manifest_to_toml(manifest)
    parse_manifest(tomllib.loads(text), file=path)  # every field validated as a reader will
    return write_text(path, text)


def _is_scene_file(path: Path) -> bool:
    """Whether ``path`` is TOML with a ``[target]`` table (a scene file, which ``save_scene``
    may replace; a dataset's manifest or any other file it must not)."""
    try:
        return isinstance(tomllib.loads(path.read_text(encoding="utf-8")).get("target"), dict)
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return False


def save_dataset(dataset: Dataset, folder, *, truth_layers: dict[str, dict[str, np.ndarray]] | None = None,
                 truth_mesh=None, marker: str = MANIFEST_NAME) -> Path:
    """Write ``dataset`` as a dataset folder, all or nothing.

    Everything is validated and encoded before anything is written; the folder appears whole
    (``fsswarp.atomic.output_folder``): an earlier dataset there (a folder holding ``marker``:
    ``simulate`` passes its truth model, so a simulation never replaces a recording) is
    replaced, any other non-empty folder is refused. ``truth_layers`` (view -> component -> image) go to
    ``truth/<view>_<component>.tiff``; ``truth_mesh`` (a trimesh.Trimesh) to ``truth/model.ply``,
    and the manifest's ``truth.model`` then names it. Without them, a dataset loaded from a
    folder keeps the truth layers and model found there. Both need a ``[truth]`` table.
    """
    folder = Path(folder)
    manifest = dataset.manifest
    manifest_path = folder / MANIFEST_NAME
    if not isinstance(manifest, Manifest):
        raise InputError("must be a Manifest", field="dataset.manifest", value=type(manifest).__name__)
    truth = manifest.truth
    if truth is None and (truth_layers or truth_mesh is not None):
        raise InputError("truth layers and a truth mesh need a [truth] table in the manifest",
                         file=manifest_path, field="truth")
    files: dict[str, bytes] = {}

    if truth_mesh is not None:
        files[TRUTH_MODEL] = _mesh_bytes(truth_mesh)
        manifest = replace(manifest, truth=replace(truth, model=TRUTH_MODEL))
    elif truth is not None and truth.model is not None:
        source = dataset.truth_model_path
        if source is None or not source.is_file():
            raise InputError("file not found; pass truth_mesh to save_dataset", file=manifest_path,
                             field="truth.model", value=truth.model)
        files[truth.model] = source.read_bytes()

    text = manifest_to_toml(manifest)
    parse_manifest(tomllib.loads(text), file=manifest_path)  # every field validated as a reader will

    sonar, names = manifest.sonar, manifest.rig.names
    tiffs: dict[str, np.ndarray] = {}  # file -> image, validated; all encoded at once below
    images = dataset.images
    if not isinstance(images, dict):
        raise InputError("must be a dict of view name -> image", field="dataset.images",
                         value=type(images).__name__)
    for name in images:
        if name not in names:
            raise InputError("no view of that name in the manifest", file=manifest_path,
                             field="images", value=name)
    for i, view in enumerate(manifest.rig.views):
        rel = image_file(view)
        if view.name not in images:
            raise InputError("no image for this view", file=folder / rel, field=f"views[{i}].image",
                             value=view.name)
        tiffs[rel] = sonar.check_image(images[view.name], file=folder / rel, field=f"images[{view.name!r}]")

    if truth_layers is None and truth is not None and dataset.root is not None:
        truth_layers = {view: {c: dataset.truth_layer(view, c) for c in COMPONENTS
                               if (dataset.root / _truth_layer_file(view, c)).is_file()}
                        for view in names}
    for view, layers in (truth_layers or {}).items():
        if view not in names:
            raise InputError("no view of that name in the manifest", file=manifest_path,
                             field="truth_layers", value=view)
        if not isinstance(layers, dict):
            raise InputError("must be a dict of component -> image", field=f"truth_layers[{view!r}]",
                             value=type(layers).__name__)
        for component, layer in layers.items():
            if component not in COMPONENTS:
                raise InputError(f"must be one of {', '.join(COMPONENTS)}",
                                 field=f"truth_layers[{view!r}]", value=component)
            rel = _truth_layer_file(view, component)
            tiffs[rel] = sonar.check_image(layer, file=folder / rel,
                                           field=f"truth_layers[{view!r}][{component!r}]")
    files.update(tiff_bytes(tiffs))
    files[MANIFEST_NAME] = text.encode("utf-8")

    with output_folder(folder, marker=marker) as tmp:
        for rel, data in files.items():
            target = tmp / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(data)
    return folder


# --- parsing helpers ---------------------------------------------------------------------

class _Table:
    """One TOML table being read: typed getters that raise InputError naming the field."""

    def __init__(self, value: Any, field: str, file, keys: tuple[str, ...]):
        self.field, self.file = field, file
        if not isinstance(value, dict):
            raise InputError("must be a table", file=file, field=field or "manifest", value=value)
        for key, item in value.items():
            if key not in keys:
                raise InputError(f"unknown key; expected one of: {', '.join(keys)}", file=file,
                                 field=self.path(key), value=item)
        self.items = value

    def path(self, key: str) -> str:
        return f"{self.field}.{key}" if self.field else key

    def error(self, key: str, message: str) -> InputError:
        return InputError(message, file=self.file, field=self.path(key), value=self.items[key])

    def _missing(self, key: str, default: Any) -> Any:
        if default is _REQUIRED:
            raise InputError("is required", file=self.file, field=self.path(key))
        return default

    def table(self, key: str, *, required: bool = True) -> dict | None:
        if key not in self.items:
            if required:
                raise InputError(f"is required (a [{self.path(key)}] table)", file=self.file,
                                 field=self.path(key))
            return None
        if not isinstance(self.items[key], dict):
            raise self.error(key, "must be a table")
        return self.items[key]

    def number(self, key: str, default: Any = _REQUIRED, *, unit: str = "m") -> float:
        if key not in self.items:
            return self._missing(key, default)
        value = self.items[key]
        if not is_number(value):
            raise self.error(key, f"must be a number ({unit})")
        try:
            value = float(value)
        except OverflowError:
            raise self.error(key, "is too large") from None
        if not math.isfinite(value):
            raise self.error(key, "must be finite")
        return value

    def angle(self, key: str, default: Any = _REQUIRED, *, limit: float | None = None,
              open_limit: bool = False) -> float:
        """A degree value, returned in radians; |value| <= limit (or < limit when open)."""
        if key not in self.items:
            return self._missing(key, default)
        value = self.number(key, unit="degrees")
        if limit is not None and (abs(value) >= limit if open_limit else abs(value) > limit):
            raise self.error(key, f"must lie in {'(' if open_limit else '['}-{limit:g}, {limit:g}"
                                  f"{')' if open_limit else ']'} degrees")
        return math.radians(value)

    def integer(self, key: str, default: Any = _REQUIRED) -> int:
        if key not in self.items:
            return self._missing(key, default)
        value = self.items[key]
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(key, "must be an integer")
        return value

    def string(self, key: str, default: Any = _REQUIRED) -> str:
        if key not in self.items:
            return self._missing(key, default)
        value = self.items[key]
        if not isinstance(value, str) or not value:
            raise self.error(key, "must be a non-empty string")
        return value

    def boolean(self, key: str, default: Any = _REQUIRED) -> bool:
        if key not in self.items:
            return self._missing(key, default)
        value = self.items[key]
        if not isinstance(value, bool):
            raise self.error(key, "must be true or false")
        return value

    def numbers(self, key: str, count: int | None = None, default: Any = _REQUIRED, *,
                unit: str = "m") -> list[float]:
        if key not in self.items:
            return self._missing(key, default)
        value = self.items[key]
        what = f"[{', '.join('xyz'[:count])}]" if count is not None and count <= 3 else "a list of numbers"
        if not isinstance(value, list) or (count is not None and len(value) != count):
            raise self.error(key, f"must be {what}" + (f" ({count} numbers, {unit})" if count else f" ({unit})"))
        if not all(is_number(v) for v in value):
            raise self.error(key, f"must hold numbers only ({unit})")
        try:
            out = [float(v) for v in value]
        except OverflowError:
            raise self.error(key, "holds a number too large") from None
        if not all(math.isfinite(v) for v in out):
            raise self.error(key, "must hold finite numbers only")
        return out


def _parse_sonar(table: dict, file) -> SonarSpec:
    t = _Table(table, "sonar", file, _SONAR_KEYS)
    beams, bins = t.integer("beams"), t.integer("bins")
    angles = None
    if "beam_angles_deg" in t.items:
        angles = np.array([math.radians(v) for v in t.numbers("beam_angles_deg", unit="degrees")],
                          dtype=np.float64)
    if "azimuth_fov_deg" in t.items or angles is None:
        azimuth = math.radians(t.number("azimuth_fov_deg", unit="degrees"))
    else:
        azimuth = float(angles[-1] - angles[0]) if angles.size else 0.0
    elevation = math.radians(t.number("elevation_fov_deg", unit="degrees"))
    range_min, range_max = t.number("range_min_m"), t.number("range_max_m")
    try:
        return SonarSpec(beams=beams, bins=bins, azimuth_fov=azimuth, elevation_fov=elevation,
                         range_min=range_min, range_max=range_max, beam_angles=angles)
    except InputError as err:
        raise err.with_file(file) from None


def _parse_surface(table: dict | None, file) -> SurfaceEstimate | None:
    if table is None:  # deep water: the [rig] table gives the known depth and tilt
        return None
    t = _Table(table, "surface", file, _SURFACE_KEYS)
    values = dict(depth=t.number("depth_m"), tilt=t.angle("tilt_deg", limit=90, open_limit=True),
                  depth_sigma=t.number("depth_sigma_m", 0.05),
                  tilt_sigma=t.angle("tilt_sigma_deg", math.radians(2.0)))
    try:
        return SurfaceEstimate(**values)
    except InputError as err:
        raise err.with_file(file) from None


def _parse_truth(table: dict | None, file, *, deep_water: bool) -> Truth | None:
    if table is None:
        return None
    t = _Table(table, "truth", file, _TRUTH_KEYS)
    if deep_water:  # the poses are known: a deep-water truth is its model alone
        for key in ("depth_m", "tilt_deg"):
            if key in t.items:
                raise t.error(key, "deep water (no [surface]): the depth and tilt are known ([rig] depth_m, "
                                   "tilt_deg); remove this key")
        values = dict(depth=None, tilt=None, model=t.string("model", None))
    else:
        values = dict(depth=t.number("depth_m"), tilt=t.angle("tilt_deg", limit=90, open_limit=True),
                      model=t.string("model", None))
    try:
        return Truth(**values)
    except InputError as err:
        raise err.with_file(file) from None


def _parse_target(table: dict | None, file) -> Target | None:
    if table is None:
        return None
    t = _Table(table, "target", file, _TARGET_KEYS)
    values = dict(mesh=t.string("mesh", None), builtin=t.string("builtin", None),
                  scale=t.number("scale_m", 1.0), position=tuple(t.numbers("position_m", 3)),
                  rotation=tuple(math.radians(v) for v in t.numbers("rotation_deg", 3, [0.0] * 3,
                                                                    unit="degrees")))
    try:
        return Target(**values)
    except InputError as err:
        raise err.with_file(file) from None


def _parse_views(top: _Table, file) -> tuple[View, ...]:
    if "views" not in top.items:
        raise InputError("is required (one [[views]] table per view)", file=file, field="views")
    raw = top.items["views"]
    if not isinstance(raw, list) or not all(isinstance(v, dict) for v in raw):
        raise top.error("views", "must be an array of tables ([[views]])")
    if not raw:
        raise top.error("views", "at least one view is required")
    views, names, images = [], {}, {}
    for i, item in enumerate(raw):
        t = _Table(item, f"views[{i}]", file, _VIEW_KEYS)
        name = t.string("name")
        if name in names:
            raise t.error("name", f"duplicate view name (also views[{names[name]}])")
        image = t.string("image", None)
        if image is not None:
            try:
                _check_inner_path(f"views[{i}].image", image, (".tif", ".tiff"))
            except InputError as err:
                raise err.with_file(file) from None
        values = dict(position=tuple(t.numbers("position_m", 2)),
                      heading=t.angle("heading_deg", limit=360), roll=t.angle("roll_deg", limit=180),
                      depth_offset=t.number("depth_offset_m", 0.0),
                      tilt_offset=t.angle("tilt_offset_deg", 0.0, limit=90, open_limit=True),
                      optimize=t.boolean("optimize", True))
        try:
            view = View(name=name, image=image, **values)
        except InputError as err:
            if err.field == "views.name":
                raise InputError(err.message, file=file, field=f"views[{i}].name", value=name) from None
            raise err.with_file(file) from None
        rel = str(PurePosixPath(image_file(view)))
        if rel in images:
            raise InputError(f"two views share this image file (also views[{images[rel]}])", file=file,
                             field=f"views[{i}].image", value=image_file(view))
        names[name], images[rel] = i, i
        views.append(view)
    return tuple(views)


def _parse_rig(table: dict | None, views: tuple[View, ...], file, *,
               deep_water: bool) -> tuple[Rig, KnownPose | None]:
    """The rig and, for deep water (no [surface]), the known depth and tilt of [rig]."""
    reference, known = 0, None
    t = _Table({} if table is None else table, "rig", file, _RIG_KEYS)
    name = t.string("reference_view", None)
    if name is not None:
        names = [v.name for v in views]
        if name not in names:
            shown = ", ".join(names[:6]) + (", ..." if len(names) > 6 else "")
            raise t.error("reference_view", f"no view of that name (views: {shown})")
        reference = names.index(name)
    if not deep_water:
        for key in ("depth_m", "tilt_deg"):
            if key in t.items:
                raise t.error(key, "only without a [surface] table (deep water); with one, the depth and tilt "
                                   "are [surface]'s")
    elif "depth_m" not in t.items and "tilt_deg" not in t.items:
        raise InputError("is required (a [surface] table); for deep water (no sea surface in view) give the "
                         "known [rig] depth_m and tilt_deg instead", file=file, field="surface")
    else:
        try:
            known = KnownPose(depth=t.number("depth_m"), tilt=t.angle("tilt_deg", limit=90, open_limit=True))
        except InputError as err:
            raise err.with_file(file) from None
    try:
        return Rig(views, reference=reference), known
    except InputError as err:
        raise err.with_file(file) from None


def _check_scene(manifest: Manifest, file) -> None:
    """The rules a scene file adds to a manifest."""
    if manifest.target is None:
        raise InputError("is required: a scene file needs a [target] table", file=file, field="target")
    if manifest.truth is None and not manifest.deep_water:
        raise InputError("is required: a scene file needs a [truth] table (true depth_m, tilt_deg)",
                         file=file, field="truth")
    if manifest.truth is not None and manifest.deep_water:
        raise InputError("a deep-water scene (no [surface]) places its sonar by [rig] depth_m and tilt_deg; "
                         "remove this table", file=file, field="truth")
    if manifest.truth is not None and manifest.truth.model is not None:
        raise InputError("a scene's true model is its target; remove this key", file=file,
                         field="truth.model", value=manifest.truth.model)
    for i, view in enumerate(manifest.rig.views):
        if view.image is not None:
            raise InputError("a scene file has no images; remove this key", file=file,
                             field=f"views[{i}].image", value=view.image)


# --- value checks ------------------------------------------------------------------------

def _check_depth(field: str, value: Any) -> None:
    check_number(field, value, lambda v: v > 0, "must be > 0 (the sonar lies below the surface)")


def _check_tilt(field: str, value: Any) -> None:
    check_number(field, value, lambda v: abs(v) < math.pi / 2, "must lie in (-90, 90) degrees",
                  degrees=True)


def _check_vector(field: str, value: Any, count: int, *, degrees: bool = False) -> None:
    if not isinstance(value, (tuple, list)) or len(value) != count:
        raise InputError(f"must hold {count} numbers", field=field, value=value)
    for v in value:
        check_number(field, v, lambda _: True, "", degrees=degrees)


def _check_inner_path(field: str, value: Any, suffixes: tuple[str, ...]) -> None:
    """A relative path that stays inside the dataset folder and ends in one of ``suffixes``."""
    if not isinstance(value, str) or not value:
        raise InputError("must be a non-empty relative path", field=field, value=value)
    path = PurePosixPath(value)
    if path.is_absolute() or "\\" in value or ":" in value or ".." in path.parts:
        raise InputError("must be a relative path inside the dataset folder (no '..')", field=field, value=value)
    if path.suffix.lower() not in suffixes:
        raise InputError(f"must end in {' or '.join(suffixes)}", field=field, value=value)


# --- files -------------------------------------------------------------------------------

def _truth_layer_file(view: str, component: str) -> str:
    return f"truth/{view}_{component}.tiff"


def _read_image(path: Path, sonar: SonarSpec, *, field: str) -> np.ndarray:
    """A TIFF image of one page, validated against ``sonar`` (InputError naming the file
    otherwise: a second page would be dropped unseen)."""
    try:
        with tifffile.TiffFile(path) as tiff:
            pages = len(tiff.pages)
            array = tiff.asarray() if pages == 1 else None
    except Exception as err:  # noqa: BLE001 - any failure to decode is a bad file
        raise InputError(f"not a readable TIFF image ({type(err).__name__}: {err})", file=path,
                         field=field) from None
    if array is None:
        raise InputError("must hold one image (one page), one view per file", file=path, field=field,
                         value=f"{pages} pages")
    array = np.asarray(array)
    if array.dtype.kind == "f" and array.dtype.itemsize == 4 and not array.dtype.isnative:
        array = array.astype(np.float32)
    return sonar.check_image(array, file=path, field=field)


def tiff_bytes(images: dict) -> dict:
    """{key: the image's zlib-compressed TIFF file (bytes)} of ``images`` ({key: 2-D array}),
    encoded on threads (zlib releases the GIL): a simulated dataset's 80 files took 0.48 s one
    after another on a GPU host, profiled (docs/decisions.md, "TIFF files are encoded on threads")."""
    def encode(array) -> bytes:
        buffer = io.BytesIO()
        tifffile.imwrite(buffer, np.ascontiguousarray(array), compression="zlib")
        return buffer.getvalue()

    return dict(zip(images, map_on_threads(encode, images.values(), name="fsswarp-tiff")))


def _mesh_bytes(mesh) -> bytes:
    import trimesh

    if not isinstance(mesh, trimesh.Trimesh):
        raise InputError("must be a trimesh.Trimesh", field="truth_mesh", value=type(mesh).__name__)
    if len(mesh.faces) == 0 or not np.all(np.isfinite(mesh.vertices)):
        raise InputError("must hold triangles with finite vertices", field="truth_mesh",
                         value=f"{len(mesh.vertices)} vertices, {len(mesh.faces)} faces")
    return mesh.export(file_type="ply")


# --- writing helpers ---------------------------------------------------------------------

def _degrees(radians: float) -> float:
    """The shortest degree value d with ``math.radians(d) == radians`` (near degrees(radians)),
    so that the file reads back to the same float; ``math.degrees`` where none exists."""
    radians = float(radians)
    guess = math.degrees(radians)
    if not math.isfinite(guess):
        return guess
    best = None
    below = above = guess
    candidates = [guess]
    for _ in range(16):
        below, above = math.nextafter(below, -math.inf), math.nextafter(above, math.inf)
        candidates += [below, above]
    for d in candidates:
        if math.radians(d) == radians:
            key = (len(repr(d)), abs(d - guess))
            if best is None or key < best[0]:
                best = (key, d)
    return guess if best is None else best[1]


def _toml_value(value: Any) -> str:
    """One TOML value: scalars as tomli_w writes them, number lists inline (wrapped)."""
    if isinstance(value, list):
        items = [_toml_value(v) for v in value]
        one_line = "[" + ", ".join(items) + "]"
        if len(one_line) <= 80:
            return one_line
        rows = [", ".join(items[i:i + 6]) for i in range(0, len(items), 6)]
        return "[\n    " + ",\n    ".join(rows) + ",\n]"
    return tomli_w.dumps({"v": value})[len("v = "):].rstrip("\n")
