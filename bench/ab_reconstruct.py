"""Side-by-side wall time of one reconstruction (or the whole demo) with two code trees, in one run:

    python bench/ab_reconstruct.py BEFORE AFTER [--rounds K] [--scene NAME] [--backend B]
                                   [--device D] [--timeout S] [--demo]

BEFORE and AFTER are folders that each hold an ``fsswarp`` package (and ``kernels/`` for the
OpenCL backend), e.g. ``git archive REV fsswarp kernels | tar -x -C DIR``. The scene is
simulated once (noisy, seed 0) with AFTER; then each tree reconstructs it from the measured
start once with one iteration (to fill the kernel caches: without iterations the pose and
shape steps' kernels would be compiled in the first timed round) and ``--rounds`` times in
alternation, each run in its own process with the tree first on ``PYTHONPATH``. Prints one
Markdown table: per tree the median and each run's seconds of ``fsswarp.reconstruction`` (the
process start and the dataset load are not timed), the final D, β, E_I and the model's digest
(the first 12 hex digits of SHA-256 over its float64 vertices and int64 faces; the trees should
agree); then AFTER's median over BEFORE's and each round's ratio (``paired``). Both trees are
compiled to bytecode first, as an install is, and where Python may not write bytecode
(``PYTHONDONTWRITEBYTECODE``) a warning names the imported packages that have none: each run
would compile them from source (2-3 s of a GPU host's run, bench/notes.md). Timings taken one
after the other drift with the machine's load; alternating rounds put that drift into both
columns alike. A run past ``--timeout`` seconds (default 300) is stopped with its processes:
one line on stderr, exit 1. With ``--demo`` each run is the command ``fsswarp demo SCENE``
instead, timed from its process's first import to its end (simulation, reconstruction,
enhancement, figures and report); the digest is then of its ``model.ply``.
"""

from __future__ import annotations

import argparse
import compileall
import importlib.util
import itertools
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

RUN = """
import json, sys, time
import fsswarp
from fsswarp.backends import get_backend
from fsswarp.dataset import load_dataset
try:
    from fsswarp.reconstruction import ReconstructSettings, reconstruct
except ImportError:  # a tree from before the modules were renamed (reconstruct.py)
    from fsswarp.reconstruct import ReconstructSettings, reconstruct
dataset = load_dataset(sys.argv[1])
backend = get_backend(sys.argv[2], sys.argv[3] or None)
start = time.perf_counter()
result = reconstruct(dataset, settings=ReconstructSettings(iterations=int(sys.argv[4])), backend=backend)
import hashlib, numpy as np
seconds = time.perf_counter() - start
model = hashlib.sha256(np.ascontiguousarray(result.model.vertices, np.float64).tobytes()
                       + np.ascontiguousarray(result.model.faces, np.int64).tobytes()).hexdigest()[:12]
print(json.dumps({"seconds": seconds, "package": fsswarp.__path__[0], "depth_m": result.depth,
                  "tilt_deg": result.summary()["tilt_deg"], "E_I": result.history[result.best_iteration]["E_I"],
                  "model": model}))
"""

RUN_DEMO = """
import time
start = time.perf_counter()
import hashlib, json, sys
from pathlib import Path
import fsswarp
from fsswarp.cli import main
out, backend, device, scene, iterations = sys.argv[1:]
status = main(["--quiet", "--backend", backend, *(["--device", device] if device else []), "demo", scene, "--out", out,
               "--iterations", iterations])
seconds = time.perf_counter() - start
if status:
    sys.exit(status)
import numpy as np, trimesh
record = json.loads((Path(out) / "reconstruction" / "result.json").read_text())
mesh = trimesh.load_mesh(Path(out) / "reconstruction" / "model.ply", process=False)
model = hashlib.sha256(np.ascontiguousarray(mesh.vertices, np.float64).tobytes()
                       + np.ascontiguousarray(mesh.faces, np.int64).tobytes()).hexdigest()[:12]
print(json.dumps({"seconds": seconds, "package": fsswarp.__path__[0], "depth_m": record["depth_m"],
                  "tilt_deg": record["tilt_deg"], "E_I": record["history"][record["best_iteration"]]["E_I"],
                  "model": model}))
"""


def tree_first(tree: Path) -> dict:
    """The environment with ``tree`` first on PYTHONPATH."""
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(tree), os.environ.get("PYTHONPATH", "")]))


