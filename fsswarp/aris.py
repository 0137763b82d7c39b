"""Sound Metrics ARIS recordings (.aris) as fsswarp beam-bin images and datasets.

:func:`open_aris` memory-maps a recording (``.frame_count``, ``.frame_header(i)``,
``.frame_image(i)``: (bins, beams) float32, ``.sonar_spec(elevation_fov_deg=...)``);
:func:`import_aris` writes selected frames as a dataset folder with ``aris.json`` (source and
sensor values); :func:`read_poses` reads the CSV pose file (``frame,x_m,y_m,heading_deg,
roll_deg[,depth_offset_m,tilt_offset_deg]``).

File layout (Sound Metrics' ARIS file SDK): a 1024-byte file header, then frames of a
1024-byte frame header and ``BeamCount × SamplesPerBeam`` uint8 samples stored [sample][beam];
both headers start with the version word 0x05464444. Frames are counted from the file size; a
partial last frame is skipped with an :class:`ArisWarning`. Every size is checked against the
file size before anything is read.

Conventions of the images (DESIGN §2): column b holds ARIS beam N−1−b, so θ_b =
−centre[N−1−b] of the SDK's beam-angle table (``fsswarp/data/aris/``); a sample s (0–255) is
s·80/255 dB and the image holds the linear amplitude ``10^((dB − 80)/20)`` in [1e-4, 1] (the
inverse of ``fsswarp.rendering.log_compress(image, dynamic_range_db=80, peak=1)``); row B lies
at ``WindowStart + B·SampleLength`` (m) computed from SampleStartDelay, SamplePeriod (µs) and
SoundSpeed (m/s); the azimuth field of view is the span of the beam centres (deg). The elevation
aperture is not in the file: default 14°. docs/formats.md describes the import in full.
"""

from __future__ import annotations

import csv
import json
import math
import mmap
import re
import struct
import tomllib
import warnings
from dataclasses import dataclass, field, fields
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Iterable

import numpy as np

from .atomic import check_output_folder, json_number, output_folder, write_text
from .dataset import (Dataset, Manifest, SurfaceEstimate, load_dataset, manifest_to_toml, parse_manifest,
                      save_dataset)
from .errors import InputError, is_finite_number, is_integer, is_number
from .rig import Rig, View
from .sonar import SonarSpec

FILE_HEADER_BYTES = 1024
FRAME_HEADER_BYTES = 1024
#: The version word ("DDF" + 5) that starts the file header and every frame header.
SIGNATURE = 0x05464444
#: Samples 0..255 span 0..FULL_SCALE_DB decibels.
FULL_SCALE_DB = 80.0
#: Full elevation aperture used when none is given (deg): ARIS 1200/1800/3000 standard lenses;
#: also used for the telephoto lens, whose figure could not be confirmed.
DEFAULT_ELEVATION_FOV_DEG = 14.0
SYSTEM_NAMES = {0: "ARIS 1800", 1: "ARIS 3000", 2: "ARIS 1200"}
#: The import's record in the dataset folder; it marks a folder that a new import may replace.
ARIS_RECORD = "aris.json"

_BEAMS_BY_PING_MODE = {**dict.fromkeys((1, 2), 48), **dict.fromkeys((3, 4, 5), 96),
                       **dict.fromkeys((6, 7, 8), 64), **dict.fromkeys((9, 10, 11, 12), 128)}
# (telephoto, system type, beams) -> beam-angle table (fsswarp/data/aris/beam-angles-<name>.csv)
_TABLES = {
    (False, 0, 48): "ARIS1800_1200_48", (False, 2, 48): "ARIS1800_1200_48",
    (False, 0, 96): "ARIS1800_96", (False, 1, 64): "ARIS3000_64", (False, 1, 128): "ARIS3000_128",
    (True, 0, 48): "ARIS_Telephoto_48", (True, 2, 48): "ARIS_Telephoto_48",
    (True, 0, 96): "ARIS_Telephoto_96",
}
# linear amplitude of each sample value: 10^((s·80/255 − 80)/20)
_AMPLITUDE = np.power(10.0, (np.arange(256) * (FULL_SCALE_DB / 255.0) - FULL_SCALE_DB) / 20.0).astype(np.float32)


