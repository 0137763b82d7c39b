"""DIDSON recordings: the test writer against hand-packed headers, the reader's frames, beam
order, lens fit, intensity and window decoding against the published tables, the sample-rate
check, overrides, sensor values, bad files, and fuzzing from memory."""

import math
import random
import struct
import warnings

import numpy as np
import pytest

from didson_writer import frame_header, recording
from fsswarp.didson import (DidsonFile, DidsonWarning, beam_angles_deg, didson_dataset, linear_intensity,
                            open_didson)
from fsswarp.errors import InputError

HEADERS = {3: (512, 256), 4: (1024, 1024)}          # file and frame header bytes (MATLAB reader, Echoview)
# window lengths (m) from Sound Metrics' get_frame_header_ddf4.m: (long range, classic) -> table,
# index = length code + 2 at low frequency
LENGTHS = {(False, False): [1.25, 2.5, 5, 10, 20, 40], (False, True): [1.125, 2.25, 4.5, 9, 18, 36],
           (True, False): [2.5, 5, 10, 20, 40, 70], (True, True): [2.25, 4.5, 9, 18, 36, 72]}
# window start per code (m): 0.375 classic, 0.419 extended, at high frequency; twice at low
STARTS = {True: 0.375, False: 0.419}


def put(data: bytearray, offset: int, fmt: str, value) -> bytearray:
    struct.pack_into("<" + fmt, data, offset, value)
    return data


def frame_at(version: int, beams: int, k: int) -> int:
    head, frame_head = HEADERS[version]
    return head + k * (frame_head + 512 * beams)


def reader(data: bytes, name: str = "rec.ddf") -> DidsonFile:
    return DidsonFile(data, file=name)


# --- the writer against hand-packed bytes --------------------------------------------------------

@pytest.mark.parametrize("version", [3, 4])
def test_writer_headers_are_the_published_layout_byte_for_byte(version):
    """A few fields packed by hand at the offsets of the MATLAB reader (and, version 4, of the
    ARIS SDK's Sspd) and zeros elsewhere: the writer's headers are those bytes exactly."""
    head, frame_head = HEADERS[version]
    beams = 48
    samples = np.random.default_rng(3).integers(0, 256, (512, beams), dtype=np.uint8)
    written = recording(version=version, beams=beams, frames=[samples],
                        header={"numframes": 7, "resolution": 0, "samplerate": 1234.5, "reverse": 1,
                                "serialnumber": 321, "windowstart": 9, "windowlength": 2,
                                **({"sspd": 1490} if version == 4 else {})},
                        frame_values={"framenumber": 5, "windowstart": 12, "windowlength": 3, "depth": 0.625,
                                      "heading": 33.5, "sonarpan": 181.25, "sonartilt": -4.5, "sonarroll": 2.25,
                                      "latitude": -41.25, "configflags": 2})
    expected = bytearray(head + frame_head)
    expected[0:4] = b"DDF" + bytes([version])
    for offset, fmt, value in ((4, "i", 7), (12, "i", 0), (16, "i", 48), (20, "f", 1234.5), (24, "i", 512),
                               (32, "i", 9), (36, "i", 2), (40, "i", 1), (44, "i", 321)):
        put(expected, offset, fmt, value)
    if version == 4:
        put(expected, 384, "I", 1490)
    expected[head + 12:head + 16] = b"DDF" + bytes([version])
    for offset, fmt, value in ((0, "i", 5), (52, "i", 12), (56, "i", 3), (128, "f", 0.625), (152, "f", 33.5),
                               (160, "f", 181.25), (164, "f", -4.5), (168, "f", 2.25), (172, "d", -41.25),
                               (192, "i", 2)):
        put(expected, head + offset, fmt, value)
    assert written[:head + frame_head] == bytes(expected)
    assert len(written) == head + frame_head + 512 * beams
    data = np.frombuffer(written, np.uint8, offset=head + frame_head)
    for s, b in ((0, 0), (0, 47), (1, 0), (300, 17), (511, 47)):
        assert data[s * beams + b] == samples[s, b]                    # beam index fastest