def run_tree(tree: Path, *args: str, timeout: float = 300.0, script: str = RUN) -> dict:
    """One reconstruction (``script``: RUN, or RUN_DEMO for the demo) in its own process with
    ``tree`` first on PYTHONPATH, run from the tree (``python -c`` and ``python -m`` put the
    working folder before PYTHONPATH: a demo A/B that ran ``-m fsswarp`` from a checkout timed
    that checkout twice, bench/notes.md, twenty-third session); its JSON line. A run past
    ``timeout`` seconds is stopped with every process it started (its own session), and
    TimeoutError says so: on a lent GPU machine a hung run would spend the whole call
    (bench/notes.md, twenty-second session)."""
    with subprocess.Popen([sys.executable, "-c", script, *args], env=tree_first(tree), cwd=tree, stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True, start_new_session=True) as process:
        try:
            stdout, stderr = process.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.communicate()
            raise TimeoutError(f"{tree}: a run took more than {timeout:g} s; it and its processes were stopped") \
                from None
    if process.returncode:
        raise subprocess.CalledProcessError(process.returncode, process.args, stdout, stderr)
    found = json.loads(stdout.strip().splitlines()[-1])
    if Path(found["package"]).resolve() != (tree / "fsswarp").resolve():
        raise RuntimeError(f"{tree}: the run imported fsswarp from {found['package']}")
    return found


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--scene", default="coral-one")
    parser.add_argument("--backend", default="auto")
    parser.add_argument("--device", default="")
    parser.add_argument("--timeout", type=float, default=300.0, help="most seconds of one run (default 300)")
    parser.add_argument("--demo", action="store_true", help="time the command `fsswarp demo SCENE` instead")
    options = parser.parse_args(argv)
    from fsswarp.errors import InputError, check_integer

    trees = {"before": options.before.resolve(), "after": options.after.resolve()}
    try:
        for name, tree in trees.items():
            if not (tree / "fsswarp" / "__init__.py").is_file():
                raise InputError("holds no fsswarp package", field=name, value=str(tree))
        check_integer("--rounds", options.rounds, 1)
        if not options.timeout > 0:
            raise InputError("must be a number of seconds above 0", field="--timeout", value=options.timeout)
    except InputError as err:
        print(f"bench/ab_reconstruct.py: error: {err}", file=sys.stderr)
        return 2
    for tree in trees.values():  # as an install is; Python's own writes may be turned off
        compileall.compile_dir(tree / "fsswarp", quiet=1)
    uncompiled = packages_without_bytecode()
    if uncompiled:
        print(f"bench/ab_reconstruct.py: warning: Python writes no bytecode here and {', '.join(uncompiled)} have "
              "none: every run compiles them (python -m compileall on their folders first)", file=sys.stderr)
    with tempfile.TemporaryDirectory() as scratch:
        runs = {name: [] for name in trees}
        try:
            if options.demo:
                count = itertools.count()

                def run(tree: Path, iterations: str) -> dict:  # a fresh output folder each time
                    return run_tree(tree, str(Path(scratch) / f"demo{next(count)}"), options.backend, options.device,
                                    options.scene, iterations, timeout=options.timeout, script=RUN_DEMO)
            else:
                data = Path(scratch) / options.scene
                subprocess.run([sys.executable, "-m", "fsswarp", "--quiet", "--backend", options.backend,
                                *(["--device", options.device] if options.device else []), "simulate", options.scene,
                                "--out", str(data), "--seed", "0"], check=True, env=tree_first(trees["after"]),
                               cwd=trees["after"])

                def run(tree: Path, iterations: str) -> dict:
                    return run_tree(tree, str(data), options.backend, options.device, iterations,
                                    timeout=options.timeout)
            for tree in trees.values():
                run(tree, "1")  # one iteration launches every kernel of the loop
            for _ in range(options.rounds):
                for name, tree in trees.items():
                    runs[name].append(run(tree, "10"))
        except TimeoutError as err:
            print(f"bench/ab_reconstruct.py: error: {err}", file=sys.stderr)
            return 1
    medians = {name: statistics.median(r["seconds"] for r in found) for name, found in runs.items()}
    what = "`fsswarp demo`, the whole command" if options.demo else "measured start"
    print(f"{options.scene}, {what}, backend {options.backend} {options.device}, {options.rounds} rounds\n")
    print("| tree | median (s) | each run (s) | final D (m), β (°), E_I | model |")
    print("|---|---|---|---|---|")
    for name, found in runs.items():
        seconds = [r["seconds"] for r in found]
        last = found[-1]
        print(f"| {name} `{trees[name]}` | {medians[name]:.2f} | {' / '.join(f'{s:.2f}' for s in seconds)} | "
              f"{last['depth_m']:.6f}, {last['tilt_deg']:.5f}, {last['E_I']:.4f} | "
              f"{', '.join(sorted({r['model'] for r in found}))} |")
    print(f"\nafter / before (medians): {medians['after'] / medians['before']:.2f}")
    ratios, faster = paired([r["seconds"] for r in runs["before"]], [r["seconds"] for r in runs["after"]])
    print(f"after / before per round: {' / '.join(f'{r:.2f}' for r in ratios)}; after faster in {faster} of "
          f"{len(ratios)} rounds")
    return 0


#: Packages that every run imports: their bytecode is looked for by ``packages_without_bytecode``.
IMPORTED = ("numpy", "scipy", "trimesh", "networkx", "skimage", "warp", "pyopencl", "matplotlib")


def packages_without_bytecode() -> list[str]:
    """Where Python writes no bytecode (``sys.dont_write_bytecode``): the installed packages of
    ``IMPORTED`` whose ``__init__`` has no cached bytecode (empty otherwise)."""
    if not sys.dont_write_bytecode:
        return []
    missing = []
    for name in IMPORTED:
        spec = importlib.util.find_spec(name)
        if spec is not None and spec.origin and spec.origin.endswith(".py"):
            if not Path(importlib.util.cache_from_source(spec.origin)).is_file():
                missing.append(name)
    return missing


def paired(before: list[float], after: list[float]) -> tuple[list[float], int]:
    """Each round's after / before seconds and the rounds in which AFTER was faster. The runs
    alternate, so a round's two saw the same machine; on a GPU host whose runs of one tree
    spread by 10–20% the medians alone do not show a change of a few percent (bench/notes.md,
    twenty-first session)."""
    ratios = [a / b for b, a in zip(before, after)]
    return ratios, sum(r < 1.0 for r in ratios)


if __name__ == "__main__":
    sys.exit(main())
