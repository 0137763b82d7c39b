"""``fsswarp batch``: many ``fsswarp reconstruct`` jobs on a Ray cluster (docs/batch.md).

A batch is a JOBS.toml file: ``[defaults]`` and one ``[[jobs]]`` table per job (``name``,
``dataset``, and options of ``fsswarp reconstruct`` by their long name with '_' for '-').
:func:`load_jobs` checks the whole file against the reconstruct command's own click options
before anything runs. :func:`run_batch` makes one :class:`JobWorker` Ray actor per slot (a GPU
share or a CPU); each runs its jobs, ``fsswarp [global options] reconstruct DATASET --out
DIR/<name> ...``, one after another in a resident process of its own (:class:`Resident`,
``python -m fsswarp.resident``), which keeps its imports, backend and kernels from job to
job. A killed or crashed job is a dead process; the job's exit status 2 means bad input.
Outputs under DIR:

- ``<name>/``: the job's folder, exactly as ``fsswarp reconstruct --out`` writes it
- ``jobs.jsonl``: one JSON line per job outcome: name, status (ok, failed, skipped),
  attempts, seconds (the last attempt's wall time), error (one line or null), node, device,
  process_jobs (the job's number in its resident process)
- ``summary.json``: the totals, and the kernel warm-up of each node (:func:`warm_up_nodes`)

A job whose ``DIR/<name>/result.json`` exists is skipped. Ray is imported only inside
:func:`run_batch` and the actors (the optional extra ``fsswarp[batch]``).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path

import click

from .atomic import check_output_folder, write_text
from .errors import InputError

#: The files of a batch folder besides the job folders; ``jobs.jsonl`` marks the folder.
JOBS_FILE, SUMMARY_FILE = "jobs.jsonl", "summary.json"
#: The file whose presence in DIR/<name>/ means the job is done (reconstruct writes it).
DONE_MARKER = "result.json"
#: A job name: letters, digits, '-', '_', '.'; not starting with '.' (hidden and temporary folders).
NAME_PATTERN = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]*")
#: The exit status of ``fsswarp`` for bad input: the job fails at once, with no retry.
BAD_INPUT = 2


@dataclass(frozen=True)
class Job:
    """One reconstruction: ``name`` (its folder under DIR), ``dataset`` (absolute path) and
    ``options`` (reconstruct's option arguments, e.g. ("--iterations", "6"))."""

    name: str
    dataset: Path
    options: tuple[str, ...]

    def arguments(self, out: Path) -> list[str]:
        """The ``fsswarp reconstruct`` arguments that write this job into ``out``/<name>."""
        return ["reconstruct", str(self.dataset), "--out", str(out / self.name), *self.options]


#: JOBS.toml keys that name an option by the unit-suffixed name result.json uses.
ALIASES = {"depth_m": "depth", "tilt_deg": "tilt"}


def load_jobs(path: str | os.PathLike, command) -> list[Job]:
    """The jobs of the JOBS.toml file ``path``, every value checked by the click ``command``
    (``fsswarp reconstruct``) as its command line would; InputError naming the file, field and
    value otherwise. A dataset folder that does not exist is no error here (that job fails)."""
    path = Path(path)
    try:
        document = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("no such file", field="JOBS.toml", value=str(path)) from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise InputError(f"not a valid TOML file: {err}", file=path) from None
    options = {p.name: max(p.opts, key=len) for p in command.params
               if isinstance(p, click.Option) and p.name != "out" and not p.is_eager}
    for key, value in document.items():
        if key not in ("defaults", "jobs"):
            raise InputError("unknown key; a JOBS.toml file holds [defaults] and [[jobs]]", file=path, field=key,
                             value=value)
    defaults = document.get("defaults", {})
    if not isinstance(defaults, dict):
        raise InputError("must be a table ([defaults])", file=path, field="defaults", value=defaults)
    tables = document.get("jobs")
    if not isinstance(tables, list) or not tables or not all(isinstance(t, dict) for t in tables):
        raise InputError("must be one or more [[jobs]] tables", file=path, field="jobs",
                         **({} if tables is None else {"value": tables}))
    defaults = _options(path, command, options, "defaults", defaults)
    jobs, seen = [], {}
    for number, table in enumerate(tables, start=1):
        where = f"jobs[{number}]"
        if "name" not in table:
            raise InputError("missing: every job has a name", file=path, field=f"{where}.name")
        name = table["name"]
        if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name) or name in (JOBS_FILE, SUMMARY_FILE):
            raise InputError(f"must be letters, digits, '-', '_' and '.', not starting with '.', and not {JOBS_FILE} "
                             f"or {SUMMARY_FILE}", file=path, field=f"{where}.name", value=name)
        if name in seen:
            raise InputError(f"is the name of jobs[{seen[name]}] too; names must be unique", file=path,
                             field=f"{where}.name", value=name)
        seen[name] = number
        if "dataset" not in table:
            raise InputError("missing: every job names its dataset folder (relative to JOBS.toml)", file=path,
                             field=f"{where}.dataset")
        if not isinstance(table["dataset"], str) or not table["dataset"]:
            raise InputError("must be a folder name", file=path, field=f"{where}.dataset", value=table["dataset"])
        overrides = _options(path, command, options, where,
                             {key: value for key, value in table.items() if key not in ("name", "dataset")})
        merged = {**defaults, **overrides}
        jobs.append(Job(name, Path(os.path.abspath(path.parent / table["dataset"])),
                        tuple(a for key in sorted(merged) for a in (options[key], merged[key]))))
    return jobs


