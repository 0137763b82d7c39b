"""HoloOcean-style dataset folders, the layout NeuSIS and SonarSplat read: export and import.

The folder::

    Config.json        a HoloOcean scenario: ``agents[0].sensors[-1]`` is the ImagingSonar, whose
                       ``configuration`` holds Azimuth and Elevation (full angles, degrees), RangeMin
                       and RangeMax (m), RangeBins and AzimuthBins; and an ``fsswarp`` table with what
                       HoloOcean has no place for (view names, the surface, the truth, the scale)
    Data/000000.pkl    one per view, a pickled dict: ``ImagingSonar`` (RangeBins, AzimuthBins)
                       float32 in [0, 1] and ``PoseSensor`` (4, 4) float64 sensor-to-world
    gt.ply             the truth model in the world frame, where the dataset has one

Frames (docs/formats.md, "HoloOcean-style datasets", names the sources). HoloOcean's world is
right-handed with z up and its z = 0 the sea surface, as fsswarp's world is: the two are one
frame. Its sensor frame is x forward, y left, z up; fsswarp's sonar frame is +Y forward, +X
right, +Z up, so a PoseSensor rotation is ``R_world @ SENSOR_AXES``. Pixels: HoloOcean puts a
return at range R, azimuth θ = atan2(y, x) (positive to the left) into row ⌊(R − RangeMin)/ΔR⌋
and column ⌊(θ + Azimuth/2)/Δθ⌋, ΔR = (RangeMax − RangeMin)/RangeBins, Δθ = Azimuth/AzimuthBins;
NeuSIS reads row i at RangeMin + iΔR and column j at −Azimuth/2 + jΔθ. fsswarp's rows and
columns are the centres of those bins: RangeMin = range_min_m − δR/2, RangeMax = range_max_m +
δR/2, Azimuth = beams·δθ, and column j is fsswarp's column beams − 1 − j.
"""

from __future__ import annotations

import io
import json
import math
import pickle
import re
import tomllib
from pathlib import Path

import numpy as np

from .atomic import output_folder
from .dataset import (Dataset, KnownPose, Manifest, SurfaceEstimate, Truth, manifest_to_toml, parse_manifest,
                      read_mesh)
from .errors import InputError, is_finite_number, is_integer
from .rig import Rig, View, reference_to_world, world_to_reference
from .sonar import SonarSpec

