"""ARIS recordings: the reader against the SDK's sample file and an independent parse, the beam
order and tables, ``fsswarp import-aris`` as a user runs it, bad files, and fuzzing."""

import csv
import json
import math
import os
import struct
import subprocess
import sys
import warnings
import zipfile
from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fsswarp.aris import (ArisWarning, beam_table, import_aris, linear_intensity, open_aris, parse_frames,
                          read_poses)
from fsswarp.cli import main
from fsswarp.dataset import load_dataset
from fsswarp.errors import InputError
from fsswarp.rendering import log_compress

REPO = Path(__file__).resolve().parents[1]
DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "aris"
SAMPLE = DATA / "sample.aris"
needs_sample = pytest.mark.skipif(not SAMPLE.is_file(), reason=f"the ARIS sample recording is absent: {SAMPLE}")

SIG = 0x05464444
BEAMS, SAMPLES, FRAMES = 48, 2000, 6
FRAME = 1024 + BEAMS * SAMPLES                 # bytes per frame of sample.aris
SIZE = 1024 + FRAMES * FRAME                   # its size
TABLE_NAMES = ("ARIS1800_1200_48", "ARIS1800_96", "ARIS3000_64", "ARIS3000_128", "ARIS_Telephoto_48",
               "ARIS_Telephoto_96")


@pytest.fixture(scope="module")
def sample_bytes() -> bytes:
    if not SAMPLE.is_file():
        pytest.skip(f"the ARIS sample recording is absent: {SAMPLE}")
    return SAMPLE.read_bytes()


def put(data: bytearray, offset: int, fmt: str, value) -> bytearray:
    struct.pack_into("<" + fmt, data, offset, value)
    return data


def frame_header_at(frame: int) -> int:
    return 1024 + frame * FRAME


def raw_samples(data: bytes, frame: int) -> np.ndarray:
    """(samples, beams) uint8 of sample.aris as stored (ARIS beam order), parsed here."""
    return np.frombuffer(data, np.uint8, count=BEAMS * SAMPLES,
                         offset=frame_header_at(frame) + 1024).reshape(SAMPLES, BEAMS)


def table_csv(name: str) -> dict[str, np.ndarray]:
    """The SDK's original table (beside the checkout), independent of the packaged copy."""
    path = DATA / f"beam-angles-{name}.csv"
    if not path.is_file():
        pytest.skip(f"the SDK's beam-angle tables are absent: {path}")
    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    return {k: np.array([float(r[k]) for r in rows]) for k in ("center_deg", "left_deg", "right_deg")}


def synthetic(*, frames: int = 3, ping_mode: int = 1, samples: int = 16, system: int = 2, lens: int = 0,
              depth=0.6, pitch=4.0) -> bytes:
    """A small recording: sample value = ARIS beam number (beam 0 right-most), window start
    1352 µs · 1480 m/s / 2 = 1.00048 m, sample length 10 µs → 7.4 mm. ``depth`` and ``pitch``
    may be per-frame lists."""
    beams = 48 if ping_mode <= 2 else 96 if ping_mode <= 5 else 64 if ping_mode <= 8 else 128
    out = put(put(bytearray(1024), 0, "I", SIG), 4, "I", frames)
    for k in range(frames):
        header = bytearray(1024)
        for offset, fmt, value in ((0, "I", k), (12, "I", SIG), (436, "I", ping_mode), (452, "I", 10),
                                   (464, "f", 1480.0), (468, "I", samples), (476, "I", 1352), (480, "I", lens),
                                   (484, "I", system), (516, "I", 1),
                                   (128, "f", depth[k] if isinstance(depth, list) else depth),
                                   (164, "f", pitch[k] if isinstance(pitch, list) else pitch)):
            put(header, offset, fmt, value)
        out += header + np.tile(np.arange(beams, dtype=np.uint8), (samples, 1)).tobytes()
    return bytes(out)


def write(tmp_path: Path, data: bytes, name: str = "rec.aris") -> Path:
    path = tmp_path / name
    path.write_bytes(data)
    return path