def _options(path: Path, command, options: dict[str, str], where: str, table: dict) -> dict[str, str]:
    """{option name: its command-line text} of one table, ALIASES resolved; InputError when a
    table names one option twice (by its name and its alias)."""
    parsed = {}
    for key, value in table.items():
        name = ALIASES.get(key, key)
        if name in parsed:
            raise InputError(f"names the option {name} twice (as {name} and as its alias)", file=path,
                             field=f"{where}.{key}", value=value)
        parsed[name] = _option(path, command, options, where, key, value)
    return parsed


def _option(path: Path, command, options: dict[str, str], where: str, key: str, value) -> str:
    """``value`` of the option ``key`` as a command-line argument, parsed by ``command`` as
    ``fsswarp reconstruct`` would parse it; InputError naming ``where``.``key`` otherwise."""
    name = ALIASES.get(key, key)
    if name not in options:
        raise InputError(f"unknown key; the options of fsswarp reconstruct are {', '.join(sorted(options))}"
                         + (" (and name, dataset in [[jobs]])" if where != "defaults" else ""),
                         file=path, field=f"{where}.{key}", value=value)
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise InputError("must be a number or a string", file=path, field=f"{where}.{key}", value=value)
    text = str(value)
    try:
        command.make_context(command.name, ["DATASET", "--out", "OUT", options[name], text])
    except click.UsageError as err:
        raise InputError(f"not a valid {options[name]}: {' '.join(err.message.split())}", file=path,
                         field=f"{where}.{key}", value=value) from None
    return text


#: What a job's environment limits to its share of the node's CPUs, unless the user set it.
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def job_environment(threads: int, environment=os.environ) -> dict[str, str]:
    """``environment`` with the BLAS/OpenMP threads, the figure processes and the mesh processes
    of one job limited to its share of the node's CPUs (``threads``), where the user has not set
    them: K jobs at once with every library sized for the whole machine oversubscribe its cores."""
    from .carving import default_mesh_workers

    limits = dict.fromkeys(THREAD_VARIABLES, str(threads)) | {"FSSWARP_FIGURE_WORKERS": str(min(4, threads)),
                                                             "FSSWARP_MESH_WORKERS": str(default_mesh_workers(threads))}
    return limits | dict(environment)


