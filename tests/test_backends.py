"""Kernel backends: the projection kernel against the NumPy oracle, Warp against OpenCL, and
backend selection (get_backend, describe_backends).

Tolerance. Kernels compute in float32, the oracle (fsswarp.rig.to_view, fsswarp.sonar.to_polar,
SonarSpec.beam_bin, SonarSpec.in_elevation) in float64. They must agree exactly, and Warp must
agree exactly with OpenCL, except at points that float32 cannot place: within ``MARGIN`` of a
half-index boundary (1e-4 of an index, widened to two float32 ulps of the θ or R behind it
where that is larger: at 3 m one ulp of R is already 6e-5 of a 3.9 mm bin), or within
``ELEVATION_MARGIN`` of the elevation edge. Those are left out, and at least 99.9% of all
(view, point) pairs must be compared.
"""

from __future__ import annotations

import importlib.metadata
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from fsswarp.backends import select
from fsswarp.backends import describe_backends, get_backend
from fsswarp.errors import InputError
from fsswarp.rig import rotation_x, rotation_y, rotation_z, to_view
from fsswarp.sonar import SonarSpec, from_polar, to_polar

MARGIN = 1e-4  # index units
ULPS = 2.0  # float32 ulps of θ or R, in index units, when larger than MARGIN
ELEVATION_MARGIN = 1e-6  # rad, ~130 float32 ulps of W_φ
EPS32 = 2.0**-23


def linear_sonar() -> SonarSpec:
    return SonarSpec()  # DIDSON-like: 96 beams, 512 bins, W_θ 14.4°, W_φ 7°, 1-3 m


def table_sonar() -> SonarSpec:
    """Nonuniform beam-angle table: a cubic distortion of the linear angles (denser at the
    centre, sparser at the edges), spanning the same fan."""
    half = math.radians(14.4)
    u = np.linspace(-1.0, 1.0, 96)
    return SonarSpec(beam_angles=half * (0.7 * u + 0.3 * u**3), azimuth_fov=2 * half)


SONARS = {"linear": linear_sonar, "table": table_sonar}


def random_scene(seed: int, n_points: int = 20_000, n_views: int = 6):
    """Seeded points and poses: 70% of the points in and around the reference fan, 30% in a
    box around the sonar (behind, above, below it too); view 0 is the reference (identity),
    the others turned by heading, tilt and roll and moved by up to 0.3 m."""
    rng = np.random.default_rng(seed)
    near = int(0.7 * n_points)
    fan = from_polar(rng.uniform(0.8, 3.2, near), rng.uniform(-0.35, 0.35, near),
                     rng.uniform(-0.2, 0.2, near))
    points = np.concatenate([fan, rng.uniform(-3.0, 3.0, (n_points - near, 3))])
    rotations = (rotation_z(rng.uniform(-0.3, 0.3, n_views)) @ rotation_x(rng.uniform(-0.3, 0.3, n_views))
                 @ rotation_y(rng.uniform(-1.6, 1.6, n_views)))
    translations = rng.uniform(-0.3, 0.3, (n_views, 3))
    rotations[0], translations[0] = np.eye(3), 0.0
    return points, rotations, translations


def oracle(points, rotations, translations, sonar: SonarSpec):
    """The float64 NumPy rule: (V, P) beam, bin, inside, and which pairs float32 can decide."""
    q = to_view(points[None], rotations, translations[:, None])  # (V, P, 3)
    rng, theta, phi = to_polar(q)
    beam, bin_, inside = sonar.beam_bin(theta, rng)
    inside &= sonar.in_elevation(phi)
    h = 1e-7
    slope = np.abs(sonar.beam_coordinate(theta + h) - sonar.beam_coordinate(theta - h)) / (2 * h)
    beam_margin = np.maximum(MARGIN, ULPS * EPS32 * np.abs(theta) * slope)
    bin_margin = np.maximum(MARGIN, ULPS * EPS32 * rng / sonar.range_step)
    decidable = ((_to_boundary(sonar.beam_coordinate(theta)) > beam_margin)
                 & (_to_boundary(sonar.bin_coordinate(rng)) > bin_margin)
                 & (np.abs(np.abs(phi) - sonar.half_elevation) > ELEVATION_MARGIN))
    return beam, bin_, inside, decidable


def _to_boundary(coordinate):
    """Distance (index units) from a fractional coordinate to the nearest half-index boundary."""
    shifted = coordinate + 0.5
    return np.abs(shifted - np.round(shifted))