def test_writer_refuses_unknown_fields():
    with pytest.raises(KeyError):
        frame_header(3, depht=1.0)


# --- frames, beam order, intensity ---------------------------------------------------------------

@pytest.mark.parametrize("version, beams", [(3, 48), (3, 96), (4, 48), (4, 96)])
def test_frames_beams_and_samples(version, beams):
    rng = np.random.default_rng(version * beams)
    frames = [rng.integers(0, 256, (512, beams), dtype=np.uint8) for _ in range(3)]
    didson = reader(recording(version=version, beams=beams, frames=frames, header={"numframes": 99}))
    assert (didson.version, didson.beams, didson.frame_count) == (version, beams, 3)
    assert didson.file_header.frame_count_stored == 99
    for k in range(3):
        np.testing.assert_array_equal(didson.frame_samples(k), frames[k][:, ::-1])
        assert didson.frame_header(k).frame_number == k
        image = didson.frame_image(k)
        assert image.shape == (512, beams) and image.dtype == np.float32
    spec = didson.sonar_spec()
    assert (spec.beams, spec.bins) == (beams, 512)


@pytest.mark.parametrize("reverse", [0, 1, -1])
def test_beam_order_as_sound_metrics_shows_it(reverse):
    """An asymmetric frame (value = 2·stored beam + sample mod 2): the stored frame is mirrored
    (column b = stored beam 95 − b) unless the reverse flag is set (column b = stored beam b)."""
    stored = (2 * np.arange(96)[None, :] + (np.arange(512)[:, None] % 2)).astype(np.uint8)
    samples = reader(recording(version=3, beams=96, frames=[stored], header={"reverse": reverse})).frame_samples(0)
    expected_beam = np.arange(96) if reverse else 95 - np.arange(96)
    np.testing.assert_array_equal(samples[0], 2 * expected_beam)
    np.testing.assert_array_equal(samples[1], 2 * expected_beam + 1)
    assert (samples[0, 0] == 0) == bool(reverse)


def test_intensity_is_90_db_full_scale():
    values = np.arange(256, dtype=np.uint8)
    expected = 10.0 ** ((values * (90.0 / 255.0) - 90.0) / 20.0)
    np.testing.assert_allclose(linear_intensity(values), expected, rtol=1e-6)
    assert linear_intensity(np.uint8(0)) == pytest.approx(10 ** -4.5, rel=1e-6)
    assert linear_intensity(np.uint8(255)) == pytest.approx(1.0)
    frame = np.random.default_rng(1).integers(0, 256, (512, 48), dtype=np.uint8)
    image = reader(recording(version=3, beams=48, frames=[frame])).frame_image(0)
    np.testing.assert_allclose(image, 10.0 ** ((frame[:, ::-1] * (90 / 255) - 90) / 20), rtol=1e-6)


# --- lens fit -------------------------------------------------------------------------------------

@pytest.mark.parametrize("beams, factor, a", [(48, 1.0, (0.0015, -0.0036, 1.3351, 24.0976)),
                                              (96, 1.012, (0.0030, -0.0055, 2.6829, 48.04))])
def test_beam_angles_solve_the_cubic_lens_fit(beams, factor, a):
    """Sound Metrics' lens_distortion.m maps an angle θ (deg) to the 1-based beam round(factor·
    (a0θ³ + a1θ² + a2θ + a3) + 1): beam centres are where that is exactly b + 1."""
    theta = beam_angles_deg(beams)
    cubic = factor * (a[0] * theta ** 3 + a[1] * theta ** 2 + a[2] * theta + a[3])
    np.testing.assert_allclose(cubic, np.arange(beams), atol=1e-9)
    assert np.all(np.diff(theta) > 0)
    assert -14.5 < theta[0] < -14.0 and 14.0 < theta[-1] < 14.5     # the DIDSON's ±14.4° field of view
    spec = reader(recording(version=4, beams=beams, frames=1)).sonar_spec()
    np.testing.assert_allclose(np.degrees(spec.beam_angles), theta, atol=1e-12)