#: The file that marks an exported folder (``fsswarp.atomic.output_folder`` replaces only such a folder).
CONFIG = "Config.json"
#: The truth model of an exported folder, in the world frame.
TRUTH_FILE = "gt.ply"
#: Columns: HoloOcean's sensor axes (x forward, y left, z up) in fsswarp's sonar frame.
SENSOR_AXES = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
#: The keys of the ``fsswarp`` table of Config.json, in the order they are written.
TABLE_KEYS = ("views", "reference_view", "poses_at", "surface", "truth", "intensity_scale", "azimuth_resampled")
#: What a pickle of Data/ may name: NumPy arrays, dtypes and scalars, and bytearray; nothing else runs.
_SAFE_GLOBALS = {("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype, ("builtins", "bytearray"): bytearray,
                 **{(module, name): value for module in ("numpy.core.multiarray", "numpy._core.multiarray")
                    for name, value in (("_reconstruct", np.zeros(1).__reduce__()[0]),
                                        ("scalar", np.float32(0).__reduce__()[0]))}}


# --- export ---------------------------------------------------------------------------------

def export_holoocean(dataset: Dataset, out) -> Path:
    """Write ``dataset`` as the HoloOcean-style folder ``out`` (module docstring), all or nothing.

    PoseSensor matrices are the views' world poses at the truth's depth and tilt where the
    manifest has them (simulated data), else at the measured D0 and β0, else (deep water) at
    the known ones. Images are divided by one factor, the largest value of any view, so they
    lie in [0, 1] and keep their ratios; a beam-angle table is resampled to uniform azimuth bins
    (:func:`uniform_azimuth`). An existing ``out`` is replaced only if it holds Config.json.
    """
    manifest, sonar = dataset.manifest, dataset.sonar
    depth, tilt, source = _poses_at(manifest)
    half_bin = 0.5 * sonar.range_step
    if sonar.range_min < half_bin:
        raise InputError(f"must be at least half a range bin ({half_bin:.6g} m): HoloOcean's RangeMin, the near edge "
                         "of the first bin, cannot be negative", file=dataset.root, field="sonar.range_min_m",
                         value=sonar.range_min)
    names = dataset.rig.names
    images = np.stack([np.asarray(dataset.images[name], np.float64) for name in names])
    centres = sonar.beam_centres if sonar.beam_angles is None else uniform_azimuth(sonar)
    if sonar.beam_angles is not None:
        images = np.stack([resample_beams(image, sonar.beam_angles, centres) for image in images])
    images = images[:, :, ::-1]  # HoloOcean's column 0 is the right-most beam
    peak = float(images.max())
    scale = peak if peak > 0 else 1.0
    step = float(centres[-1] - centres[0]) / (sonar.beams - 1)
    rotations, positions = dataset.rig.world_poses(depth, tilt)
    poses = np.zeros((len(names), 4, 4))
    poses[:, :3, :3], poses[:, :3, 3], poses[:, 3, 3] = rotations @ SENSOR_AXES, positions, 1.0
    files = [f"Data/{index:06d}.pkl" for index in range(len(names))]
    truth = manifest.truth
    config = {
        "name": dataset.root.name if dataset.root is not None else "fsswarp",
        "main_agent": "auv0",
        "agents": [{"agent_name": "auv0", "agent_type": "HoveringAUV", "sensors": [
            {"sensor_type": "PoseSensor", "socket": "SonarSocket"},
            {"sensor_type": "ImagingSonar", "socket": "SonarSocket", "configuration": {
                "Azimuth": math.degrees(sonar.beams * step), "Elevation": math.degrees(sonar.elevation_fov),
                "RangeMin": sonar.range_min - half_bin, "RangeMax": sonar.range_max + half_bin,
                "RangeBins": sonar.bins, "AzimuthBins": sonar.beams}}]}],
        "fsswarp": dict(zip(TABLE_KEYS, (
            [{"name": v.name, "file": file, "optimize": v.optimize} for v, file in zip(dataset.rig.views, files)],
            names[dataset.rig.reference],
            {"depth_m": depth, "tilt_deg": math.degrees(tilt), "source": source},
            None if manifest.surface is None else {
                "depth_m": manifest.surface.depth, "tilt_deg": math.degrees(manifest.surface.tilt),
                "depth_sigma_m": manifest.surface.depth_sigma,
                "tilt_sigma_deg": math.degrees(manifest.surface.tilt_sigma)},
            None if truth is None or truth.depth is None else {"depth_m": truth.depth,
                                                                "tilt_deg": math.degrees(truth.tilt)},
            scale, sonar.beam_angles is not None))),
    }
    mesh = dataset.truth_mesh()
    with output_folder(out, marker=CONFIG) as tmp:
        (tmp / "Data").mkdir()
        for file, image, pose in zip(files, images, poses):
            (tmp / file).write_bytes(_pickle({"ImagingSonar": (image / scale).astype(np.float32),
                                              "PoseSensor": pose}))
        if mesh is not None:
            mesh.vertices = reference_to_world(mesh.vertices, dataset.rig, depth, tilt)
            (tmp / TRUTH_FILE).write_bytes(mesh.export(file_type="ply"))
        (tmp / CONFIG).write_text(json.dumps(config, indent=2) + "\n")
    return Path(out)


def uniform_azimuth(sonar: SonarSpec) -> np.ndarray:
    """(beams,) uniform beam centres (rad) replacing a beam-angle table: symmetric about 0, the
    outer ones at ±max(|first|, |last|) of the table."""
    edge = float(np.max(np.abs(sonar.beam_centres[[0, -1]])))
    return np.linspace(-edge, edge, sonar.beams)


def resample_beams(image, angles, centres) -> np.ndarray:
    """A (bins, beams) image whose columns sit at the increasing azimuths ``angles`` (rad),
    resampled to the columns ``centres``: linear between the two nearest beams, the outer beam's
    value up to half its spacing beyond it, 0 farther out (no beam saw there). Returns
    (bins, len(centres)) float64."""
    image, angles, centres = np.asarray(image, np.float64), np.asarray(angles, np.float64), np.asarray(centres)
    out = np.stack([np.interp(centres, angles, row) for row in image])
    reach = (angles[0] - 0.5 * (angles[1] - angles[0]), angles[-1] + 0.5 * (angles[-1] - angles[-2]))
    out[:, (centres < reach[0]) | (centres > reach[1])] = 0.0
    return out


def _poses_at(manifest: Manifest) -> tuple[float, float, str]:
    """(D m, β rad, source) the PoseSensor matrices are written at."""
    truth = manifest.truth
    if truth is not None and truth.depth is not None:
        return truth.depth, truth.tilt, "truth"
    if manifest.surface is not None:
        return manifest.surface.depth, manifest.surface.tilt, "measured"
    return manifest.known_pose.depth, manifest.known_pose.tilt, "known"


def _pickle(record: dict) -> bytes:
    """``record`` pickled (protocol 4, Python 3.4 on) with every array as ``numpy.ndarray(shape,
    dtype, bytearray)``: NumPy 1 and 2 both read it (NumPy 2's own pickles name ``numpy._core``,
    which NumPy before 1.26 lacks), and the array comes back writable."""
    buffer = io.BytesIO()
    _ArrayPickler(buffer, protocol=4).dump(record)
    return buffer.getvalue()


class _ArrayPickler(pickle.Pickler):
    def reducer_override(self, obj):
        if type(obj) is np.ndarray:
            array = np.ascontiguousarray(obj)
            return np.ndarray, (array.shape, array.dtype.str, bytearray(array.tobytes()))
        return NotImplemented


# --- import ---------------------------------------------------------------------------------

def is_holoocean_folder(path) -> bool:
    """Whether ``path`` is a folder holding Config.json and Data/."""
    path = Path(path)
    return path.is_dir() and (path / CONFIG).is_file() and (path / "Data").is_dir()


def holoocean_dataset(folder) -> tuple[Dataset, object, dict]:
    """The HoloOcean-style folder ``folder`` as ``(dataset, truth mesh or None, record)``, every
    file validated (InputError naming the file, field and value), nothing written.

    Views: one per ``Data/*.pkl`` in name order (numbers by value). With Config.json's
    ``fsswarp`` table (an export) the view names, surface, truth, held-out views and intensity
    scale come back; without it the dataset is deep water (no [surface]) named after the files,
    its known depth and tilt the first view's. PoseSensor matrices become positions, headings,
    tilts and rolls about the shared depth and tilt (DESIGN §2); ``gt.ply`` (world frame) becomes
    the truth model (reference frame). ``record``: the provenance, docs/formats.md's keys.
    """
    folder = Path(folder)
    if not is_holoocean_folder(folder):
        raise InputError(f"not a HoloOcean-style folder: it needs {CONFIG} and Data/", file=folder)
    config_path = folder / CONFIG
    config = _read_json(config_path)
    settings, index = _sonar_settings(config, config_path)
    files = sorted(folder.glob("Data/*.pkl"), key=lambda p: [int(t) if t.isdigit() else t
                                                              for t in re.split(r"(\d+)", p.name)])
    if not files:
        raise InputError("holds no .pkl files", file=folder / "Data")
    table = _table(config, config_path, len(files))
    images, poses = [], []
    for path in files:
        image, pose = _read_view(path, settings)
        images.append(image)
        poses.append(pose)
    shapes = {image.shape for image in images}
    if len(shapes) > 1:
        raise InputError(f"images differ in shape: {sorted(shapes)}", file=folder / "Data", field="ImagingSonar")
    bins, beams = images[0].shape
    sonar = _sonar(settings, bins, beams, config_path, index)
    rotations = np.stack([pose[:3, :3] @ SENSOR_AXES.T for pose in poses])
    positions = np.stack([pose[:3, 3] for pose in poses])
    for path, z in zip(files, positions[:, 2]):
        if not z < 0:
            raise InputError("puts the sonar at or above the sea surface (HoloOcean's z = 0): z must be < 0",
                             file=path, field="PoseSensor[2][3]", value=float(z))
    tilts = np.arctan2(rotations[:, 2, 1], np.hypot(rotations[:, 0, 1], rotations[:, 1, 1]))
    headings = np.arctan2(-rotations[:, 0, 1], rotations[:, 1, 1])
    rolls = np.arctan2(-rotations[:, 2, 0], rotations[:, 2, 2])
    if table is None:
        at = {"depth_m": float(-positions[0, 2]), "tilt_deg": math.degrees(tilts[0]),
              "source": f"the PoseSensor of {files[0].name}"}
        names, optimize, reference, scale = [p.stem for p in files], [True] * len(files), 0, 1.0
    else:
        at = table["poses_at"]
        names, optimize = [v["name"] for v in table["views"]], [v["optimize"] for v in table["views"]]
        reference, scale = names.index(table["reference_view"]), table["intensity_scale"]
    depth, tilt = at["depth_m"], math.radians(at["tilt_deg"])
    views = []
    for i, path in enumerate(files):
        offset = float(tilts[i] - tilt)
        if not abs(offset) < math.pi / 2:
            raise InputError(f"tilts the sonar {math.degrees(offset):.4g} deg from the first view's; fsswarp's rig "
                             "takes tilts within 90 deg of each other", file=path, field="PoseSensor",
                             value=f"tilt {math.degrees(tilts[i]):.4g} deg")
        try:
            views.append(View(names[i], position=(float(positions[i, 0]), float(positions[i, 1])),
                              heading=float(headings[i]), roll=float(rolls[i]),
                              depth_offset=float(-positions[i, 2] - depth), tilt_offset=offset, optimize=optimize[i]))
        except InputError as err:
            raise InputError(err.message, file=path, field="name", value=names[i]) from None
    mesh = read_mesh(folder / TRUTH_FILE, field=TRUTH_FILE) if (folder / TRUTH_FILE).is_file() else None
    surface = table["surface"] if table is not None else None
    rig = Rig(tuple(views), reference=reference)
    if mesh is not None:
        mesh.vertices = world_to_reference(mesh.vertices, rig, depth, tilt)
    truth = _truth(surface, None if table is None else table["truth"], mesh is not None, depth, tilt)
    try:
        manifest = Manifest(sonar=sonar, surface=None if surface is None else SurfaceEstimate(
            depth=surface["depth_m"], tilt=math.radians(surface["tilt_deg"]), depth_sigma=surface["depth_sigma_m"],
            tilt_sigma=math.radians(surface["tilt_sigma_deg"])), rig=rig, truth=truth,
            known_pose=KnownPose(depth=depth, tilt=tilt) if surface is None else None)
        parse_manifest(tomllib.loads(manifest_to_toml(manifest)), file=None)  # as a reader of the dataset will
    except (InputError, KeyError, TypeError) as err:
        raise InputError(f"cannot make a dataset of it: {err}", file=config_path, field="fsswarp") from None
    data = {name: (image[:, ::-1] * scale).astype(np.float32) for name, image in zip(names, images)}
    record = {"config": settings, "sensor_index": index, "files": [f"Data/{p.name}" for p in files],
              "views": names, "fsswarp_table": table is not None, "poses_at": at, "intensity_scale": scale,
              "truth_model": TRUTH_FILE if mesh is not None else None, "deep_water": surface is None}
    return Dataset(manifest, data), mesh, record


def _truth(surface, truth, has_mesh: bool, depth: float, tilt: float) -> Truth | None:
    """The imported [truth]: deep water, the model alone; with a surface, the table's truth, or
    the poses' (D, β) for a model without one (HoloOcean's PoseSensor is the true pose)."""
    model = "truth/model.ply" if has_mesh else None
    if surface is None:
        return Truth(depth=None, tilt=None, model=model) if has_mesh else None
    if truth is not None:
        return Truth(depth=truth["depth_m"], tilt=math.radians(truth["tilt_deg"]), model=model)
    return Truth(depth=depth, tilt=tilt, model=model) if has_mesh else None


def _read_json(path: Path) -> dict:
    try:
        value = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"cannot read the file ({err})", file=path) from None
    except json.JSONDecodeError as err:
        raise InputError(f"not valid JSON: {err}", file=path) from None
    if not isinstance(value, dict):
        raise InputError("must hold a JSON object", file=path)
    return value