def assert_equal_where(actual, expected, where, what: str) -> None:
    bad = (actual != expected) & where
    if bad.any():
        v, p = np.argwhere(bad)[0]
        pytest.fail(f"{what}: {int(bad.sum())} of {int(where.sum())} pairs differ; first at view {v}, "
                    f"point {p}: {actual[v, p]} != {expected[v, p]}")


# --- the projection kernel --------------------------------------------------------------------
@pytest.mark.parametrize("sonar_kind", SONARS)
def test_project_matches_numpy(backend, sonar_kind):
    sonar = SONARS[sonar_kind]()
    points, rotations, translations = random_scene(seed=7)
    beam, bin_, inside = backend.project(points, rotations, translations, sonar)
    want_beam, want_bin, want_inside, decidable = oracle(points, rotations, translations, sonar)

    assert decidable.mean() >= 0.999
    assert 0.05 < want_inside.mean() < 0.95  # the scene exercises both outcomes
    assert_equal_where(beam, want_beam, decidable, "beam")
    assert_equal_where(bin_, want_bin, decidable, "bin")
    assert_equal_where(inside, want_inside, decidable, "inside")


@pytest.mark.parametrize("sonar_kind", SONARS)
@pytest.mark.parametrize("pair", [
    pytest.param(("warp-cpu", "opencl-cpu"), id="warp-cpu-vs-opencl-cpu"),
    pytest.param(("warp-cuda", "opencl-cpu"), id="warp-cuda-vs-opencl-cpu", marks=pytest.mark.gpu),
    pytest.param(("warp-cpu", "opencl-gpu"), id="warp-cpu-vs-opencl-gpu", marks=pytest.mark.gpu),
])
def test_warp_matches_opencl(backend_for_label, pair, sonar_kind):
    """Identical outputs on the same inputs, except the pairs float32 cannot decide."""
    warp, opencl = (backend_for_label(label) for label in pair)
    sonar = SONARS[sonar_kind]()
    points, rotations, translations = random_scene(seed=11)
    *_, decidable = oracle(points, rotations, translations, sonar)
    assert decidable.mean() >= 0.999
    for what, a, b in zip(("beam", "bin", "inside"), warp.project(points, rotations, translations, sonar),
                          opencl.project(points, rotations, translations, sonar)):
        assert_equal_where(a, b, decidable, what)


@pytest.mark.parametrize("sonar_kind", SONARS)
def test_project_beam_and_bin_centres(backend, sonar_kind):
    """Points at beam/bin centres land exactly there, in any view pose; the elevation and range
    window and the fan's sides decide ``inside``."""
    sonar = SONARS[sonar_kind]()
    beams = np.array([0, 1, 47, 48, 94, 95, -3, 99, 0, 50])
    bins = np.array([0, 511, 256, 3, 100, 400, 10, 10, -2, 520])
    phi = np.zeros(10)
    phi[3], phi[4] = 0.9 * sonar.half_elevation, -1.1 * sonar.half_elevation
    view = from_polar(sonar.bin_range(bins), sonar.beam_angle(beams), phi)
    rotation = rotation_z(0.4) @ rotation_x(-0.2) @ rotation_y(1.0)
    translation = np.array([0.5, -1.0, 0.25])
    points = view @ rotation.T + translation  # P_ref = R P_view + t

    beam, bin_, inside = backend.project(points, rotation[None], translation[None], sonar)
    np.testing.assert_array_equal(beam[0], beams)
    np.testing.assert_array_equal(bin_[0], bins)
    np.testing.assert_array_equal(inside[0], [1, 1, 1, 1, 0, 1, 0, 0, 0, 0])


def test_project_behind_and_far(backend):
    """A point behind the sonar extrapolates outside the fan; absurd ranges clamp, not wrap."""
    sonar = linear_sonar()
    points = np.array([[0.0, -2.0, 0.0], [0.0, 1e12, 0.0], [0.0, 0.0, 0.5]])
    beam, bin_, inside = backend.project(points, np.eye(3)[None], np.zeros((1, 3)), sonar)
    assert not inside.any()
    assert beam[0, 0] > sonar.beams  # θ = π: far right of the fan
    assert bin_[0, 1] == 2**30
    assert bin_[0, 2] == sonar.beam_bin(0.0, 0.5)[1] == -128  # (0.5 - 1) / δR = -127.75


