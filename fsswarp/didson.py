"""Sound Metrics DIDSON recordings (.ddf, DDF versions 3 and 4) as fsswarp beam-bin images.

:class:`DidsonFile` reads a recording held in any bytes buffer (:func:`open_didson` maps a file):
``.frame_count``, ``.frame_header(i)``, ``.window(i)`` (the decoded range window beside the
sample rate's), ``.frame_image(i)`` ((512, beams) float32) and ``.sonar_spec(...)``.
:func:`didson_dataset` turns selected frames into an in-memory Dataset and the record of the
values it used; ``fsswarp.importing.import_recording`` writes both.

Layout (docs/formats.md names the source of every offset): 'DDF' and a version byte (3 or 4), a
file header of 512 (v3) or 1024 (v4) bytes, then frames of a 256 (v3) or 1024 (v4) byte header and
512 × beams uint8 samples, beam index fastest (byte s·beams + b); 48 or 96 beams; little endian.
Frames are counted from the file size; a partial last frame is skipped with a DidsonWarning.

Conventions of the images (DESIGN §2; why: docs/decisions.md, "DIDSON recordings"): column b is
what Sound Metrics' software shows there, the stored beam N−1−b (beam b where the file's reverse
flag is set); beam centres θ_b (deg) solve Sound Metrics' cubic lens fit factor·P(θ) = b; a sample
s (0–255) is s·90/255 dB and the image holds 10^((dB − 90)/20) in [3.2e-5, 1]; row B lies at
WindowStart + B·WindowLength/512 (m), decoded from the frame's codes, the file's frequency and the
configuration flags (classic or extended windows, standard or long-range lens). The elevation
aperture is not in the file: default 14°.
"""

from __future__ import annotations

import math
import mmap
import warnings
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

from .aris import (checked_manifest, header_field, header_name, parse_frames, parse_header, read_poses,
                   sensor_value, view_name)
from .atomic import json_number
from .dataset import Dataset, SurfaceEstimate
from .errors import InputError, is_finite_number, is_integer
from .rig import View
from .sonar import SonarSpec

#: File and frame header sizes (bytes) by DDF version.
FILE_HEADER_BYTES = {3: 512, 4: 1024}
FRAME_HEADER_BYTES = {3: 256, 4: 1024}
SAMPLES_PER_BEAM = 512
BEAM_COUNTS = (48, 96)
#: Samples 0..255 span 0..FULL_SCALE_DB decibels (Echoview: 0 to 90 dB).
FULL_SCALE_DB = 90.0
#: Full elevation aperture used when none is given (deg): the DIDSON's 14° beam.
DEFAULT_ELEVATION_FOV_DEG = 14.0
#: Window lengths (m) by (long-range lens, classic windows); index = length code, + 2 at low frequency.
WINDOW_LENGTHS_M = {
    (False, False): (1.25, 2.5, 5.0, 10.0, 20.0, 40.0),
    (False, True): (1.125, 2.25, 4.5, 9.0, 18.0, 36.0),
    (True, False): (2.5, 5.0, 10.0, 20.0, 40.0, 70.0),
    (True, True): (2.25, 4.5, 9.0, 18.0, 36.0, 72.0),
}
#: Window start per start code at high frequency (m; twice at low frequency), by classic windows.
START_STEP_M = {True: 0.375, False: 0.419}
#: Echoview's delay period per start code at high frequency (s; twice at low frequency).
DELAY_PERIOD_S = {True: 0.000512, False: 0.000572}
#: The sound speed (m/s) the code tables assume (0.375 m per 0.512 ms, 0.419 m per 0.572 ms);
#: the window checks use it where the file holds none.
TABLE_SOUND_SPEED_M_S = 1465.0
#: A decoded window start or length further than this (relative) from the one the sample rate
#: or delay period and the sound speed give is reported with a DidsonWarning.
WINDOW_TOLERANCE = 0.02
#: Sound Metrics' lens fit: beam (0-based column) = factor·(a0·θ³ + a1·θ² + a2·θ + a3), θ in degrees.
LENS_FIT = {48: (1.0, (0.0015, -0.0036, 1.3351, 24.0976)), 96: (1.012, (0.0030, -0.0055, 2.6829, 48.04))}