def listing(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


# --- the sample recording ----------------------------------------------------------------------

@needs_sample
def test_sample_recording_facts():
    with open_aris(SAMPLE) as aris:
        assert (aris.frame_count, aris.beams, aris.samples_per_beam) == (6, 48, 2000)
        assert aris.file_header.frame_count_stored == 6
        header = aris.frame_header(0)
        assert header.system_type == 2 and header.large_lens == 1 and header.ping_mode == 1
        assert header.sample_start_delay_us == 4593 and header.sample_period_us == 14
        assert header.window_start_m == pytest.approx(4593e-6 * header.sound_speed_m_s / 2)
        assert header.window_start_m == pytest.approx(3.298, abs=5e-4)
        assert header.window_start_m_stored == pytest.approx(3.330, abs=5e-4)
        assert header.window_length_m == pytest.approx(20.10, abs=5e-3)
        assert header.window_length_m_stored == pytest.approx(20.30, abs=5e-3)
        spec = aris.sonar_spec()
        assert (spec.beams, spec.bins) == (48, 2000)
        assert spec.range_min == header.window_start_m
        assert spec.range_max == pytest.approx(header.window_start_m + 1999 * 14e-6 * header.sound_speed_m_s / 2)
        assert math.degrees(spec.elevation_fov) == pytest.approx(14.0)
        assert math.degrees(aris.sonar_spec(elevation_fov_deg=3.0).elevation_fov) == pytest.approx(3.0)
        assert aris.beam_table().name == "ARIS_Telephoto_48"


@needs_sample
def test_frame_images_match_an_independent_parse(sample_bytes):
    with open_aris(SAMPLE) as aris:
        for frame in (0, 5):
            raw = raw_samples(sample_bytes, frame)
            expected = (10.0 ** ((raw[:, ::-1] * (80.0 / 255.0) - 80.0) / 20.0)).astype(np.float32)
            image = aris.frame_image(frame)
            assert image.shape == (2000, 48) and image.dtype == np.float32
            np.testing.assert_allclose(image, expected, rtol=1e-6)
            np.testing.assert_array_equal(aris.frame_samples(frame), raw[:, ::-1])
            # the image spans the file's values, and 8-bit log compression at 80 dB gives them back
            assert image.min() == pytest.approx(10 ** ((int(raw.min()) * 80 / 255 - 80) / 20), rel=1e-6)
            assert image.max() == pytest.approx(10 ** ((int(raw.max()) * 80 / 255 - 80) / 20), rel=1e-6)
            np.testing.assert_array_equal(log_compress(image, dynamic_range_db=80.0, peak=1.0), raw[:, ::-1])
    assert raw.min() < raw.max()


def test_intensity_scale_end_points():
    values = linear_intensity(np.array([0, 255], np.uint8))
    np.testing.assert_allclose(values, [1e-4, 1.0], rtol=1e-6)
    assert values.dtype == np.float32


@needs_sample
def test_beam_angles_are_the_telephoto_table_reversed():
    table = table_csv("ARIS_Telephoto_48")
    with open_aris(SAMPLE) as aris:
        spec = aris.sonar_spec()
    np.testing.assert_allclose(np.degrees(spec.beam_angles), -table["center_deg"][::-1], atol=1e-12)
    assert math.degrees(spec.azimuth_fov) == pytest.approx(2 * 7.339)
    assert spec.beam_angles[0] < 0 < spec.beam_angles[-1]


def test_column_zero_is_the_left_most_beam(tmp_path):
    """ARIS beam 0 is the right-most: it lands in the last column, at the most positive θ."""
    path = write(tmp_path, synthetic(ping_mode=3, system=0))           # ARIS 1800, 96 beams
    table = table_csv("ARIS1800_96")                                   # an asymmetric table
    with open_aris(path) as aris:
        samples = aris.frame_samples(1)
        spec = aris.sonar_spec(frame=1)
    np.testing.assert_array_equal(samples[0], np.arange(96)[::-1])    # column b holds ARIS beam 95 - b
    np.testing.assert_allclose(np.degrees(spec.beam_angles), -table["center_deg"][::-1], atol=1e-12)
    assert np.degrees(spec.beam_angles[0]) == pytest.approx(-13.8759)
    assert spec.range_min == pytest.approx(1352e-6 * 1480 / 2)
    assert spec.range_step == pytest.approx(10e-6 * 1480 / 2)


@pytest.mark.parametrize("name", TABLE_NAMES)
def test_packaged_tables_are_the_sdk_tables_in_fsswarp_order(name):
    packaged = REPO / "fsswarp" / "data" / "aris" / f"beam-angles-{name}.csv"
    if (DATA / packaged.name).is_file():
        assert packaged.read_bytes() == (DATA / packaged.name).read_bytes()
    table = beam_table(name)
    with open(packaged, newline="") as handle:
        rows = list(csv.DictReader(handle))
    centre = np.array([float(r["center_deg"]) for r in rows])
    np.testing.assert_array_equal(table.centre, -centre[::-1])
    assert np.all(np.diff(table.centre) > 0)
    assert table.aperture_deg == pytest.approx(float(rows[-1]["right_deg"]) - float(rows[0]["left_deg"]))


@pytest.mark.parametrize("system, lens, ping_mode, name", [
    (2, 0, 1, "ARIS1800_1200_48"), (0, 0, 2, "ARIS1800_1200_48"), (0, 0, 3, "ARIS1800_96"),
    (1, 0, 6, "ARIS3000_64"), (1, 0, 9, "ARIS3000_128"), (2, 1, 1, "ARIS_Telephoto_48"),
    (0, 1, 1, "ARIS_Telephoto_48"), (0, 1, 4, "ARIS_Telephoto_96"),
    (1, 1, 6, "telephoto lens and 64 beams"), (2, 0, 3, "ARIS 1200 with the standard lens and 96"),
    (3, 0, 1, "TheSystemType"), (2, 2, 1, "LargeLens"),
])
def test_beam_table_follows_system_lens_and_beams(tmp_path, system, lens, ping_mode, name):
    with open_aris(write(tmp_path, synthetic(ping_mode=ping_mode, system=system, lens=lens))) as aris:
        if name in TABLE_NAMES:
            assert aris.beam_table().name == name
        else:
            with pytest.raises(InputError, match=name) as info:
                aris.sonar_spec()
            assert "\n" not in str(info.value) and "rec.aris" in str(info.value)


# --- import into a dataset ---------------------------------------------------------------------

def run_cli(*args, cwd=None):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    return subprocess.run([sys.executable, "-m", "fsswarp", *map(str, args)], capture_output=True, text=True,
                          timeout=300, cwd=cwd, env=env)


@needs_sample
def test_import_aris_writes_a_dataset_that_loads_and_checks(tmp_path):
    out = tmp_path / "ds"
    done = run_cli("import-aris", SAMPLE, "--out", out, "--depth", "0.5")
    assert done.returncode == 0, done.stderr
    assert "3.298" in done.stdout and "3.33" in done.stdout           # computed and stored window start
    dataset = load_dataset(out)
    names = [f"f{i:04d}" for i in range(6)]
    assert dataset.rig.names == names
    with open_aris(SAMPLE) as aris:
        for i, name in enumerate(names):
            np.testing.assert_array_equal(dataset.images[name], aris.frame_image(i))
        pitch = [aris.frame_header(i).compass_pitch_deg for i in range(6)]
        spec = aris.sonar_spec()
    assert dataset.manifest.surface.depth == 0.5
    assert math.degrees(dataset.manifest.surface.tilt) == pytest.approx(float(np.median(pitch)))
    np.testing.assert_allclose(dataset.sonar.beam_angles, spec.beam_angles, atol=1e-15)
    assert (dataset.sonar.range_min, dataset.sonar.range_max) == pytest.approx((spec.range_min, spec.range_max))
    record = json.loads((out / "aris.json").read_text())
    assert record["system"] == "ARIS 1200" and record["lens"] == "telephoto"
    assert record["frames"][0]["window_start_m_stored"] == pytest.approx(3.330, abs=5e-4)
    assert record["surface"]["depth_source"] == "--depth"
    assert "CompassPitch" in record["surface"]["tilt_source"]
    figure = out / "figures" / "frame0_fan.png"
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    check = run_cli("check", out)
    assert check.returncode == 0, check.stderr


def test_import_takes_frames_poses_and_sensor_values(tmp_path):
    path = write(tmp_path, synthetic(frames=4, depth=[0.5, 0.7, 0.6, 9.0], pitch=[3.0, 5.0, 4.0, 80.0]))
    poses = tmp_path / "poses.csv"
    poses.write_text("# x, y in metres; angles in degrees\n"
                     "frame,x_m,y_m,heading_deg,roll_deg,tilt_offset_deg\n"
                     "0, 0, 0, 0, 0, 0\n"
                     "1, 0.5, -0.25, 90, 22.5, 1\n\n"
                     "2, 1, 2, 180, -45, 0\n"
                     "3, 9, 9, 9, 9, 9\n")
    dataset = import_aris(path, tmp_path / "ds", frames="2,0-1", poses=poses, elevation_fov_deg=3.0)
    assert dataset.rig.names == ["f0002", "f0000", "f0001"]
    view = dataset.rig.views[2]
    assert view.position == (0.5, -0.25)
    assert (view.heading, view.roll, view.tilt_offset) == (math.radians(90), math.radians(22.5), math.radians(1))
    assert dataset.manifest.surface.depth == pytest.approx(0.6)         # median of the selected frames
    assert math.degrees(dataset.manifest.surface.tilt) == pytest.approx(4.0)
    assert math.degrees(dataset.sonar.elevation_fov) == pytest.approx(3.0)
    assert dataset.images["f0002"].shape == (16, 48)
    record = json.loads((tmp_path / "ds" / "aris.json").read_text())
    assert [f["sensor_depth_m"] for f in record["frames"]] == pytest.approx([0.6, 0.5, 0.7])
    assert record["elevation_source"] == "--elevation-fov-deg"
    # without poses every view sits at the origin; given values replace the sensors'
    again = import_aris(path, tmp_path / "ds", frames=[1], depth_m=0.45, tilt_deg=-2.0)
    assert again.rig.views[0].position == (0.0, 0.0)
    assert (again.manifest.surface.depth, math.degrees(again.manifest.surface.tilt)) == pytest.approx((0.45, -2.0))


@pytest.mark.parametrize("spec, expected", [
    (None, [0, 1, 2, 3, 4, 5]), ("all", [0, 1, 2, 3, 4, 5]), ("0-3,5", [0, 1, 2, 3, 5]), (" 4 , 1-2", [4, 1, 2]),
    ([5, 0], [5, 0]), ("3", [3]),
])
def test_frames_spec_selects_frames(spec, expected):
    assert parse_frames(spec, 6) == expected


@pytest.mark.parametrize("spec", ["", "6", "0-6", "3-1", "1,1", "0-2,2", "a", "1;2", "-1", "1-", "٣", [6], [True],
                                  "99999999999999999999"])
def test_frames_spec_mistakes_are_refused(spec):
    with pytest.raises(InputError, match="--frames") as info:
        parse_frames(spec, 6, file="rec.aris")
    assert "\n" not in str(info.value) and "rec.aris" in str(info.value)


@pytest.mark.parametrize("text, field", [
    ("frame,x_m,y_m,heading_deg\n0,0,0,0\n", "roll_deg"),
    ("frame,x_m,y_m,heading_deg,roll_deg,speed\n", "speed"),
    ("frame,x_m,y_m,heading_deg,roll_deg\n0,0,0,0,zero\n", "line 2.roll_deg"),
    ("frame,x_m,y_m,heading_deg,roll_deg\n0,nan,0,0,0\n", "line 2.x_m"),
    ("frame,x_m,y_m,heading_deg,roll_deg\n0,0,0,0,0\n0,1,1,1,1\n", "line 3.frame"),
    ("frame,x_m,y_m,heading_deg,roll_deg\n0,0,0,0\n", "line 2"),
    ("frame,x_m,y_m,heading_deg,roll_deg\nx,0,0,0,0\n", "line 2.frame"),
    ("frame,x_m,y_m,heading_deg,roll_deg\n1,0,0,0,0\n", "frame = 0"),
    ("# nothing\n", "--poses"),
])
def test_pose_file_mistakes_are_refused(tmp_path, text, field):
    path = tmp_path / "poses.csv"
    path.write_text(text)
    with pytest.raises(InputError) as info:
        read_poses(path, [0])
    message = str(info.value)
    assert "\n" not in message and str(path) in message and field in message


def test_an_import_and_a_simulation_never_replace_each_other(tmp_path):
    """import-aris replaces only an earlier import (its aris.json), simulate only an earlier
    simulation (its truth model): a recording is never lost to a simulation with swapped
    arguments, nor a simulation to an import; each refuses before its work."""
    from fsswarp.simulation import simulate

    path = write(tmp_path, synthetic(frames=1))
    imported = tmp_path / "imported"
    import_aris(path, imported)
    import_aris(path, imported)  # an earlier import is replaced
    before = sorted((p.relative_to(imported), p.stat().st_mtime_ns) for p in imported.rglob("*"))
    with pytest.raises(InputError, match="--out = .*imported.*not an fsswarp output of this command "
                                         r"\(no truth/model\.ply\)"):
        simulate("coral-one", imported)
    assert sorted((p.relative_to(imported), p.stat().st_mtime_ns) for p in imported.rglob("*")) == before
    simulated = tmp_path / "simulated"
    simulated.mkdir()
    (simulated / "dataset.toml").write_text("# a dataset of another kind\n")
    with pytest.raises(InputError, match=r"no aris\.json"):
        import_aris(path, simulated)
    assert [p.name for p in simulated.iterdir()] == ["dataset.toml"]


@pytest.mark.parametrize("row, field", [("0,0,0,0,999,0", "roll_deg = 999.0"), ("0,0,0,0,0,90", "tilt_offset_deg")])
def test_pose_values_out_of_range_name_the_pose_file(tmp_path, row, field):
    """A pose row that the manifest refuses (a roll of 999°) is reported against the pose
    file before anything is written, not against the temporary manifest of the output."""
    path = write(tmp_path, synthetic(frames=1))
    poses = tmp_path / "poses.csv"
    poses.write_text(f"frame,x_m,y_m,heading_deg,roll_deg,tilt_offset_deg\n{row}\n")
    with pytest.raises(InputError) as info:
        import_aris(path, tmp_path / "ds", poses=poses)
    message = str(info.value)
    assert message.startswith(f"{poses}: views[") and field in message and ".tmp" not in message
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([path.name, "poses.csv"])


# --- bad recordings on the command line --------------------------------------------------------

def _bad_cases(data: bytes) -> dict[str, tuple[bytes, list[str], str]]:
    """id -> (file bytes, extra arguments, text the error must name)."""
    rng = np.random.default_rng(9)
    head = frame_header_at(0)
    return {
        "empty": (b"", [], "too short"),
        "truncated-header": (data[:1500], [], "size = 1500"),
        "file-version": (bytes(put(bytearray(data), 0, "I", 0x05464443)), [], "header.Version = '0x05464443'"),
        "frame-version": (bytes(put(bytearray(data), head + 12, "I", 0)), [], "frames[0].Version"),
        "later-frame-version": (bytes(put(bytearray(data), frame_header_at(3) + 12, "I", 1)), [], "frames[3].Version"),
        "zero-samples": (bytes(put(bytearray(data), head + 468, "I", 0)), [], "frames[0].SamplesPerBeam = 0"),
        "ping-mode-0": (bytes(put(bytearray(data), head + 436, "I", 0)), [], "frames[0].PingMode = 0"),
        "ping-mode-13": (bytes(put(bytearray(data), head + 436, "I", 13)), [], "frames[0].PingMode = 13"),
        "claims-more-data": (bytes(put(bytearray(data), head + 468, "I", 0xFFFFFFFF)), [], "SamplesPerBeam"),
        "headers-only": (data[:2048], [], "frames[0].SamplesPerBeam = 2000"),
        "sound-speed-nan": (bytes(put(bytearray(data), head + 464, "f", math.nan)), [], "frames[0].SoundSpeed"),
        "random-bytes": (rng.integers(0, 256, 200_000, dtype=np.uint8).tobytes(), [], "header.Version"),
        "no-depth-sensor": (data, [], "frames[0].Depth = 0.0"),
        "no-such-frame": (data, ["--frames", "2-6"], "--frames = '2-6'"),
        "bad-elevation": (data, ["--elevation-fov-deg", "0"], "--elevation-fov-deg = 0.0"),
    }


@pytest.fixture(scope="module")
def bad_cases(sample_bytes):
    return _bad_cases(sample_bytes)


@needs_sample
@pytest.mark.parametrize("case", list(_bad_cases(bytes(SIZE))))
def test_bad_recordings_exit_2_with_one_line_and_write_nothing(bad_cases, tmp_path, capsys, case):
    data, args, needle = bad_cases[case]
    path = write(tmp_path, data, f"{case}.aris")
    before = listing(tmp_path)
    depth = [] if case == "no-depth-sensor" else ["--depth", "0.5"]
    code = main(["import-aris", str(path), "--out", str(tmp_path / "out"), *args, *depth])
    lines = capsys.readouterr().err.splitlines()
    assert code == 2, lines
    assert len(lines) == 1 and lines[0].startswith("fsswarp: error: "), lines
    assert str(path) in lines[0] or case == "bad-elevation"
    assert needle in lines[0], lines[0]
    assert listing(tmp_path) == before                                 # no output, no temporary folder


@needs_sample
def test_a_bad_recording_exits_2_from_the_installed_command(bad_cases, tmp_path):
    path = write(tmp_path, bad_cases["random-bytes"][0], "random.aris")
    done = run_cli("import-aris", path, "--out", tmp_path / "out", "--depth", "0.5")
    assert done.returncode == 2 and "Traceback" not in done.stderr
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"fsswarp: error: {path}: header.Version = "), lines
    assert listing(tmp_path) == ["random.aris"]


