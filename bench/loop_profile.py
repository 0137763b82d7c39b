"""Where a reconstruction's time goes, without a sampling profiler, one command:

    python bench/loop_profile.py [--scene NAME] [--backend B] [--device D] [--iterations T]
                                 [--seed S]

Simulates the scene (noisy, ``--seed``), reconstructs it once with one iteration (none with
``--iterations 0``; to fill the kernel caches), then once with ``--iterations`` while the loop's main functions are wrapped
to count their calls and sum their wall time (inclusive: a function's time holds that of the
functions it calls, so the rows overlap). Prints one Markdown table, slowest first: calls,
seconds, share of the run and milliseconds per call. A sampling profiler (py-spy) slowed the
H100 run 1.5–3.5 times and so hid where the run waited (bench/notes.md); these wrappers cost
microseconds per call.
"""

from __future__ import annotations

import argparse
import collections
import functools
import importlib.util
import sys
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
#: Functions that other modules import by name: those modules get the wrapper too.
REBOUND = {"estimate_pose": ("fsswarp.reconstruction",), "refine_shape": ("fsswarp.reconstruction",),
           "carve": ("fsswarp.reconstruction",)}

_spec = importlib.util.spec_from_file_location("bench_profiling", Path(__file__).resolve().parent / "profiling.py")
profiling = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(profiling)


class CallTimes(profiling.Patches):
    """Calls and inclusive wall seconds per wrapped function (``totals``: label -> [calls, s])."""

    def __init__(self):
        super().__init__()
        self.totals = collections.defaultdict(lambda: [0, 0.0])

    def wrap(self, owner, name: str, label: str):
        """Replace ``owner.name`` by a timed wrapper, and return it."""
        original = getattr(owner, name)

        @functools.wraps(original)
        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                entry = self.totals[label]
                entry[0] += 1
                entry[1] += time.perf_counter() - start

        self.replace(owner, name, timed)
        return timed

    def table(self, total: float) -> str:
        """Markdown: one row per function, slowest first; shares of ``total`` seconds."""
        lines = ["| function | calls | s | share | ms per call |", "|---|---|---|---|---|"]
        for label, (calls, seconds) in sorted(self.totals.items(), key=lambda item: -item[1][1]):
            lines.append(f"| `{label}` | {calls} | {seconds:.3f} | {100 * seconds / total:.1f}% | "
                         f"{1e3 * seconds / calls:.2f} |")
        return "\n".join(lines)


def instrument(times: CallTimes, backend) -> None:
    """Wrap ``WRAPPED`` (and rebind the names in ``REBOUND``) and ``backend``'s ``BACKEND_METHODS``."""
    import importlib

    wrapped = {}
    for module_name, owner_name, names in WRAPPED:
        module = importlib.import_module(module_name)
        owner = getattr(module, owner_name) if owner_name else module
        for name in names:
            label = f"{owner_name}.{name}" if owner_name else name
            wrapped[label] = times.wrap(owner, name, label)
    for name, modules in REBOUND.items():
        for module_name in modules:
            times.replace(importlib.import_module(module_name), name, wrapped[name])
    for name in BACKEND_METHODS:
        if hasattr(type(backend), name):
            times.wrap(type(backend), name, f"backend.{name}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    profiling.add_scene_options(parser)
    parser.add_argument("--iterations", type=int, default=10)
    args = parser.parse_args(argv)
    from fsswarp.errors import check_integer
    from fsswarp.reconstruction import ReconstructSettings, reconstruct

    backend = profiling.scene_backend(args, "loop_profile", lambda: check_integer("--iterations", args.iterations, 0))
    if backend is None:
        return 2
    with profiling.simulated(args, backend) as dataset:
        reconstruct(dataset, settings=ReconstructSettings(iterations=min(1, args.iterations)), backend=backend)
        times = CallTimes()
        instrument(times, backend)
        try:
            start = time.perf_counter()
            result = reconstruct(dataset, settings=ReconstructSettings(iterations=args.iterations), backend=backend)
            total = time.perf_counter() - start
        finally:
            times.restore()
    print(f"{args.scene} from the measured start on {backend.name} {backend.device}: {total:.2f} s, "
          f"{result.iterations} iterations\n")
    print(times.table(total))
    return 0


if __name__ == "__main__":
    sys.exit(main())