# --- the range window -----------------------------------------------------------------------------

WINDOW_CASES = [(flags, high, start, length) for flags in range(4) for high in (True, False)
                for start, length in ((0, 0), (1, 3), (31, 2))]


@pytest.mark.parametrize("flags, high, start_code, length_code", WINDOW_CASES)
def test_window_decoding_follows_the_published_tables(flags, high, start_code, length_code):
    classic, long_range = bool(flags & 1), bool(flags & 2)
    data = recording(version=4, beams=96 if high else 48, frames=1, header={"resolution": int(high)},
                     frame_values={"configflags": flags | 0x10, "windowstart": start_code,
                                   "windowlength": length_code})
    window = reader(data).window(0)
    expected_length = LENGTHS[long_range, classic][length_code + (0 if high else 2)]
    expected_start = start_code * STARTS[classic] * (1 if high else 2)
    assert (window.classic, window.long_range, window.high_frequency) == (classic, long_range, high)
    assert window.start_m == pytest.approx(expected_start, abs=1e-12)
    assert window.length_m == pytest.approx(expected_length, abs=1e-12)
    assert window.configuration == (f"DIDSON-{'LR' if long_range else 'S'} "
                                    f"{'classic' if classic else 'extended'} windows")
    spec = reader(data).sonar_spec()
    assert spec.range_min == pytest.approx(expected_start)
    assert spec.range_max == pytest.approx(expected_start + 511 * expected_length / 512)


@pytest.mark.parametrize("serial, flags, expected", [(18, 2, (True, False)), (0, 0, (True, False)),
                                                     (15, 0, (True, True)), (19, 2, (False, True)),
                                                     (19, 0, (False, False))])
def test_old_serial_numbers_override_the_configuration_flags(serial, flags, expected):
    """The MATLAB reader's special cases: serial numbers below 19 are classic DIDSON-S, serial
    number 15 is a classic DIDSON-LR, whatever configflags says."""
    data = recording(version=3, beams=96, frames=1, header={"serialnumber": serial},
                     frame_values={"configflags": flags, "windowlength": 3})
    window = reader(data).window(0)
    assert (window.classic, window.long_range) == expected
    assert window.length_m == LENGTHS[expected[1], expected[0]][3]
    assert ("serial number" in window.config_source) == (serial < 19)


def test_window_check_uses_the_sample_rate_and_sound_speed():
    """length = 512·c/(2·samplerate); start = code · delay period · c/2 (Echoview): the file's
    sspd in version 4, else the 1465 m/s the tables assume."""
    rate = 512 * 1500.0 / (2 * 4.6)
    window = reader(recording(version=4, beams=96, frames=1, header={"sspd": 1500, "samplerate": rate},
                              frame_values={"windowstart": 4, "windowlength": 2, "configflags": 1})).window(0)
    assert (window.start_m, window.length_m) == (1.5, 4.5)
    assert window.length_from_sample_rate_m == pytest.approx(4.6, rel=1e-6)
    assert window.start_from_delay_m == pytest.approx(4 * 0.000512 * 1500 / 2)
    assert window.sound_speed_source == "file header sspd"
    assert set(window.disagreements()) == {"start", "length"}           # 2.4% and 2.2%
    v3 = reader(recording(version=3, beams=48, frames=1, header={"resolution": 0, "samplerate": rate},
                          frame_values={"windowstart": 4, "windowlength": 0, "configflags": 0})).window(0)
    assert v3.sound_speed_m_s == 1465.0 and "assumed" in v3.sound_speed_source
    assert v3.start_m == pytest.approx(4 * 0.838) and v3.length_m == 5.0
    assert v3.start_from_delay_m == pytest.approx(4 * 0.001144 * 1465 / 2)
    assert v3.length_from_sample_rate_m == pytest.approx(512 * 1465 / (2 * rate))
    assert set(v3.disagreements()) == {"length"}                       # 4.6 m · 1465/1500 against 5 m