def _sonar_settings(config: dict, path: Path) -> tuple[dict, int]:
    """The ImagingSonar ``configuration`` of the first agent (the last such sensor, as NeuSIS
    reads it) and the sensor's index."""
    try:
        sensors = config["agents"][0]["sensors"]
        found = [i for i, s in enumerate(sensors) if isinstance(s, dict) and s.get("sensor_type") == "ImagingSonar"]
    except (KeyError, IndexError, TypeError):
        raise InputError("must list the sensors of an agent", file=path, field="agents[0].sensors") from None
    if not found:
        raise InputError("holds no sensor of sensor_type ImagingSonar", file=path, field="agents[0].sensors")
    index = found[-1]
    settings = sensors[index].get("configuration")
    field = f"agents[0].sensors[{index}].configuration"
    if not isinstance(settings, dict):
        raise InputError("must be an object", file=path, field=field, value=settings)
    for key in ("Azimuth", "Elevation", "RangeMin", "RangeMax"):
        if not is_finite_number(settings.get(key)):
            raise InputError("is required: a finite number", file=path, field=f"{field}.{key}",
                             value=settings.get(key))
    for key in ("RangeBins", "AzimuthBins"):
        if key in settings and not (is_integer(settings[key]) and settings[key] >= 2):
            raise InputError("must be an integer >= 2", file=path, field=f"{field}.{key}", value=settings[key])
    return settings, index