class Resident:
    """The resident process of one batch slot, which runs the jobs it is sent one after another
    in one interpreter (``fsswarp.resident.serve``), so that a job after the first finds the
    imports, the backend, the loaded kernels and the mesh processes of the ones before
    (docs/batch.md, "Resident processes"). It runs under ``fsswarp.resident.supervise``
    (``python -m fsswarp.resident``), is started with ``environment`` at the first job, and
    ends after ``jobs_per_process`` jobs (0: no limit) and after a job that failed other than
    by bad input, so that the next job starts a fresh one."""

    def __init__(self, environment: dict[str, str], jobs_per_process: int):
        self.environment, self.limit = environment, jobs_per_process
        self.process: subprocess.Popen | None = None
        self.served = 0

    def run(self, arguments: list[str]) -> tuple[int, str, int]:
        """(exit status, stderr, the job's number in its process: 1 in a fresh one) of
        ``fsswarp ARGUMENTS`` run in the process; the status is 128 + N where signal N killed it."""
        # stderr into a file, not a pipe, which a process the job left behind could hold open
        with tempfile.NamedTemporaryFile("w+", errors="replace", prefix="fsswarp-job-", suffix=".txt") as stderr:
            if self.process is None:
                self.process = subprocess.Popen([sys.executable, "-m", "fsswarp.resident"], stdin=subprocess.PIPE,
                                                stdout=subprocess.PIPE, stderr=stderr, env=self.environment,
                                                text=True)
                self.served = 0
            self.served += 1
            process, served = self.process, self.served
            try:
                process.stdin.write(json.dumps({"arguments": arguments, "stderr": stderr.name}) + "\n")
                process.stdin.flush()
                reply = process.stdout.readline()
            except (OSError, ValueError):  # the pipe broke or was closed: the process died or was stopped
                reply = ""
            returncode = json.loads(reply)["returncode"] if reply else process.wait()
            stderr.seek(0)
            text = stderr.read()
        if not reply or returncode not in (0, BAD_INPUT) or served == self.limit:
            self.close()
        return returncode, text, served

    def close(self) -> None:
        """End the process: its supervisor kills its group (the job, its figure and mesh processes)."""
        process, self.process = self.process, None
        if process is not None:
            process.terminate()  # a no-op where it has ended
            process.wait()
            for pipe in (process.stdin, process.stdout):
                with contextlib.suppress(OSError):
                    pipe.close()


class JobWorker:
    """One slot of a batch (a share of a GPU, or a CPU), as a Ray actor: it runs the jobs it is
    given one after another in its :class:`Resident` process, with ``threads`` CPUs
    (:func:`job_environment`)."""

    def __init__(self, threads: int, jobs_per_process: int):
        import platform

        import ray

        gpus = ray.get_gpu_ids()
        self.node, self.device = platform.node(), "gpu " + ",".join(map(str, gpus)) if gpus else "cpu"
        self.resident = Resident(job_environment(threads), jobs_per_process)

    def run(self, arguments: list[str], out: str, name: str) -> dict:
        """Run ``fsswarp ARGUMENTS`` (one reconstruction into ``out``/``name``); returns its
        ``returncode`` (-N: killed by signal N), ``error`` (one line or None), ``seconds``,
        ``node``, ``device`` (the GPUs Ray gave this actor, or "cpu") and ``process_jobs`` (the
        job's number in its resident process: 1 where it started a fresh one)."""
        remove_leftovers(Path(out), name)  # of an attempt whose process died
        start = time.perf_counter()
        returncode, stderr, served = self.resident.run(arguments)
        returncode = 128 - returncode if returncode > 128 else returncode
        seconds = time.perf_counter() - start
        if returncode != 0:
            remove_leftovers(Path(out), name)
        return {"returncode": returncode, "error": _error_line(returncode, stderr), "seconds": seconds,
                "node": self.node, "device": self.device, "process_jobs": served}

    def stop(self) -> None:
        """End the resident process, and with it the job it runs (Ctrl-C: :func:`_cancel`)."""
        self.resident.close()