class ArisWarning(UserWarning):
    """A recording that can be read but is not quite whole (e.g. a partial last frame)."""


def header_field(fmt: str, offset: int, source: str):
    """A header dataclass field: struct format ``fmt`` at byte ``offset``; ``source`` is its name
    in the format's documents (used in error messages). ARIS and DIDSON headers use it."""
    return field(metadata={"at": (fmt, offset), "source": source})


@dataclass(frozen=True)
class FileHeader:
    """The file header fields fsswarp reads (the others are legacy DIDSON fields)."""

    version: int = header_field("I", 0, "Version")
    frame_count_stored: int = header_field("I", 4, "FrameCount")
    num_raw_beams: int = header_field("I", 16, "NumRawBeams")
    samples_per_channel: int = header_field("I", 24, "SamplesPerChannel")
    serial_number: int = header_field("I", 44, "SN")


@dataclass(frozen=True)
class FrameHeader:
    """One frame header's fields (SDK names in snake case, units in the suffix).

    ``window_*_stored`` are the floats the sonar stored; the ``window_start_m`` and
    ``window_length_m`` properties are computed from the timing fields (prefer those)."""

    frame_index: int = header_field("I", 0, "FrameIndex")
    frame_time_us: int = header_field("Q", 4, "FrameTime")
    version: int = header_field("I", 12, "Version")
    window_start_m_stored: float = header_field("f", 52, "WindowStart")
    window_length_m_stored: float = header_field("f", 56, "WindowLength")
    receiver_gain_db: int = header_field("I", 68, "ReceiverGain")
    depth_m: float = header_field("f", 128, "Depth")
    pitch_deg: float = header_field("f", 136, "Pitch")
    roll_deg: float = header_field("f", 144, "Roll")
    heading_deg: float = header_field("f", 152, "Heading")
    compass_heading_deg: float = header_field("f", 160, "CompassHeading")
    compass_pitch_deg: float = header_field("f", 164, "CompassPitch")
    compass_roll_deg: float = header_field("f", 168, "CompassRoll")
    latitude_deg: float = header_field("d", 172, "Latitude")
    longitude_deg: float = header_field("d", 180, "Longitude")
    water_temp_c: float = header_field("f", 224, "WaterTemp")
    sonar_x: float = header_field("f", 232, "SonarX")
    sonar_y: float = header_field("f", 236, "SonarY")
    sonar_z: float = header_field("f", 240, "SonarZ")
    sonar_pan: float = header_field("f", 244, "SonarPan")
    sonar_tilt: float = header_field("f", 248, "SonarTilt")
    sonar_roll: float = header_field("f", 252, "SonarRoll")
    ping_mode: int = header_field("I", 436, "PingMode")
    frequency_hi_low: int = header_field("I", 440, "FrequencyHiLow")
    pulse_width_us: int = header_field("I", 444, "PulseWidth")
    sample_period_us: int = header_field("I", 452, "SamplePeriod")
    frame_rate_hz: float = header_field("f", 460, "FrameRate")
    sound_speed_m_s: float = header_field("f", 464, "SoundSpeed")
    samples_per_beam: int = header_field("I", 468, "SamplesPerBeam")
    sample_start_delay_us: int = header_field("I", 476, "SampleStartDelay")
    large_lens: int = header_field("I", 480, "LargeLens")
    system_type: int = header_field("I", 484, "TheSystemType")
    serial_number: int = header_field("I", 488, "SonarSerialNumber")
    reordered_samples: int = header_field("I", 516, "ReorderedSamples")
    salinity: int = header_field("I", 520, "Salinity")

    @property
    def sample_length_m(self) -> float:
        """Range step between samples: SamplePeriod·1e-6·SoundSpeed/2 (m)."""
        return self.sample_period_us * 1e-6 * self.sound_speed_m_s / 2

    @property
    def window_start_m(self) -> float:
        """Range of the first sample: SampleStartDelay·1e-6·SoundSpeed/2 (m)."""
        return self.sample_start_delay_us * 1e-6 * self.sound_speed_m_s / 2

    @property
    def window_length_m(self) -> float:
        """SamplesPerBeam·SampleLength (m)."""
        return self.samples_per_beam * self.sample_length_m

    @property
    def last_sample_range_m(self) -> float:
        """Range of the last sample (m): the sonar spec's range_max."""
        return self.window_start_m + (self.samples_per_beam - 1) * self.sample_length_m