# linear amplitude of each sample value: 10^((s·90/255 − 90)/20)
_AMPLITUDE = np.power(10.0, (np.arange(256) * (FULL_SCALE_DB / 255.0) - FULL_SCALE_DB) / 20.0).astype(np.float32)


class DidsonWarning(UserWarning):
    """A recording that can be read but is doubtful (a partial last frame, a window that
    disagrees with the sample rate)."""


@dataclass(frozen=True)
class FileHeader:
    """The file header fields fsswarp reads (the sources' names in ``source``).

    ``sound_speed_m_s`` (Sspd) exists in version 4 only: None in version 3."""

    version: int = header_field("B", 3, "version")
    frame_count_stored: int = header_field("i", 4, "numframes")
    resolution: int = header_field("i", 12, "resolution")
    beams: int = header_field("i", 16, "numbeams")
    sample_rate_hz: float = header_field("f", 20, "samplerate")
    samples_per_channel: int = header_field("i", 24, "samplesperchannel")
    reverse: int = header_field("i", 40, "reverse")
    serial_number: int = header_field("i", 44, "serialnumber")
    sound_speed_m_s: int | None = header_field("I", 384, "sspd")

    @property
    def high_frequency(self) -> bool:
        """resolution: 0 = low frequency, else high."""
        return self.resolution != 0


@dataclass(frozen=True)
class FrameHeader:
    """One frame header's fields (the sources' names in ``source``; angles in degrees)."""

    frame_number: int = header_field("i", 0, "framenumber")
    window_start_code: int = header_field("i", 52, "windowstart")
    window_length_code: int = header_field("i", 56, "windowlength")
    depth_m: float = header_field("f", 128, "depth")
    heading_deg: float = header_field("f", 152, "heading")
    sonar_pan_deg: float = header_field("f", 160, "sonarpan")
    sonar_tilt_deg: float = header_field("f", 164, "sonartilt")
    sonar_roll_deg: float = header_field("f", 168, "sonarroll")
    config_flags: int = header_field("i", 192, "configflags")


@dataclass(frozen=True)
class Window:
    """A frame's range window (m) decoded from its codes, beside what the timing gives.

    start_m, length_m : from the code tables; start_from_delay_m : start code · delay period ·
    c/2; length_from_sample_rate_m : 512·c/(2·samplerate), None where the sample rate is not a
    positive number; c = sound_speed_m_s (the file's Sspd, else the tables' 1465 m/s)."""

    long_range: bool
    classic: bool
    config_source: str
    high_frequency: bool
    start_code: int
    length_code: int
    start_m: float
    length_m: float
    sound_speed_m_s: float
    sound_speed_source: str
    sample_rate_hz: float
    start_from_delay_m: float
    length_from_sample_rate_m: float | None

    @property
    def configuration(self) -> str:
        """The sources' name of the configuration, e.g. 'DIDSON-S classic windows'."""
        return f"DIDSON-{'LR' if self.long_range else 'S'} {'classic' if self.classic else 'extended'} windows"

    def disagreements(self) -> dict[str, str]:
        """{"start" / "length": why} where the decoded value is further than WINDOW_TOLERANCE
        from the timing's (or the length cannot be checked)."""
        found = {}
        for name, decoded, timed, source in (
                ("start", self.start_m, self.start_from_delay_m, "the delay period"),
                ("length", self.length_m, self.length_from_sample_rate_m, "the sample rate")):
            if timed is None:
                found[name] = f"cannot be checked: samplerate = {self.sample_rate_hz!r} Hz is not a positive number"
            elif abs(decoded - timed) > WINDOW_TOLERANCE * max(abs(timed), 1e-9):
                found[name] = (f"{decoded:.4g} m from the code tables against {timed:.4g} m from {source} at "
                               f"{self.sound_speed_m_s:g} m/s ({self.sound_speed_source}), "
                               f"{100 * abs(decoded / timed - 1):.1f}% apart")
        return found


