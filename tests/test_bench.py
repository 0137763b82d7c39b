"""The benchmark suite (fsswarp/benchmark/, ``fsswarp bench``, bench/report.py) at tiny sizes:
record structure and arithmetic, the budget's skip rule, the command line and the report.
No assertion depends on how fast anything runs."""

from __future__ import annotations

import importlib.util
import json
import math
import os
import re
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from fsswarp.benchmark import families, harness
from fsswarp.cli import main

from conftest import backend_for

UNITS = {"raycast": "rays", "synthesis": "views", "carving": "voxel-views", "pose": "cell-views",
         "reconstruction": "views"}


def check_record(r: dict) -> None:
    """What must hold of every timed record, whatever the machine."""
    for key in ("family", "kernel", "mode", "backend", "device", "sweep", "x", "size", "work", "work_unit",
                "median_s", "min_s", "max_s", "repeat", "throughput", "throughput_unit", "limit"):
        assert key in r, key
    assert r["skipped"] is None
    assert r["work_unit"] == UNITS[r["family"]] and r["throughput_unit"] == r["work_unit"] + "/s"
    assert 0 < r["min_s"] <= r["median_s"] <= r["max_s"] and math.isfinite(r["max_s"]) and r["repeat"] >= 1
    assert r["throughput"] == pytest.approx(r["work"] / r["median_s"], rel=1e-12)
    for name, value in r["rates"].items():
        assert value > 0 and math.isfinite(value), name
    limit = r["limit"]
    parts = {k[:-2]: v for k, v in limit.items() if k in ("memory_s", "compute_s", "link_s")}
    assert all(v > 0 and math.isfinite(v) for v in parts.values())
    assert limit["limit_s"] == max(parts.values()) and limit["bound"] in parts
    assert limit["limit_s"] == parts[limit["bound"]]
    assert limit["fraction"] == pytest.approx(limit["limit_s"] / r["median_s"], rel=1e-12)
    assert limit["bytes"] > 0 and limit["ops"] > 0
    json.dumps(r, allow_nan=False)


@pytest.fixture(scope="module")
def carve_scene():
    return families.carve_scene(backend_for("opencl-cpu") if _has("opencl-cpu") else backend_for("warp-cpu"))


def _has(label: str) -> bool:
    try:
        backend_for(label)
    except pytest.skip.Exception:
        return False
    return True


@pytest.mark.parametrize("label", ["warp-cpu", "opencl-cpu"])
def test_every_family_gives_consistent_records(label, carve_scene):
    backend = backend_for(label)
    peer = families.NUMPY
    profiles = harness.probe_machine([backend, peer], quick=True)["profiles"]
    common = dict(profiles=profiles, repeat=1, budget=30.0)
    records = (families.raycast(backend, (1,), rays=2048, **common)
               + families.synthesis(backend, (1, 2), samples=(1, 4), streamed=(3,), batch=2, first_run=True,
                                    **common)
               + families.carving(backend, (8,), scene=carve_scene, **common)
               + families.pose_grid(backend, (2,), **common)
               + families.reconstruction(backend, ((0, 16),), **common)
               + families.numpy_carving((6,), scene=carve_scene, **common))
    assert {r["family"] for r in records} == set(families.FAMILIES)
    assert {(r["family"], r["mode"]) for r in records if r["backend"] == backend.name} >= {
        ("raycast", "resident"), ("raycast", "end to end"), ("synthesis", "resident"), ("carving", "resident"),
        ("pose", "end to end"), ("pose", "resident"), ("reconstruction", "end to end")}
    for r in records:
        check_record(r)
    ray = next(r for r in records if r["family"] == "raycast")
    assert ray["size"] == {"triangles": 80, "rays": 2048, "hits": ray["size"]["hits"]}
    assert 0 < ray["size"]["hits"] < 2048
    streamed = {r["kernel"]: r for r in records if r["family"] == "synthesis" and r["x"] == 3}
    assert set(streamed) == {"render per batch of 2 (pageable, in turn)", "render_batches of 2 (pinned, overlapped)"}
    for r in streamed.values():
        assert r["mode"] == "end to end" and r["size"]["batch"] == 2 and r["work"] == 3
        assert r["rates"]["bytes to the host"] == pytest.approx(3 * 4 * 4 * 512 * 96 / r["median_s"])
    first = {r["mode"]: r for r in records if r["kernel"] == "render, first call of a new process"}
    assert set(first) == {"first run (cold cache)", "first run (warm cache)"}
    for r in first.values():  # the first call includes the backend's creation, a warm call does not
        assert r["repeat"] == 1 and 0 < r["size"]["backend_s"] < r["median_s"] and r["size"]["again_s"] > 0
    carve = next(r for r in records if r["family"] == "carving" and r["backend"] == backend.name)
    assert carve["work"] == 8**3 * 16 and 1 <= carve["size"]["tests_per_voxel"] <= 16


def test_embree_peer_is_timed_or_unavailable():
    peer = families.EMBREE
    profiles = harness.probe_machine([peer], quick=True)["profiles"]
    records = families.embree_raycast((1,), profiles=profiles, repeat=1, rays=1024)
    assert len(records) == 1
    if records[0]["skipped"] is None:
        check_record(records[0])
    else:
        assert records[0]["skipped"]["reason"].startswith("unavailable")


def test_array_module_carving_runs_on_numpy(carve_scene):
    sonar, masks, rot, t, centre = carve_scene
    h, origin = families.carving_grid(centre, 8)
    keep = families.carve_array_module(np, masks, rot, t, sonar, h, origin, 8, chunk=100)
    assert keep.shape == (512,) and keep.dtype == bool
    assert keep.any() and not keep.all()
    np.testing.assert_array_equal(keep, families.carve_array_module(np, masks, rot, t, sonar, h, origin, 8))