@needs_sample
def test_partial_last_frame_is_ignored_with_a_warning(tmp_path, sample_bytes):
    path = write(tmp_path, sample_bytes[: SIZE - 1000])
    with pytest.warns(ArisWarning, match="partial frame"):
        aris = open_aris(path)
    with aris:
        assert aris.frame_count == 5
        with pytest.raises(InputError, match="no such frame"):
            aris.frame_header(5)
        np.testing.assert_array_equal(aris.frame_samples(4), raw_samples(sample_bytes, 4)[:, ::-1])


def test_frames_of_another_size_or_window_are_refused(tmp_path):
    data = bytearray(synthetic(frames=3))
    frame = 1024 + 48 * 16
    put(data, 1024 + 2 * frame + 468, "I", 17)                         # frame 2 claims another size
    with open_aris(write(tmp_path, bytes(data))) as aris:
        with pytest.raises(InputError, match=r"frames\[2\].SamplesPerBeam = 17"):
            aris.frame_image(2)
    data = bytearray(synthetic(frames=3))
    put(data, 1024 + frame + 476, "I", 2000)                           # frame 1 starts further out
    path = write(tmp_path, bytes(data), "window.aris")
    with pytest.raises(InputError, match="range window"):
        import_aris(path, tmp_path / "ds")
    assert import_aris(path, tmp_path / "ds", frames="1").sonar.range_min == pytest.approx(2000e-6 * 1480 / 2)


