"""``fsswarp import``: format detection, source.json, ARIS and DIDSON through one command (and
its alias import-aris), a DIDSON dataset that checks and carves like the simulation it was
written from, bad files on the command line, and fuzzing through the files and the CLI."""

import dataclasses
import json
import math
import os
import random
import re
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from didson_writer import recording
from fsswarp.cli import main
from fsswarp.dataset import load_dataset
from fsswarp.didson import DidsonWarning
from fsswarp.errors import InputError
from fsswarp.importing import detect_format, import_recording
from test_aris import synthetic as aris_recording
from test_didson import BASES, bad_cases, mutate

REPO = Path(__file__).resolve().parents[1]


def write(tmp_path: Path, data: bytes, name: str = "rec.ddf") -> Path:
    path = tmp_path / name
    path.write_bytes(data)
    return path


def listing(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def run_cli(*args):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    return subprocess.run([sys.executable, "-m", "fsswarp", *map(str, args)], capture_output=True, text=True,
                          timeout=300, env=env)


def json_keys(record, data_keys=frozenset()) -> set[str]:
    found = set()
    if isinstance(record, dict):
        for key, value in record.items():
            found |= ({key} - data_keys) | json_keys(value, data_keys)
    elif isinstance(record, list):
        for value in record:
            found |= json_keys(value, data_keys)
    return found


# --- format detection ----------------------------------------------------------------------------

@pytest.mark.parametrize("start, expected", [(b"DDF\x05", "aris"), (b"DDF\x03", "didson"), (b"DDF\x04", "didson")])
def test_formats_are_told_apart_by_their_magic_bytes(tmp_path, start, expected):
    assert detect_format(write(tmp_path, start + bytes(100), "any.name")) == expected


@pytest.mark.parametrize("data, needle", [(b"", "too short"), (b"DDF", "size = 3"),
                                          (b"DDF\x02" + bytes(9), "header.Version = '0x02464444': DDF version 2"),
                                          (b"CDF\x05" + bytes(9), "header.Version = '0x05464443'"),
                                          (b"\x89PNG\r\n", "not an ARIS or DIDSON recording")])
def test_other_files_are_one_line_errors(tmp_path, data, needle):
    path = write(tmp_path, data)
    with pytest.raises(InputError) as info:
        detect_format(path)
    assert needle in str(info.value) and str(path) in str(info.value)
    with pytest.raises(InputError, match="no such file"):
        detect_format(tmp_path / "none.ddf")
    with pytest.raises(InputError) as info:                             # a folder: only a HoloOcean dataset
        detect_format(tmp_path)
    assert str(info.value).startswith(f"{tmp_path}: ") and "\n" not in str(info.value)


# --- DIDSON through the command ------------------------------------------------------------------

@pytest.mark.parametrize("version, beams", [(3, 48), (4, 96)])
def test_import_writes_a_didson_dataset_that_checks(tmp_path, capsys, version, beams):
    path = write(tmp_path, recording(version=version, beams=beams, frames=3))
    out = tmp_path / "ds"
    assert main(["import", str(path), "--out", str(out), "--frames", "0-1", "--tilt", "3.5"]) == 0
    stdout = capsys.readouterr().out
    assert "DIDSON-S classic windows" in stdout and "window start 0.75 m" in stdout
    assert sorted(p.name for p in out.iterdir()) == ["dataset.toml", "figures", "images", "source.json"]
    source = json.loads((out / "source.json").read_text())
    assert (source["format"], source["version"], source["source"]) == ("DIDSON", version, str(path.resolve()))
    assert source["given"] == {"frames": "0-1", "tilt_deg": 3.5}
    assert source["header_values"]["window"]["length_m"] == 2.25
    dataset = load_dataset(out)
    assert dataset.rig.names == ["f0000", "f0001"] and dataset.images["f0001"].shape == (512, beams)
    assert (dataset.sonar.range_min, dataset.manifest.surface.depth) == (0.75, 0.5)
    assert main(["check", str(out)]) == 0
    assert (out / "figures" / "frame0_fan.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_every_source_json_key_is_documented(tmp_path):
    formats = (REPO / "docs" / "formats.md").read_text()
    documented = set(re.findall(r"`([^`\s]+)`", formats))
    poses = tmp_path / "poses.csv"
    poses.write_text("frame,x_m,y_m,heading_deg,roll_deg\n0,0,0,0,0\n")
    didson = write(tmp_path, recording(version=4, beams=48, frames=1, header={"samplerate": 1.0}))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DidsonWarning)
        import_recording(didson, tmp_path / "d", frames=[0], poses=poses, depth_m=0.4, tilt_deg=1.0,
                         elevation_fov_deg=12.0, window_start_m=1.0, window_length_m=2.0)
    import_recording(write(tmp_path, aris_recording(frames=1), "rec.aris"), tmp_path / "a")
    for folder in ("d", "a"):
        source = json.loads((tmp_path / folder / "source.json").read_text())
        missing = sorted(json_keys(source) - documented)
        assert not missing, f"{folder}/source.json: keys not in docs/formats.md as `key`: {missing}"
    assert set(source["given"]) == set() and source["format"] == "ARIS"


def test_the_window_warning_reaches_the_user_and_the_import_goes_on(tmp_path):
    path = write(tmp_path, recording(version=4, beams=96, frames=1, header={"sspd": 1500}))
    done = run_cli("import", path, "--out", tmp_path / "ds")
    assert done.returncode == 0, done.stderr
    warning = [line for line in done.stderr.splitlines() if line.startswith("fsswarp: warning: ")]
    assert len(warning) == 2 and "window start" in warning[0] and "window length" in warning[1], done.stderr
    assert "1500 m/s" in warning[0] and "--window-start M" in warning[0]
    quiet = run_cli("import", path, "--out", tmp_path / "ds", "--window-start", "0.77", "--window-length", "2.3")
    assert quiet.returncode == 0 and "warning" not in quiet.stderr, quiet.stderr
    record = json.loads((tmp_path / "ds" / "source.json").read_text())
    assert record["given"] == {"window_start_m": 0.77, "window_length_m": 2.3}
    assert load_dataset(tmp_path / "ds").sonar.range_min == 0.77


# --- ARIS through the same command ---------------------------------------------------------------

def test_aris_through_import_keeps_aris_json_and_adds_source_json(tmp_path):
    path = write(tmp_path, aris_recording(frames=2), "rec.aris")
    dataset = import_recording(path, tmp_path / "ds", depth_m=0.45)
    aris = json.loads((tmp_path / "ds" / "aris.json").read_text())
    source = json.loads((tmp_path / "ds" / "source.json").read_text())
    assert (source["format"], source["version"], source["given"]) == ("ARIS", 5, {"depth_m": 0.45})
    assert source["header_values"] == aris and aris["system"] == "ARIS 1200"
    assert dataset.manifest.surface.depth == 0.45
    with pytest.raises(InputError, match=r"--window-length = 2.0: does not apply to ARIS recordings"):
        import_recording(path, tmp_path / "other", window_length_m=2.0)
    assert not (tmp_path / "other").exists()


def test_import_replaces_earlier_imports_of_either_kind_and_nothing_else(tmp_path):
    aris, didson = write(tmp_path, aris_recording(frames=1), "rec.aris"), write(tmp_path, recording(frames=1))
    out = tmp_path / "ds"
    from fsswarp.aris import import_aris

    import_aris(aris, out)                                             # an import-aris folder: aris.json only
    assert not (out / "source.json").exists()
    import_recording(didson, out)
    import_recording(aris, out)
    import_recording(didson, out)
    assert json.loads((out / "source.json").read_text())["format"] == "DIDSON" and not (out / "aris.json").exists()
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    with pytest.raises(InputError, match=r"no source\.json"):
        import_recording(didson, mine)
    assert listing(mine) == ["notes.txt"]


def test_import_aris_is_another_name_for_import(tmp_path, capsys):
    path = write(tmp_path, recording(version=3, beams=48, frames=1))
    assert main(["import-aris", str(path), "--out", str(tmp_path / "ds"), "--window-start", "1.5"]) == 0
    assert load_dataset(tmp_path / "ds").sonar.range_min == 1.5
    assert "DIDSON v3" in capsys.readouterr().out


# --- a DIDSON dataset carves like the simulation it came from ------------------------------------

@pytest.mark.slow
def test_an_imported_recording_carves_like_its_simulation(tmp_path, capsys):
    """coral-one simulated with the DIDSON's 96-beam lens and window (start code 3, length code 1,
    high frequency, classic windows), written as a .ddf in stored order (mirrored) at 90 dB, and
    imported with its poses: ``fsswarp check`` passes and ``fsswarp carve`` keeps the volume it
    keeps from the simulation (beam order, lens and range all matter to that)."""
    from fsswarp.didson import beam_angles_deg
    from fsswarp.rendering import RenderSettings
    from fsswarp.scenes import builtin_scene
    from fsswarp.simulation import simulate
    from fsswarp.sonar import SonarSpec

    start, length = 3 * 0.375, 2.25
    sonar = SonarSpec.from_degrees(beams=96, bins=512, azimuth_fov_deg=None, elevation_fov_deg=14.0,
                                   range_min_m=start, range_max_m=start + 511 * length / 512,
                                   beam_angles_deg=beam_angles_deg(96))
    scene = dataclasses.replace(builtin_scene("coral-one"), sonar=sonar)
    sim = simulate(scene, tmp_path / "sim", settings=RenderSettings(samples=(1, 16)))
    frames = []
    for view in sim.rig.views:
        image = sim.images[view.name]
        db = 90 + 20 * np.log10(np.maximum(image, 1e-12) / image.max())
        frames.append(np.clip(np.rint(db * 255 / 90), 0, 255).astype(np.uint8)[:, ::-1])
    surface = sim.manifest.surface
    path = write(tmp_path, recording(version=4, beams=96, frames=frames, frame_values={
        "windowstart": 3, "windowlength": 1, "depth": surface.depth, "sonartilt": math.degrees(surface.tilt)}))
    poses = tmp_path / "poses.csv"
    poses.write_text("frame,x_m,y_m,heading_deg,roll_deg,depth_offset_m,tilt_offset_deg\n" + "".join(
        f"{k},{v.position[0]!r},{v.position[1]!r},{math.degrees(v.heading)!r},{math.degrees(v.roll)!r},"
        f"{v.depth_offset!r},{math.degrees(v.tilt_offset)!r}\n" for k, v in enumerate(sim.rig.views)))
    out = tmp_path / "ds"
    assert main(["import", str(path), "--out", str(out), "--poses", str(poses)]) == 0
    assert main(["check", str(out)]) == 0
    imported = load_dataset(out)
    assert imported.manifest.surface.depth == pytest.approx(surface.depth, abs=1e-6)
    assert [v.roll for v in imported.rig.views] == pytest.approx([v.roll for v in sim.rig.views], abs=1e-9)
    volumes = []
    for folder in (out, tmp_path / "sim"):
        carved = tmp_path / f"carve-{folder.name}"
        assert main(["carve", str(folder), "--out", str(carved), "--resolution", "32"]) == 0
        record = json.loads((carved / "carve.json").read_text())
        assert len(record["views"]) == 16 and record["mesh"]["faces"] > 0
        volumes.append(record["mesh"]["volume_m3"])
    assert volumes[0] == pytest.approx(volumes[1], rel=0.05)
    capsys.readouterr()


# --- bad recordings on the command line ----------------------------------------------------------

@pytest.mark.parametrize("case", [*bad_cases(), "empty", "poses-roll", "frames-beyond"])
def test_bad_recordings_exit_2_with_one_line_and_write_nothing(tmp_path, capsys, case):
    args = []
    if case == "empty":
        data, needle = b"", "too short"
    elif case == "poses-roll":
        (tmp_path / "poses.csv").write_text("frame,x_m,y_m,heading_deg,roll_deg\n0,0,0,0,999\n1,0,0,0,0\n")
        data, needle, args = recording(frames=2), "views[0].roll_deg = 999.0", ["--poses", str(tmp_path / "poses.csv")]
    elif case == "frames-beyond":
        data, needle, args = recording(frames=2), "--frames = '1-2'", ["--frames", "1-2"]
    else:
        data, needle = bad_cases()[case]
    path = write(tmp_path, data, f"{case}.ddf")
    before = listing(tmp_path)
    code = main(["import", str(path), "--out", str(tmp_path / "out"), *args])
    lines = capsys.readouterr().err.splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("fsswarp: error: "), lines
    assert needle in lines[0] and (str(path) in lines[0] or case == "poses-roll"), lines[0]
    assert listing(tmp_path) == before                                 # no output, no temporary folder


def test_a_bad_recording_exits_2_from_the_installed_command(tmp_path):
    path = write(tmp_path, bad_cases()["length-code-4"][0])
    done = run_cli("import", path, "--out", tmp_path / "out")
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert done.stderr.splitlines() == [f"fsswarp: error: {path}: frames[0].windowlength = 4: must be a length "
                                        "code 0-3"]
    assert listing(tmp_path) == ["rec.ddf"]


# --- fuzzing through files ------------------------------------------------------------------------

def check_outcome(code: int, err: str, path: Path, out: Path) -> str:
    if code == 0:
        assert load_dataset(out).rig.names
        return "dataset"
    lines = err.splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith(f"fsswarp: error: {path}"), (code, lines)
    assert not out.exists() and not [p for p in out.parent.iterdir() if p.name.startswith(".out.")]
    return "error"


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::fsswarp.didson.DidsonWarning")
def test_fuzz_mutated_files_through_the_import_and_the_command_line(tmp_path, capsys):
    """600 mutated recordings written to disk and imported (``import_recording``, what the
    command runs), and 40 through ``fsswarp import`` itself (a dataset and exit 0, or one line
    and exit 2, and no output folder)."""
    rng = random.Random(36)
    path, out = tmp_path / "fuzz.ddf", tmp_path / "out"
    outcomes = {"dataset": 0, "error": 0}
    for i in range(640):
        path.write_bytes(mutate(rng, BASES[i % 3]))
        if out.exists():
            for p in sorted(out.rglob("*"), reverse=True):
                p.unlink() if p.is_file() else p.rmdir()
            out.rmdir()
        if i < 600:
            try:
                import_recording(path, out, depth_m=0.5, tilt_deg=0.0)
                code, err = 0, ""
            except InputError as error:
                code, err = 2, f"fsswarp: error: {error}"
        else:
            code = main(["--quiet", "import", str(path), "--out", str(out), "--depth", "0.5", "--tilt", "0"])
            err = capsys.readouterr().err
        outcomes[check_outcome(code, err, path, out)] += 1
    assert outcomes["dataset"] > 100 and outcomes["error"] > 100, outcomes
