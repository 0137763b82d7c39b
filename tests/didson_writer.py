"""A test-only DIDSON (.ddf) writer that follows the published layout, not fsswarp's reader.

The headers are packed field after field in the order, types and sizes of Sound Metrics' MATLAB
reader (get_file_header_ddf3/4.m, get_frame_header_ddf3/4.m: int32, float32, float64, char
arrays, little endian), the version 4 file header continued with the ARIS SDK's FileHeader.h
fields after frameinterval (flags, auxflags, sspd, ...), each header zero-padded to its size:
512/256 bytes (version 3), 1024/1024 (version 4). A frame's samples follow its header as
512 × beams uint8, beam index fastest (MATLAB's fread(fid, [numbeams, 512])).
"""

from __future__ import annotations

import struct

import numpy as np

FILE_HEADER_BYTES = {3: 512, 4: 1024}
FRAME_HEADER_BYTES = {3: 256, 4: 1024}
FILE_FIELDS = [("version", "4s"), ("numframes", "i"), ("framerate", "i"), ("resolution", "i"), ("numbeams", "i"),
               ("samplerate", "f"), ("samplesperchannel", "i"), ("receivergain", "i"), ("windowstart", "i"),
               ("windowlength", "i"), ("reverse", "i"), ("serialnumber", "i"), ("date", "32s"),
               ("idstring", "256s"), ("id1", "i"), ("id2", "i"), ("id3", "i"), ("id4", "i"), ("startframe", "i"),
               ("endframe", "i"), ("timelapse", "i"), ("recordinterval", "i"), ("radioseconds", "i"),
               ("frameinterval", "i")]
V4_FILE_FIELDS = [("flags", "I"), ("auxflags", "I"), ("sspd", "I"), ("flags3d", "I"), ("softwareversion", "I")]
FRAME_FIELDS = [("framenumber", "i"), ("frametime", "8s"), ("version", "4s"), ("status", "i"), ("year", "i"),
                ("month", "i"), ("day", "i"), ("hour", "i"), ("minute", "i"), ("second", "i"), ("hsecond", "i"),
                ("transmit", "i"), ("windowstart", "i"), ("windowlength", "i"), ("threshold", "i"),
                ("intensity", "i"), ("receivergain", "i"), ("degc1", "i"), ("degc2", "i"), ("humidity", "i"),
                ("focus", "i"), ("battery", "i"), ("status1", "16s"), ("status2", "8s"), ("panwcom", "f"),
                ("tiltwcom", "f"), ("velocity", "f"), ("depth", "f"), ("altitude", "f"), ("pitch", "f"),
                ("pitchrate", "f"), ("roll", "f"), ("rollrate", "f"), ("heading", "f"), ("headingrate", "f"),
                ("sonarpan", "f"), ("sonartilt", "f"), ("sonarroll", "f"), ("latitude", "d"), ("longitude", "d"),
                ("sonarposition", "f"), ("configflags", "i")]


def _pack(layout: list[tuple[str, str]], values: dict, size: int) -> bytes:
    unknown = set(values) - {name for name, _ in layout}
    if unknown:
        raise KeyError(f"no such header field: {sorted(unknown)}")
    defaults = {"s": b"", "i": 0, "I": 0, "f": 0.0, "d": 0.0}
    data = struct.pack("<" + "".join(fmt for _, fmt in layout),
                       *(values.get(name, defaults[fmt[-1]]) for name, fmt in layout))
    assert len(data) <= size
    return data.ljust(size, b"\0")


def file_header(version: int, **values) -> bytes:
    """The file header of a version 3 or 4 recording; fields by the sources' names."""
    layout = FILE_FIELDS + (V4_FILE_FIELDS if version == 4 else [])
    return _pack(layout, {"version": b"DDF" + bytes([version]), **values}, FILE_HEADER_BYTES[version])


def frame_header(version: int, **values) -> bytes:
    """A frame header of a version 3 or 4 recording; fields by the sources' names."""
    return _pack(FRAME_FIELDS, {"version": b"DDF" + bytes([version]), **values}, FRAME_HEADER_BYTES[version])


def recording(*, version: int = 4, beams: int = 96, frames=2, header=None, frame_values=None) -> bytes:
    """A whole recording. ``frames``: a count (samples = stored beam number + sample number,
    mod 256) or a list of (512, beams) arrays in stored order. ``header`` updates the file
    header's defaults (high frequency, serial 100, reverse 0, 512 samples per channel, sample
    rate and sspd consistent with DIDSON-S classic windows at code 2/1); ``frame_values`` updates
    every frame's header (a dict) or each one (a list of dicts)."""
    if isinstance(frames, int):
        frames = [(np.arange(beams)[None, :] + np.arange(512)[:, None]) % 256 for _ in range(frames)]
    base = {"numframes": len(frames), "resolution": 1, "numbeams": beams, "samplerate": 512 * 1465.0 / (2 * 2.25),
            "samplesperchannel": 512, "serialnumber": 100, "reverse": 0}
    if version == 4:
        base["sspd"] = 1465
    out = bytearray(file_header(version, **{**base, **(header or {})}))
    for k, samples in enumerate(frames):
        values = frame_values[k] if isinstance(frame_values, list) else (frame_values or {})
        defaults = {"framenumber": k, "windowstart": 2, "windowlength": 1, "configflags": 1, "depth": 0.5,
                    "sonartilt": 10.0}
        out += frame_header(version, **{**defaults, **values})
        stored = np.asarray(samples)
        assert stored.shape == (512, beams)
        out += stored.astype(np.uint8).tobytes()
    return bytes(out)