def _error_line(returncode: int, stderr: str) -> str | None:
    """The one-line error of a job: its ``fsswarp: error:`` line, the signal that killed it, or
    the last line it wrote (a traceback's exception)."""
    if returncode == 0:
        return None
    lines = [line.strip() for line in stderr.splitlines() if line.strip()]
    errors = [line.removeprefix("fsswarp: error:").strip() for line in lines if line.startswith("fsswarp: error:")]
    if errors:
        return errors[-1]
    if returncode < 0:
        return f"killed by {signal.Signals(-returncode).name}"
    return f"exit status {returncode}" + (f": {lines[-1]}" if lines else "")


def remove_leftovers(out: Path, name: str) -> None:
    """Remove the temporary siblings (``.<name>.XXXXXXXX.tmp`` and ``.old``, see
    ``fsswarp.atomic.output_folder``) that a killed job left in ``out``."""
    with contextlib.suppress(OSError):
        for entry in out.iterdir():
            stem, _, suffix = entry.name.rpartition(".")  # stem: .<name>.XXXXXXXX
            if suffix in ("tmp", "old") and stem.startswith(".") and stem[1:].rpartition(".")[0] == name:
                shutil.rmtree(entry, ignore_errors=True)


@dataclass
class Outcome:
    """One line of jobs.jsonl."""

    name: str
    status: str
    attempts: int = 0
    seconds: float | None = None
    error: str | None = None
    node: str | None = None
    device: str | None = None
    process_jobs: int | None = None


