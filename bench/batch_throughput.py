"""Throughput of batch reconstruction: N `fsswarp reconstruct` commands at once on one machine.

    python bench/batch_throughput.py [--jobs N ...] [--rounds R] [--scene S] [--seed K]
                                     [--iterations T] [-- GLOBAL OPTIONS...]

A reconstruction on a GPU spends most of its wall time in host Python and NumPy between short
kernel calls (bench/notes.md), so the device idles; a server with many host cores can run
several at once. The scene is simulated once (noisy, seed ``--seed``); then, for every N of
``--jobs``, N copies of the user's command ``fsswarp -q OPTIONS reconstruct DATASET --out
OUT_k --iterations T`` start together, each a fresh process (imports, backend start and
figures included), and the wall time until the last one ends is taken, ``--rounds`` times
(the N in turn within a round, so that drift falls on all of them). A first, uncounted round
of one command warms the kernel caches. Every command must exit 0 and write the same
``result.json`` values (D, β, E_I per iteration: the same inputs give the same outputs on the
same backend). Prints one Markdown table: per N the median wall time (min–max), the seconds
per reconstruction (wall / N) and the throughput relative to N = 1.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

_spec = importlib.util.spec_from_file_location("bench_profiling", Path(__file__).resolve().parent / "profiling.py")
profiling = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(profiling)

#: The values of result.json that every command of a batch must agree on.
AGREED = ("depth_m", "tilt_deg", "best_iteration")


def run_batch(dataset: Path, outs: list[Path], iterations: int, options: list[str]) -> tuple[float, list[dict]]:
    """(wall seconds until the last of len(outs) simultaneous reconstructions ended, their
    result.json) ; RuntimeError naming the command when one fails."""
    commands = [[sys.executable, "-m", "fsswarp", "-q", *options, "reconstruct", str(dataset), "--out", str(out),
                 "--iterations", str(iterations)] for out in outs]
    start = time.perf_counter()
    running = [subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
               for command in commands]
    errors = [process.communicate()[1] for process in running]
    wall = time.perf_counter() - start
    for command, process, error in zip(commands, running, errors):
        if process.returncode != 0:
            raise RuntimeError(f"{' '.join(command)} exited {process.returncode}: {error.strip()[-500:]}")
    return wall, [json.loads((out / "result.json").read_text()) for out in outs]


def agreed(result: dict) -> tuple:
    """What every command of a batch must agree on: AGREED and each iteration's (D, β, E_I)."""
    return tuple(result[key] for key in AGREED) + tuple(
        (entry["depth_m"], entry["tilt_deg"], entry["E_I"]) for entry in result["history"])


def add_run_options(parser) -> None:
    """The options that the batch benchmarks share: ``--scene``, ``--seed``, ``--iterations`` and
    the global fsswarp options after ``--``."""
    parser.add_argument("--scene", default="coral-one")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("options", nargs="*", help="global fsswarp options, e.g. --backend warp --device cuda:0")


def reference_run(root: Path, scene: str, seed: int, iterations: int, options: list[str]) -> tuple[Path, dict]:
    """(the dataset folder, the reference result.json) of ``scene`` simulated (noisy, ``seed``)
    into ``root``/dataset and reconstructed once (``iterations``; this also warms the kernel
    caches) into ``root``/warm, with the global ``options``. Where a command fails, its stderr
    goes to stderr and SystemExit ends the benchmark with its status."""
    dataset, warm = root / "dataset", root / "warm"
    profiling.run_fsswarp(*options, "simulate", scene, "--out", str(dataset), "--seed", str(seed))
    profiling.run_fsswarp(*options, "reconstruct", str(dataset), "--out", str(warm), "--iterations", str(iterations))
    return dataset, json.loads((warm / "result.json").read_text())


def table_markdown(walls: dict[int, list[float]]) -> str:
    """The Markdown table of the wall times per N (module docstring)."""
    base = statistics.median(walls[min(walls)]) / min(walls)
    lines = ["| reconstructions at once | wall time, median (min–max) | runs | seconds per reconstruction | "
             "throughput relative to one at a time |", "|---|---|---|---|---|"]
    for jobs, values in sorted(walls.items()):
        median = statistics.median(values)
        lines.append(f"| {jobs} | {median:.1f} s ({min(values):.1f}–{max(values):.1f}) | {len(values)} | "
                     f"{median / jobs:.2f} s | {base / (median / jobs):.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--rounds", type=int, default=2)
    add_run_options(parser)
    args = parser.parse_args(argv)
    from fsswarp.errors import InputError, check_integer

    try:
        for name, lowest in (("rounds", 1), ("seed", 0), ("iterations", 0)):
            check_integer(f"--{name}", getattr(args, name), lowest)
        for jobs in args.jobs:
            if not 1 <= jobs <= 64:
                raise InputError("must be in [1, 64]", field="--jobs", value=jobs)
    except InputError as err:
        print(f"bench/batch_throughput.py: error: {err}", file=sys.stderr)
        return 2
    walls: dict[int, list[float]] = {n: [] for n in args.jobs}
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder)
        profiling.run_fsswarp(*args.options, "simulate", args.scene, "--out", str(root / "dataset"), "--seed",
                              str(args.seed))
        _, (reference,) = run_batch(root / "dataset", [root / "warm"], args.iterations, args.options)
        for round_ in range(args.rounds):
            for jobs in args.jobs:
                wall, results = run_batch(root / "dataset", [root / f"out{round_}-{jobs}-{k}" for k in range(jobs)],
                                          args.iterations, args.options)
                if any(agreed(result) != agreed(reference) for result in results):
                    print(f"bench/batch_throughput.py: error: the {jobs} reconstructions of round {round_ + 1} "
                          "disagree with the first run's result.json", file=sys.stderr)
                    return 1
                walls[jobs].append(wall)
                print(f"round {round_ + 1}: {jobs} at once: {wall:.1f} s ({wall / jobs:.2f} s each)", flush=True)
    print(f"{args.scene}, seed {args.seed}, {args.iterations} iterations, "
          f"options {' '.join(args.options) or '(none)'}; {os.cpu_count()} logical CPUs; "
          f"the same result.json in every run: D {reference['depth_m']:.4f} m, tilt {reference['tilt_deg']:.3f} deg")
    print(table_markdown(walls))
    return 0


if __name__ == "__main__":
    sys.exit(main())