class FakeClock:
    """A clock that only moves when the code under test 'runs' something."""

    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_measure_stops_repeating_at_the_budget_but_keeps_one_run():
    clock = FakeClock()

    def call():
        clock.now += 4.0

    timing = harness.measure(call, 5, budget=10.0, clock=clock)
    assert timing["repeat"] == 1 and timing["median_s"] == 4.0 and timing["timed_s"] == 8.0  # warm-up + 1
    timing = harness.measure(call, 3, budget=100.0, clock=clock)
    assert timing["repeat"] == 3 and timing["min_s"] == timing["max_s"] == 4.0
    timing = harness.measure(call, 3, warmup=0, budget=1.0, clock=clock)
    assert timing["repeat"] == 1


def test_sweep_skips_points_projected_past_the_budget():
    clock = FakeClock()
    ran = []

    def run_point(x):
        clock.now += 1.0  # setup, grows with the size
        clock.now += 2.0 * x  # timed calls, grow with the work
        ran.append(x)
        return [{"x": x, "timed_s": 2.0 * x}]

    def skipped(x, projected):
        return [{"x": x, "skipped": {"projected_s": projected}}]

    points = [(1, 1, 1), (2, 2, 2), (4, 4, 4), (8, 8, 8), (3, 3, 3)]
    records = harness.sweep(points, run_point, skipped, budget=10.0, clock=clock)
    # 1 took 1 + 2 s; 2 is projected at 2 + 4 = 6 s and runs (1 + 4 s); 4 is projected at
    # 2 + 8 = 10 s (not past the budget) and runs (1 + 8 s); 8 at 2 + 16 = 18 s is skipped,
    # and so is every later point, even a smaller one
    assert ran == [1, 2, 4]
    assert [r["x"] for r in records] == [1, 2, 4, 8, 3]
    assert records[3]["skipped"]["projected_s"] == pytest.approx(18.0)
    assert records[4]["skipped"]["projected_s"] == pytest.approx(0.25 * 3 + 8 * 3 / 4)


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench") / "run"
    status = main(["--quiet", "bench", "--out", str(out), "--quick", "--families", "raycast,carving",
                   "--repeat", "1"])
    return status, out


def test_cli_writes_json_tables_and_plots(cli_run):
    status, out = cli_run
    assert status == 0
    run = json.loads((out / "bench.json").read_text())
    assert run["quick"] and run["command"].startswith("fsswarp bench --out")
    assert {r["family"] for r in run["records"]} == {"raycast", "carving"}
    for r in run["records"]:
        if r.get("skipped") is None:
            check_record(r)
    text = (out / "bench.md").read_text()
    assert "| kernel | mode |" in text and "fraction of limit" in text and "measured NumPy copy" in text
    assert (out / "raycast.png").stat().st_size > 0 and (out / "carving.png").stat().st_size > 0


@pytest.mark.parametrize("args", [["--families", "raycast,nope"], ["--budget", "0"], ["--budget", "nan"],
                                  ["--repeat", "0"], ["--families", ","]])