def test_project_output_contract(backend):
    sonar = linear_sonar()
    points, rotations, translations = random_scene(seed=3, n_points=100, n_views=3)
    beam, bin_, inside = backend.project(points.tolist(), rotations.astype(np.float32),
                                         translations, sonar)
    for array, dtype in ((beam, np.int32), (bin_, np.int32), (inside, np.bool_)):
        assert array.shape == (3, 100) and array.dtype == dtype and array.flags.c_contiguous
    again = backend.project(points, rotations, translations, sonar)
    for a, b in zip((beam, bin_, inside), again):
        np.testing.assert_array_equal(a, b)

    ints = backend.project(np.array([[0, 2, 0]]), np.eye(3, dtype=int)[None], np.zeros((1, 3), int), sonar)
    assert ints[0].tolist() == [[48]] and ints[1].tolist() == [[256]]  # θ = 0 rounds up: 47.5 -> 48

    for n_points, n_views in ((0, 3), (5, 0)):
        beam, bin_, inside = backend.project(np.zeros((n_points, 3)), np.zeros((n_views, 3, 3)),
                                             np.zeros((n_views, 3)), sonar)
        assert beam.shape == bin_.shape == inside.shape == (n_views, n_points)
        assert (beam.dtype, inside.dtype) == (np.int32, np.bool_)


@pytest.mark.parametrize("args, error, text", [
    ({"points": np.zeros((4, 2))}, ValueError, "points must have shape (P, 3), got (4, 2)"),
    ({"points": np.zeros(3)}, ValueError, "got (3,)"),
    ({"points": [[0, 0, 0], [1, 2]]}, ValueError, "points must be an array"),
    ({"points": np.zeros((4, 3), complex)}, TypeError, "dtype complex128"),
    ({"points": np.array([["a", "b", "c"]])}, TypeError, "points must hold real numbers"),
    ({"points": np.array([[0, np.nan, 0]])}, ValueError, "got nan at index (0, 1)"),
    ({"points": np.array([[0, 1e39, 0]])}, ValueError, "finite in float32, got inf"),
    ({"rotations": np.zeros((2, 3))}, ValueError, "rotations must have shape (V, 3, 3), got (2, 3)"),
    ({"translations": np.zeros((3, 3))}, ValueError, "2 rotations and 3 translations"),
    ({"translations": np.zeros((2, 3), bool)}, TypeError, "dtype bool"),
    ({"sonar": "didson"}, TypeError, "got str"),
])
def test_project_rejects_bad_input(backend, args, error, text):
    call = {"points": np.zeros((4, 3)), "rotations": np.tile(np.eye(3), (2, 1, 1)),
            "translations": np.zeros((2, 3)), "sonar": linear_sonar()}
    call.update(args)
    with pytest.raises(error) as info:
        backend.project(**call)
    assert text in str(info.value)


# --- selection --------------------------------------------------------------------------------
def test_backend_attributes(backend):
    assert backend.name in ("warp", "opencl")
    assert isinstance(backend.device, str) and backend.device
    assert isinstance(backend.is_gpu, bool)
    if backend.name == "opencl":
        assert ": " in backend.device  # "<platform>: <device name>"


def test_warp_devices(wp_device):
    backend = get_backend("warp", wp_device)
    assert (backend.name, backend.device, backend.is_gpu) == ("warp", wp_device, wp_device != "cpu")
    assert get_backend("warp", wp_device) is backend
    if wp_device.startswith("cuda"):
        import warp as wp

        from fsswarp.backends.warp.backend import MEMPOOL_KEEP

        assert get_backend("warp", "cuda") is get_backend("warp", "cuda:0")
        if wp.is_mempool_enabled(wp_device):  # the pool keeps a quarter of the memory between launches
            kept = wp.get_mempool_release_threshold(wp_device)
            assert kept == pytest.approx(MEMPOOL_KEEP * wp.get_device(wp_device).total_memory, rel=0.01)


