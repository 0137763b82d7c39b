"""The command line's contract (DESIGN §12): Ctrl-C, bad input before any output, the JSON
files written by fsswarp.outputs and their fields documented in docs/formats.md."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from fsswarp.backends import describe_backends
from fsswarp.cli import main
from fsswarp.errors import InputError

REPO = Path(__file__).resolve().parent.parent


def _opencl_cpu() -> int | None:
    """The index of an OpenCL CPU device (the coral_one fixture's backend), or None."""
    rows = [r for r in describe_backends() if r["backend"] == "opencl" and r["kind"] == "cpu" and r["available"]]
    return rows[0]["index"] if rows else None


def _backend_args() -> list[str]:
    """--backend opencl on that device where there is one."""
    return [] if _opencl_cpu() is None else ["--backend", "opencl", "--device", str(_opencl_cpu())]


# --- Ctrl-C ----------------------------------------------------------------------------------

@pytest.mark.parametrize("command, wait_for", [("reconstruct", "reconstructing"), ("reconstruct", "iteration 0: D"),
                                               ("demo", "simulating")])
def test_ctrl_c_prints_one_line_and_leaves_nothing(coral_one, tmp_path, command, wait_for):
    """SIGINT to the whole process group (as a terminal's Ctrl-C) at the first progress line
    (figure processes starting) or once the truth-metrics process works: exit 130, one line
    on stderr, no traceback from any process, no output folder."""
    out = tmp_path / "out"
    args = ([str(coral_one.root), "--resolution", "32", "--iterations", "3"] if command == "reconstruct"
            else ["coral-one", "--iterations", "1"])
    env = dict(os.environ, FSSWARP_FIGURE_WORKERS="1",
               PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    child = subprocess.Popen([sys.executable, "-m", "fsswarp", *_backend_args(), command, *args, "--out", str(out)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                             env=env, cwd=tmp_path)
    try:
        lines = []
        while not lines or (wait_for not in lines[-1] and lines[-1]):
            lines.append(child.stdout.readline())
        assert wait_for in lines[-1], (lines, child.communicate(timeout=60))
        os.killpg(child.pid, signal.SIGINT)
        stdout, stderr = child.communicate(timeout=120)
    finally:
        if child.poll() is None:
            child.kill()
    assert child.returncode == 130, stderr
    assert stderr == "fsswarp: interrupted\n"
    assert "Traceback" not in stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == []


# --- nothing printed before the input is checked -----------------------------------------------

BAD_OPTIONS = {
    "carve depth": (["carve", "{data}", "--out", "{out}", "--depth", "-1"], "--depth = -1.0"),
    "carve tilt": (["carve", "{data}", "--out", "{out}", "--tilt", "95"], "--tilt = 95.0"),
    "carve box": (["carve", "{data}", "--out", "{out}", "--box", "1", "1", "1", "0", "0", "0"], "--box = "),
    "reconstruct depth": (["reconstruct", "{data}", "--out", "{out}", "--depth", "-1"], "--depth = -1.0"),
    "reconstruct tilt": (["reconstruct", "{data}", "--out", "{out}", "--tilt", "90"], "--tilt = 90.0"),
    "enhance view": (["enhance", "{data}", "--model", "{truth}", "--out", "{out}", "--view", "nope"],
                     "view = 'nope'"),
    "enhance depth": (["enhance", "{data}", "--model", "{truth}", "--out", "{out}", "--depth", "0"],
                      "--depth = 0.0"),
    "pose tilt": (["pose", "{data}", "--model", "{truth}", "--out", "{out}", "--tilt", "-91"], "--tilt = -91.0"),
    "demo scene": (["demo", "coral1", "--out", "{out}"], "SCENE = 'coral1'"),
    "simulate scene": (["simulate", "coral1", "--out", "{out}"], "SCENE = 'coral1'"),
}


@pytest.mark.parametrize("case", list(BAD_OPTIONS))
def test_a_bad_option_prints_one_error_line_and_nothing_else(coral_one, tmp_path, capsys, case):
    args, named = BAD_OPTIONS[case]
    values = {"data": coral_one.root, "out": tmp_path / "out", "truth": coral_one.root / "truth" / "model.ply"}
    code = main(_backend_args() + [a.format(**values) for a in args])
    captured = capsys.readouterr()
    assert code == 2
    assert captured.out == ""
    assert captured.err.count("\n") == 1 and captured.err.startswith("fsswarp: error: ") and named in captured.err
    assert not (tmp_path / "out").exists()


# --- the JSON outputs ----------------------------------------------------------------------

@pytest.fixture(scope="module")
def outputs(coral_one, tmp_path_factory):
    """carve.json, result.json, pose.json and enhance.json of small runs on coral-one
    (truth present, so the truth-only fields are written): {file name: parsed record}."""
    root = tmp_path_factory.mktemp("outputs")
    data, truth = str(coral_one.root), str(coral_one.root / "truth" / "model.ply")
    runs = {"carve.json": ["carve", data, "--out", root / "carve", "--resolution", "32"],
            "result.json": ["reconstruct", data, "--out", root / "rec", "--resolution", "32", "--iterations", "1"],
            "pose.json": ["pose", data, "--model", truth, "--out", root / "pose", "--levels", "1"],
            "enhance.json": ["enhance", data, "--model", truth, "--out", root / "enhance",
                             "--initial-model", root / "carve" / "carved.ply"]}
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("FSSWARP_FIGURE_WORKERS", "0")
        records = {}
        for file, args in runs.items():
            assert main(["--quiet", *_backend_args(), *map(str, args)]) == 0, file
            records[file] = json.loads((Path(args[args.index("--out") + 1]) / file).read_text())
    return records


def json_keys(record, data_keys: set[str]) -> set[str]:
    """Every key of ``record``, recursively, less the keys that are data (``data_keys``: view
    names; figure file names)."""
    found = set()
    if isinstance(record, dict):
        for key, value in record.items():
            if key not in data_keys and not key.endswith(".png"):
                found.add(key)
            found |= json_keys(value, data_keys)
    elif isinstance(record, list):
        for value in record:
            found |= json_keys(value, data_keys)
    return found


def test_every_json_field_is_documented(outputs, coral_one):
    formats = (REPO / "docs" / "formats.md").read_text()
    documented = set(re.findall(r"`([^`\s]+)`", formats))
    for file, record in outputs.items():
        missing = sorted(json_keys(record, set(coral_one.rig.names)) - documented)
        assert not missing, f"{file}: fields not in docs/formats.md as `key`: {missing}"


def test_the_library_writes_what_the_command_line_writes(outputs, coral_one, tmp_path):
    """fsswarp.outputs from the Python API: the same carve.json as `fsswarp carve` but for the
    times."""
    import time

    from fsswarp.backends import get_backend
    from fsswarp.carving import carve
    from fsswarp.dataset import load_dataset
    from fsswarp.outputs import carve_record, write_carve

    start = time.perf_counter()
    dataset = load_dataset(coral_one.root)
    loaded = time.perf_counter() - start
    backend = get_backend() if _opencl_cpu() is None else get_backend("opencl", _opencl_cpu())
    result = carve(dataset, resolution=32, backend=backend)
    record = carve_record(str(coral_one.root), dataset, result, resolution=32, given=False, load_s=loaded,
                          truth=dataset.truth_mesh())
    write_carve(tmp_path, result, record)
    written = json.loads((tmp_path / "carve.json").read_text())
    expected = outputs["carve.json"]
    for record in (written, expected):
        record["timings_s"] = sorted(record["timings_s"])
    assert written == expected
    assert sorted(p.name for p in tmp_path.iterdir()) == ["carve.json", "carved.ply"]


def test_reconstruct_and_demo_start_the_mesh_processes_before_the_backend(coral_one, tmp_path, monkeypatch):
    """Spawned before the backend starts, the mesh processes' imports overlap the command's
    input and simulation (``State.start_mesh_workers``); without iterations, which alone mesh
    carvings ahead, none start."""
    import fsswarp.carving as carving
    import fsswarp.cli as cli

    order = []
    monkeypatch.setenv("FSSWARP_FIGURE_WORKERS", "0")
    monkeypatch.setattr(carving, "start_mesh_workers", lambda: order.append("mesh processes"))

    def backend(state):
        order.append("backend")
        raise InputError("stopped here", field="test")

    monkeypatch.setattr(cli.State, "get_backend", backend)
    assert cli.main(["-q", "reconstruct", str(coral_one.root), "--out", str(tmp_path / "r")]) == 2
    assert cli.main(["-q", "demo", "coral-one", "--out", str(tmp_path / "d")]) == 2
    assert order == ["mesh processes", "backend"] * 2
    order.clear()
    for command in (["reconstruct", str(coral_one.root)], ["demo", "coral-one"]):
        assert cli.main(["-q", *command, "--out", str(tmp_path / "z"), "--iterations", "0"]) == 2
    assert order == ["backend", "backend"]


END_SCRIPT = """
import atexit, concurrent.futures, sys
pool = concurrent.futures.ThreadPoolExecutor(2)
pool.submit(lambda: None).result()  # an idle pool's threads, as a warm-up leaves them
mark = sys.argv[1]
atexit.register(lambda: open(mark, "w").write("ran"))
sys.argv = ["fsswarp", *sys.argv[2:]]
from fsswarp.cli import run
run()
print("not reached")
"""


@pytest.mark.parametrize("args, status", [(["check", "{data}"], 0), (["check", "{data}/nowhere"], 2)])
def test_the_command_ends_at_once_after_its_threads_and_exit_handlers(coral_one, tmp_path, args, status):
    """``fsswarp.cli.run`` (the console script, ``python -m fsswarp``) ends the process with the
    command's status once its exit handlers have run, without hanging on an idle thread pool and
    without returning; with a profiler attached it ends as usual, so the profile is written."""
    mark = tmp_path / "ran"
    args = [a.format(data=coral_one.root) for a in args]
    done = subprocess.run([sys.executable, "-c", END_SCRIPT, str(mark), *args], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == status, done.stderr
    assert mark.read_text() == "ran" and "not reached" not in done.stdout
    profile = tmp_path / "profile"
    done = subprocess.run([sys.executable, "-m", "cProfile", "-o", str(profile), "-m", "fsswarp", *args],
                          capture_output=True, text=True, timeout=120)
    assert profile.stat().st_size > 0, done.stderr  # (cProfile itself swallows the command's SystemExit)
