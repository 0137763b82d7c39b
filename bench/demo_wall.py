"""Wall time of the whole `fsswarp demo` (what a user waits for, imports included), each run a
fresh process, with the figures drawn in the command's own process (FSSWARP_FIGURE_WORKERS=0)
and in figure processes (the default), alternating so that both see the same machine.

    python bench/demo_wall.py [--rounds R] [--scene S] [-- GLOBAL OPTIONS...]

Prints one line per run and the medians with their ratio. A first run, not counted, warms the
kernel caches.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time


def run_demo(scene: str, out: str, workers: str | None, options: list[str]) -> float:
    env = dict(os.environ)
    env.pop("FSSWARP_FIGURE_WORKERS", None)
    if workers is not None:
        env["FSSWARP_FIGURE_WORKERS"] = workers
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "fsswarp", "-q", *options, "demo", scene, "--out", out], env=env,
                   check=True)
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--scene", default="coral-one")
    parser.add_argument("options", nargs="*", help="global fsswarp options, e.g. --backend warp --device cuda:0")
    args = parser.parse_args(argv)
    settings = {"in the command's process": "0", "in figure processes": None}
    seconds = {label: [] for label in settings}
    with tempfile.TemporaryDirectory() as folder:
        run_demo(args.scene, os.path.join(folder, "warm"), None, args.options)
        for round_ in range(args.rounds):
            for label, workers in settings.items():
                wall = run_demo(args.scene, os.path.join(folder, "out"), workers, args.options)
                seconds[label].append(wall)
                print(f"round {round_ + 1}: figures {label}: {wall:.1f} s", flush=True)
    medians = {label: statistics.median(values) for label, values in seconds.items()}
    for label, values in seconds.items():
        print(f"figures {label}: median {medians[label]:.1f} s ({min(values):.1f}-{max(values):.1f})")
    first, second = medians.values()
    print(f"ratio {second / first:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