@pytest.mark.parametrize("rate, warns", [(512 * 1465 / (2 * 2.25 * 1.019), False),
                                         (512 * 1465 / (2 * 2.25 * 1.021), True), (0.0, True), (math.nan, True)])
def test_a_window_off_the_sample_rate_by_more_than_2_percent_warns(rate, warns):
    didson = reader(recording(version=4, beams=96, frames=1, header={"samplerate": rate}))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        didson_dataset(didson)
    messages = [str(w.message) for w in caught if issubclass(w.category, DidsonWarning)]
    assert len(messages) == int(warns), messages
    if warns:
        assert "window length" in messages[0] and "--window-length" in messages[0] and "\n" not in messages[0]


def test_given_window_start_and_length_replace_the_decoded_ones():
    didson = reader(recording(version=4, beams=96, frames=1, header={"samplerate": 512 * 1465 / (2 * 2.5)}))
    with warnings.catch_warnings():
        warnings.simplefilter("error")                                 # the given length is not checked
        dataset, record = didson_dataset(didson, window_start_m=1.2, window_length_m=2.5)
    assert dataset.sonar.range_min == 1.2
    assert dataset.sonar.range_max == pytest.approx(1.2 + 511 * 2.5 / 512)
    window = record["window"]
    assert (window["start_m"], window["start_source"], window["start_table_m"]) == (1.2, "--window-start", 0.75)
    assert (window["length_m"], window["length_source"], window["length_table_m"]) == (2.5, "--window-length", 2.25)
    assert "length" in window["disagreements"]
    for bad in ({"window_start_m": -1.0}, {"window_length_m": 0.0}, {"window_length_m": math.inf}):
        with pytest.raises(InputError, match="--window-"):
            didson_dataset(didson, **bad)


# --- sensors and frames ---------------------------------------------------------------------------

def test_measured_depth_and_tilt_are_the_median_sensor_values():
    data = recording(version=3, beams=48, frames=4,
                     frame_values=[{"depth": d, "sonartilt": t, "sonarroll": r, "sonarpan": p, "heading": h}
                                   for d, t, r, p, h in ((0.5, 3.0, 1.0, 10.0, 90.0), (0.7, 5.0, 2.0, 11.0, 91.0),
                                                         (0.6, 4.0, 3.0, 12.0, 92.0), (9.0, 80.0, 4.0, 13.0, 93.0))])
    dataset, record = didson_dataset(reader(data), frames="2,0-1", elevation_fov_deg=12.0)
    assert dataset.rig.names == ["f0002", "f0000", "f0001"]
    assert dataset.manifest.surface.depth == pytest.approx(0.6)
    assert math.degrees(dataset.manifest.surface.tilt) == pytest.approx(4.0)
    assert math.degrees(dataset.sonar.elevation_fov) == pytest.approx(12.0)
    assert [f["sensor_sonar_roll_deg"] for f in record["frames"]] == [3.0, 1.0, 2.0]
    assert [f["sensor_sonar_pan_deg"] for f in record["frames"]] == [12.0, 10.0, 11.0]
    assert [f["sensor_heading_deg"] for f in record["frames"]] == [92.0, 90.0, 91.0]
    assert "sonartilt" in record["surface"]["tilt_source"] and record["elevation_source"] == "--elevation-fov-deg"
    given, record = didson_dataset(reader(data), depth_m=0.45, tilt_deg=-2.0)
    assert (given.manifest.surface.depth, math.degrees(given.manifest.surface.tilt)) == pytest.approx((0.45, -2.0))
    assert record["surface"]["depth_source"] == "--depth"


@pytest.mark.parametrize("values, needle", [({"depth": 0.0}, "frames[1].depth = 0.0"),
                                            ({"depth": math.nan}, "frames[1].depth = nan"),
                                            ({"sonartilt": 95.0}, "frames[1].sonartilt = 95.0")])