def test_warp_reuses_an_input_upload_for_the_same_bytes(backend_for_label):
    """``WarpBackend._constant`` keeps read-only kernel inputs on the device: the same bytes
    (of the same type and shape) give the same device array, different ones their own with
    their values; inputs above ``CONSTANT_BYTES`` are uploaded each time; the least recently
    used go first beyond ``CONSTANTS``."""
    import warp as wp

    from fsswarp.backends.warp import backend as warp_backend

    backend = backend_for_label("warp-cpu")
    backend._constants.clear()
    a = np.arange(12, dtype=np.float32)
    first = backend._constant(a, float)
    assert backend._constant(a.copy(), float) is first
    np.testing.assert_array_equal(first.numpy(), a)
    other = backend._constant(a + 1, float)
    assert other is not first
    np.testing.assert_array_equal(other.numpy(), a + 1)
    assert backend._constant(a.reshape(3, 4), float) is not first  # another shape
    assert backend._constant(a.view(np.int32), wp.int32) is not first  # another type
    big = np.zeros(warp_backend.CONSTANT_BYTES // 4 + 1, np.float32)
    assert backend._constant(big, float) is not backend._constant(big, float)
    for k in range(warp_backend.CONSTANTS):
        backend._constant(np.array([k], np.int32), wp.int32)
        backend._constant(a, float)  # used again and again: kept
    assert len(backend._constants) == warp_backend.CONSTANTS
    assert backend._constant(a, float) is first
    assert backend._constant(a + 1, float) is not other  # dropped


def test_warp_uploads_several_inputs_as_views_of_one_array(backend_for_label):
    """``WarpBackend._arrays``: each (host array, dtype) comes back with its shape and float32
    values, matrices and vectors as such, laid one after another in one device array; an empty
    input gives an empty array of its type."""
    import warp as wp

    backend = backend_for_label("warp-cpu")
    rotations = np.arange(18.0).reshape(2, 3, 3) / 7.0
    empty, offsets = np.zeros((0, 3)), np.array([0.25, 1.0 / 3.0])
    got = backend._arrays((rotations, wp.mat33), (empty, wp.vec3), (offsets, float))
    assert [a.dtype for a in got] == [wp.mat33, wp.vec3, wp.float32] and [a.shape for a in got] == [(2,), (0,), (2,)]
    np.testing.assert_array_equal(got[0].numpy(), rotations.astype(np.float32))
    np.testing.assert_array_equal(got[2].numpy(), offsets.astype(np.float32))
    assert got[2].ptr == got[0].ptr + rotations.size * 4  # the next run of the one upload


def test_opencl_keeps_a_launchs_buffers_until_its_queue_finishes(backend_for_label, monkeypatch):
    """``OpenCLBackend._finish``: the buffers handed to a launch (its inputs and results) are
    still held when the queue is waited for, and released right after (NVIDIA's OpenCL would
    stall every thread on a buffer released while its kernel runs)."""
    backend = backend_for_label("opencl-cpu")
    held_at_finish = []
    finish = backend._finish

    def recording_finish():
        held_at_finish.append(len(backend._held))
        finish()
    monkeypatch.setattr(backend, "_finish", recording_finish)
    points, rotations, translations = random_scene(seed=7)
    beam, _, _ = backend.project(points, rotations, translations, SONARS["linear"]())
    assert held_at_finish == [7]  # points, rotations, translations, beam table; beam, bin, inside
    assert backend._held == [] and beam.shape == (len(rotations), len(points))


def test_get_backend_is_cached():
    auto = get_backend()
    assert get_backend("auto") is auto
    assert get_backend(auto.name, auto.device) is auto
    assert get_backend("warp", "cpu") is get_backend("WARP", " cpu ")
    rows = [r for r in describe_backends() if r["backend"] == "opencl" and r["available"]]
    if rows:
        assert get_backend("opencl", rows[0]["index"]) is get_backend("opencl", rows[0]["device"].upper())
        assert get_backend("opencl", str(rows[0]["index"])) is get_backend("opencl", rows[0]["index"])


@pytest.mark.parametrize("name", ["cuda", "numpy", "", 3, None])
def test_get_backend_unknown_name(name):
    with pytest.raises(InputError) as info:
        get_backend(name)
    message = str(info.value)
    assert "\n" not in message and "--backend" in message and "auto, warp, opencl" in message


@pytest.mark.parametrize("name, device, available", [
    ("warp", "cuda:7", "available: cpu"),
    ("warp", "gpu", "cpu, cuda or cuda:N"),
    ("opencl", "nosuchdevice", "available: 0 = "),
    ("opencl", 99, "available: 0 = "),
    ("auto", "nosuchdevice", "available: 0 = "),
])
def test_get_backend_unknown_device(name, device, available):
    if name == "warp" and device == "cuda:7" and any(
            r["device"] == "cuda:7" for r in describe_backends()):
        pytest.skip("this machine has a cuda:7")
    if name != "warp" and not any(r["backend"] == "opencl" and r["available"] for r in describe_backends()):
        pytest.skip("no OpenCL device here")
    with pytest.raises(InputError) as info:
        get_backend(name, device)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"--device = {device!r}: ")
    assert available in message