def test_wheel_ships_the_beam_tables_and_their_licence(tmp_path):
    subprocess.run([sys.executable, "-m", "build", "--wheel", "--no-isolation", "--outdir", str(tmp_path), str(REPO)],
                   check=True, capture_output=True)
    names = set(zipfile.ZipFile(next(tmp_path.glob("fsswarp-*.whl"))).namelist())
    for name in TABLE_NAMES:
        assert f"fsswarp/data/aris/beam-angles-{name}.csv" in names
    assert "fsswarp/data/aris/LICENSE-SoundMetrics-aris-file-sdk.txt" in names


# --- fuzzing ------------------------------------------------------------------------------------

def check_error(err: InputError, path: Path) -> None:
    message = str(err)
    assert "\n" not in message and message and str(path) in message, message


def exercise(path: Path) -> None:
    """Read what the reader offers (the first eight frames and the last); only InputError may
    stop it, and what it returns must be sane."""
    size = path.stat().st_size
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ArisWarning)
        try:
            aris = open_aris(path)
        except InputError as err:
            check_error(err, path)
            return
    with aris:
        assert aris.frame_count >= 1 and 1024 + aris.frame_count * aris.frame_bytes <= size
        for frame in sorted({*range(min(8, aris.frame_count)), aris.frame_count - 1}):
            try:
                aris.frame_header(frame)
                image = aris.frame_image(frame)
            except InputError as err:
                check_error(err, path)
                continue
            assert image.shape == (aris.samples_per_beam, aris.beams) and image.dtype == np.float32
            assert float(image.min()) >= np.float32(1e-4) * 0.999 and float(image.max()) <= 1.0
            try:
                spec = aris.sonar_spec(frame=frame)
            except InputError as err:
                check_error(err, path)
                continue
            assert spec.bins == aris.samples_per_beam and spec.range_max > spec.range_min >= 0