def parse_header(cls, buffer, offset: int = 0, skip=()):
    """The header dataclass ``cls`` read little-endian from ``buffer`` at ``offset``; the fields
    named in ``skip`` are None."""
    return cls(**{f.name: None if f.name in skip else
                  struct.unpack_from("<" + f.metadata["at"][0], buffer, offset + f.metadata["at"][1])[0]
                  for f in fields(cls)})


def header_name(cls, name: str) -> str:
    """The documents' name of the field ``name`` of the header dataclass ``cls``."""
    return next(f.metadata["source"] for f in fields(cls) if f.name == name)


@dataclass(frozen=True)
class BeamTable:
    """A lens's per-beam angles (deg) in fsswarp's column order (left to right, θ increasing).

    centre, left, right : (beams,) arrays; name : the SDK table's name."""

    name: str
    centre: np.ndarray
    left: np.ndarray
    right: np.ndarray

    @property
    def aperture_deg(self) -> float:
        """Edge-to-edge azimuth aperture (deg)."""
        return float(self.right[-1] - self.left[0])


@cache
def beam_table(name: str) -> BeamTable:
    """The packaged SDK table ``name`` (e.g. "ARIS_Telephoto_48"), reversed and negated into
    fsswarp's order: column b is ARIS beam N−1−b, θ_b = −centre[N−1−b]."""
    source = resources.files("fsswarp") / "data" / "aris" / f"beam-angles-{name}.csv"
    with source.open("r", encoding="utf-8") as handle:
        rows = list(csv.DictReader(handle))
    beams = np.array([int(r["beam"]) for r in rows])
    centre, left, right = (np.array([float(r[k]) for r in rows]) for k in ("center_deg", "left_deg", "right_deg"))
    if not np.array_equal(beams, np.arange(len(rows))) or np.any(np.diff(centre) <= 0):
        raise ValueError(f"packaged beam-angle table {name} is corrupt")  # an installation fault
    table = BeamTable(name, -centre[::-1], -right[::-1], -left[::-1])
    for array in (table.centre, table.left, table.right):
        array.setflags(write=False)
    return table


def linear_intensity(samples: np.ndarray) -> np.ndarray:
    """uint8 samples (any shape) as float32 linear amplitude 10^((s·80/255 − 80)/20)."""
    return _AMPLITUDE[np.asarray(samples, dtype=np.uint8)]