@pytest.mark.parametrize("package, name, hint", [
    ("warp", "warp", "pip install warp-lang"),
    ("pyopencl", "opencl", 'pip install "fsswarp[pocl]"'),
])
def test_missing_package(monkeypatch, package, name, hint):
    """A missing package is an InputError naming the option and the install command, and a
    row of describe_backends (which never raises)."""
    monkeypatch.setitem(sys.modules, package, None)  # import raises ImportError
    monkeypatch.setattr(select, "_CACHE", {})
    with pytest.raises(InputError) as info:
        get_backend(name)
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"--backend = {name!r}: ") and hint in message

    rows = describe_backends()
    missing = [r for r in rows if r["backend"] == name]
    assert len(missing) == 1 and not missing[0]["available"] and hint in missing[0]["note"]
    assert sum(r["auto"] for r in rows) <= 1
    assert all(r["backend"] != name for r in rows if r["auto"])


def test_no_opencl_platform(monkeypatch):
    cl = pytest.importorskip("pyopencl")
    monkeypatch.setattr(cl, "get_platforms", lambda: [])
    monkeypatch.setattr(select, "_CACHE", {})
    with pytest.raises(InputError, match=r"^--backend = 'opencl': no OpenCL platform found.*fsswarp\[pocl\]"):
        get_backend("opencl")
    rows = [r for r in describe_backends() if r["backend"] == "opencl"]
    assert len(rows) == 1 and "no OpenCL platform" in rows[0]["note"]


def test_describe_backends():
    rows = describe_backends()
    keys = set(rows[0])
    assert all(set(r) == keys for r in rows)
    assert any(r["backend"] == "warp" and r["device"] == "cpu" and r["available"] for r in rows)
    try:
        importlib.metadata.version("pocl-binary-distribution")
    except importlib.metadata.PackageNotFoundError:
        pass
    else:  # fsswarp[pocl] installed: its CPU device must be found
        assert any(r["backend"] == "opencl" and r["kind"] == "cpu" and r["available"]
                   and "portable computing language" in r["platform"].lower() for r in rows)

    picked = [r for r in rows if r["auto"]]
    assert len(picked) == 1
    auto = get_backend("auto")
    assert (picked[0]["backend"], picked[0]["device"]) == (auto.name, auto.device)
    cuda = any(r["backend"] == "warp" and r["kind"] == "gpu" and r["available"] for r in rows)
    cpu_opencl = any(r["backend"] == "opencl" and r["kind"] == "cpu" and r["available"] for r in rows)
    if cuda:
        assert (auto.name, auto.device) == ("warp", "cuda:0")
    elif cpu_opencl:
        assert auto.name == "opencl" and not auto.is_gpu
    else:
        assert (auto.name, auto.device) == ("warp", "cpu")


def test_import_does_not_import_warp_or_pyopencl():
    code = ("import sys, fsswarp.backends; "
            "print(sorted(m for m in ('warp', 'pyopencl') if m in sys.modules))")
    env = dict(os.environ, PYTHONWARNINGS="error")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    assert out.stdout.strip() == "[]"


# --- OpenCL sources ----------------------------------------------------------------------------
def test_kernel_sources_inline_our_headers():
    pytest.importorskip("pyopencl")
    from fsswarp.backends.opencl import kernel_dir, kernel_source

    assert {"project.cl", "sonar.h"} <= {p.name for p in kernel_dir().iterdir()}
    source = kernel_source("project.cl")
    assert '#include "' not in source
    assert source.count("float fss_beam_coordinate(") == 1
    assert "__kernel void project_points(" in source


def test_build_error_names_options_and_saved_source(backend_for_label):
    opencl = backend_for_label("opencl-cpu")
    from fsswarp.backends.opencl import KernelBuildError, build

    source = "__kernel void broken(__global float *x) { x[0] = undeclared_name; }\n"
    with pytest.raises(KernelBuildError) as info:
        build(opencl.context, source, ("-DFSSWARP_TEST=1",), label="broken.cl")
    message = str(info.value)
    assert "broken.cl" in message and "-DFSSWARP_TEST=1" in message
    saved = message.split("source saved as ")[1].split(")")[0]
    try:
        with open(saved, encoding="utf-8") as handle:
            assert handle.read() == source
    finally:
        os.unlink(saved)