def test_cli_bad_options_exit_2_with_one_line(args, tmp_path, capsys):
    assert main(["bench", "--out", str(tmp_path / "x"), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("fsswarp: error:") and "\n" not in err
    assert not (tmp_path / "x").exists()


def test_report_regenerates_results_from_records(cli_run, tmp_path):
    _, out = cli_run
    report = _bench_module("report")
    records = tmp_path / "records"
    records.mkdir()
    (records / "tiny-cpu.json").write_bytes((out / "bench.json").read_bytes())
    notes = tmp_path / "notes.md"
    notes.write_text("## Notes\n\nkept by hand\n")
    results = tmp_path / "RESULTS.md"
    args = [str(records / "tiny-cpu.json"), "--notes", str(notes), "--out", str(results),
            "--figures", str(tmp_path / "figures")]
    assert report.main(args) == 0
    text = results.read_text()
    assert "## tiny-cpu" in text and "Furthest from their limits" in text and text.rstrip().endswith("kept by hand")
    assert "](figures/tiny-cpu-raycast.png)" in text and (tmp_path / "figures" / "tiny-cpu-carving.png").is_file()
    assert report.main([str(tmp_path / "missing.json"), "--out", str(tmp_path / "R2.md")]) == 2
    for name, text in (("garbage.json", "not json"), ("other.json", '{"runs": []}')):
        (tmp_path / name).write_text(text)
        assert report.main([str(tmp_path / name), "--out", str(tmp_path / "R3.md")]) == 2
        assert not (tmp_path / "R3.md").exists()
    # figures in a folder beside, not below, the report's: links climb out of its folder
    elsewhere = tmp_path / "elsewhere" / "RESULTS.md"
    assert report.main([str(records / "tiny-cpu.json"), "--out", str(elsewhere), "--figures",
                        str(tmp_path / "figures")]) == 0
    assert "](../figures/tiny-cpu-raycast.png)" in elsewhere.read_text()


def _bench_module(name: str):
    """bench/NAME.py, loaded by path (bench/ is not a package)."""
    spec = importlib.util.spec_from_file_location(f"bench_{name}", Path(__file__).parents[1] / "bench" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _paper_table():
    return _bench_module("paper_table")


def test_paper_table_runs_both_starts_and_renders_the_table(tmp_path, capsys):
    """bench/paper_table.py end to end at zero iterations: the record, the two starts (the
    measured one, and a tilt sensor 2° off on the measured side with σ_β 2°), the intervals and
    the calibration line, and the Markdown that report.py renders."""
    table = _paper_table()
    assert table.main(["--scenes", "coral-one", "--seeds", "0", "--iterations", "0", "--records", str(tmp_path),
                       "--name", "tiny", "--backend", "opencl"]) == 0
    record = json.loads((tmp_path / "tiny.json").read_text())
    measured, off = record["runs"]
    assert (measured["depth0_m"], measured["tilt0_deg"]) == (0.432, pytest.approx(11.1))
    assert (measured["depth_sigma_m"], measured["tilt_sigma_deg"]) == (0.003, pytest.approx(0.6))
    assert off["tilt0_deg"] == pytest.approx(10.3 + 2.0) and off["depth0_m"] == 0.432
    assert off["tilt_sigma_deg"] == pytest.approx(2.0)
    for run in record["runs"]:
        s = table.summary(run)
        assert s["depth_error_m"] == pytest.approx(0.002) and s["E_I_change"] == 0.0 and s["E_V_change"] == 0.0
        assert not (s["pose_ok"] or s["E_I_ok"] or s["E_V_ok"])
        lo, hi = run["tilt_interval_deg"]
        assert lo < run["tilt_deg"] < hi and s["tilt_covered"] == (lo <= 10.3 <= hi)
    text = table.table_markdown(record, "tiny")
    assert "| coral-one (0, β +2°, σ_β 2°) | 0.4320, 12.30 | 0.4320, 12.300 | +2.0 | +2.000 | no | " in text
    assert "Calibration: the 95% intervals hold the true D in " in text and " of 2 runs" in text
    for run in record["runs"]:  # the pose step alone with the true model, from the same starts
        pose = run["true_model_pose"]
        assert abs(pose["depth_m"] - 0.43) <= 0.005 and abs(pose["tilt_deg"] - 10.3) <= 0.2
        assert pose["E_mu_m"] < 0.2 * pose["E_mu_start_m"]
    assert "with the true model in place of the reconstruction" in text
    assert record["positions"] is None and "sonar positions" not in text
    assert "seeds 0; sonar positions SNEW; realistic sensors" in table.table_markdown({**record, "positions": "SNEW"},
                                                                                      "tiny")
    assert "### tiny" in capsys.readouterr().out
    rendered = _bench_module("report").report([], None, None, tmp_path, [tmp_path / "tiny.json"])
    assert "## Reconstruction: the paper's table" in rendered and "### tiny" in rendered


def test_paper_table_summary_judges_the_aims():
    table = _paper_table()
    run = {"scene": "coral-one", "depth_m": 0.4329, "truth_depth_m": 0.43, "tilt_deg": 10.449, "truth_tilt_deg": 10.3,
           "best_iteration": 1, "depth_interval_m": [0.431, 0.436], "tilt_interval_deg": [10.2, 10.6],
           "history": [{"E_I": 1.0, "E_V": 0.40}, {"E_I": 0.75, "E_V": 0.35}, {"E_I": 0.8, "E_V": 0.30}]}
    s = table.summary(run)  # of the kept iteration 1, not the last
    assert s["depth_error_m"] == pytest.approx(0.0029) and s["tilt_error_deg"] == pytest.approx(0.149)
    assert s["pose_ok"] and s["E_I_ok"] and not s["E_V_ok"]  # E_V down 12.5% < 25%
    assert s["E_V_change"] == pytest.approx(-0.125) and s["E_I_change"] == pytest.approx(-0.25)
    assert not s["depth_covered"] and s["tilt_covered"]  # 0.43 below [0.431, 0.436]
    table_run = {**run, "scene": "table", "tilt_deg": 10.6, "depth_m": 0.44}  # the table: β within 0.5°, no D aim
    assert table.summary(table_run)["pose_ok"] and table.summary(table_run)["E_V_ok"]


@pytest.mark.parametrize("args", [["--tilt-offset", "20"], ["--iterations", "-1"], ["--scenes", "nowhere"],
                                  ["--positions", "SQ"]])
def test_paper_table_bad_options_exit_2(args, tmp_path):
    table = _paper_table()
    try:
        code = table.main([*args, "--records", str(tmp_path)])
    except SystemExit as stop:  # argparse's own errors
        code = stop.code
    assert code == 2 and not list(tmp_path.iterdir())


def test_ab_reconstruct_runs_each_tree_from_its_own_package(coral_south, tmp_path):
    """bench/ab_reconstruct.py times a tree's own code: the run imports fsswarp from that tree,
    not from the working folder or the installed package."""
    import shutil

    repo = Path(__file__).parents[1]
    tree = tmp_path / "tree"
    for name in ("fsswarp", "kernels"):
        shutil.copytree(repo / name, tree / name, ignore=shutil.ignore_patterns("__pycache__"))
    found = _bench_module("ab_reconstruct").run_tree(tree, str(coral_south.root), "auto", "", "0")
    assert Path(found["package"]) == tree / "fsswarp" and found["E_I"] == 1.0 and found["seconds"] > 0
    assert len(found["model"]) == 12 and int(found["model"], 16) >= 0  # the model's digest, to compare trees


def test_ab_reconstruct_stops_a_run_that_hangs_with_every_process_it_started(tmp_path):
    """A run past its timeout is stopped with the processes it started, even one that holds its
    output open (a hung pool's children did so on a GPU machine), and TimeoutError names the tree."""
    tree = tmp_path / "tree"
    (tree / "fsswarp").mkdir(parents=True)
    marker = tmp_path / "child.pid"
    (tree / "fsswarp" / "__init__.py").write_text(
        "import subprocess, sys, time\n"
        f"child = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])\n"
        f"open({str(marker)!r}, 'w').write(str(child.pid))\n"
        "time.sleep(60)\n")
    start = time.perf_counter()
    with pytest.raises(TimeoutError, match=f"{tree}: a run took more than 3 s"):
        _bench_module("ab_reconstruct").run_tree(tree, "data", "auto", "", "0", timeout=3)
    assert time.perf_counter() - start < 20
    status = Path(f"/proc/{int(marker.read_text())}/status")
    for _ in range(50):  # the child is gone (or a zombie: killed, not yet reaped) once the kill reaches it
        if not status.exists() or "\nState:\tZ" in status.read_text():
            break
        time.sleep(0.1)
    else:
        pytest.fail("the run's child process was left running")


def test_ab_reconstruct_names_the_imported_packages_without_bytecode(tmp_path, monkeypatch):
    """Where Python writes no bytecode, a package whose bytecode was never compiled is named (each
    run would compile it from source); once compiled, or where Python writes bytecode, none is."""
    import compileall
    import sys

    ab = _bench_module("ab_reconstruct")
    package = tmp_path / "fsswarp_uncompiled"
    package.mkdir()
    (package / "__init__.py").write_text("VALUE = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(ab, "IMPORTED", ("fsswarp_uncompiled", "numpy_not_installed_here"))
    monkeypatch.setattr(sys, "dont_write_bytecode", True)
    assert ab.packages_without_bytecode() == ["fsswarp_uncompiled"]
    compileall.compile_dir(package, quiet=1)
    assert ab.packages_without_bytecode() == []
    for cached in (package / "__pycache__").iterdir():
        cached.unlink()
    monkeypatch.setattr(sys, "dont_write_bytecode", False)
    assert ab.packages_without_bytecode() == []


def test_ab_reconstruct_refuses_a_timeout_of_no_time(capsys, monkeypatch):
    monkeypatch.chdir(Path(__file__).parents[1])
    assert _bench_module("ab_reconstruct").main([".", ".", "--timeout", "0"]) == 2
    assert "--timeout" in capsys.readouterr().err


def test_ab_reconstruct_pairs_the_rounds():
    """Each round's after / before, and the rounds in which AFTER was faster."""
    ratios, faster = _bench_module("ab_reconstruct").paired([10.0, 8.0, 9.0], [9.0, 9.0, 9.0])
    assert ratios == [0.9, 1.125, 1.0] and faster == 1


@pytest.mark.parametrize("args", [["nowhere", "."], [".", ".", "--rounds", "0"]])
def test_ab_reconstruct_bad_options_exit_2_with_one_line(args, capsys, monkeypatch):
    monkeypatch.chdir(Path(__file__).parents[1])
    assert _bench_module("ab_reconstruct").main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("bench/ab_reconstruct.py:") and "\n" not in err


def _identifiability():
    return _bench_module("identifiability")


def test_identifiability_valley_keeps_the_centroid_below_the_surface():
    """valley_depth against the closed form in the world frame: the centroid's world height is
    c_y sin(β + δβ) + c_z cos(β + δβ) − (D + δD) for a reference of any heading ψ, so D(β)
    follows that sum's change from the true tilt; ψ and δD drop out."""
    from fsswarp.rig import Rig, View

    study = _identifiability()
    rig = Rig((View("a", position=(0.3, -1.0), heading=0.7, depth_offset=0.05, tilt_offset=math.radians(1.5)),
               View("b", heading=math.pi)))
    centroid = np.array([0.04, 2.1, -0.07])
    depth_true, tilt_true, offset = 0.43, math.radians(10.3), math.radians(1.5)

    def height(tilt):
        return centroid[1] * math.sin(tilt + offset) + centroid[2] * math.cos(tilt + offset)

    assert study.valley_depth(rig, centroid, depth_true, tilt_true, tilt_true) == pytest.approx(depth_true, abs=1e-12)
    for delta in (-2.0, -0.5, 1.0):
        tilt = tilt_true + math.radians(delta)
        expected = depth_true + height(tilt) - height(tilt_true)
        assert study.valley_depth(rig, centroid, depth_true, tilt_true, tilt) == pytest.approx(expected, abs=1e-12)
    # about 3.7 cm per degree at 2.1 m: the valley of the README
    slope = study.valley_depth(rig, centroid, depth_true, tilt_true, tilt_true + math.radians(1.0)) - depth_true
    assert 0.03 < slope < 0.04


def test_identifiability_runs_every_start_and_renders_the_table(tmp_path, capsys):
    """bench/identifiability.py end to end at one valley point and no refinement: the truth
    starts score E_V 0 (to rounding) at the truth, the carved start more, and report.py renders the record."""
    study = _identifiability()
    assert study.main(["--scenes", "coral-one", "--tilts", "0", "--rounds", "0", "--records", str(tmp_path),
                       "--name", "tiny", "--backend", "opencl"]) == 0
    record = json.loads((tmp_path / "tiny.json").read_text())
    result = record["scenes"]["coral-one"]
    assert result["valley"] == [[0.0, pytest.approx(0.43, abs=1e-12)]]
    assert set(result["starts"]) == set(study.STARTS)
    for start, series in result["starts"].items():
        (only,) = series[0]
        assert set(only) == set(study.METRICS) and all(math.isfinite(v) for v in only.values())
        assert (only["E_V"] < 1e-9) == start.startswith("true shape")
    carved, truth = (result["starts"][s][0][0] for s in ("carved", "true shape"))
    assert carved["AIE"] > truth["AIE"] and carved["E_V"] > 0.1
    text = study.table_markdown(record, "tiny")
    assert f"| true shape | AIE | 0 | {truth['AIE']:.3f} | +0° |" in text and "#### coral-one" in text
    assert record["positions"] is None and "sonar positions" not in text
    assert "seed 0; sonar positions EW; 0 rounds" in study.table_markdown({**record, "positions": "EW"}, "tiny")
    assert "### tiny" in capsys.readouterr().out
    rendered = _bench_module("report").report([], None, tmp_path / "figs", tmp_path, [], [tmp_path / "tiny.json"])
    assert "## Reconstruction: where the images pin the tilt" in rendered and "### tiny" in rendered
    assert "![tiny](figs/identifiability-tiny.png)" in rendered
    assert (tmp_path / "figs" / "identifiability-tiny.png").read_bytes().startswith(b"\x89PNG")


def test_identifiability_lowest_at_skips_missing_values_and_names_ties():
    study = _identifiability()
    assert study.lowest_at([0.5, math.nan, 0.2, 0.3], [-1.0, -0.5, 0.0, 0.5]) == "+0°"
    assert study.lowest_at([math.nan], [1.0]) == "—"
    assert study.lowest_at([3e-16, 0.0, 1e-15], [-1.0, 0.0, 1.0]) == "all equal"
    assert study.lowest_at([0.2], [1.0]) == "+1°"


def test_identifiability_parabola_finds_the_minimum_and_the_noise_of_its_residuals():
    """A parabola 2 (δ − 0.3)² + 1 plus residuals orthogonal to 1, δ, δ² (so least squares
    returns it exactly): the minimum 0.3°, the curvature 2, the noise the residuals' RMS over
    N − 3, and at δ_min ± the resolution the parabola rises by the noise."""
    study = _identifiability()
    tilts = np.array([-1.0, -0.5, -0.2, 0.0, 0.2, 0.5, 1.0])
    basis = np.vander(tilts, 3)
    rng = np.random.default_rng(3)
    raw = rng.normal(size=tilts.size)
    residual = 0.05 * (raw - basis @ np.linalg.lstsq(basis, raw, rcond=None)[0])
    fit = study.parabola_fit(tilts, 2.0 * (tilts - 0.3) ** 2 + 1.0 + residual)
    noise = math.sqrt(float(residual @ residual) / (tilts.size - 3))
    assert fit["minimum_deg"] == pytest.approx(0.3, abs=1e-9) and fit["curvature"] == pytest.approx(2.0, abs=1e-9)
    assert fit["noise"] == pytest.approx(noise, rel=1e-9)
    assert 2.0 * fit["resolution_deg"] ** 2 == pytest.approx(noise, rel=1e-9)
    assert study.parabola_cell(2.0 * (tilts - 0.3) ** 2 + 1.0 + residual, tilts) == \
        f"+0.30° ± {fit['resolution_deg']:.2f}°"
    # an exact parabola through NaN gaps: no noise, a resolution of 0
    values = 0.5 * (tilts + 0.2) ** 2
    values[1] = math.nan
    exact = study.parabola_fit(tilts, values)
    assert exact["minimum_deg"] == pytest.approx(-0.2, abs=1e-9) and exact["resolution_deg"] == pytest.approx(0.0, abs=1e-6)


def test_identifiability_parabola_without_a_minimum():
    study = _identifiability()
    tilts = [-1.0, -0.5, 0.0, 0.5, 1.0]
    flat = study.parabola_fit(tilts, [0.7] * 5)
    assert math.isnan(flat["minimum_deg"]) and flat["resolution_deg"] == math.inf and flat["noise"] < 1e-12
    down = study.parabola_fit(tilts, [-(t ** 2) for t in tilts])
    assert down["curvature"] == pytest.approx(-1.0) and math.isnan(down["minimum_deg"])
    assert down["resolution_deg"] == math.inf
    assert study.parabola_cell([-(t ** 2) for t in tilts], tilts) == "none"
    three = study.parabola_fit([-1.0, 0.0, 1.0], [1.0, 0.0, 1.0])  # no degrees of freedom left for the noise
    assert three["minimum_deg"] == pytest.approx(0.0, abs=1e-12) and math.isnan(three["resolution_deg"])
    assert study.parabola_cell([1.0, 0.0, 3.0], [-1.0, 0.0, 1.0]) == "-0.25°"  # 2δ² + δ
    assert study.parabola_cell([1.0, math.nan, 1.0], [-1.0, 0.0, 1.0]) == "—"
    assert math.isnan(study.parabola_fit([0.0, 0.0, 0.0, 0.0], [1.0, 2.0, 3.0, 4.0])["curvature"])


@pytest.mark.parametrize("args", [["--tilts", "7"], ["--rounds", "-1"], ["--scenes", "nowhere"]])
def test_identifiability_bad_options_exit_2(args, tmp_path):
    try:
        code = _identifiability().main([*args, "--records", str(tmp_path)])
    except SystemExit as stop:  # argparse's own errors
        code = stop.code
    assert code == 2 and not list(tmp_path.iterdir())


def _gpu_runner(tmp_path, *args):
    env_file = tmp_path / "env.sh"
    env_file.write_text("export FSW_TEST_ENV=1\n")
    script = Path(__file__).resolve().parents[1] / "bench" / "device" / "gpu.sh"
    return subprocess.run(["bash", str(script), *args], capture_output=True, text=True,
                          env=dict(os.environ, FSW_ENV=str(env_file), OUT=str(tmp_path)))


def test_gpu_runner_names_every_run_it_knows_and_refuses_others_with_exit_2(tmp_path):
    """bench/device/gpu.sh: every run its header lists has a case, and an unknown one is a
    one-line error with exit status 2."""
    script = (Path(__file__).resolve().parents[1] / "bench" / "device" / "gpu.sh").read_text()
    listed = set(re.findall(r"^#   bash bench/device/gpu\.sh (\w+)", script, re.M))
    handled = set(re.findall(r"^  (\w+)\)$", script, re.M))
    assert listed == handled == {"tests", "table", "study", "bench", "ab", "profile", "grid", "demo", "batch", "ray",
                                 "resident"}
    for args, message in ((["nowhere"], "unknown run 'nowhere'"), ([], "name a run"),
                          (["table", "h100"], "table needs NAME and at least one SCENE")):
        done = _gpu_runner(tmp_path, *args)
        assert done.returncode == 2
        assert done.stderr.strip().startswith(f"bench/device/gpu.sh: error: {message}")
        assert "\n" not in done.stderr.strip()


def test_loop_profile_call_times_count_time_and_restore():
    """CallTimes against a function that sleeps a known time: calls counted, inclusive seconds
    at least the sleeps, and the original back after restore."""
    import time
    import types

    times = _bench_module("loop_profile").CallTimes()
    owner = types.SimpleNamespace(nap=lambda seconds: time.sleep(seconds) or seconds)
    original = owner.nap
    times.wrap(owner, "nap", "nap")
    assert owner.nap(0.02) == 0.02 and owner.nap(0.01) == 0.01
    calls, seconds = times.totals["nap"]
    assert calls == 2 and 0.03 <= seconds < 1.0
    times.restore()
    assert owner.nap is original
    assert "| `nap` | 2 |" in times.table(seconds)


def test_loop_profile_outermost_calls_count_once_per_thread():
    """An outermost-only wrapper called inside another (the same thread) is not counted; in
    another thread it is; plain wrappers count every call."""
    import threading
    import types

    times = _bench_module("loop_profile").CallTimes()
    owner = types.SimpleNamespace()
    owner.inner = lambda: 1
    owner.outer = lambda: owner.inner() + owner.inner()
    owner.plain = lambda: owner.outer()
    originals = dict(vars(owner))
    for name, outermost in (("inner", True), ("outer", True), ("plain", False)):
        times.wrap(owner, name, name, outermost=outermost)
    assert owner.plain() == 2 and owner.inner() == 1
    worker = threading.Thread(target=owner.outer)
    worker.start()
    worker.join()
    assert {label: calls for label, (calls, _) in times.totals.items()} == {"plain": 1, "outer": 2, "inner": 1}
    assert "| `inner` |" not in times.table(1.0, ["outer"])
    times.restore()
    assert vars(owner) == originals


def test_loop_profile_times_a_reconstruction_and_leaves_fsswarp_as_it_was(capsys):
    import fsswarp.carving
    import fsswarp.compare
    import fsswarp.reconstruction

    before = (fsswarp.reconstruction.carve, fsswarp.reconstruction.refine_shape, fsswarp.compare.ViewComparison.exact)
    assert _bench_module("loop_profile").main(["--backend", "opencl", "--iterations", "0"]) == 0
    assert (fsswarp.reconstruction.carve, fsswarp.reconstruction.refine_shape,
            fsswarp.compare.ViewComparison.exact) == before
    assert fsswarp.reconstruction.carve is fsswarp.carving.carve
    out = capsys.readouterr().out
    assert "0 iterations" in out and "| `carve` | 1 |" in out and "| `_image_errors` | 1 |" in out
    assert "| `backend.render_planned` |" in out  # the render is timed (its method's name is current)


def test_loop_profile_main_partitions_the_main_thread(capsys):
    """``--main``: each call only where no wrapped call encloses it, so the rows (with the rest of
    the main thread) add up to the run's seconds and the calls inside ``carve`` are not counted."""
    import re

    assert _bench_module("loop_profile").main(["--backend", "opencl", "--iterations", "0", "--main"]) == 0
    out = capsys.readouterr().out
    total = float(re.search(r": ([0-9.]+) s, 0 iterations", out).group(1))
    rows = dict(re.findall(r"^\| `([^`]+)` \| \d+ \| ([0-9.-]+) \|", out, flags=re.MULTILINE))
    assert "carve" in rows and "(the rest of the main thread)" in rows and "backend.carve" not in rows
    assert sum(float(seconds) for seconds in rows.values()) == pytest.approx(total, abs=0.002 * len(rows))
    with pytest.raises(SystemExit) as exited:
        _bench_module("loop_profile").main(["--warp", "--main"])
    assert exited.value.code == 2


def test_loop_profile_fresh_times_the_process_s_first_reconstruction(coral_one, monkeypatch, capsys):
    """``--fresh``: the scene comes from a ``fsswarp simulate`` child process (here a stand-in
    that copies a simulated folder), and the timed reconstruction is the only one (no warm-up
    run); a child that fails ends the script with its status and stderr."""
    import shutil
    import subprocess

    import fsswarp.reconstruction

    loop_profile = _bench_module("loop_profile")
    commands, runs, original = [], [], fsswarp.reconstruction.reconstruct

    def simulate(command, **kwargs):
        commands.append(command)
        shutil.copytree(coral_one.root, command[command.index("--out") + 1])
        return subprocess.CompletedProcess(command, 0, "", "")

    monkeypatch.setattr(subprocess, "run", simulate)
    monkeypatch.setattr(fsswarp.reconstruction, "reconstruct", lambda *a, **k: runs.append(k) or original(*a, **k))
    assert loop_profile.main(["--backend", "opencl", "--iterations", "0", "--fresh", "--seed", "3"]) == 0
    assert len(runs) == 1 and len(commands) == 1
    assert commands[0][1:] == ["-m", "fsswarp", "-q", "--backend", "opencl", "simulate", "coral-one", "--out",
                               commands[0][9], "--seed", "3"]
    out = capsys.readouterr().out
    assert "from the process's first reconstruction on opencl" in out
    assert "packages with modules first imported during the run: " in out and "| `carve` | 1 |" in out
    monkeypatch.setattr(subprocess, "run", lambda command, **kwargs: subprocess.CompletedProcess(
        command, 2, "", "fsswarp: error: no such scene"))
    with pytest.raises(SystemExit) as exited:
        loop_profile.main(["--backend", "opencl", "--iterations", "0", "--fresh"])
    assert exited.value.code == 2 and "no such scene" in capsys.readouterr().err


def test_loop_profile_bad_options_exit_2(capsys):
    assert _bench_module("loop_profile").main(["--iterations", "-1"]) == 2
    assert _bench_module("loop_profile").main(["--backend", "opencl", "--warp"]) == 2
    assert "--warp needs a Warp backend" in capsys.readouterr().err


def test_demo_wall_alternates_the_settings_after_a_warm_up(monkeypatch, capsys):
    """bench/demo_wall.py with the demo replaced by a stand-in that takes known times: one
    uncounted warm-up run, then the two figure settings in turn, and medians with their ratio."""
    demo_wall = _bench_module("demo_wall")
    calls, times = [], iter([99.0, 30.0, 20.0, 34.0, 22.0, 32.0, 21.0])
    monkeypatch.setattr(demo_wall, "run_demo", lambda scene, out, workers, options: calls.append(
        (scene, workers, tuple(options))) or next(times))
    assert demo_wall.main(["--rounds", "3", "--scene", "table", "--", "--backend", "warp"]) == 0
    assert calls == [("table", None, ("--backend", "warp"))] + [("table", w, ("--backend", "warp"))
                                                                 for _ in range(3) for w in ("0", None)]
    out = capsys.readouterr().out
    assert "figures in the command's process: median 32.0 s (30.0-34.0)" in out
    assert "figures in figure processes: median 21.0 s (20.0-22.0)" in out and out.rstrip().endswith("ratio 0.66")


def test_batch_throughput_runs_commands_at_once_and_they_agree(coral_south, tmp_path):
    """bench/batch_throughput.py: two reconstructions started together both write result.json,
    with the same values (determinism), and the wall time covers both."""
    batch = _bench_module("batch_throughput")
    wall, results = batch.run_batch(coral_south.root, [tmp_path / "a", tmp_path / "b"], 0, ["--backend", "opencl"])
    assert wall > 0 and len(results) == 2
    assert batch.agreed(results[0]) == batch.agreed(results[1])
    assert results[0]["history"][0]["E_I"] == 1.0 and results[0]["best_iteration"] == 0
    with pytest.raises(RuntimeError, match="exited 2"):
        batch.run_batch(tmp_path / "nowhere", [tmp_path / "c"], 0, ["--backend", "opencl"])


def test_reference_run_failing_exits_with_the_command_s_status(tmp_path, capsys):
    """bench/batch_throughput.py's reference_run (batch_ray.py's and resident_jobs.py's first
    step): a command that fails ends the benchmark with its status and its stderr."""
    with pytest.raises(SystemExit) as stopped:
        _bench_module("batch_throughput").reference_run(tmp_path, "coral-one", 0, 0, ["--backend", "nonsense"])
    assert stopped.value.code == 2
    assert "'nonsense' is not one of" in capsys.readouterr().err


def test_batch_throughput_table_reports_seconds_per_reconstruction():
    text = _bench_module("batch_throughput").table_markdown({1: [10.0, 12.0], 4: [20.0, 22.0, 30.0]})
    assert "| 1 | 11.0 s (10.0–12.0) | 2 | 11.00 s | 1.00 |" in text
    assert "| 4 | 22.0 s (20.0–30.0) | 3 | 5.50 s | 2.00 |" in text


@pytest.mark.parametrize("args", [["--jobs", "0"], ["--rounds", "0"], ["--iterations", "-1"], ["--jobs", "65"]])
def test_batch_throughput_bad_options_exit_2(args, capsys):
    assert _bench_module("batch_throughput").main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("bench/batch_throughput.py: error:") and "\n" not in err


@pytest.mark.parametrize("script, options", [("exact_profile", ["--calls", "0"]), ("refine_profile", ["--seed", "-1"]),
                                             ("mesh_profile", ["--repeats", "0"]), ("grid_profile", ["--repeat", "0"]),
                                             ("grid_profile", ["--sides", "0"])])
def test_the_profile_scripts_refuse_bad_options_with_exit_2(script, options, capsys):
    assert _bench_module(script).main(options) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"{script}: error: ")


def test_grid_profile_gives_every_launch_size_the_same_costs(capsys):
    """The grid in launches of one cell and in one launch: one table row each, the same checksum
    of the costs (a pair's costs do not depend on its launch), no kernel table off CUDA."""
    assert _bench_module("grid_profile").main(["--backend", "opencl", "--sides", "3", "--launch-mib", "2", "4096",
                                                "--repeat", "1", "--kernels", "--gaps"]) == 0
    out = capsys.readouterr().out
    rows = [line.split(" | ") for line in out.splitlines() if line.startswith("| ") and "MiB" in line]
    assert [row[0] for row in rows] == ["| 2 MiB", "| 4096 MiB"] and [row[2] for row in rows] == ["1", "3603"]
    assert rows[0][5] == rows[1][5] and float(rows[0][5].rstrip(" |")) > 0
    assert "--kernels: the GPU's times need Warp on a CUDA device" in out
    assert "--gaps: the GPU's times need Warp on a CUDA device" in out


def test_grid_profile_gaps_sum_the_kernels_and_the_gpus_waits_for_the_host():
    """--gaps' summary of (kernel, issued, GPU start, GPU end) marks, in s from the call's start:
    the kernels' own time, the time between them and the part of it before the host issued the
    next kernel, each kernel that waited, and the call's end after the last (by hand: 3 + 4 +
    7.5 ms of kernels; 1 + 2.5 ms between; kernel c issued 2 ms after b ended)."""
    summary = _bench_module("grid_profile").gap_summary
    text = summary(0.0215, [("a", 0.001, 0.002, 0.005), ("b", 0.003, 0.006, 0.010), ("c", 0.012, 0.0125, 0.020)])
    assert text.splitlines()[0] == ("call 21.5 ms: the first kernel began at 2.00 ms; 3 kernels 14.5 ms; between them "
                                    "3.5 ms, of which the GPU waited for the host 2.0 ms; the call ended 1.50 ms after "
                                    "the last kernel")
    assert "| c | 12.00 | 12.50 | 2.00 |" in text and "| b |" not in text
    assert summary(0.01, []) == "no kernel launched"


def test_grid_profile_timeline_lists_each_launchs_plan_render_and_costs(capsys):
    """--timeline: one row per host call of one more call, in order of start: every launch of
    one cell renders what it planned and reads its costs (the located cell reuses the located
    layers: no plan, no render)."""
    assert _bench_module("grid_profile").main(["--backend", "opencl", "--sides", "3", "--launch-mib", "2",
                                                "--repeat", "1", "--timeline"]) == 0
    out = capsys.readouterr().out
    assert "2 MiB, 3 × 3: one call's host calls" in out
    rows = [line.strip("| ").split(" | ") for line in out.splitlines()[out.splitlines().index("| start ms | ms | "
                                                                                            "thread | call |") + 2:]
            if line.startswith("| ")]
    starts = [float(row[0]) for row in rows]
    calls = [row[3] for row in rows]
    assert starts == sorted(starts) and all(float(row[1]) >= 0 for row in rows)
    assert calls.count("view_costs") == 9 and calls.count("plan_pairs") == calls.count("render_planned") >= 8
    assert [c for c in calls if c != "view_costs"][:2] == ["plan_pairs", "render_planned"]


def test_patches_put_back_what_the_owner_held_and_remove_what_it_found_elsewhere():
    """Patches.restore: an attribute the owner held is set back; one it found on its class (or
    inherited) is removed, so the instance again finds the class's."""

    class Base:
        def method(self):
            return "base"

    class Child(Base):
        pass

    thing, patches = Child(), _bench_module("profiling").Patches()
    thing.own = "own"
    patches.replace(thing, "method", lambda: "patched")
    patches.replace(Child, "method", lambda self: "child")
    patches.replace(thing, "own", "patched")
    assert thing.method() == "patched" and Child().method() == "child" and thing.own == "patched"
    patches.restore()
    assert "method" not in vars(thing) and "method" not in vars(Child) and thing.method() == "base"
    assert thing.own == "own" and patches.undo == []


def test_the_stage_table_lists_the_ordered_stages_present_with_their_share():
    table = _bench_module("profiling").stage_table({"total": 0.004, "align": 0.001, "host": 0.003},
                                                   ["total", "render", "align", "host"])
    assert table.splitlines() == ["| stage | median ms | share |", "|---|---|---|", "| `total` | 4.00 | 100.0% |",
                                  "| `align` | 1.00 | 25.0% |", "| `host` | 3.00 | 75.0% |"]


def test_stage_times_count_a_nested_stage_under_its_outer_one_and_restore_the_originals():
    from types import SimpleNamespace

    profiling = _bench_module("profiling")
    owner = SimpleNamespace()
    owner.inner = lambda: time.sleep(0.01)
    owner.outer = lambda: owner.inner()
    originals = (owner.inner, owner.outer)
    times = profiling.StageTimes("outer", {"inner"})
    times.wrap(owner, "inner", "inner")
    times.wrap(owner, "outer", "outer")
    owner.outer()
    assert set(times.current) == {"outer"} and times.current["outer"] >= 0.01  # inner counted under outer
    owner.inner()
    assert times.current["inner"] >= 0.01  # alone, it counts
    times.restore()
    assert (owner.inner, owner.outer) == originals and times.undo == []


def test_ab_reconstruct_times_the_demo_command_of_each_tree(tmp_path):
    """--demo: each run is `fsswarp demo` with the tree's own package, its result and model's
    digest read from what it wrote."""
    import shutil

    repo = Path(__file__).parents[1]
    tree = tmp_path / "tree"
    for name in ("fsswarp", "kernels"):
        shutil.copytree(repo / name, tree / name, ignore=shutil.ignore_patterns("__pycache__"))
    module = _bench_module("ab_reconstruct")
    found = module.run_tree(tree, str(tmp_path / "demo"), "auto", "", "coral-one", "0", script=module.RUN_DEMO)
    assert Path(found["package"]) == tree / "fsswarp" and found["E_I"] == 1.0 and found["seconds"] > 0
    assert (tmp_path / "demo" / "reconstruction" / "report.html").is_file()
    assert len(found["model"]) == 12 and found["depth_m"] == pytest.approx(0.432)  # the measured start, kept


def test_exact_profile_replays_the_render_and_every_other_backend_call(tmp_path, capsys):
    """With --replay every backend call answers from the recording: the render (through
    ``render_planned``) is among them and takes no device time, and E_mu stays the same."""
    out = tmp_path / "exact.json"
    assert _bench_module("exact_profile").main(["--backend", "opencl", "--calls", "2", "--replay",
                                                "--out", str(out)]) == 0
    medians = json.loads(out.read_text())["median_ms"]
    for call in ("render_planned", "contour_cost", "icp_runs", "frontal_faces"):
        assert 0.0 <= medians[f"backend.{call}"] < 0.5  # a PoCL render alone takes tens of ms here
    assert medians["host"] > 0.9 * medians["total"]