def run_batch(jobs: list[Job], out: str | os.PathLike, *, address: str | None = None, jobs_per_gpu: int = 1,
              retries: int = 2, global_options: tuple[str, ...] = (), quiet: bool = False,
              warm_up: bool | None = None, jobs_per_process: int = 0) -> list[Outcome]:
    """Run ``jobs`` into ``out`` on Ray: the cluster at ``address`` ('auto', HOST:PORT), or a
    local instance started here when None. One :class:`JobWorker` per slot: on a cluster with
    GPUs 1/jobs_per_gpu of a GPU each; else one CPU each, on OpenCL unless ``global_options``
    names a backend. Each runs its jobs in a resident process that serves ``jobs_per_process``
    jobs (0: no limit). With ``warm_up`` (default: unless the jobs run on OpenCL, whose programs
    are built as a process's backend is made) every node first compiles the kernels
    (:func:`warm_up_nodes`). A job that exits 2 fails at once; one killed, crashed or whose
    worker died is run again, at most ``retries`` times. Writes out/jobs.jsonl and
    out/summary.json after every outcome; returns the outcomes (KeyboardInterrupt after the
    running jobs are stopped)."""
    out = check_output_folder(out, marker=JOBS_FILE)
    ray = _start_ray(address)
    try:
        resources = ray.cluster_resources()
        gpus = resources.get("GPU", 0)
        options = tuple(global_options)
        if not gpus and not any(o in ("--backend", "--device") for o in options):
            options += ("--backend", "opencl")
        slots = max(1, int(gpus * jobs_per_gpu) if gpus else int(resources.get("CPU", 1)))
        threads = max(1, int(resources.get("CPU", 1) // slots)) if gpus else 1
        worker = ray.remote(JobWorker).options(num_cpus=1, num_gpus=1 / jobs_per_gpu if gpus else 0, max_restarts=0,
                                               max_concurrency=2)  # run, and stop beside it

        def workers(count: int) -> list:
            return [worker.remote(threads, jobs_per_process) for _ in range(count)]

        if warm_up is None:
            warm_up = warms_up_by_default(options)
        return _schedule(ray, workers, jobs, out, ["-q", *options], retries, slots, quiet,
                         {"GPU": gpus, "CPU": resources.get("CPU", 0), "jobs_per_gpu": jobs_per_gpu,
                          "jobs_per_process": jobs_per_process},
                         (lambda: warm_up_nodes(ray, list(options), gpu_share=1 / jobs_per_gpu if gpus else 0))
                         if warm_up else None)
    finally:
        ray.shutdown()


def _start_ray(address: str | None):
    """The ``ray`` module, connected to ``address`` or to a new local instance (quietly)."""
    import logging

    try:
        import ray
    except ImportError:
        raise InputError("needs Ray: pip install 'fsswarp[batch]'", field="fsswarp batch") from None
    settings = {"log_to_driver": False, "logging_level": logging.ERROR}
    if address is not None and address != "auto" and "://" not in address:
        _check_reachable(address)
    try:
        if address is None:
            ray.init(address="local", include_dashboard=False, **settings)
        else:
            ray.init(address=address, **settings)
    except (ConnectionError, ValueError, RuntimeError) as err:
        raise InputError(f"cannot start or join Ray: {' '.join(str(err).split())}", field="--address",
                         value=address) from None
    return ray


def _check_reachable(address: str) -> None:
    """InputError (field --address) unless a TCP connection to HOST:PORT opens within 10 s (Ray
    itself would try for minutes)."""
    import socket

    host, _, port = address.rpartition(":")
    try:
        socket.create_connection((host, int(port)), timeout=10).close()
    except ValueError:
        raise InputError("must be 'auto' or HOST:PORT of the cluster's head", field="--address",
                         value=address) from None
    except OSError as err:
        raise InputError(f"no Ray head answers there: {err.strerror or err}", field="--address",
                         value=address) from None


def _schedule(ray, workers, jobs: list[Job], out: Path, global_options: list[str], retries: int, slots: int,
              quiet: bool, resources: dict, warm_up=None) -> list[Outcome]:
    """Run every job not done yet on ``workers(n)``'s n JobWorker actors, at most ``slots``, each
    given its next job when it ends one (after ``warm_up()``, if given, where any is left: {node:
    its warm-up's record}, kept in summary.json); run the retried ones again and record each
    outcome. A worker that dies is replaced."""
    start = time.perf_counter()
    done = {job.name for job in jobs if (out / job.name / DONE_MARKER).is_file()}
    outcomes = [Outcome(job.name, "skipped") for job in jobs if job.name in done]
    todo = [job for job in jobs if job.name not in done]
    attempts = {job.name: 0 for job in todo}
    running: dict = {}  # ref -> (job, worker)
    warmed = {}
    if todo and warm_up is not None:
        if not quiet:
            click.echo("warming up the kernels on every node")
        warmed = warm_up()
        for node, record in ([] if quiet else warmed.items()):
            click.echo(f"  {node}: {record['line'] if record['returncode'] == 0 else record['error']}")
    idle = workers(min(slots, len(todo)))

    def submit(job: Job) -> None:
        attempts[job.name] += 1
        worker = idle.pop()
        running[worker.run.remote([*global_options, *job.arguments(out)], str(out), job.name)] = (job, worker)

    def record() -> None:
        _write_records(out, outcomes, len(jobs), time.perf_counter() - start, resources, warmed)

    record()
    with _Progress(len(jobs), quiet) as progress:
        for outcome in outcomes:
            progress.finished(outcome)
        try:
            while todo or running:
                while todo and idle:
                    submit(todo.pop(0))
                progress.update(running=len(running))
                ready, _ = ray.wait(list(running), num_returns=1, timeout=0.5)
                for ref in ready:
                    job, worker = running.pop(ref)
                    outcome, lost = _outcome(ray, ref, job.name, attempts[job.name])
                    if lost:
                        with contextlib.suppress(Exception):
                            ray.kill(worker)
                        worker, = workers(1)
                    idle.append(worker)
                    if outcome.status == "retry" and attempts[job.name] <= retries:
                        progress.say(f"retrying {job.name} (attempt {attempts[job.name] + 1} of {retries + 1}): "
                                     f"{outcome.error}")
                        todo.insert(0, job)
                        continue
                    if outcome.status == "retry":
                        outcome.status = "failed"
                    outcomes.append(outcome)
                    progress.finished(outcome)
                    record()
        except KeyboardInterrupt:
            _cancel(ray, running)
            raise
        finally:
            for name in {job.name for job, _ in running.values()} | {o.name for o in outcomes if o.status == "failed"}:
                remove_leftovers(out, name)
        progress.update(running=0)
    counts = _counts(outcomes)
    progress.say(f"wrote {out}: {counts['ok']} ok, {counts['failed']} failed, {counts['skipped']} skipped; "
                 f"{JOBS_FILE}, {SUMMARY_FILE} ({time.perf_counter() - start:.1f} s)")
    return outcomes


def warms_up_by_default(global_options: tuple[str, ...]) -> bool:
    """Whether a batch whose jobs run with ``global_options`` warms its nodes up unless told:
    not where they run on OpenCL, which builds every program as a resident process's backend is
    made (~3 s on PoCL), but where Warp would compile its modules one after another at their
    first launches in the first job of each worker (5.1 s on an H200, docs/batch.md)."""
    options = list(global_options)
    return "--backend" not in options or options[options.index("--backend") + 1] != "opencl"


#: Most seconds that the warm-up of the nodes may take before the jobs start anyway.
WARM_UP_SECONDS = 600


def warm_up_nodes(ray, global_options: list[str], *, gpu_share: float = 0) -> dict[str, dict]:
    """``fsswarp [global options] info --warm-up`` once on every alive node that can run a job (with
    ``gpu_share`` > 0: the nodes with a GPU, each task taking that share of one), side by side,
    before the first job: the workers' resident processes are processes of their own, and the
    first job of each on a fresh node would compile the same kernels (docs/batch.md). Returns
    {node: :func:`warm_up_node`'s record}; a node whose warm-up fails or passes
    ``WARM_UP_SECONDS`` gets an error, and its jobs run all the same (compiling as they go)."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    nodes = [n for n in ray.nodes() if n.get("Alive") and (n["Resources"].get("GPU", 0) if gpu_share else True)]
    task = ray.remote(warm_up_node)
    refs = {task.options(num_cpus=0, num_gpus=gpu_share, max_retries=0,
                         scheduling_strategy=NodeAffinitySchedulingStrategy(node["NodeID"], soft=False))
            .remote(global_options): node.get("NodeManagerHostname", node["NodeID"]) for node in nodes}
    ready, late = ray.wait(list(refs), num_returns=len(refs), timeout=WARM_UP_SECONDS)
    found = {}
    for ref in ready:
        try:
            found[refs[ref]] = ray.get(ref)
        except ray.exceptions.RayError as err:
            first = next((line.strip() for line in str(err).splitlines() if line.strip()), "")
            found[refs[ref]] = {"returncode": None, "seconds": None, "line": None, "error": f"Ray: {first}"}
    for ref in late:
        ray.cancel(ref, force=True)
        found[refs[ref]] = {"returncode": None, "seconds": None, "line": None,
                            "error": f"the warm-up took more than {WARM_UP_SECONDS} s"}
    return found


def warm_up_node(global_options: list[str]) -> dict:
    """Run ``python -m fsswarp [global options] info --warm-up`` here; returns its ``returncode``,
    ``seconds``, the ``line`` that says what it compiled, and ``error`` (its last line of stderr,
    or None). The Ray task of :func:`warm_up_nodes`."""
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "fsswarp", *global_options, "info", "--warm-up"],
                          stdin=subprocess.DEVNULL, capture_output=True, text=True, check=False)
    line = next((line for line in done.stdout.splitlines() if line.startswith("warm-up of ")), None)
    error = None if done.returncode == 0 else (done.stderr.strip().splitlines() or [f"exit {done.returncode}"])[-1]
    return {"returncode": done.returncode, "seconds": time.perf_counter() - start, "line": line, "error": error}


def _cancel(ray, running: dict) -> None:
    """Stop the running jobs, ``running`` {ref: (job, its JobWorker)}: each worker ends its
    resident process (the job's process group is killed) and its run removes the job's
    temporary folder; a worker whose run has not returned 30 s later is killed."""
    for _, worker in running.values():
        with contextlib.suppress(Exception):
            worker.stop.remote()
    with contextlib.suppress(Exception):
        ray.wait(list(running), num_returns=len(running), timeout=30)
    for _, worker in running.values():
        with contextlib.suppress(Exception):
            ray.kill(worker)


def _outcome(ray, ref, name: str, attempts: int) -> tuple[Outcome, bool]:
    """The outcome of one attempt, ok, failed (bad input) or retry (killed, crashed, the worker
    died), and whether its worker died."""
    try:
        done = ray.get(ref)
    except ray.exceptions.RayError as err:
        first = next((line.strip() for line in str(err).splitlines() if line.strip()), "")
        return Outcome(name, "retry", attempts, error=f"Ray: {type(err).__name__}: {first}"), True
    status = "ok" if done["returncode"] == 0 else "failed" if done["returncode"] == BAD_INPUT else "retry"
    return Outcome(name, status, attempts, done["seconds"], done["error"], done["node"], done["device"],
                   done["process_jobs"]), False


def _counts(outcomes: list[Outcome]) -> dict[str, int]:
    """The number of outcomes of each status: ok, failed, skipped."""
    return {status: sum(o.status == status for o in outcomes) for status in ("ok", "failed", "skipped")}


def _write_records(out: Path, outcomes: list[Outcome], jobs: int, seconds: float, resources: dict,
                   warm_up: dict) -> None:
    """out/jobs.jsonl and out/summary.json (with ``warm_up``, :func:`warm_up_nodes`' records), each atomically."""
    write_text(out / JOBS_FILE, "".join(json.dumps(vars(o)) + "\n" for o in outcomes))
    write_text(out / SUMMARY_FILE, json.dumps({
        "jobs": jobs, **_counts(outcomes), "unfinished": jobs - len(outcomes), "attempts": sum(o.attempts for o in outcomes),
        "seconds": seconds, "resources": resources, "warm_up": warm_up}, indent=2))


class _Progress:
    """One rich progress bar over the jobs (done, failed, running) and a line per finished job
    on stdout; silent when ``quiet``."""

    def __init__(self, total: int, quiet: bool):
        self.quiet, self.counts, self.running = quiet, {"ok": 0, "failed": 0, "skipped": 0}, 0
        self.bar = None
        if not quiet:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

            self.bar = Progress(TextColumn("jobs"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.description}"),
                                TimeElapsedColumn())
            self.task = self.bar.add_task(self._description(), total=total)

    def __enter__(self) -> "_Progress":
        if self.bar is not None:
            self.bar.start()
        return self

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.stop()

    def _description(self) -> str:
        done = self.counts["ok"] + self.counts["skipped"]
        return f"done {done}, failed {self.counts['failed']}, running {self.running}"

    def update(self, *, running: int) -> None:
        self.running = running
        if self.bar is not None:
            self.bar.update(self.task, description=self._description())

    def say(self, line: str) -> None:
        if self.bar is not None:
            self.bar.console.print(line, markup=False, highlight=False, soft_wrap=True)

    def finished(self, outcome: Outcome) -> None:
        self.counts[outcome.status] += 1
        if outcome.status == "ok":
            detail = f"{outcome.seconds:.1f} s on {outcome.node} ({outcome.device})"
        elif outcome.status == "failed":
            detail = f"after {outcome.attempts} attempt{'s' if outcome.attempts != 1 else ''}: {outcome.error}"
        else:
            detail = f"{DONE_MARKER} exists"
        self.say(f"{outcome.status:7} {outcome.name}: {detail}")
        if self.bar is not None:
            self.bar.update(self.task, advance=1, description=self._description())
