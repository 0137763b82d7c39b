"""Throughput of `fsswarp batch` (Ray): N reconstructions of one scene per run, for K jobs per GPU
and a number of GPUs.

    python bench/batch_ray.py [--jobs N] [--per-gpu K ...] [--gpus G ...] [--per-process P ...]
                              [--scene S] [--seed K] [--iterations T] [-- GLOBAL OPTIONS...]

The scene is simulated once (noisy, seed ``--seed``), and one uncounted `fsswarp reconstruct`
warms the kernel caches and gives the reference result.json. Then, for every G of ``--gpus``,
K of ``--per-gpu`` and P of ``--per-process`` (default 0), a JOBS.toml of N jobs on that
dataset (``iterations = T``) runs through ``fsswarp GLOBAL OPTIONS batch JOBS.toml --out DIR
--jobs-per-gpu K --jobs-per-process P`` in a fresh DIR, with a
local Ray instance that sees the first G GPUs (CUDA_VISIBLE_DEVICES), and the command's wall
time is taken (Ray's start and stop included). Every job must end ok with the reference's
result.json values (D, β, E_I per iteration). Prints one Markdown table: per (G, K, P) the wall
time, the seconds per job (wall / N) and the throughput relative to the first row (G = 1,
K = 1 by default: one job at a time on one GPU). On a machine without a GPU, G and K change
nothing: each job takes one CPU (PoCL).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from batch_throughput import add_run_options, agreed, reference_run


def run_batch(dataset: Path, root: Path, jobs: int, iterations: int, per_gpu: int, gpus: int, per_process: int,
              options: list[str]) -> tuple[float, list[dict], list[dict]]:
    """(wall seconds of one `fsswarp batch` of ``jobs`` reconstructions of ``dataset`` into
    ``root``/out, its jobs.jsonl lines, the jobs' result.json); RuntimeError if it fails."""
    lines = [f"[defaults]\niterations = {iterations}\n"]
    lines += [f"[[jobs]]\nname = \"job{k:03d}\"\ndataset = {json.dumps(str(dataset))}\n" for k in range(jobs)]
    jobs_file = root / "JOBS.toml"
    jobs_file.write_text("\n".join(lines))
    env = dict(os.environ, CUDA_VISIBLE_DEVICES=",".join(map(str, range(gpus))))
    command = [sys.executable, "-m", "fsswarp", "-q", *options, "batch", str(jobs_file), "--out", str(root / "out"),
               "--jobs-per-gpu", str(per_gpu), "--jobs-per-process", str(per_process)]
    start = time.perf_counter()
    done = subprocess.run(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} exited {done.returncode}: {done.stderr.strip()[-500:]}")
    records = [json.loads(line) for line in (root / "out" / "jobs.jsonl").read_text().splitlines()]
    results = [json.loads((root / "out" / r["name"] / "result.json").read_text()) for r in records]
    return wall, records, results


def table_markdown(rows: list[tuple[int, int, int, int, float]]) -> str:
    """The Markdown table of (GPUs, K, P, jobs, wall seconds) rows (module docstring)."""
    base = rows[0][4] / rows[0][3]
    lines = ["| GPUs | jobs per GPU (K) | jobs per process (P) | jobs | wall time | seconds per job | "
             "throughput relative to the first row |", "|---|---|---|---|---|---|---|"]
    lines += [f"| {gpus} | {per_gpu} | {per_process} | {jobs} | {wall:.1f} s | {wall / jobs:.2f} s | "
              f"{base / (wall / jobs):.2f} |" for gpus, per_gpu, per_process, jobs, wall in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=16)
    parser.add_argument("--per-gpu", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--gpus", type=int, nargs="+", default=[1])
    parser.add_argument("--per-process", type=int, nargs="+", default=[0],
                        help="--jobs-per-process of the batch (0: no limit; 1: a process per job)")
    add_run_options(parser)
    args = parser.parse_args(argv)
    from fsswarp.errors import InputError, check_integer

    try:
        for name, lowest in (("jobs", 1), ("seed", 0), ("iterations", 0)):
            check_integer(f"--{name}", getattr(args, name), lowest)
        for name, lowest in (("per_gpu", 1), ("gpus", 1), ("per_process", 0)):
            for value in getattr(args, name):
                check_integer(f"--{name.replace('_', '-')}", value, lowest)
    except InputError as err:
        print(f"bench/batch_ray.py: error: {err}", file=sys.stderr)
        return 2
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder)
        dataset, reference = reference_run(root, args.scene, args.seed, args.iterations, args.options)
        for gpus in args.gpus:
            for per_gpu in args.per_gpu:
                for per_process in args.per_process:
                    run = root / f"run{len(rows)}-g{gpus}-k{per_gpu}-p{per_process}"
                    run.mkdir()
                    wall, records, results = run_batch(dataset, run, args.jobs, args.iterations, per_gpu, gpus,
                                                       per_process, args.options)
                    if any(agreed(result) != agreed(reference) for result in results):
                        print(f"bench/batch_ray.py: error: a job of G = {gpus}, K = {per_gpu}, P = {per_process} "
                              "disagrees with the reference result.json", file=sys.stderr)
                        return 1
                    devices = sorted({r["device"] for r in records})
                    print(f"G = {gpus}, K = {per_gpu}, P = {per_process}: {wall:.1f} s ({wall / args.jobs:.2f} s "
                          f"per job) on {', '.join(devices)}", flush=True)
                    rows.append((gpus, per_gpu, per_process, args.jobs, wall))
    print(f"{args.scene}, seed {args.seed}, {args.iterations} iterations, {args.jobs} jobs per run, options "
          f"{' '.join(args.options) or '(none)'}; {os.cpu_count()} logical CPUs; backend {reference['backend']} on "
          f"{reference['device']}; every job: D {reference['depth_m']:.4f} m, tilt {reference['tilt_deg']:.3f} deg")
    print(table_markdown(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