@pytest.fixture(scope="module")
def fuzz_file(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz") / "fuzz.aris"


HEADERS = [0] + [frame_header_at(0)] * 4 + [frame_header_at(k) for k in range(1, FRAMES)]
FIELDS = [0, 4, 12, 52, 56, 128, 164, 436, 452, 464, 468, 476, 480, 484, 516]
U32 = [0, 1, 2, 3, 6, 9, 12, 13, 48, 96, 128, 2000, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFE, 0xFFFFFFFF, SIG]
F32 = [0.0, -0.0, -1.0, 1e-45, 999.0, 1480.0, 2001.0, 1e38, -1e38, math.inf, -math.inf, math.nan]
mutations = st.one_of(
    st.tuples(st.just("flip"), st.sampled_from(HEADERS), st.integers(0, 1023), st.integers(0, 7)),
    st.tuples(st.just("I"), st.sampled_from(HEADERS), st.sampled_from(FIELDS), st.sampled_from(U32)),
    st.tuples(st.just("f"), st.sampled_from(HEADERS), st.sampled_from(FIELDS), st.sampled_from(F32)),
    st.tuples(st.just("byte"), st.integers(0, SIZE - 1), st.just(0), st.integers(0, 255)),
)
FUZZ = dict(derandomize=True, database=None, deadline=timedelta(seconds=5),
            suppress_health_check=[HealthCheck.too_slow])


def mutate(data: bytes, changes, cut) -> bytes:
    out = bytearray(data)
    for kind, base, offset, value in changes:
        if kind == "flip":
            out[base + offset] ^= 1 << value
        elif kind == "byte":
            out[base] = value
        else:
            put(out, base + offset, kind, value)
    return bytes(out if cut is None else out[:cut])


@needs_sample
@settings(max_examples=2500, **FUZZ)
@given(changes=st.lists(mutations, min_size=1, max_size=6), cut=st.none() | st.integers(0, SIZE))
def test_fuzz_mutated_headers_never_crash_the_reader(sample_bytes, fuzz_file, changes, cut):
    fuzz_file.write_bytes(mutate(sample_bytes, changes, cut))
    exercise(fuzz_file)


@needs_sample
@settings(max_examples=400, **FUZZ)
@given(cut=st.integers(0, SIZE))
def test_fuzz_truncated_copies_never_crash_the_reader(sample_bytes, fuzz_file, cut):
    fuzz_file.write_bytes(sample_bytes[:cut])
    exercise(fuzz_file)


@settings(max_examples=600, **FUZZ)
@given(head=st.binary(min_size=0, max_size=2100), valid=st.booleans(), ping_mode=st.integers(0, 13),
       samples=st.integers(0, 70), tail=st.integers(0, 40_000), seed=st.integers(0, 2**32 - 1))
def test_fuzz_random_bytes_never_crash_the_reader(fuzz_file, head, valid, ping_mode, samples, tail, seed):
    """Random bytes; with ``valid``, behind version words and a plausible ping mode and size."""
    data = bytearray(head.ljust(2048, b"\0") if valid else head)
    if valid:
        put(put(put(put(data, 0, "I", SIG), 1024 + 12, "I", SIG), 1024 + 436, "I", ping_mode), 1024 + 468, "I", samples)
    data += np.random.default_rng(seed).integers(0, 256, tail, dtype=np.uint8).tobytes()
    fuzz_file.write_bytes(bytes(data))
    exercise(fuzz_file)


@needs_sample
@settings(max_examples=40, **FUZZ)
@given(changes=st.lists(mutations, min_size=1, max_size=4), cut=st.none() | st.integers(2048, SIZE))
def test_fuzz_import_gives_a_dataset_or_an_input_error(sample_bytes, fuzz_file, changes, cut):
    fuzz_file.write_bytes(mutate(sample_bytes, changes, cut))
    out = fuzz_file.parent / "ds"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ArisWarning)
        try:
            dataset = import_aris(fuzz_file, out, depth_m=0.5, tilt_deg=0.0)
        except InputError as err:
            check_error(err, fuzz_file)
            return
    assert load_dataset(out).rig.names == dataset.rig.names