class ArisFile:
    """An open .aris recording; frames are read on demand. Use as a context manager.

    Frame geometry (beams, samples per beam) comes from frame 0 and must hold for every frame."""

    def __init__(self, path):
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError("no such file" if not self.path.exists() else "is not a file", file=self.path)
        try:
            with open(self.path, "rb") as handle:
                size = handle.seek(0, 2)
                if size < FILE_HEADER_BYTES + FRAME_HEADER_BYTES:
                    raise InputError(f"too short for an ARIS recording ({size} bytes; the file and frame "
                                     f"headers alone take {FILE_HEADER_BYTES + FRAME_HEADER_BYTES})",
                                     file=self.path, field="size", value=size)
                self._map = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)
        except OSError as err:
            raise InputError(f"cannot read the file ({err.strerror or err})", file=self.path) from None
        self.size = len(self._map)
        try:
            self._open()
        except BaseException:
            self.close()
            raise

    def _open(self) -> None:
        self.file_header = parse_header(FileHeader, self._map[:FILE_HEADER_BYTES])
        self._check_version(self.file_header.version, "header.Version")
        first = parse_header(FrameHeader, self._map[FILE_HEADER_BYTES:FILE_HEADER_BYTES + FRAME_HEADER_BYTES])
        self._check_version(first.version, "frames[0].Version")
        if first.ping_mode not in _BEAMS_BY_PING_MODE:
            raise self._error(0, first, "ping_mode", "must be 1-12 (it sets the beam count)")
        if first.samples_per_beam < 2:
            raise self._error(0, first, "samples_per_beam", "must be >= 2")
        #: beams and samples per beam of every frame
        self.beams = _BEAMS_BY_PING_MODE[first.ping_mode]
        self.samples_per_beam = first.samples_per_beam
        data = self.beams * self.samples_per_beam
        if FILE_HEADER_BYTES + FRAME_HEADER_BYTES + data > self.size:
            raise self._error(0, first, "samples_per_beam",
                              f"a frame of {self.beams} beams x {self.samples_per_beam} samples needs "
                              f"{FRAME_HEADER_BYTES + data} bytes but the file holds {self.size - FILE_HEADER_BYTES} "
                              "after its header")
        #: bytes per frame: header and samples
        self.frame_bytes = FRAME_HEADER_BYTES + data
        #: complete frames in the file (from its size, not the header's FrameCount)
        self.frame_count, rest = divmod(self.size - FILE_HEADER_BYTES, self.frame_bytes)
        if rest:
            warnings.warn(ArisWarning(f"{self.path}: ignoring a partial frame at the end ({rest} of "
                                      f"{self.frame_bytes} bytes); {self.frame_count} whole frames"), stacklevel=3)

    def close(self) -> None:
        self._map.close()

    def __enter__(self) -> "ArisFile":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- frames ------------------------------------------------------------------------------
    def _offset(self, frame: int) -> int:
        return FILE_HEADER_BYTES + frame * self.frame_bytes

    def _index(self, frame) -> int:
        if not is_integer(frame) or not 0 <= frame < self.frame_count:
            raise InputError(f"no such frame: the file holds {self.frame_count} (0-{self.frame_count - 1})",
                             file=self.path, field="frame", value=frame)
        return int(frame)

    def frame_header(self, frame: int) -> FrameHeader:
        """The header of frame ``frame`` (0-based position in the file), checked: its version
        word, and a beam count and sample count equal to frame 0's."""
        i = self._index(frame)
        start = self._offset(i)
        header = parse_header(FrameHeader, self._map[start:start + FRAME_HEADER_BYTES])
        self._check_version(header.version, f"frames[{i}].Version")
        if _BEAMS_BY_PING_MODE.get(header.ping_mode) != self.beams:
            raise self._error(i, header, "ping_mode", f"changes the beam count (frame 0: {self.beams} beams); "
                                                      "import such frames from a file of their own")
        if header.samples_per_beam != self.samples_per_beam:
            raise self._error(i, header, "samples_per_beam",
                              f"changes the samples per beam (frame 0: {self.samples_per_beam})")
        return header

    def frame_samples(self, frame: int) -> np.ndarray:
        """(samples, beams) uint8 samples of ``frame`` in fsswarp's column order (left to right)."""
        header = self.frame_header(frame)
        if header.reordered_samples == 0:
            raise self._error(int(frame), header, "reordered_samples",
                              "the samples are in the sonar's raw order (not a recording); cannot read them")
        start = self._offset(int(frame)) + FRAME_HEADER_BYTES
        raw = self._map[start:start + self.beams * self.samples_per_beam]
        return np.frombuffer(raw, dtype=np.uint8).reshape(self.samples_per_beam, self.beams)[:, ::-1].copy()

    def frame_image(self, frame: int) -> np.ndarray:
        """(bins, beams) = (samples, beams) float32 beam-bin image of ``frame``: linear amplitude
        relative to 80 dB full scale, in fsswarp's column order."""
        return linear_intensity(self.frame_samples(frame))

    # --- sonar -------------------------------------------------------------------------------
    def beam_table(self, frame: int = 0) -> BeamTable:
        """The beam-angle table for ``frame``'s system type, lens and beam count."""
        header = self.frame_header(frame)
        if header.system_type not in SYSTEM_NAMES:
            raise self._error(frame, header, "system_type", "must be 0 (ARIS 1800), 1 (ARIS 3000) or 2 (ARIS 1200)")
        if header.large_lens not in (0, 1):
            raise self._error(frame, header, "large_lens", "must be 0 or 1 (telephoto)")
        name = _TABLES.get((header.large_lens == 1, header.system_type, self.beams))
        if name is None:
            lens = "the telephoto lens" if header.large_lens else "the standard lens"
            raise self._error(frame, header, "ping_mode", f"no beam-angle table for {SYSTEM_NAMES[header.system_type]} "
                                                          f"with {lens} and {self.beams} beams")
        return beam_table(name)

    def sonar_spec(self, *, elevation_fov_deg: float | None = None, frame: int = 0) -> SonarSpec:
        """The sonar of ``frame``: its beams and samples, the computed range window (first and
        last sample), the lens's beam-centre table, and the given (or default 14°) full
        elevation aperture, which the file does not hold."""
        elevation = _elevation(elevation_fov_deg)
        header = self.frame_header(frame)
        table = self.beam_table(frame)
        if not 1000.0 <= header.sound_speed_m_s <= 2000.0:
            raise self._error(frame, header, "sound_speed_m_s", "must be a sound speed in water (1000-2000 m/s)")
        if header.sample_period_us < 1:
            raise self._error(frame, header, "sample_period_us", "must be >= 1 (microseconds)")
        return SonarSpec.from_degrees(beams=self.beams, bins=self.samples_per_beam, azimuth_fov_deg=None,
                                      elevation_fov_deg=elevation, range_min_m=header.window_start_m,
                                      range_max_m=header.last_sample_range_m, beam_angles_deg=table.centre)

    # --- errors ------------------------------------------------------------------------------
    def _check_version(self, version: int, where: str) -> None:
        if version != SIGNATURE:
            raise InputError(f"not an ARIS recording: the version word must be {SIGNATURE:#010x}", file=self.path,
                             field=where, value=f"{version:#010x}")

    def _error(self, frame: int, header: FrameHeader, name: str, message: str) -> InputError:
        return InputError(message, file=self.path, field=f"frames[{frame}].{header_name(FrameHeader, name)}",
                          value=getattr(header, name))