@cache
def beam_angles_deg(beams: int) -> np.ndarray:
    """(beams,) beam-centre azimuths (deg, increasing) of Sound Metrics' lens fit: column b at
    the θ where factor·P(θ) = b (LENS_FIT; the cubic rises monotonically)."""
    if beams not in LENS_FIT:
        raise ValueError(f"the DIDSON lens fit exists for 48 and 96 beams, not {beams}")
    factor, (a3, a2, a1, a0) = LENS_FIT[beams]
    angles = []
    for b in range(beams):
        roots = np.roots([a3, a2, a1, a0 - b / factor])
        angles.append(float(next(r.real for r in roots if abs(r.imag) < 1e-9)))
    out = np.array(angles)
    out.setflags(write=False)
    return out


def linear_intensity(samples: np.ndarray) -> np.ndarray:
    """uint8 samples (any shape) as float32 linear amplitude 10^((s·90/255 − 90)/20)."""
    return _AMPLITUDE[np.asarray(samples, dtype=np.uint8)]


class DidsonFile:
    """A DIDSON recording in a bytes buffer (bytes, bytearray or mmap); frames are read on
    demand. ``file`` names the recording in errors. Beams, samples and the frame size come from
    the file header; every size is checked against the buffer before anything is read."""

    def __init__(self, buffer, *, file):
        self.file = str(file)
        self._buffer = buffer
        self.size = len(buffer)
        if self.size < 4:
            raise InputError("too short for a DIDSON recording", file=self.file, field="size", value=self.size)
        word = f"{int.from_bytes(bytes(buffer[:4]), 'little'):#010x}"
        if bytes(buffer[:3]) != b"DDF":
            raise InputError("not a DIDSON recording: it must start with 'DDF'", file=self.file,
                             field="header.Version", value=word)
        version = buffer[3]
        if version not in FILE_HEADER_BYTES:
            raise InputError(f"DDF version {version}: DIDSON recordings are versions 3 and 4", file=self.file,
                             field="header.Version", value=word)
        head, frame_head = FILE_HEADER_BYTES[version], FRAME_HEADER_BYTES[version]
        if self.size < head + frame_head:
            raise InputError(f"too short for a DIDSON version {version} recording ({self.size} bytes; the file "
                             f"and frame headers alone take {head + frame_head})", file=self.file, field="size",
                             value=self.size)
        #: the file header; the frame header size (bytes)
        self.file_header = parse_header(FileHeader, buffer, 0, skip=("sound_speed_m_s",) if version == 3 else ())
        self.frame_header_bytes = frame_head
        header = self.file_header
        if header.beams not in BEAM_COUNTS:
            raise self._file_error("beams", "must be 48 or 96")
        if header.samples_per_channel != SAMPLES_PER_BEAM:
            raise self._file_error("samples_per_channel", "must be 512 (DIDSON frames hold 512 samples per beam)")
        #: beams of every frame
        self.beams = header.beams
        #: bytes per frame: header and samples
        self.frame_bytes = frame_head + self.beams * SAMPLES_PER_BEAM
        if head + self.frame_bytes > self.size:
            raise self._file_error("beams", f"a frame of {self.beams} beams x 512 samples needs {self.frame_bytes} "
                                            f"bytes but the file holds {self.size - head} after its header")
        #: complete frames in the buffer (from its size, not the header's numframes)
        self.frame_count, rest = divmod(self.size - head, self.frame_bytes)
        if rest:
            warnings.warn(DidsonWarning(f"{self.file}: ignoring a partial frame at the end ({rest} of "
                                        f"{self.frame_bytes} bytes); {self.frame_count} whole frames"), stacklevel=2)

    @property
    def version(self) -> int:
        """The DDF version: 3 or 4."""
        return self.file_header.version

    def close(self) -> None:
        """Release a mapped file (a bytes buffer needs nothing)."""
        if isinstance(self._buffer, mmap.mmap):
            self._buffer.close()

    def __enter__(self) -> "DidsonFile":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- frames ------------------------------------------------------------------------------
    def _offset(self, frame) -> int:
        if not is_integer(frame) or not 0 <= frame < self.frame_count:
            raise InputError(f"no such frame: the file holds {self.frame_count} (0-{self.frame_count - 1})",
                             file=self.file, field="frame", value=frame)
        return FILE_HEADER_BYTES[self.version] + int(frame) * self.frame_bytes

    def frame_header(self, frame: int) -> FrameHeader:
        """The header of frame ``frame`` (0-based position in the file)."""
        return parse_header(FrameHeader, self._buffer, self._offset(frame))

    def frame_samples(self, frame: int) -> np.ndarray:
        """(512, beams) uint8 samples of ``frame`` in the order Sound Metrics' software shows
        them: column b is the stored beam N−1−b, or beam b where the reverse flag is set."""
        start = self._offset(frame) + self.frame_header_bytes
        stored = np.frombuffer(self._buffer[start:start + self.beams * SAMPLES_PER_BEAM], dtype=np.uint8)
        stored = stored.reshape(SAMPLES_PER_BEAM, self.beams)
        return (stored if self.file_header.reverse else stored[:, ::-1]).copy()

    def frame_image(self, frame: int) -> np.ndarray:
        """(bins, beams) = (512, beams) float32 beam-bin image of ``frame``: linear amplitude
        relative to 90 dB full scale, columns as ``frame_samples``."""
        return linear_intensity(self.frame_samples(frame))

    # --- the range window -----------------------------------------------------------------------
    def window(self, frame: int = 0) -> Window:
        """The range window of ``frame``: its codes decoded with the configuration flags (two
        low bits: bit 0 classic windows, bit 1 long-range lens; serial numbers below 19 are
        classic DIDSON-S, serial number 15 classic DIDSON-LR) and the file's frequency, beside the
        start and length that the delay period, the sample rate and the sound speed give."""
        header = self.frame_header(frame)
        serial = self.file_header.serial_number
        flags, source = header.config_flags & 3, "configflags"
        if serial == 15:
            flags, source = 3, "serial number 15: DIDSON-LR classic windows"
        elif serial < 19:
            flags, source = 1, "serial number below 19: DIDSON-S classic windows"
        classic, long_range = bool(flags & 1), bool(flags & 2)
        high = self.file_header.high_frequency
        if not 0 <= header.window_start_code <= 31:
            raise self._frame_error(frame, header, "window_start_code", "must be a start code 0-31")
        if not 0 <= header.window_length_code <= 3:
            raise self._frame_error(frame, header, "window_length_code", "must be a length code 0-3")
        scale = 1 if high else 2
        speed, speed_source = float(TABLE_SOUND_SPEED_M_S), "assumed by the code tables; the file holds none"
        stored_speed = self.file_header.sound_speed_m_s
        if stored_speed is not None and 1000 <= stored_speed <= 2000:
            speed, speed_source = float(stored_speed), "file header sspd"
        rate = self.file_header.sample_rate_hz
        return Window(
            long_range=long_range, classic=classic, config_source=source, high_frequency=high,
            start_code=header.window_start_code, length_code=header.window_length_code,
            start_m=header.window_start_code * START_STEP_M[classic] * scale,
            length_m=WINDOW_LENGTHS_M[long_range, classic][header.window_length_code + (0 if high else 2)],
            sound_speed_m_s=speed, sound_speed_source=speed_source, sample_rate_hz=rate,
            start_from_delay_m=header.window_start_code * DELAY_PERIOD_S[classic] * scale * speed / 2,
            length_from_sample_rate_m=SAMPLES_PER_BEAM * speed / (2 * rate) if math.isfinite(rate) and rate > 0
            else None)

    def sonar_spec(self, frame: int = 0, *, elevation_fov_deg: float | None = None,
                   window_start_m: float | None = None, window_length_m: float | None = None) -> SonarSpec:
        """The sonar of ``frame``: its beams, the lens fit's beam centres, the range window (the
        decoded one, or the given start and length, m; row B at start + B·length/512) and the
        given (or default 14°) full elevation aperture, which the file does not hold."""
        elevation = _checked_option("--elevation-fov-deg", elevation_fov_deg, DEFAULT_ELEVATION_FOV_DEG,
                                    lambda v: 0 < v < 180, "must be a full aperture in (0, 180) degrees")
        window = self.window(frame)
        start = _checked_option("--window-start", window_start_m, window.start_m, lambda v: v >= 0,
                                "must be a range >= 0 m")
        length = _checked_option("--window-length", window_length_m, window.length_m, lambda v: v > 0,
                                 "must be a length > 0 m")
        return SonarSpec.from_degrees(beams=self.beams, bins=SAMPLES_PER_BEAM, azimuth_fov_deg=None,
                                      elevation_fov_deg=elevation, range_min_m=start,
                                      range_max_m=start + (SAMPLES_PER_BEAM - 1) * length / SAMPLES_PER_BEAM,
                                      beam_angles_deg=beam_angles_deg(self.beams))

    # --- errors ------------------------------------------------------------------------------
    def _file_error(self, name: str, message: str) -> InputError:
        return InputError(message, file=self.file, field=f"header.{header_name(FileHeader, name)}",
                          value=getattr(self.file_header, name))

    def _frame_error(self, frame: int, header: FrameHeader, name: str, message: str) -> InputError:
        return InputError(message, file=self.file, field=f"frames[{frame}].{header_name(FrameHeader, name)}",
                          value=getattr(header, name))


