"""Seconds per job of a `fsswarp batch` worker, with a fresh process per job and with one resident
process for all its jobs (`--jobs-per-process 1` against the default), without Ray:

    python bench/resident_jobs.py [--jobs N] [--rounds R] [--scene S] [--seed K] [--iterations T]
                                  [-- GLOBAL OPTIONS...]

The scene is simulated once (noisy, ``--seed``), and one uncounted `fsswarp reconstruct` warms
the kernel caches and gives the reference result.json. Then ``--rounds`` rounds, each running N
reconstructions (``iterations = T``) through ``fsswarp.batch.Resident`` twice, as a worker
does: with ``jobs_per_process`` 1 (a fresh process each) and 0 (one resident process: its first
job starts it, the others find it warm); the two alternate, and which goes first alternates by
round. A job's seconds are the worker's (the request to the answer, the process's start and end
included where it starts or ends one). Every job must agree with the reference (D, β, E_I per
iteration). Prints each round's seconds and one Markdown table: the median of the fresh
processes' jobs, of the resident's first jobs and of its later ones, and later / fresh.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

from batch_throughput import add_run_options, agreed, reference_run


def run_jobs(dataset: Path, root: Path, jobs: int, iterations: int, per_process: int, options: list[str],
             reference: dict) -> list[float]:
    """Seconds of each of ``jobs`` reconstructions of ``dataset`` into ``root``/jobNNN through one
    Resident of ``per_process`` jobs per process; RuntimeError where one fails or disagrees."""
    from fsswarp.batch import Resident, job_environment

    resident = Resident(job_environment(os.cpu_count() or 1), per_process)
    seconds = []
    try:
        for k in range(jobs):
            out = root / f"job{k:03d}"
            arguments = ["-q", *options, "reconstruct", str(dataset), "--out", str(out), "--iterations",
                         str(iterations)]
            start = time.perf_counter()
            returncode, stderr, _ = resident.run(arguments)
            seconds.append(time.perf_counter() - start)
            if returncode != 0:
                raise RuntimeError(f"job {k} exited {returncode}: {stderr.strip()[-500:]}")
            if agreed(json.loads((out / "result.json").read_text())) != agreed(reference):
                raise RuntimeError(f"job {k} (jobs_per_process {per_process}) disagrees with the reference")
    finally:
        resident.close()
    return seconds


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=4, help="jobs per worker run (>= 2)")
    parser.add_argument("--rounds", type=int, default=2)
    add_run_options(parser)
    args = parser.parse_args(argv)
    from fsswarp.errors import InputError, check_integer

    try:
        for name, lowest in (("jobs", 2), ("rounds", 1), ("seed", 0), ("iterations", 0)):
            check_integer(f"--{name}", getattr(args, name), lowest)
    except InputError as err:
        print(f"bench/resident_jobs.py: error: {err}", file=sys.stderr)
        return 2
    fresh, first, later = [], [], []
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder)
        dataset, reference = reference_run(root, args.scene, args.seed, args.iterations, args.options)
        for r in range(args.rounds):
            for per_process in ((1, 0) if r % 2 == 0 else (0, 1)):
                run = root / f"round{r}-p{per_process}"
                try:
                    seconds = run_jobs(dataset, run, args.jobs, args.iterations, per_process, args.options,
                                       reference)
                except RuntimeError as err:
                    print(f"bench/resident_jobs.py: error: {err}", file=sys.stderr)
                    return 1
                if per_process == 1:
                    fresh += seconds
                else:
                    first.append(seconds[0])
                    later += seconds[1:]
                kind = "a process per job" if per_process == 1 else "one resident process"
                print(f"round {r + 1}, {kind}: " + " / ".join(f"{s:.2f}" for s in seconds) + " s", flush=True)
    print(f"{args.scene}, seed {args.seed}, {args.iterations} iterations, {args.jobs} jobs per run, {args.rounds} "
          f"rounds, options {' '.join(args.options) or '(none)'}; {os.cpu_count()} logical CPUs; backend "
          f"{reference['backend']} on {reference['device']}; every job: D {reference['depth_m']:.4f} m, tilt "
          f"{reference['tilt_deg']:.3f} deg")
    print("| a process per job (median) | resident: first job | resident: later jobs (median) | later / fresh |")
    print("|---|---|---|---|")
    print(f"| {statistics.median(fresh):.2f} s ({len(fresh)} jobs) | {statistics.median(first):.2f} s "
          f"({len(first)}) | {statistics.median(later):.2f} s ({len(later)} jobs) | "
          f"{statistics.median(later) / statistics.median(fresh):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