def open_aris(path) -> ArisFile:
    """Open an .aris recording (InputError if it is not a readable one)."""
    return ArisFile(path)


# --- import into a dataset -------------------------------------------------------------------

_FRAMES_PART = re.compile(r"\s*([0-9]+)\s*(?:-\s*([0-9]+)\s*)?", re.ASCII)


def parse_frames(spec, count: int, *, file=None) -> list[int]:
    """Frame positions from ``spec``: None or "all", a text like "0-3,5" (0-based, inclusive
    ranges, in the given order), or a sequence of ints. Each frame at most once, all < count."""
    if spec is None or (isinstance(spec, str) and spec.strip() == "all"):
        return list(range(count))
    if isinstance(spec, str):
        frames = []
        for part in spec.split(","):
            match = _FRAMES_PART.fullmatch(part)
            if match is None:
                raise InputError("must be 'all' or frame numbers like '0-3,5' (0-based)", file=file,
                                 field="--frames", value=spec)
            first, last = int(match[1]), int(match[2] if match[2] is not None else match[1])
            if last < first or last >= count:
                raise InputError(f"no such frames: the file holds {count} (0-{count - 1})" if last >= count
                                 else "a range must run upward", file=file, field="--frames", value=spec)
            frames.extend(range(first, last + 1))
    else:
        frames = list(spec)
        if not all(is_integer(f) and 0 <= f < count for f in frames):
            raise InputError(f"must be frame numbers 0-{count - 1}", file=file, field="--frames", value=frames)
        frames = [int(f) for f in frames]
    if not frames:
        raise InputError("selects no frames", file=file, field="--frames", value=spec)
    if len(set(frames)) != len(frames):
        raise InputError("names a frame twice", file=file, field="--frames", value=spec)
    return frames