def open_didson(path) -> DidsonFile:
    """Map a .ddf recording (InputError if it is not a readable one). Use as a context manager."""
    path = Path(path)
    if not path.is_file():
        raise InputError("no such file" if not path.exists() else "is not a file", file=path)
    try:
        with open(path, "rb") as handle:
            if handle.seek(0, 2) == 0:
                raise InputError("is empty, not a DIDSON recording", file=path, field="size", value=0)
            buffer = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)
    except OSError as err:
        raise InputError(f"cannot read the file ({err.strerror or err})", file=path) from None
    try:
        return DidsonFile(buffer, file=path)
    except BaseException:
        buffer.close()
        raise


def _checked_option(flag: str, value, default: float, ok, message: str) -> float:
    if value is None:
        return float(default)
    if not (is_finite_number(value) and ok(value)):
        raise InputError(message, field=flag, value=value)
    return float(value)


# --- into a dataset -------------------------------------------------------------------------

def didson_dataset(didson: DidsonFile, *, frames=None, elevation_fov_deg: float | None = None, poses=None,
                   depth_m: float | None = None, tilt_deg: float | None = None,
                   window_start_m: float | None = None, window_length_m: float | None = None) -> tuple[Dataset, dict]:
    """Selected frames of ``didson`` as an in-memory Dataset, and the record of the values used.

    One view per frame (``fsswarp.aris.view_name``); the sonar from the first selected frame,
    whose window codes and configuration every selected frame must share. The window's start
    and length (m) are the given ``window_start_m`` / ``window_length_m``, else the decoded ones,
    with a DidsonWarning where those disagree with the timing by more than 2%. Measured D0 and
    β0 and the poses follow the ARIS import: the given values, else the median over the frames of
    depth and sonartilt (a depth that is not > 0 needs ``depth_m``); ``read_poses(poses)``, else
    every view at the origin, heading 0, roll 0.
    """
    chosen = parse_frames(frames, didson.frame_count, file=didson.file)
    first = chosen[0]
    headers = {i: didson.frame_header(i) for i in chosen}
    sonar = didson.sonar_spec(first, elevation_fov_deg=elevation_fov_deg, window_start_m=window_start_m,
                              window_length_m=window_length_m)
    window = didson.window(first)
    for i in chosen[1:]:
        other = didson.window(i)
        if (other.start_code, other.length_code, other.configuration) != (window.start_code, window.length_code,
                                                                           window.configuration):
            raise InputError(f"has another range window or configuration (codes {other.start_code}/"
                             f"{other.length_code}, {other.configuration}) than frame {first} (codes "
                             f"{window.start_code}/{window.length_code}, {window.configuration}); import them "
                             "separately", file=didson.file, field="--frames", value=i)
    given = {"start": window_start_m, "length": window_length_m}
    disagreements = window.disagreements()
    for name, why in disagreements.items():
        if given[name] is None:
            warnings.warn(DidsonWarning(f"{didson.file}: frames[{first}]: the window {name}: {why}; give "
                                        f"--window-{name} M to choose"), stacklevel=2)
    depth = sensor_value(didson.file, FrameHeader, headers, "depth_m", depth_m, "--depth", "M", lambda v: v > 0,
                         "must be > 0 m below the surface")
    tilt = sensor_value(didson.file, FrameHeader, headers, "sonar_tilt_deg", tilt_deg, "--tilt", "DEG",
                        lambda v: abs(v) < 90, "must lie in (-90, 90) degrees")
    pose_rows = read_poses(poses, chosen) if poses is not None else {}
    views = tuple(View(view_name(i), **pose_rows.get(i, {})) for i in chosen)
    images = {view_name(i): didson.frame_image(i) for i in chosen}
    manifest = checked_manifest(sonar, SurfaceEstimate(depth=depth[0], tilt=math.radians(tilt[0])), views,
                                file=didson.file, poses=poses)
    used = {"start_m": window.start_m if window_start_m is None else float(window_start_m),
            "length_m": window.length_m if window_length_m is None else float(window_length_m),
            "start_source": "code table" if window_start_m is None else "--window-start",
            "length_source": "code table" if window_length_m is None else "--window-length"}
    record = _record(didson, window, used, disagreements, math.degrees(sonar.elevation_fov),
                     elevation_fov_deg is None, headers, depth, tilt)
    return Dataset(manifest, images), record