def _sonar(settings: dict, bins: int, beams: int, path: Path, index: int) -> SonarSpec:
    """fsswarp's sonar for HoloOcean's bins (module docstring): rows and columns at bin centres."""
    field = f"agents[0].sensors[{index}].configuration"
    for key, count in (("RangeBins", bins), ("AzimuthBins", beams)):
        if settings.get(key, count) != count:
            raise InputError(f"disagrees with the images, which have {count}", file=path, field=f"{field}.{key}",
                             value=settings[key])
    azimuth, rng = settings["Azimuth"], (settings["RangeMin"], settings["RangeMax"])
    for key in ("Azimuth", "Elevation"):
        if not 0 < settings[key] < 180:
            raise InputError("must be a full aperture in (0, 180) degrees", file=path, field=f"{field}.{key}",
                             value=settings[key])
    if not 0 <= rng[0] < rng[1]:
        raise InputError(f"must be >= 0 and below RangeMax = {rng[1]:g}", file=path, field=f"{field}.RangeMin",
                         value=rng[0])
    half_bin = 0.5 * (rng[1] - rng[0]) / bins
    try:
        return SonarSpec(beams=beams, bins=bins, azimuth_fov=math.radians(azimuth * (beams - 1) / beams),
                         elevation_fov=math.radians(settings["Elevation"]), range_min=rng[0] + half_bin,
                         range_max=rng[1] - half_bin)
    except InputError as err:
        raise InputError(err.message, file=path, field=field, value=err.value) from None