def test_build_log_of_a_successful_build_is_not_raised(backend_for_label):
    """NVIDIA's OpenCL compiler logs on success and pyopencl warns about any log (an error under
    -W error): ``build`` must return the program regardless. A #warning makes PoCL log too."""
    opencl = backend_for_label("opencl-cpu")
    import pyopencl as cl

    from fsswarp.backends.opencl import build

    source = "#warning fsswarp test: a log on success\n__kernel void fine(__global float *x) { x[0] = 1.0f; }\n"
    with pytest.warns(cl.CompilerWarning):
        cl.Program(opencl.context, source).build()
    program = build(opencl.context, source, (), label="fine.cl")
    assert program.get_info(cl.program_info.NUM_KERNELS) == 1


# --- the sonar struct and the shared constants ---------------------------------------------------
def test_sonar_struct_layout_warp():
    """SONAR_DTYPE is 3 int32 and 5 float32 with no padding, and the Warp struct lists the same
    fields in the same order with the same types."""
    wp = pytest.importorskip("warp")
    from fsswarp.backends.base import SONAR_DTYPE, SonarConstants
    from fsswarp.backends.warp.sonar import KernelSonar, kernel_sonar

    assert SONAR_DTYPE.itemsize == 32
    assert [SONAR_DTYPE.fields[n][1] for n in SONAR_DTYPE.names] == list(range(0, 32, 4))
    assert list(KernelSonar.vars) == list(SONAR_DTYPE.names)
    kinds = {wp.int32: np.int32, wp.float32: np.float32}
    assert [kinds[v.type] for v in KernelSonar.vars.values()] == [SONAR_DTYPE[n].type for n in SONAR_DTYPE.names]
    consts = SonarConstants.of(table_sonar())
    packed = kernel_sonar(consts)
    for name in SONAR_DTYPE.names:
        assert getattr(packed, name) == getattr(consts, name)


def test_sonar_struct_layout_opencl(backend_for_label):
    """The host's SONAR_DTYPE record and kernels/sonar.h's fss_sonar agree byte for byte: a kernel
    reads every field of the struct argument back, and pyopencl's layout check inserts no padding."""
    opencl = backend_for_label("opencl-cpu")
    import pyopencl as cl
    from pyopencl.tools import match_dtype_to_c_struct

    from fsswarp.backends.base import SONAR_DTYPE, SonarConstants
    from fsswarp.backends.opencl import build, kernel_source
    from fsswarp.backends.opencl.programs import BUILD_OPTIONS

    matched, _ = match_dtype_to_c_struct(opencl.cl_device, "fss_sonar_check", SONAR_DTYPE, opencl.context)
    assert matched == SONAR_DTYPE
    source = kernel_source("sonar.h") + """
__kernel void echo(const fss_sonar s, __global int *ints, __global float *floats)
{
    ints[0] = s.use_table; ints[1] = s.beams; ints[2] = s.bins; ints[3] = (int)sizeof(fss_sonar);
    floats[0] = s.half_azimuth; floats[1] = s.beam_scale; floats[2] = s.range_min;
    floats[3] = s.inv_range_step; floats[4] = s.half_elevation;
}
"""
    kernel = build(opencl.context, source, BUILD_OPTIONS, label="echo.cl").echo
    consts = SonarConstants.of(table_sonar())
    ints, floats = np.zeros(4, np.int32), np.zeros(5, np.float32)
    flags = cl.mem_flags.WRITE_ONLY
    ints_buf = cl.Buffer(opencl.context, flags, size=ints.nbytes)
    floats_buf = cl.Buffer(opencl.context, flags, size=floats.nbytes)
    kernel(opencl.queue, (1,), None, consts.record(), ints_buf, floats_buf)
    cl.enqueue_copy(opencl.queue, ints, ints_buf)
    cl.enqueue_copy(opencl.queue, floats, floats_buf)
    record = consts.record()
    assert ints.tolist() == [record["use_table"], record["beams"], record["bins"], SONAR_DTYPE.itemsize]
    assert floats.tolist() == [record[n] for n in SONAR_DTYPE.names[3:]]
    assert record["use_table"] == 1 and record["beams"] == 96


