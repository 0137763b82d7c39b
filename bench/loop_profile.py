"""Where a reconstruction's time goes, without a sampling profiler, one command:

    python bench/loop_profile.py [--scene NAME] [--backend B] [--device D] [--iterations T]
                                 [--seed S] [--warp | --main] [--fresh]

Simulates the scene (noisy, ``--seed``), reconstructs it once with one iteration (none with
``--iterations 0``; to fill the kernel caches), then once with ``--iterations`` while the loop's main functions are wrapped
to count their calls and sum their wall time (inclusive: a function's time holds that of the
functions it calls, so the rows overlap). Prints one Markdown table, slowest first: calls,
seconds, share of the run and milliseconds per call. A sampling profiler (py-spy) slowed the
H100 run 1.5–3.5 times and so hid where the run waited (bench/notes.md); these wrappers cost
microseconds per call. ``--warp`` (a Warp backend) also times Warp's own calls (``WARP_CALLS``:
launches, arrays, copies, waits; the outermost of them in each thread, any thread) in a second
table: how much of the run is Warp's Python and waiting for the device. ``--main`` times the main
thread alone, each call only where no wrapped call encloses it: the rows then partition the
main thread's run (plus a row for the rest: the loop's own code between them), the path that
sets the wall time while the helper threads (the answer ahead, the planning) keep up with it.
``--fresh`` times the process's first reconstruction, as a fresh ``fsswarp reconstruct`` runs it:
the scene simulated by a ``fsswarp simulate`` child process and loaded from its folder, no
warm-up run; it also lists the packages that the run imported first.
"""

from __future__ import annotations

import argparse
import collections
import functools
import importlib.util
import sys
import threading
import time
from pathlib import Path

#: (module, class name or None, function names) wrapped where the loop looks them up.
WRAPPED = (
    ("fsswarp.compare", "ViewComparison", ("__init__", "use", "locate", "exact", "surrogate", "view_costs", "align",
                                           "frontal_motions", "contour_errors", "_detection_shift", "_data_contours")),
    ("fsswarp.compare", None, ("patch_motions",)),
    ("fsswarp.pose", None, ("estimate_pose", "_polish")),
    ("fsswarp.refine", None, ("refine_shape",)),
    ("fsswarp.refine", "_Membrane", ("solve",)),
    ("fsswarp.carving", None, ("carve", "voxel_mesh")),
    ("fsswarp.reconstruction", None, ("_image_errors", "_complete", "sighting", "_valley_answer")),
)
BACKEND_METHODS = ("render_planned", "contour_cost", "view_costs", "icp_runs", "frontal_faces", "load_mesh",
                   "device_distances", "carve")
#: Warp's calls that ``--warp`` times: functions of the ``warp`` module and methods of ``warp.array``.
WARP_CALLS = (("launch", "empty", "zeros", "copy", "synchronize_device"), ("__init__", "numpy"))
#: Functions that other modules import by name: those modules get the wrapper too.
REBOUND = {"estimate_pose": ("fsswarp.reconstruction",), "refine_shape": ("fsswarp.reconstruction",),
           "carve": ("fsswarp.reconstruction",)}

_spec = importlib.util.spec_from_file_location("bench_profiling", Path(__file__).resolve().parent / "profiling.py")
profiling = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(profiling)


class CallTimes(profiling.Patches):
    """Calls and inclusive wall seconds per wrapped function (``totals``: label -> [calls, s])."""

    def __init__(self, main_only: bool = False):
        super().__init__()
        self.totals = collections.defaultdict(lambda: [0, 0.0])
        self._inside = threading.local()  # .depth: outermost-only wrappers entered in this thread
        self.main_only = main_only  # count the main thread's calls alone

    def wrap(self, owner, name: str, label: str, *, outermost: bool = False):
        """Replace ``owner.name`` by a timed wrapper, and return it. With ``outermost``, a call made
        inside another outermost-only wrapped call (in the same thread) is not counted."""
        original = getattr(owner, name)

        @functools.wraps(original)
        def timed(*args, **kwargs):
            if self.main_only and threading.current_thread() is not threading.main_thread():
                return original(*args, **kwargs)
            if outermost:
                if getattr(self._inside, "depth", 0):
                    return original(*args, **kwargs)
                self._inside.depth = 1
            start = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                if outermost:
                    self._inside.depth = 0
                entry = self.totals[label]
                entry[0] += 1
                entry[1] += time.perf_counter() - start

        self.replace(owner, name, timed)
        return timed

    def table(self, total: float, labels=None) -> str:
        """Markdown: one row per function (of ``labels``, default all), slowest first; shares of
        ``total`` seconds."""
        lines = ["| function | calls | s | share | ms per call |", "|---|---|---|---|---|"]
        rows = [(label, entry) for label, entry in self.totals.items() if labels is None or label in labels]
        for label, (calls, seconds) in sorted(rows, key=lambda item: -item[1][1]):
            lines.append(f"| `{label}` | {calls} | {seconds:.3f} | {100 * seconds / total:.1f}% | "
                         f"{1e3 * seconds / calls:.2f} |")
        return "\n".join(lines)