def _table(config: dict, path: Path, count: int) -> dict | None:
    """Config.json's ``fsswarp`` table, checked against ``count`` pkl files; None without one."""
    table = config.get("fsswarp")
    if table is None:
        return None
    if not isinstance(table, dict) or set(table) != set(TABLE_KEYS):
        raise InputError(f"must be an object of the keys {', '.join(TABLE_KEYS)}", file=path, field="fsswarp")
    views = table["views"]
    if not (isinstance(views, list) and len(views) == count and all(isinstance(v, dict) for v in views)):
        raise InputError(f"must list one view per pkl file ({count})", file=path, field="fsswarp.views")
    names = [v.get("name") for v in views]
    if not all(isinstance(v.get("optimize"), bool) for v in views):
        raise InputError("must give every view an optimize of true or false", file=path, field="fsswarp.views")
    if table["reference_view"] not in names:
        raise InputError("names no view", file=path, field="fsswarp.reference_view", value=table["reference_view"])
    at, scale = table["poses_at"], table["intensity_scale"]
    if not (isinstance(at, dict) and all(is_finite_number(at.get(k)) for k in ("depth_m", "tilt_deg"))):
        raise InputError("must hold depth_m and tilt_deg", file=path, field="fsswarp.poses_at", value=at)
    if not (is_finite_number(scale) and scale > 0):
        raise InputError("must be a number > 0", file=path, field="fsswarp.intensity_scale", value=scale)
    return table