def test_a_frame_without_a_usable_sensor_value_needs_the_option(values, needle):
    data = recording(version=4, beams=48, frames=[np.zeros((512, 48))] * 2, frame_values=[{}, values])
    with pytest.raises(InputError) as info:
        didson_dataset(reader(data))
    assert needle in str(info.value) and "rec.ddf" in str(info.value) and "give --" in str(info.value)
    flag = "depth_m" if "depth" in values else "tilt_deg"
    assert didson_dataset(reader(data), **{flag: 0.5})[0].rig.names == ["f0000", "f0001"]


def test_frames_with_another_window_are_imported_separately():
    data = recording(version=4, beams=96, frames=3, frame_values=[{}, {"windowstart": 5}, {}])
    with pytest.raises(InputError, match=r"--frames = 1: has another range window"):
        didson_dataset(reader(data))
    assert didson_dataset(reader(data), frames="0,2")[0].rig.names == ["f0000", "f0002"]
    assert didson_dataset(reader(data), frames="1")[0].sonar.range_min == pytest.approx(5 * 0.375)


def test_partial_last_frame_is_skipped_with_a_warning(tmp_path):
    data = recording(version=3, beams=48, frames=3)
    path = tmp_path / "cut.ddf"
    path.write_bytes(data[:-100])
    with pytest.warns(DidsonWarning, match="partial frame"):
        didson = open_didson(path)
    with didson:
        assert didson.frame_count == 2
        with pytest.raises(InputError, match="no such frame"):
            didson.frame_header(2)


# --- bad recordings -------------------------------------------------------------------------------

def bad_cases() -> dict[str, tuple[bytes, str]]:
    """id -> (bytes, text the one-line error must hold)."""
    good = recording(version=4, beams=96, frames=2)
    first = frame_at(4, 96, 0)
    return {
        "not-ddf": (b"XDF\x04" + good[4:], "header.Version = '0x04464458'"),
        "version-2": (b"DDF\x02" + good[4:], "header.Version = '0x02464444'"),
        "short": (good[:1500], "size = 1500"),
        "beams-50": (bytes(put(bytearray(good), 16, "i", 50)), "header.numbeams = 50"),
        "samples-0": (bytes(put(bytearray(good), 24, "i", 0)), "header.samplesperchannel = 0"),
        "headers-only": (good[:2048], "header.numbeams = 96"),
        "length-code-4": (bytes(put(bytearray(good), first + 56, "i", 4)), "frames[0].windowlength = 4"),
        "start-code-32": (bytes(put(bytearray(good), first + 52, "i", 32)), "frames[0].windowstart = 32"),
        "start-code-negative": (bytes(put(bytearray(good), first + 52, "i", -1)), "frames[0].windowstart = -1"),
    }


@pytest.mark.parametrize("case", list(bad_cases()))
def test_bad_recordings_are_one_line_input_errors(case):
    data, needle = bad_cases()[case]
    with pytest.raises(InputError) as info:
        didson_dataset(reader(data), depth_m=0.5)
    message = str(info.value)
    assert "\n" not in message and message.startswith("rec.ddf: ") and needle in message, message


