"""``fsswarp batch`` on a real local Ray instance (this machine's CPUs, no GPU, OpenCL): the
jobs' outputs match ``fsswarp reconstruct`` alone, also where a job runs after another in the
same resident process, a bad job fails alone, a killed worker or job is retried, a rerun skips
the finished jobs, Ctrl-C stops cleanly, and a bad JOBS.toml exits 2 before anything is written."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

#: Reconstruct options of every job: few voxels, the carving alone (a few seconds a job).
DEFAULTS = {"iterations": 0, "resolution": 32}
#: name -> per-job overrides of DEFAULTS.
JOBS = {"plain": {}, "given-start": {"depth": 0.435, "tilt": 11.9}, "finer.v2": {"resolution": 40}}


@pytest.fixture(scope="module")
def ray_env(tmp_path_factory):
    """The environment of the batch commands: Ray's session files in a short temporary folder
    of their own (Ray's sockets need a short path)."""
    folder = tempfile.mkdtemp(prefix="ray-")
    yield dict(os.environ, RAY_TMPDIR=folder)
    import shutil

    shutil.rmtree(folder, ignore_errors=True)


def fsswarp(*args, env=None, **kwargs):
    return subprocess.run([sys.executable, "-m", "fsswarp", "--backend", "opencl", *map(str, args)],
                          capture_output=True, text=True, env=env, timeout=300, **kwargs)


def write_jobs(path: Path, jobs: dict[str, tuple[str, dict]], defaults=DEFAULTS) -> Path:
    """A JOBS.toml of ``jobs`` (name -> (dataset, overrides))."""
    lines = ["[defaults]"] + [f"{k} = {v!r}" for k, v in defaults.items()]
    for name, (dataset, overrides) in jobs.items():
        lines += ["", "[[jobs]]", f'name = "{name}"', f'dataset = "{dataset}"']
        lines += [f"{k} = {v!r}" for k, v in overrides.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


def records(out: Path) -> dict[str, dict]:
    return {r["name"]: r for r in map(json.loads, (out / "jobs.jsonl").read_text().splitlines())}


def result(folder: Path) -> dict:
    """result.json without its wall time."""
    record = json.loads((folder / "result.json").read_text())
    record.pop("seconds")
    return record


def snapshot(folder: Path) -> dict[str, tuple[int, bytes]]:
    return {p.relative_to(folder).as_posix(): (p.stat().st_mtime_ns, p.read_bytes())
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def first_batch(coral_south, tmp_path_factory, ray_env):
    """JOBS plus one job whose dataset folder is missing, run once, the nodes warmed up first (on
    OpenCL they are not unless asked): (JOBS.toml, DIR, process)."""
    root = tmp_path_factory.mktemp("batch")
    dataset = os.path.relpath(coral_south.root, root)
    jobs_file = write_jobs(root / "JOBS.toml", {**{n: (dataset, o) for n, o in JOBS.items()},
                                                "lost": ("no-such-dataset", {})})
    done = fsswarp("batch", jobs_file, "--out", root / "out", "--warm-up", env=ray_env)
    return jobs_file, root / "out", done


def test_each_job_writes_what_reconstruct_alone_writes(first_batch, coral_south, tmp_path):
    _, out, done = first_batch
    for name, overrides in JOBS.items():
        options = [a for k, v in {**DEFAULTS, **overrides}.items() for a in (f"--{k}", v)]
        alone = fsswarp("-q", "reconstruct", coral_south.root, "--out", tmp_path / name, *options)
        assert alone.returncode == 0, alone.stderr
        assert sorted(snapshot(out / name)) == sorted(snapshot(tmp_path / name))
        assert result(out / name) == result(tmp_path / name), name
        for mesh in ("model.ply", "carved.ply"):
            assert (out / name / mesh).read_bytes() == (tmp_path / name / mesh).read_bytes(), (name, mesh)
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == []


def test_two_slots_run_the_four_jobs_in_two_resident_processes(first_batch):
    """On two CPUs, two workers, each with one resident process for all its jobs: the comparison
    with reconstruct alone above holds for jobs that found a warm process."""
    _, out, _ = first_batch
    lines = records(out)
    numbers = sorted(r["process_jobs"] for r in lines.values())
    assert numbers[:2] == [1, 1] and numbers[2:] in ([2, 2], [2, 3]), lines
    assert any(lines[n]["process_jobs"] >= 2 for n in JOBS), lines  # the lost job may be one of the two


def test_a_missing_dataset_fails_alone_with_its_message(first_batch):
    _, out, done = first_batch
    assert done.returncode == 1 and done.stderr == "", done.stderr
    lines = records(out)
    assert {n: r["status"] for n, r in lines.items()} == {**{n: "ok" for n in JOBS}, "lost": "failed"}
    lost = lines["lost"]
    assert lost["attempts"] == 1 and "no-such-dataset" in lost["error"] and "no such" in lost["error"]
    assert all(lines[n]["attempts"] == 1 and lines[n]["error"] is None for n in JOBS)
    assert all(lines[n]["device"] == "cpu" or lines[n]["device"].startswith("gpu ") for n in JOBS)
    assert set(lines["plain"]) == {"name", "status", "attempts", "seconds", "error", "node", "device", "process_jobs"}
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["jobs"], summary["ok"], summary["failed"], summary["skipped"]) == (4, 3, 1, 0)
    assert "failed  lost" in done.stdout and "wrote" in done.stdout
    assert not (out / "lost").exists()


def test_the_kernels_are_warmed_up_on_the_node_before_the_first_job(first_batch):
    """With --warm-up, one warm-up (``fsswarp info --warm-up`` with the jobs' backend) on the one
    local node, said and kept in summary.json, before any job."""
    _, out, done = first_batch
    warm_up = json.loads((out / "summary.json").read_text())["warm_up"]
    assert len(warm_up) == 1, warm_up
    (node, record), = warm_up.items()
    assert record["returncode"] == 0 and record["error"] is None and record["seconds"] > 0, record
    assert record["line"].startswith("warm-up of opencl on "), record
    lines = done.stdout.splitlines()
    assert lines[0] == "warming up the kernels on every node" and lines[1] == f"  {node}: {record['line']}", lines[:3]
    assert all(not line.startswith(("ok ", "failed ")) for line in lines[:2])


@pytest.mark.parametrize("options, warms", [(("--backend", "opencl"), False),
                                             (("--backend", "opencl", "--device", "pocl"), False),
                                             (("--backend", "warp", "--device", "cuda"), True), ((), True)])
def test_a_batch_warms_up_its_nodes_unless_its_jobs_run_on_opencl(options, warms):
    from fsswarp.batch import warms_up_by_default

    assert warms_up_by_default(options) is warms


def test_a_rerun_skips_the_finished_jobs_and_leaves_their_files(first_batch, ray_env):
    jobs_file, out, _ = first_batch
    before = {name: snapshot(out / name) for name in JOBS}
    again = fsswarp("batch", jobs_file, "--out", out, "--jobs-per-process", 1, env=ray_env)
    assert again.returncode == 1 and again.stderr == "", again.stderr  # the lost dataset is still lost
    assert {n: r["status"] for n, r in records(out).items()} == {**{n: "skipped" for n in JOBS}, "lost": "failed"}
    assert {name: snapshot(out / name) for name in JOBS} == before
    summary = json.loads((out / "summary.json").read_text())
    assert summary["resources"]["jobs_per_process"] == 1 and records(out)["lost"]["process_jobs"] == 1
    # on OpenCL, and not asked to, the rerun warmed no node up
    assert summary["warm_up"] == {} and "warming up" not in again.stdout


def job_process(out: Path, env: dict) -> int | None:
    """The pid of the resident process (``python -m fsswarp.resident --serve``) of the batch run
    with ``env`` once it has started the job whose folder is ``out`` (its temporary sibling
    exists), or None."""
    if not any(p.name.startswith(f".{out.name}.") for p in out.parent.glob(".*")):
        return None
    marker = f"FSSWARP_TEST_RUN={env['FSSWARP_TEST_RUN']}".encode()
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            command = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            if command[-3:] == [b"fsswarp.resident", b"--serve", b""] and \
                    marker in Path(f"/proc/{pid}/environ").read_bytes().split(b"\0"):
                return int(pid)
        except OSError:
            continue
    return None


def processes_left(env: dict, wait: float = 10.0) -> list[int]:
    """The processes still running, after up to ``wait`` seconds, whose environment holds
    ``env``'s FSSWARP_TEST_RUN (the batch, Ray, the jobs and whatever they started)."""
    marker = f"FSSWARP_TEST_RUN={env['FSSWARP_TEST_RUN']}".encode()
    deadline = time.monotonic() + wait
    while True:
        left = []
        for pid in filter(str.isdigit, os.listdir("/proc")):
            try:
                if marker in Path(f"/proc/{pid}/environ").read_bytes().split(b"\0"):
                    left.append(int(pid))
            except OSError:
                continue
        if not left or time.monotonic() > deadline:
            return left
        time.sleep(0.2)


def parent(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


def when_started(out: Path, env: dict, act, timeout: float = 120.0) -> threading.Thread:
    """A thread that calls ``act(pid)``, ``pid`` the job's resident process, once the
    reconstruction into ``out`` has run a second."""
    def watch():
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            pid = job_process(out, env)
            if pid is not None:
                time.sleep(1.0)
                act(pid)
                return
            time.sleep(0.05)

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    return thread


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the Ray worker through /proc")
@pytest.mark.parametrize("target, reason", [("worker", "Ray: ActorDiedError"), ("job", "killed by SIGKILL")])
def test_a_killed_worker_or_job_is_retried_and_the_job_ends_ok(first_batch, coral_south, tmp_path, ray_env, target,
                                                                reason):
    """SIGKILL to the Ray actor running the job (its resident process dies with it: the
    supervisor between them kills the resident's group), or to the resident process alone."""
    jobs_file = write_jobs(tmp_path / "JOBS.toml", {"plain": (str(coral_south.root), JOBS["plain"])})
    out = tmp_path / "out"
    killed = []

    def kill(pid):
        victim = parent(parent(pid)) if target == "worker" else pid
        killed.append(victim)
        os.kill(victim, signal.SIGKILL)

    env = dict(ray_env, FSSWARP_TEST_RUN=f"kill-{target}-{os.getpid()}")
    watcher = when_started(out / "plain", env, kill)
    done = fsswarp("batch", jobs_file, "--out", out, "--retries", 1, env=env)
    watcher.join()
    assert killed and done.returncode == 0, done.stderr
    assert processes_left(env) == []
    line = records(out)["plain"]
    assert (line["status"], line["attempts"], line["process_jobs"]) == ("ok", 2, 1)  # in a fresh process
    assert f"retrying plain (attempt 2 of 2): {reason}" in done.stdout
    assert result(out / "plain") == result(first_batch[1] / "plain")
    assert sorted(p.name for p in out.iterdir()) == ["jobs.jsonl", "plain", "summary.json"]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the job's process through /proc")
def test_ctrl_c_stops_the_batch_and_leaves_no_half_written_folder(coral_south, tmp_path, ray_env):
    jobs_file = write_jobs(tmp_path / "JOBS.toml", {"plain": (str(coral_south.root), JOBS["plain"])})
    out = tmp_path / "out"
    env = dict(ray_env, FSSWARP_TEST_RUN=f"ctrl-c-{os.getpid()}")
    driver = subprocess.Popen([sys.executable, "-m", "fsswarp", "--backend", "opencl", "batch", str(jobs_file),
                               "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              env=env)
    seen = []
    when_started(out / "plain", env, lambda pid: (seen.append(pid), driver.send_signal(signal.SIGINT))).join()
    _, stderr = driver.communicate(timeout=120)
    assert seen and driver.returncode == 130, stderr
    assert stderr.strip().splitlines() == ["fsswarp: interrupted"]
    assert sorted(p.name for p in out.iterdir()) == ["jobs.jsonl", "summary.json"]
    assert processes_left(env) == []


@pytest.mark.parametrize("text, field", [
    ('[[jobs]]\nname = "a"\ndataset = "d"\ncolour = 3\n', "jobs[1].colour = 3"),
    ('[[jobs]]\nname = "a"\ndataset = "d"\n[[jobs]]\nname = "a"\ndataset = "e"\n', "jobs[2].name = 'a'"),
    ('[[jobs]]\nname = "a"\n', "jobs[1].dataset"),
    ('[defaults]\niterations = -1\n[[jobs]]\nname = "a"\ndataset = "d"\n', "defaults.iterations = -1"),
    ('[[jobs]]\nname = "a"\ndataset = "d"\nresolution = 12.5\n', "jobs[1].resolution = 12.5"),
    ('[[jobs]]\nname = "a/b"\ndataset = "d"\n', "jobs[1].name = 'a/b'"),
    ("[defaults]\niterations = 1\n", "jobs"),
    ('[[jobs]]\nname = "a"\ndataset = "d"\ndepth = 0.4\ndepth_m = 0.43\n', "jobs[1].depth_m = 0.43"),
])
def test_a_bad_jobs_file_exits_2_with_one_line_and_writes_nothing(tmp_path, text, field):
    jobs_file = tmp_path / "JOBS.toml"
    jobs_file.write_text(text)
    done = fsswarp("batch", jobs_file, "--out", tmp_path / "out")
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and f"JOBS.toml: {field}" in done.stderr, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["JOBS.toml"]


def test_depth_m_and_tilt_deg_name_the_depth_and_tilt_options(tmp_path):
    """The unit-suffixed names of result.json are aliases of --depth and --tilt."""
    from fsswarp.batch import load_jobs
    from fsswarp.cli import reconstruct

    jobs_file = tmp_path / "JOBS.toml"
    jobs_file.write_text('[defaults]\ntilt_deg = 10.3\n[[jobs]]\nname = "a"\ndataset = "d"\ndepth_m = 0.43\n'
                         '[[jobs]]\nname = "b"\ndataset = "d"\ndepth = 0.43\ntilt = 10.3\n')
    first, second = load_jobs(jobs_file, reconstruct)
    assert first.options == second.options == ("--depth", "0.43", "--tilt", "10.3")


def test_a_job_gets_its_share_of_the_cpus_unless_the_user_chose():
    from fsswarp.batch import job_environment

    shared = job_environment(2, {"PATH": "/bin"})
    assert shared["OMP_NUM_THREADS"] == shared["OPENBLAS_NUM_THREADS"] == shared["MKL_NUM_THREADS"] == "2"
    assert shared["FSSWARP_FIGURE_WORKERS"] == "2" and shared["PATH"] == "/bin"
    assert shared["FSSWARP_MESH_WORKERS"] == "0"
    assert job_environment(16, {})["FSSWARP_FIGURE_WORKERS"] == "4"
    assert job_environment(16, {})["FSSWARP_MESH_WORKERS"] == "3"
    chosen = job_environment(2, {"OMP_NUM_THREADS": "8", "FSSWARP_FIGURE_WORKERS": "0"})
    assert chosen["OMP_NUM_THREADS"] == "8" and chosen["FSSWARP_FIGURE_WORKERS"] == "0"


def test_a_resident_process_serves_jobs_up_to_its_limit_and_keeps_going_after_bad_input(tmp_path):
    """``Resident`` without Ray: the job's number in its process, the limit of jobs per process,
    and bad input (exit 2, its one line captured) which leaves the process serving."""
    from fsswarp.batch import Resident, job_environment

    limited = Resident(job_environment(1), 2)
    try:
        served = [limited.run(["--help"])[::2] for _ in range(3)]
    finally:
        limited.close()
    assert served == [(0, 1), (0, 2), (0, 1)]
    resident = Resident(job_environment(1), 0)
    try:
        status, stderr, first = resident.run(["check", str(tmp_path / "no-such-folder")])
        pid = resident.process.pid
        again = resident.run(["--help"])
        assert resident.process.pid == pid
    finally:
        resident.close()
    assert (status, first) == (2, 1) and stderr.startswith("fsswarp: error: ") and "no-such-folder" in stderr, stderr
    assert stderr.count("\n") == 1 and again == (0, "", 2)
