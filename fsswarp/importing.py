"""One import for every recording format fsswarp reads: ARIS (.aris) and DIDSON (.ddf), and
HoloOcean-style folders (Config.json and Data/, ``fsswarp.holoocean``).

:func:`detect_format` names a recording's format from its first bytes ('DDF' and a version
byte: 5 ARIS, 3 or 4 DIDSON). :func:`import_recording` writes it as a dataset folder with
``source.json`` (the format, its version, the header values used and the options given; ARIS
imports also keep their ``aris.json``), all or nothing. The readers are ``fsswarp.aris`` and
``fsswarp.didson``; docs/formats.md lists every key.
"""

from __future__ import annotations

import json
from pathlib import Path

from .aris import ARIS_RECORD, aris_dataset
from .atomic import check_output_folder, output_folder, write_text
from .dataset import Dataset, load_dataset, save_dataset
from .didson import didson_dataset, open_didson
from .errors import InputError
from .holoocean import holoocean_dataset, is_holoocean_folder

#: The record every import writes; it marks a folder that a new import may replace.
SOURCE_RECORD = "source.json"
#: Format -> (name in messages and source.json, the options it takes).
FORMATS = {
    "aris": ("ARIS", ("frames", "elevation_fov_deg", "poses", "depth_m", "tilt_deg")),
    "didson": ("DIDSON", ("frames", "elevation_fov_deg", "poses", "depth_m", "tilt_deg", "window_start_m",
                          "window_length_m")),
    "holoocean": ("HoloOcean", ()),  # a folder: Config.json holds the sonar, each pkl its view's pose
}
#: Each option's command-line flag (for messages).
FLAGS = {"frames": "--frames", "elevation_fov_deg": "--elevation-fov-deg", "poses": "--poses", "depth_m": "--depth",
         "tilt_deg": "--tilt", "window_start_m": "--window-start", "window_length_m": "--window-length"}
_MAGIC = {b"DDF\x05": "aris", b"DDF\x03": "didson", b"DDF\x04": "didson"}


def detect_format(path) -> str:
    """The format of the recording at ``path``, "aris" or "didson", from its first four bytes;
    InputError (one line naming the file) for anything else."""
    path = Path(path)
    if not path.exists():
        raise InputError("no such file", file=path)
    if path.is_dir():
        if is_holoocean_folder(path):
            return "holoocean"
        raise InputError("is a folder without Config.json and Data/ (a HoloOcean-style dataset); or name an ARIS "
                         "(.aris) or DIDSON (.ddf) recording", file=path)
    if not path.is_file():
        raise InputError("is not a file; name an ARIS (.aris) or DIDSON (.ddf) recording", file=path)
    try:
        with open(path, "rb") as handle:
            start = handle.read(4)
    except OSError as err:
        raise InputError(f"cannot read the file ({err.strerror or err})", file=path) from None
    if len(start) < 4:
        raise InputError(f"too short for an ARIS or DIDSON recording ({len(start)} bytes)", file=path,
                         field="size", value=len(start))
    if start in _MAGIC:
        return _MAGIC[start]
    word = f"{int.from_bytes(start, 'little'):#010x}"
    if start[:3] == b"DDF":
        raise InputError(f"DDF version {start[3]}: fsswarp reads versions 3 and 4 (DIDSON) and 5 (ARIS)", file=path,
                         field="header.Version", value=word)
    raise InputError("not an ARIS or DIDSON recording: it must start with 'DDF' and a version byte", file=path,
                     field="header.Version", value=word)


def import_recording(path, out, **options) -> Dataset:
    """Write the recording at ``path`` (any format of ``detect_format``) as the dataset folder
    ``out`` with ``source.json``; returns the dataset, loaded.

    options (None = not given): ``frames`` ("all", "0-3,5" or a list), ``elevation_fov_deg``,
    ``poses`` (CSV path), ``depth_m``, ``tilt_deg`` for both formats; ``window_start_m`` and
    ``window_length_m`` (DIDSON only). ``out`` may replace an earlier import (its source.json, or
    the aris.json of an ``import-aris`` before source.json existed) and nothing else.
    """
    path = Path(path)
    unknown = sorted(set(options) - set(FLAGS))
    if unknown:
        raise TypeError(f"import_recording() got unknown options: {', '.join(unknown)}")
    given = {name: value for name, value in options.items() if value is not None}
    form = detect_format(path)
    name, accepted = FORMATS[form]
    for option, value in given.items():
        if option not in accepted:
            raise InputError(f"does not apply to {name} recordings such as {path} (they take "
                             f"{', '.join(FLAGS[o] for o in accepted) or 'no options'})", field=FLAGS[option],
                             value=value)
    marker = _marker(out)
    check_output_folder(out, marker=marker)  # before reading the recording
    truth_mesh = None
    if form == "aris":
        dataset, header_values = aris_dataset(path, **given)
        records, version = {ARIS_RECORD: header_values}, 5
    elif form == "holoocean":
        dataset, truth_mesh, header_values = holoocean_dataset(path)
        records, version = {}, None
    else:
        with open_didson(path) as didson:
            dataset, header_values = didson_dataset(didson, **given)
            records, version = {}, didson.version
    records[SOURCE_RECORD] = {
        "format": name, "version": version, "source": str(path.resolve()),
        "given": {option: _json_value(value) for option, value in given.items()},
        "header_values": header_values,
    }
    out = Path(out)
    with output_folder(out, marker=marker) as tmp:  # the folder appears whole
        save_dataset(dataset, tmp, truth_mesh=truth_mesh)
        for file, record in records.items():
            write_text(tmp / file, json.dumps(record, indent=2) + "\n")
    return load_dataset(out)


def _marker(out) -> str:
    """source.json, or aris.json for a folder an earlier import-aris wrote before source.json."""
    out = Path(out)
    try:
        earlier_aris = (out / ARIS_RECORD).is_file() and not (out / SOURCE_RECORD).exists()
    except OSError:  # check_output_folder reports the path
        earlier_aris = False
    return ARIS_RECORD if earlier_aris else SOURCE_RECORD


def _json_value(value):
    """A given option as JSON: a path or text as text, frame numbers as ints, numbers as floats."""
    if isinstance(value, (str, Path)):
        return str(value)
    if isinstance(value, (list, tuple)):
        return [int(v) for v in value]
    return float(value)