def instrument(times: CallTimes, backend, *, outermost: bool = False) -> None:
    """Wrap ``WRAPPED`` (and rebind the names in ``REBOUND``) and ``backend``'s ``BACKEND_METHODS``
    (``outermost``: each call counted only outside the other wrapped calls)."""
    import importlib

    wrapped = {}
    for module_name, owner_name, names in WRAPPED:
        module = importlib.import_module(module_name)
        owner = getattr(module, owner_name) if owner_name else module
        for name in names:
            label = f"{owner_name}.{name}" if owner_name else name
            wrapped[label] = times.wrap(owner, name, label, outermost=outermost)
    for name, modules in REBOUND.items():
        for module_name in modules:
            times.replace(importlib.import_module(module_name), name, wrapped[name])
    for name in BACKEND_METHODS:
        if hasattr(type(backend), name):
            times.wrap(type(backend), name, f"backend.{name}", outermost=outermost)


def instrument_warp(times: CallTimes) -> list[str]:
    """Wrap ``WARP_CALLS`` (outermost only); returns their labels."""
    import warp as wp

    functions, methods = WARP_CALLS
    labels = [f"wp.{name}" for name in functions] + [f"wp.array.{name}" for name in methods]
    for owner, names, prefix in ((wp, functions, "wp."), (wp.array, methods, "wp.array.")):
        for name in names:
            times.wrap(owner, name, prefix + name, outermost=True)
    return labels


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    profiling.add_scene_options(parser)
    parser.add_argument("--iterations", type=int, default=10)
    modes = parser.add_mutually_exclusive_group()
    modes.add_argument("--warp", action="store_true", help="also time Warp's own calls (a Warp backend)")
    modes.add_argument("--main", action="store_true", help="the main thread's calls, outermost only")
    parser.add_argument("--fresh", action="store_true",
                        help="time the process's first reconstruction (the scene simulated by a child process)")
    args = parser.parse_args(argv)
    from fsswarp.errors import check_integer
    from fsswarp.reconstruction import ReconstructSettings, reconstruct

    backend = profiling.scene_backend(args, "loop_profile", lambda: check_integer("--iterations", args.iterations, 0))
    if backend is None:
        return 2
    if args.warp and backend.name != "warp":
        print(f"loop_profile: error: --warp needs a Warp backend, got {backend.name}", file=sys.stderr)
        return 2
    with (profiling.simulated_apart(args) if args.fresh else profiling.simulated(args, backend)) as dataset:
        if not args.fresh:
            reconstruct(dataset, settings=ReconstructSettings(iterations=min(1, args.iterations)), backend=backend)
        times, warp_labels = CallTimes(main_only=args.main), []
        imported = set(sys.modules)
        try:
            instrument(times, backend, outermost=args.main)
            if args.warp:
                warp_labels = instrument_warp(times)
            start = time.perf_counter()
            result = reconstruct(dataset, settings=ReconstructSettings(iterations=args.iterations), backend=backend)
            total = time.perf_counter() - start
        finally:
            times.restore()
        imported = sorted({name.split(".")[0] for name in set(sys.modules) - imported if not name.startswith("_")})
    start_kind = "the process's first reconstruction" if args.fresh else "the measured start"
    print(f"{args.scene} from {start_kind} on {backend.name} {backend.device}: {total:.2f} s, "
          f"{result.iterations} iterations\n")
    if args.fresh:
        print(f"packages with modules first imported during the run: {', '.join(imported) or 'none'}\n")
    if args.main:
        times.totals["(the rest of the main thread)"] = [1, total - sum(s for _, s in times.totals.values())]
    print(times.table(total, [label for label in times.totals if label not in warp_labels]))
    if warp_labels:
        print("\nWarp's own calls (the outermost in each thread; any thread):\n")
        print(times.table(total, warp_labels))
    return 0


if __name__ == "__main__":
    sys.exit(main())
