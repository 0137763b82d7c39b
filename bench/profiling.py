"""Pieces shared by the profile scripts of bench/ (exact_profile, refine_profile, mesh_profile,
loop_profile) and the batch benchmarks: their scene options, checked, with the backend they name
and the scene simulated into a temporary folder (in this process or a child's), an fsswarp
command run to its end, functions replaced until restored (timed stages), the CPU's name for a
record, and per-stage medians and their Markdown table."""

from __future__ import annotations

import argparse
import contextlib
import functools
import hashlib
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable


def add_scene_options(parser: argparse.ArgumentParser) -> None:
    """--scene (a built-in scene), --backend, --device and --seed (the simulation's noise)."""
    parser.add_argument("--scene", default="coral-one", choices=("coral-one", "coral-two", "table"))
    parser.add_argument("--backend", default=None, help="warp or opencl (default: fsswarp's choice)")
    parser.add_argument("--device", default=None, help="backend device, e.g. cuda:0, cpu, pocl, nvidia")
    parser.add_argument("--seed", type=int, default=0, help="noise seed of the simulation")


def scene_backend(args: argparse.Namespace, script: str, check: Callable[[], None] = lambda: None):
    """The backend that the scene options (:func:`add_scene_options`) name, after ``check()``
    (the script's own option checks) and the seed's; on an InputError None, with the error
    printed as ``SCRIPT: error: ...`` (the script exits 2)."""
    from fsswarp.backends import get_backend
    from fsswarp.errors import InputError, check_integer

    try:
        check()
        check_integer("--seed", args.seed, 0)
        return get_backend(args.backend or "auto", args.device)
    except InputError as err:
        print(f"{script}: error: {err}", file=sys.stderr)
        return None


@contextlib.contextmanager
def simulated(args: argparse.Namespace, backend):
    """The dataset of the scene options' scene and seed, simulated on ``backend`` into a
    temporary folder that lives while the block runs."""
    from fsswarp.simulation import simulate

    with tempfile.TemporaryDirectory() as folder:
        yield simulate(args.scene, Path(folder) / args.scene, seed=args.seed, backend=backend)


def run_fsswarp(*arguments: str) -> None:
    """Run ``python -m fsswarp -q ARGUMENTS`` (global options first) in a child process; where it
    fails, its stderr goes to stderr and SystemExit ends the benchmark with its status."""
    done = subprocess.run([sys.executable, "-m", "fsswarp", "-q", *arguments], capture_output=True, text=True)
    if done.returncode:
        print(done.stderr.strip(), file=sys.stderr)
        raise SystemExit(done.returncode)


@contextlib.contextmanager
def simulated_apart(args: argparse.Namespace):
    """The dataset of the scene options' scene and seed, simulated on their backend by a
    ``fsswarp simulate`` child process into a temporary folder and loaded from it (this process
    then has computed nothing of it yet)."""
    from fsswarp.dataset import load_dataset

    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / args.scene
        run_fsswarp(*(["--backend", args.backend] if args.backend else []),
                    *(["--device", args.device] if args.device else []),
                    "simulate", args.scene, "--out", str(out), "--seed", str(args.seed))
        yield load_dataset(out)


def mesh_digest(mesh) -> str:
    """SHA-256 of the mesh's float64 vertices and int64 faces (C order)."""
    import numpy as np

    digest = hashlib.sha256(np.ascontiguousarray(mesh.vertices, np.float64).tobytes())
    digest.update(np.ascontiguousarray(mesh.faces, np.int64).tobytes())
    return digest.hexdigest()


def medians(rows) -> dict[str, float]:
    """Median seconds per label over the calls (rows: label -> seconds; 0 where a call lacks it)."""
    labels = sorted({label for row in rows for label in row})
    return {label: statistics.median(row.get(label, 0.0) for row in rows) for label in labels}


def cpu_model() -> str:
    """The CPU's model name (``fsswarp.benchmark.cpu_info``)."""
    from fsswarp.benchmark import cpu_info

    return cpu_info()["model"]


def stage_table(med: dict[str, float], order: list[str]) -> str:
    """Markdown rows ``| stage | median ms | share |`` of the labels of ``order`` present in
    ``med`` (label -> seconds; its "total" the 100%)."""
    lines = ["| stage | median ms | share |", "|---|---|---|"]
    for label in order:
        if label in med:
            lines.append(f"| `{label}` | {1e3 * med[label]:.2f} | {100 * med[label] / med['total']:.1f}% |")
    return "\n".join(lines)


class Patches:
    """Attributes replaced (:meth:`replace`) until :meth:`restore` puts the originals back, the
    last replaced first: an attribute the owner did not hold itself (a method of its class, or
    inherited) is removed again, so that the owner finds it where it did before."""

    def __init__(self):
        self.undo = []

    def replace(self, owner, name: str, value) -> None:
        """Set ``owner.name`` to ``value`` until :meth:`restore`."""
        self.undo.append((owner, name, getattr(owner, name), name in vars(owner)))
        setattr(owner, name, value)

    def restore(self) -> None:
        for owner, name, original, held in reversed(self.undo):
            if held:
                setattr(owner, name, original)
            else:
                delattr(owner, name)
        self.undo.clear()


class StageTimes(Patches):
    """Inclusive wall seconds per wrapped callable within the current call (``current``: label
    -> s); a ``nested`` label called inside the ``outer`` one is counted under the outer only."""

    def __init__(self, outer: str | None = None, nested=()):
        super().__init__()
        self.current: dict[str, float] = {}
        self.outer, self.nested, self.depth = outer, frozenset(nested), 0  # depth > 0 inside outer

    def wrap(self, owner, name: str, label: str) -> None:
        original = getattr(owner, name)

        @functools.wraps(original)
        def timed(*args, **kwargs):
            if label in self.nested and self.depth:
                return original(*args, **kwargs)
            outer = label == self.outer
            self.depth += outer
            start = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                self.current[label] = self.current.get(label, 0.0) + time.perf_counter() - start
                self.depth -= outer

        self.replace(owner, name, timed)

    def wrap_backend(self, backend, names) -> None:
        """Time those of ``names`` that ``backend``'s class has, as ``backend.NAME``."""
        for name in names:
            if hasattr(type(backend), name):
                self.wrap(type(backend), name, f"backend.{name}")