def test_kernel_constants_come_from_python():
    """The OpenCL sources define none of the shared constants themselves; the -D options give
    Python's values."""
    pytest.importorskip("pyopencl")
    from fsswarp.backends import constants
    from fsswarp.backends.opencl import kernel_dir
    from fsswarp.backends.opencl.programs import BUILD_OPTIONS

    for path in kernel_dir().iterdir():
        text = path.read_text(encoding="utf-8")
        for name in ("FSS_INDEX_LIMIT", "FSS_FIXED", "FSS_SPAN_MARGIN"):
            assert f"#define {name}" not in text, (path.name, name)
    defines = dict(option[2:].split("=") for option in BUILD_OPTIONS)
    assert float(defines["FSS_INDEX_LIMIT"].rstrip("f")) == constants.INDEX_LIMIT
    assert float(defines["FSS_FIXED"].rstrip("f")) == constants.FIXED_SCALE
    assert float(defines["FSS_SPAN_MARGIN"].rstrip("f")) == constants.SPAN_MARGIN


def test_beam_widths():
    for sonar in (linear_sonar(), table_sonar()):
        widths = sonar.beam_widths
        assert widths.dtype == np.float32 and widths.shape == (sonar.beams,)
        c = np.asarray(sonar.beam_centres, np.float64)
        np.testing.assert_array_equal(widths[1:-1], ((c[2:] - c[:-2]) / 2).astype(np.float32))
        np.testing.assert_array_equal(widths[[0, -1]], np.float32([c[1] - c[0], c[-1] - c[-2]]))


# --- launches on resident data (the benchmark's) ------------------------------------------------
def test_prepared_cast_matches_cast_rays(backend):
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    handle = backend.load_mesh(sphere.vertices + [0.0, 2.0, 0.0], sphere.faces)
    rng = np.random.default_rng(3)
    origins = rng.normal(0.0, 0.05, (5000, 3))
    dirs = rng.normal(0.0, 0.15, (5000, 3)) + [0.0, 1.0, 0.0]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    for limit in ({}, {"max_distance": 1.9}):
        want = backend.cast_rays(handle, origins, dirs, **limit)
        launch = backend.prepared_cast(handle, origins, dirs, **limit)
        assert launch() is None
        launch()
        got = launch.read()
        assert np.isfinite(got[0]).any() and (got[1] >= 0).any() and (got[1] < 0).any()
        for a, b in zip(got, want):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="at least one ray"):
        backend.prepared_cast(handle, np.zeros((0, 3)), np.zeros((0, 3)))


def test_prepared_carve_matches_carve(backend):
    sonar = table_sonar()
    _, rotations, translations = random_scene(5, n_points=10, n_views=4)
    masks = np.random.default_rng(5).random((4, sonar.bins, sonar.beams)) > 0.995
    origin, side, size = np.array([-0.6, 1.2, -0.3]), 24, 0.025
    want = backend.carve(masks, rotations, translations, sonar, size, origin=origin, shape=(side,) * 3)
    launch = backend.prepared_carve(masks, rotations, translations, sonar, size, origin, side)
    assert launch() is None
    got = launch.read()
    assert want[0].any() and want[1].any()
    for a, b in zip(got, want):
        assert a.dtype == np.uint8 and a.shape == (side**3,)
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="side must be an integer >= 1"):
        backend.prepared_carve(masks, rotations, translations, sonar, size, origin, 0)


def test_transfer_calls_and_device_name(backend):
    calls = backend.transfer_calls(1 << 16)
    assert len(calls) == 3
    for call in calls:
        assert call() is None
    with pytest.raises(ValueError, match="nbytes"):
        backend.transfer_calls(2)
    assert isinstance(backend.device_name, str) and backend.device_name.strip() == backend.device_name != ""
    if backend.name == "opencl":
        assert backend.device_name == backend.cl_device.name.strip()
    else:
        import warp as wp

        assert backend.device_name == wp.get_device(backend.device).name


# --- OpenCL devices that cannot build a kernel ------------------------------------------------------
class _FakeCLDevice:
    version, driver_version, max_compute_units, global_mem_size = "OpenCL 1.2", "1.0", 2, 1 << 30

    def __init__(self, name: str):
        self.name = name


def _fake_devices(*names):
    platform = _FakeCLDevice("Portable Computing Language")
    return [select.OpenCLDevice(i, f"Portable Computing Language: {name}", platform, _FakeCLDevice(name),
                                 False, True, True) for i, name in enumerate(names)]