def test_open_names_missing_and_empty_files(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        open_didson(tmp_path / "none.ddf")
    (tmp_path / "empty.ddf").write_bytes(b"")
    with pytest.raises(InputError, match="size = 0"):
        open_didson(tmp_path / "empty.ddf")
    with pytest.raises(InputError, match="is not a file"):
        open_didson(tmp_path)


# --- fuzzing from memory --------------------------------------------------------------------------

def check_error(err: InputError) -> None:
    message = str(err)
    assert message and "\n" not in message and message.startswith("fuzz.ddf"), message


BASES = [recording(version=3, beams=48, frames=2), recording(version=4, beams=96, frames=1),
         recording(version=4, beams=48, frames=2, header={"reverse": 1, "resolution": 0})]
U32 = [0, 1, 2, 3, 4, 5, 15, 18, 19, 31, 32, 48, 96, 512, 0x7FFFFFFF, -0x80000000, -1]
F32 = [0.0, -0.0, -1.0, 1e-45, 0.5, 89.9, 90.0, 1465.0, 1e38, -1e38, math.inf, -math.inf, math.nan]
# the fields the reader reads, by header: file (offset) and frame (offset within the frame header)
FILE_FIELDS = [(4, "i"), (12, "i"), (16, "i"), (20, "f"), (24, "i"), (40, "i"), (44, "i"), (384, "I")]
FRAME_FIELDS = [(0, "i"), (52, "i"), (56, "i"), (128, "f"), (152, "f"), (160, "f"), (164, "f"), (168, "f"),
                (192, "i")]


def mutate(rng: random.Random, base: bytes) -> bytes:
    data = bytearray(base)
    version = base[3]
    head, frame_head = HEADERS[version]
    beams = struct.unpack_from("<i", base, 16)[0]
    frames = (len(base) - head) // (frame_head + 512 * beams)
    for _ in range(rng.randint(1, 4)):
        kind = rng.random()
        if kind < 0.45:                                                # a field the reader reads
            where, fields = (0, FILE_FIELDS) if rng.random() < 0.4 else (frame_at(version, beams, rng.randrange(
                frames)), FRAME_FIELDS)
            offset, fmt = rng.choice(fields)
            value = rng.choice(F32) if fmt == "f" else rng.choice(U32) % 2 ** 32 if fmt == "I" else rng.choice(U32)
            struct.pack_into("<" + fmt, data, where + offset, value)
        elif kind < 0.7:                                               # a bit anywhere in a header
            where = rng.choice([0] + [frame_at(version, beams, k) for k in range(frames)])
            bit = rng.randrange(8 * (head if where == 0 else frame_head))
            data[where + bit // 8] ^= 1 << (bit % 8)
        elif kind < 0.8:                                               # the magic or the version byte
            data[rng.randrange(4)] = rng.randrange(256)
        else:                                                          # a byte anywhere
            data[rng.randrange(len(data))] = rng.randrange(256)
    if rng.random() < 0.15:                                            # a cut
        del data[rng.randrange(len(data) + 1):]
    return bytes(data)


def exercise(data: bytes, *, dataset: bool) -> str:
    """Read what the reader offers; only InputError may stop it, and what it returns must be
    sane. With ``dataset``, also build the import's Dataset. Returns 'error' or 'read'."""
    try:
        didson = DidsonFile(data, file="fuzz.ddf")
    except InputError as err:
        check_error(err)
        return "error"
    head = HEADERS[didson.version][0]
    assert didson.frame_count >= 1 and head + didson.frame_count * didson.frame_bytes <= len(data)
    try:
        for frame in {0, didson.frame_count - 1}:
            spec = didson.sonar_spec(frame)
            assert spec.bins == 512 and spec.beams == didson.beams and spec.range_max > spec.range_min >= 0
            image = didson.frame_image(frame)
            assert image.shape == (512, didson.beams) and float(image.min()) >= 3.1e-5 and float(image.max()) <= 1
        if dataset:
            built, record = didson_dataset(didson)
            assert built.rig.names and record["window"]["length_m"] > 0
    except InputError as err:
        check_error(err)
        return "error"
    return "read"


@pytest.mark.slow
def test_fuzz_40k_mutated_recordings_from_memory():
    """40,000 mutated copies of three small recordings (v3 48 beams, v4 96 beams, v4 48 beams
    low frequency reversed): each is read, or refused with a one-line InputError; every 25th
    also goes through the whole import into a Dataset. (100,000 until the suite neared CI's 15
    minutes: 27 s of it on the 2-core CPU.)"""
    rng = random.Random(35)
    outcomes = {"error": 0, "read": 0}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DidsonWarning)
        for i in range(40_000):
            outcomes[exercise(mutate(rng, BASES[i % 3]), dataset=i % 25 == 0)] += 1
    assert outcomes["error"] > 4_000 and outcomes["read"] > 4_000, outcomes