def _record(didson: DidsonFile, window: Window, used: dict, disagreements: dict, elevation: float,
            default_elevation: bool, headers: dict[int, FrameHeader], depth, tilt) -> dict:
    """What a DIDSON import used from the file (source.json's ``header_values``)."""
    header = didson.file_header
    factor, coefficients = LENS_FIT[didson.beams]
    return {
        "serial_number": header.serial_number,
        "beams": didson.beams,
        "samples_per_beam": SAMPLES_PER_BEAM,
        "frames_in_file": didson.frame_count,
        "frame_count_stored": header.frame_count_stored,
        "frequency": "high" if window.high_frequency else "low",
        "reverse": header.reverse,
        "beam_order": "column 0 = left-most beam as Sound Metrics' software shows it: "
                      + ("stored beam b (reverse flag set)" if header.reverse else "stored beam N-1-b"),
        "beam_angles": f"Sound Metrics' lens fit for {didson.beams} beams: column b at the angle t (deg) where "
                       f"{factor:g}*({coefficients[0]:g} t^3 {coefficients[1]:+g} t^2 {coefficients[2]:+g} t "
                       f"{coefficients[3]:+g}) = b",
        "configuration": window.configuration,
        "config_flags": next(iter(headers.values())).config_flags,
        "config_source": window.config_source,
        "window": {
            "start_code": window.start_code, "length_code": window.length_code, **used,
            "start_table_m": window.start_m, "length_table_m": window.length_m,
            "sample_rate_hz": json_number(window.sample_rate_hz), "sound_speed_m_s": window.sound_speed_m_s,
            "sound_speed_source": window.sound_speed_source, "start_from_delay_m": window.start_from_delay_m,
            "length_from_sample_rate_m": window.length_from_sample_rate_m, "disagreements": disagreements,
        },
        "intensity": "linear amplitude 10^((dB - 90)/20), dB = sample * 90/255",
        "elevation_fov_deg": elevation,
        "elevation_source": "default; not in the file" if default_elevation else "--elevation-fov-deg",
        "surface": {"depth_m": depth[0], "depth_source": depth[1], "tilt_deg": tilt[0], "tilt_source": tilt[1]},
        "frames": [{
            "view": view_name(i), "frame": i, "frame_number": h.frame_number,
            "sensor_depth_m": json_number(h.depth_m), "sensor_sonar_tilt_deg": json_number(h.sonar_tilt_deg),
            "sensor_sonar_roll_deg": json_number(h.sonar_roll_deg),
            "sensor_sonar_pan_deg": json_number(h.sonar_pan_deg), "sensor_heading_deg": json_number(h.heading_deg),
        } for i, h in headers.items()],
    }