def test_a_device_that_cannot_build_is_not_picked(monkeypatch):
    """A device whose runtime fails the trivial build is skipped by auto and by the default
    OpenCL choice, listed unavailable with the reason, and probed once."""
    found = _fake_devices("broken", "good")
    probed = []

    def probe(d):
        probed.append(d.label)
        return "cannot build an OpenCL kernel: error: unknown target CPU 'generic'" if "broken" in d.label else None

    monkeypatch.setattr(select, "_opencl_devices", lambda: (found, None))
    monkeypatch.setattr(select, "_probe", probe)
    monkeypatch.setattr(select, "_PROBES", {})
    assert select._resolve_opencl_device(None) is found[1]
    assert select._resolve_opencl_device(0) is found[0]  # named: still selected
    wp, _ = select.import_warp()
    if wp is None or not wp.is_cuda_available():
        assert select._auto_choice(None) == ("opencl", 1)
    rows = {r["device"]: r for r in describe_backends() if r["backend"] == "opencl"}
    broken, good = rows[found[0].label], rows[found[1].label]
    assert not broken["available"] and not broken["auto"] and "unknown target CPU 'generic'" in broken["note"]
    assert "\n" not in broken["note"]
    assert good["available"] and good["note"] == ""
    assert sorted(probed) == sorted(d.label for d in found)  # once each, however often asked

    monkeypatch.setattr(select, "_probe", lambda d: "cannot build an OpenCL kernel: error: nothing works")
    monkeypatch.setattr(select, "_PROBES", {})
    with pytest.raises(InputError, match=r"^--backend = 'opencl': no usable OpenCL device .*nothing works"):
        select._resolve_opencl_device(None)
    if wp is not None and not wp.is_cuda_available():
        assert select._auto_choice(None) == ("warp", "cpu")


def test_probe_reports_a_build_failure_in_one_line(monkeypatch):
    cl = pytest.importorskip("pyopencl")

    class Failing:
        def __init__(self, *args):
            pass

        def build(self):
            raise cl.RuntimeError("clBuildProgram failed: BUILD_PROGRAM_FAILURE\n\nBuild on <device>:\n\n"
                                  "error: unknown target CPU 'generic'\nDevice failed to build the program")

    monkeypatch.setattr(cl, "Context", lambda devices: None)
    monkeypatch.setattr(cl, "Program", Failing)
    reason = select._probe(_fake_devices("broken")[0])
    assert reason == "cannot build an OpenCL kernel: error: unknown target CPU 'generic'"


@pytest.mark.gpu
def test_warp_uploads_through_the_page_locked_ring_arrive_whole(backend_for_label):
    """A CUDA backend's uploads go through a ring of page-locked memory (``_Staging``). Behind a
    kernel that keeps the stream busy, 300 uploads of every staged dtype, ~12 times the ring in
    all, each write their bytes only where the copies queued before have ended: every array
    arrives bit for bit. A dtype that is not staged (uint8) still arrives through ``_array``."""
    import warp as wp

    from fsswarp.backends.warp.backend import _Staging

    @wp.kernel
    def spin(steps: int, out: wp.array(dtype=float)):
        x = float(0.0)
        for i in range(steps):
            x = wp.sin(x + 1.0)
        out[0] = x

    backend = backend_for_label("warp-cuda")
    staging = _Staging(backend._device, 1 << 16, smallest=1)
    busy = wp.zeros(1, dtype=float, device=backend._device)
    wp.launch(spin, dim=1, inputs=[200_000], outputs=[busy], device=backend._device)
    rng = np.random.default_rng(5)
    kinds = [(float, lambda n: rng.normal(size=n).astype(np.float32)),
             (wp.int32, lambda n: rng.integers(-2**31, 2**31 - 1, n, dtype=np.int64).astype(np.int32)),
             (wp.vec3, lambda n: rng.normal(size=(n, 3))),  # float64 data, converted as wp.array does
             (wp.mat33, lambda n: rng.normal(size=(n // 4 + 1, 3, 3)).astype(np.float32)),
             (wp.float64, lambda n: rng.normal(size=n))]
    made = []
    for i in range(300):
        dtype, draw = kinds[i % len(kinds)]
        data = draw(int(rng.integers(1, 800)))
        made.append((staging.upload(data, dtype), wp.array(data, dtype=dtype, device="cpu").numpy()))
    assert all(array is not None for array, _ in made) and staging.pending
    for array, want in made:
        np.testing.assert_array_equal(array.numpy(), want)
    assert staging.upload(np.zeros(5, np.uint8), wp.uint8) is None
    assert _Staging(backend._device, 1 << 16).upload(np.zeros(5, np.float32), float) is None  # small: pageable
    np.testing.assert_array_equal(backend._array(np.arange(5, dtype=np.uint8), wp.uint8).numpy(), np.arange(5))

