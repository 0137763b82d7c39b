"""Worker processes (fsswarp.processes): jobs run in spawned children that ignore Ctrl-C and end
with status 0 when the pool closes; the workers setting of an environment variable."""

import os
import signal

import pytest

from fsswarp.errors import InputError
from fsswarp.processes import WorkerProcesses, worker_count


def _ready(marker: str) -> None:
    os.environ["FSSWARP_TEST_READY"] = marker


def _where() -> tuple[int, str | None]:
    return os.getpid(), os.environ.get("FSSWARP_TEST_READY")


def test_jobs_run_in_their_own_processes_which_ignore_ctrl_c_and_end_cleanly():
    processes = WorkerProcesses(2, _ready, "set up")
    try:
        children = list(processes.pool._processes.values())
        assert len(children) == 2  # started when the pool was made
        for child in children:
            os.kill(child.pid, signal.SIGINT)
        answers = {processes.submit(_where).result() for _ in range(6)}
        assert {marker for _, marker in answers} == {"set up"}
        assert {pid for pid, _ in answers} <= {child.pid for child in children} and os.getpid() not in answers
    finally:
        processes.close()
    assert [child.exitcode for child in children] == [0, 0]


def test_worker_count_reads_its_variable(monkeypatch):
    monkeypatch.delenv("FSSWARP_TEST_WORKERS", raising=False)
    assert worker_count("FSSWARP_TEST_WORKERS", 5) == 5
    for value, expected in (("0", 0), (" 3 ", 3), ("64", 64)):
        monkeypatch.setenv("FSSWARP_TEST_WORKERS", value)
        assert worker_count("FSSWARP_TEST_WORKERS", 5) == expected
    for bad in ("-1", "two", "1.5", "65"):
        monkeypatch.setenv("FSSWARP_TEST_WORKERS", bad)
        with pytest.raises(InputError, match=f"FSSWARP_TEST_WORKERS = '{bad}': must be an integer from 0 to 64"):
            worker_count("FSSWARP_TEST_WORKERS", 5)


def test_a_process_that_dies_breaks_the_pool_once():
    """Processes killed: a job submitted then gets no outcome (None, or no future at all), the
    pool closes, ``lost`` is called once, and every later submit gives None (the caller does the
    job itself)."""
    losses = []
    processes = WorkerProcesses(2, lost=lambda: losses.append(1))
    try:
        assert processes.outcome(processes.submit(_where))[0] != os.getpid()
        children = list(processes.pool._processes.values())
        for child in children:
            os.kill(child.pid, signal.SIGKILL)
        for child in children:
            child.join()
        job = processes.submit(_where)  # None where the pool knows already
        assert job is None or processes.outcome(job) is None
        assert processes.submit(_where) is None and processes.broken and losses == [1]
    finally:
        processes.close()