def _read_view(path: Path, settings: dict) -> tuple[np.ndarray, np.ndarray]:
    """(image (bins, beams) float64 >= 0, pose (4, 4) float64) of one pkl file, validated."""
    try:
        with open(path, "rb") as handle:
            record = _SafeUnpickler(handle).load()
    except InputError as err:
        raise err.with_file(path) from None
    except Exception as err:  # noqa: BLE001 - any failure to decode is a bad file
        raise InputError(f"not a readable pickle ({type(err).__name__}: {err})", file=path) from None
    if not isinstance(record, dict) or not {"ImagingSonar", "PoseSensor"} <= set(record):
        raise InputError("must hold a dict with ImagingSonar and PoseSensor", file=path)
    image = np.asarray(record["ImagingSonar"])
    if image.ndim != 2 or image.dtype.kind not in "fiu" or min(image.shape) < 2:
        raise InputError("must be a 2-D array of numbers (range bins, azimuth bins)", file=path, field="ImagingSonar",
                         value=f"{image.dtype} {image.shape}")
    image = image.astype(np.float64)
    if not np.all(np.isfinite(image)) or image.min() < 0:
        raise InputError("must hold finite values >= 0", file=path, field="ImagingSonar",
                         value=f"min {np.nanmin(image):g}, {int((~np.isfinite(image)).sum())} not finite")
    pose = np.asarray(record["PoseSensor"])
    if pose.shape != (4, 4) or pose.dtype.kind not in "fiu" or not np.all(np.isfinite(pose)):
        raise InputError("must be a finite 4 x 4 matrix", file=path, field="PoseSensor", value=f"{pose.dtype} {pose.shape}")
    pose = pose.astype(np.float64)
    rotation = pose[:3, :3]
    if (not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-5) or np.linalg.det(rotation) <= 0
            or not np.allclose(pose[3], (0.0, 0.0, 0.0, 1.0))):
        raise InputError("must be [R, p; 0 0 0 1] with R a rotation (orthonormal, determinant 1)", file=path,
                         field="PoseSensor", value=np.round(pose, 4).tolist())
    return image, pose


class _SafeUnpickler(pickle.Unpickler):
    """An unpickler that builds NumPy arrays and plain containers and runs nothing else: a pkl
    file from elsewhere cannot execute code."""

    def find_class(self, module: str, name: str):
        if (module, name) not in _SAFE_GLOBALS:
            raise InputError(f"names {module}.{name}, which a HoloOcean data file does not need (only NumPy arrays "
                             "are read)", field="pickle")
        return _SAFE_GLOBALS[(module, name)]