_POSE_REQUIRED = ("frame", "x_m", "y_m", "heading_deg", "roll_deg")
_POSE_OPTIONAL = ("depth_offset_m", "tilt_offset_deg")


def read_poses(path, frames: Iterable[int]) -> dict[int, dict]:
    """Per-frame poses from a CSV file, as ``View`` keyword arguments (metres, radians).

    Header row ``frame,x_m,y_m,heading_deg,roll_deg`` and optionally ``depth_offset_m``,
    ``tilt_offset_deg``; one row per frame (0-based position in the file); blank lines and
    lines starting with '#' are skipped. Every frame in ``frames`` needs a row."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("no such file", file=path, field="--poses") from None
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"cannot read the file ({err})", file=path, field="--poses") from None
    lines = [(n, line) for n, line in enumerate(text.splitlines(), 1)
             if line.strip() and not line.lstrip().startswith("#")]
    rows = list(csv.reader(line for _, line in lines))
    if not rows:
        raise InputError(f"holds no header row ({','.join(_POSE_REQUIRED)})", file=path, field="--poses")
    header = [h.strip() for h in rows[0]]
    for name in header:
        if name not in _POSE_REQUIRED + _POSE_OPTIONAL or header.count(name) > 1:
            raise InputError(f"unknown or repeated column; expected {', '.join(_POSE_REQUIRED + _POSE_OPTIONAL)}",
                             file=path, field=f"line {lines[0][0]}", value=name)
    for name in _POSE_REQUIRED:
        if name not in header:
            raise InputError("a required column is missing", file=path, field=f"line {lines[0][0]}", value=name)
    poses: dict[int, dict] = {}
    for (n, _), row in zip(lines[1:], rows[1:]):
        if len(row) != len(header):
            raise InputError(f"has {len(row)} fields; the header has {len(header)}", file=path, field=f"line {n}")
        cells = {k: v.strip() for k, v in zip(header, row)}
        if not re.fullmatch(r"[0-9]+", cells["frame"], re.ASCII):
            raise InputError("must be a frame number (0-based)", file=path, field=f"line {n}.frame", value=cells["frame"])
        frame = int(cells["frame"])
        if frame in poses:
            raise InputError("a second row for this frame", file=path, field=f"line {n}.frame", value=frame)
        values = {}
        for key, text in cells.items():
            if key == "frame":
                continue
            try:
                values[key] = float(text)
            except ValueError:
                values[key] = math.nan
            if not math.isfinite(values[key]):
                raise InputError("must be a finite number", file=path, field=f"line {n}.{key}", value=text)
        poses[frame] = dict(position=(values["x_m"], values["y_m"]), heading=math.radians(values["heading_deg"]),
                            roll=math.radians(values["roll_deg"]), depth_offset=values.get("depth_offset_m", 0.0),
                            tilt_offset=math.radians(values.get("tilt_offset_deg", 0.0)))
    out = {}
    for frame in frames:
        if frame not in poses:
            raise InputError("no row for this frame (every imported frame needs one)", file=path,
                             field="frame", value=frame)
        out[frame] = poses[frame]
    return out


def view_name(frame: int) -> str:
    """The view name of frame ``frame`` (its 0-based position in the file): f0000, f0001, ..."""
    return f"f{frame:04d}"


def import_aris(path, out, *, frames=None, elevation_fov_deg: float | None = None, poses=None,
                depth_m: float | None = None, tilt_deg: float | None = None) -> Dataset:
    """Write the frames of an .aris recording as a dataset folder ``out``; returns it, loaded.

    One view per frame (``view_name``); images from ``ArisFile.frame_image``; the sonar from
    the first selected frame (every selected frame must share its lens and range window within
    half a sample). Measured D0 and β0 ([surface]): ``depth_m``/``tilt_deg`` when given, else
    the median over the frames of the sensor values Depth and CompassPitch; a Depth that is not
    > 0 (a recording without a depth sensor) is refused unless ``depth_m`` is given. Poses from
    ``read_poses(poses)``, else every view at the origin with heading 0 and roll 0. Beside the
    manifest and images, ``out/aris.json`` records the source, the per-frame sensor values and
    the computed and stored range windows.
    """
    check_output_folder(out, marker=ARIS_RECORD)  # before reading the recording
    dataset, record = aris_dataset(path, frames=frames, elevation_fov_deg=elevation_fov_deg, poses=poses,
                                   depth_m=depth_m, tilt_deg=tilt_deg)
    out = Path(out)
    # the folder appears whole: save_dataset fills the (empty) temporary folder, aris.json joins it
    with output_folder(out, marker=ARIS_RECORD) as tmp:  # only an earlier import is replaced
        save_dataset(dataset, tmp)
        write_text(tmp / ARIS_RECORD, json.dumps(record, indent=2) + "\n")
    return load_dataset(out)


def aris_dataset(path, *, frames=None, elevation_fov_deg: float | None = None, poses=None,
                 depth_m: float | None = None, tilt_deg: float | None = None) -> tuple[Dataset, dict]:
    """What ``import_aris`` writes, in memory: the Dataset (no folder) and the aris.json record."""
    path = Path(path)
    elevation = _elevation(elevation_fov_deg)
    with open_aris(path) as aris:
        chosen = parse_frames(frames, aris.frame_count, file=path)
        headers = {i: aris.frame_header(i) for i in chosen}
        sonar = aris.sonar_spec(elevation_fov_deg=elevation, frame=chosen[0])
        table = aris.beam_table(chosen[0])
        for i in chosen[1:]:
            other = aris.sonar_spec(elevation_fov_deg=elevation, frame=i)
            half_bin = 0.5 * sonar.range_step
            if (aris.beam_table(i).name != table.name or abs(other.range_min - sonar.range_min) > half_bin
                    or abs(other.range_max - sonar.range_max) > half_bin):
                raise InputError(f"has another lens or range window ({other.range_min:.4g}-{other.range_max:.4g} m) "
                                 f"than frame {chosen[0]} ({sonar.range_min:.4g}-{sonar.range_max:.4g} m); "
                                 "import them separately", file=path, field="--frames", value=i)
        depth, depth_source = sensor_value(path, FrameHeader, headers, "depth_m", depth_m, "--depth", "M",
                                      lambda v: v > 0, "must be > 0 m below the surface")
        tilt, tilt_source = sensor_value(path, FrameHeader, headers, "compass_pitch_deg", tilt_deg, "--tilt", "DEG",
                                    lambda v: abs(v) < 90, "must lie in (-90, 90) degrees")
        pose_rows = read_poses(poses, chosen) if poses is not None else {}
        views = tuple(View(view_name(i), **pose_rows.get(i, {})) for i in chosen)
        images = {view_name(i): aris.frame_image(i) for i in chosen}
        record = _record(aris, path, table, elevation, elevation_fov_deg is None, headers,
                         (depth, depth_source), (tilt, tilt_source))
    manifest = checked_manifest(sonar, SurfaceEstimate(depth=depth, tilt=math.radians(tilt)), views,
                                file=path, poses=poses)
    return Dataset(manifest, images), record


def checked_manifest(sonar: SonarSpec, surface: SurfaceEstimate, views: tuple[View, ...], *, file,
                     poses=None) -> Manifest:
    """The manifest of an import, validated as a reader of the folder will; an error in a view
    names the pose file (when given), any other the recording ``file``."""
    manifest = Manifest(sonar=sonar, surface=surface, rig=Rig(views))
    try:  # validated before writing (else the error would name a temporary manifest)
        parse_manifest(tomllib.loads(manifest_to_toml(manifest)), file=None)
    except InputError as err:
        raise err.with_file(poses if poses is not None and (err.field or "").startswith("views") else file) from None
    return manifest


def _elevation(value) -> float:
    if value is None:
        return DEFAULT_ELEVATION_FOV_DEG
    if not (is_number(value) and 0 < value < 180):
        raise InputError("must be a full aperture in (0, 180) degrees", field="--elevation-fov-deg", value=value)
    return float(value)


def sensor_value(path: Path, header: type, headers: dict, name: str, given, flag: str, unit: str, ok,
                 message: str):
    """(value, source) of a measured D0 or β0: ``given`` (the option ``flag``), or the median of
    the frame headers' field ``name`` (headers: {frame: an instance of the dataclass ``header``});
    InputError naming ``path`` and the frame where a value is not finite or not ``ok``. ARIS and
    DIDSON use it."""
    if given is not None:
        if not (is_finite_number(given) and ok(given)):
            raise InputError(message, field=flag, value=given)
        return float(given), flag
    for i, frame in headers.items():
        value = getattr(frame, name)
        if not (math.isfinite(value) and ok(value)):
            raise InputError(f"{message}; the recording holds no usable sensor value: give {flag} {unit}",
                             file=path, field=f"frames[{i}].{header_name(header, name)}", value=value)
    value = float(np.median([getattr(h, name) for h in headers.values()]))
    return value, f"sensor {header_name(header, name)}, median of {len(headers)} frames"


def _record(aris: ArisFile, path: Path, table: BeamTable, elevation: float, default_elevation: bool,
            headers: dict[int, FrameHeader], depth, tilt) -> dict:
    """The aris.json provenance record of an import."""
    first = next(iter(headers.values()))
    return {
        "source": str(path.resolve()),
        "system": SYSTEM_NAMES[first.system_type],
        "serial_number": first.serial_number,
        "lens": "telephoto" if first.large_lens else "standard",
        "beam_table": table.name,
        "ping_mode": first.ping_mode,
        "beams": aris.beams,
        "samples_per_beam": aris.samples_per_beam,
        "frames_in_file": aris.frame_count,
        "frame_count_stored": aris.file_header.frame_count_stored,
        "beam_order": "column 0 = left-most beam (ARIS beam N-1); theta_b = -table_centre[N-1-b]",
        "intensity": "linear amplitude 10^((dB - 80)/20), dB = sample * 80/255",
        "azimuth_aperture_deg": table.aperture_deg,
        "elevation_fov_deg": elevation,
        "elevation_source": "default; not in the file" if default_elevation else "--elevation-fov-deg",
        "surface": {"depth_m": depth[0], "depth_source": depth[1], "tilt_deg": tilt[0], "tilt_source": tilt[1]},
        "frames": [{
            "view": view_name(i), "frame": i, "frame_index": h.frame_index, "frame_time_us": h.frame_time_us,
            "sensor_depth_m": json_number(h.depth_m), "sensor_compass_pitch_deg": json_number(h.compass_pitch_deg),
            "sensor_compass_roll_deg": json_number(h.compass_roll_deg),
            "sensor_compass_heading_deg": json_number(h.compass_heading_deg),
            "window_start_m": h.window_start_m, "window_start_m_stored": json_number(h.window_start_m_stored),
            "window_length_m": h.window_length_m, "window_length_m_stored": json_number(h.window_length_m_stored),
            "last_sample_range_m": h.last_sample_range_m, "sound_speed_m_s": h.sound_speed_m_s,
        } for i, h in headers.items()],
    }
