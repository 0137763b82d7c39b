"""The pose step's (D, β) grid end to end, per launch size, one command:

    python bench/grid_profile.py [--scene NAME] [--backend B] [--device D] [--seed S]
                                 [--sides N ...] [--launch-mib M ...] [--repeat R] [--kernels]
                                 [--timeline] [--gaps]

Simulates the scene (noisy, ``--seed``) with every view to optimize, locates its true model at
the true (D, β) (as ``fsswarp bench``'s pose family does), and times ``ViewComparison.surrogate``
over side × side cells of ± 5 cm × ± 2° for each launch size (``PoseSettings.launch_bytes``,
default 4096 MiB as the loop and 16384 MiB as ``fsswarp bench``), after one untimed call. Prints
one Markdown table: cells per launch, the median (min–max) of ``--repeat`` calls, and a checksum
of the costs (to compare code before and after a change: the same costs, the same checksum; a
pair's costs do not depend on the launch it shares, so every launch size gives the same one).
``--kernels`` (Warp on a CUDA device): the GPU time of each kernel and copy over one more call
(Warp's activity timing); the wall time less the GPU's is host work the GPU waited for.
``--timeline``: the host's calls in one more call, from its start: each launch's plan
(``plan_pairs``; on a GPU in the planning thread), render and costs, with the thread that made
them; a plan that ends after the GPU finished the launch before leaves the GPU idle.
``--gaps`` (Warp on a CUDA device): one more call with a timing event recorded on the stream
before and after each of fsswarp's kernel launches: when the GPU began the call's first kernel,
the kernels' own time, the time between them (copies, zeroing and waiting for the host), the
part of that the GPU spent waiting for the host to issue the next launch, and the call's end
after the last kernel, with each launch where the GPU waited for the host.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import tempfile
from pathlib import Path

_spec = importlib.util.spec_from_file_location("bench_profiling", Path(__file__).resolve().parent / "profiling.py")
profiling = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(profiling)


def kernel_times(problem, depths, tilts) -> list[tuple[str, int, float]]:
    """(kernel or copy, calls, GPU ms) over one ``surrogate`` call, slowest first (Warp CUDA)."""
    import warp as wp

    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    problem.surrogate(depths, tilts)
    wp.synchronize()
    totals: dict[str, list] = {}
    for record in wp.timing_end():
        entry = totals.setdefault(record.name.split("(")[0], [0, 0.0])
        entry[0] += 1
        entry[1] += record.elapsed
    return sorted(((name, calls, ms) for name, (calls, ms) in totals.items()), key=lambda row: -row[2])


def timeline(problem, depths, tilts) -> tuple[float, list[tuple[float, float, str, str]]]:
    """(the call's seconds, [(start s from the call's start, seconds, thread, call)]) of the
    host's plan, render and cost calls (``plan_pairs``, ``render_planned``, ``view_costs``) in
    one ``surrogate`` call, in order of start."""
    import threading
    import time

    patches, stamps, start = profiling.Patches(), [], 0.0

    def stamp(owner, name: str) -> None:
        original = getattr(owner, name)

        def timed(*args, **kwargs):
            begin = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                stamps.append((begin - start, time.perf_counter() - begin, threading.current_thread().name, name))

        patches.replace(owner, name, timed)

    for owner, name in ((problem, "plan_pairs"), (problem.backend, "render_planned"), (problem.backend, "view_costs")):
        stamp(owner, name)
    try:
        start = time.perf_counter()
        problem.surrogate(depths, tilts)
        return time.perf_counter() - start, sorted(stamps)
    finally:
        patches.restore()


def gaps(problem, depths, tilts) -> tuple[float, list[tuple[str, float, float, float]]]:
    """(the call's seconds, [(kernel, host issue s, GPU start s, GPU end s)]) of one ``surrogate``
    call, times from the call's start, for each launch of ``fsswarp.backends.warp.backend._launch``
    (a timing event recorded on the stream before and after it; the first event, recorded at the
    call's start on an idle GPU, aligns the GPU's clock with the host's)."""
    import time

    import warp as wp

    from fsswarp.backends.warp import backend as warp_backend

    patches, marks, device = profiling.Patches(), [], problem.backend.device
    original = warp_backend._launch

    def marked(kernel, dim, **kwargs):
        before, after = wp.Event(device, enable_timing=True), wp.Event(device, enable_timing=True)
        issued = time.perf_counter()
        wp.record_event(before)
        original(kernel, dim, **kwargs)
        wp.record_event(after)
        marks.append((kernel.key, issued, before, after))

    wp.synchronize()
    origin = wp.Event(device, enable_timing=True)
    patches.replace(warp_backend, "_launch", marked)
    try:
        start = time.perf_counter()
        wp.record_event(origin)
        problem.surrogate(depths, tilts)
        total = time.perf_counter() - start
    finally:
        patches.restore()
    wp.synchronize()
    return total, [(name, issued - start, 1e-3 * wp.get_event_elapsed_time(origin, before),
                    1e-3 * wp.get_event_elapsed_time(origin, after)) for name, issued, before, after in marks]


def gap_summary(total: float, marks: list[tuple[str, float, float, float]]) -> str:
    """Markdown lines of :func:`gaps`' marks: the GPU's first start, its kernels' own time, the
    time between kernels and the part of it waited for the host, the end after the last kernel,
    and each launch that the GPU waited for (more than 0.1 ms)."""
    if not marks:
        return "no kernel launched"
    own = sum(end - begin for _, _, begin, end in marks)
    between = waited = 0.0
    rows = []
    for (_, _, _, previous), (name, issued, begin, end) in zip(marks, marks[1:]):
        between += max(begin - previous, 0.0)
        wait = min(max(issued - previous, 0.0), max(begin - previous, 0.0))
        waited += wait
        if wait > 1e-4:
            rows.append(f"| {name} | {1e3 * issued:.2f} | {1e3 * begin:.2f} | {1e3 * wait:.2f} |")
    lines = [f"call {1e3 * total:.1f} ms: the first kernel began at {1e3 * marks[0][2]:.2f} ms; "
             f"{len(marks)} kernels {1e3 * own:.1f} ms; between them {1e3 * between:.1f} ms, of which the GPU "
             f"waited for the host {1e3 * waited:.1f} ms; the call ended {1e3 * (total - marks[-1][3]):.2f} ms "
             "after the last kernel"]
    if rows:
        lines += ["", "| kernel the GPU waited for | issued ms | began ms | waited ms |", "|---|---|---|---|", *rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    profiling.add_scene_options(parser)
    parser.add_argument("--sides", type=int, nargs="+", default=[64, 256])
    parser.add_argument("--launch-mib", type=int, nargs="+", default=[4096, 16384])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--kernels", action="store_true")
    parser.add_argument("--timeline", action="store_true")
    parser.add_argument("--gaps", action="store_true")
    args = parser.parse_args(argv)
    import numpy as np

    from fsswarp.benchmark.families import every_view_scene, grid_cells
    from fsswarp.benchmark.harness import measure
    from fsswarp.compare import PoseSettings, ViewComparison
    from fsswarp.errors import check_integer

    def check() -> None:
        check_integer("--repeat", args.repeat, 1)
        for side in args.sides:
            check_integer("--sides", side, 1)
        for size in args.launch_mib:
            check_integer("--launch-mib", size, 1)

    backend = profiling.scene_backend(args, "grid_profile", check)
    if backend is None:
        return 2
    with tempfile.TemporaryDirectory() as folder:
        dataset, model = every_view_scene(backend, folder, args.scene, args.seed)
    truth = dataset.manifest.truth
    print(f"{args.scene} (seed {args.seed}), {len(dataset.images)} views, on {backend.name} {backend.device}\n")
    print("| launch | side | cells per launch | median ms | min–max ms | checksum |\n|---|---|---|---|---|---|")
    kernels, timelines, gapped = [], [], []
    for size in args.launch_mib:
        problem = ViewComparison(dataset, settings=PoseSettings(launch_bytes=size << 20), backend=backend).use(
            model, truth.depth, truth.tilt)
        for side in args.sides:
            depths, tilts = grid_cells(truth, side)
            costs = problem.surrogate(depths, tilts)  # also the warm-up
            timing = measure(lambda: problem.surrogate(depths, tilts), args.repeat, warmup=0)  # noqa: B023
            per = problem.grid_launches(problem.settings.samples)[3]
            print(f"| {size} MiB | {side} | {per} | {1e3 * timing['median_s']:.1f} | "
                  f"{1e3 * timing['min_s']:.1f}–{1e3 * timing['max_s']:.1f} | {float(np.nansum(costs)):.9g} |",
                  flush=True)
            if args.kernels and backend.name == "warp" and backend.is_gpu:
                kernels.append((size, side, kernel_times(problem, depths, tilts)))
            if args.gaps and backend.name == "warp" and backend.is_gpu:
                gapped.append((size, side, *gaps(problem, depths, tilts)))
            if args.timeline:
                timelines.append((size, side, *timeline(problem, depths, tilts)))
    if args.kernels and not kernels:
        print("\n--kernels: the GPU's times need Warp on a CUDA device")
    if args.gaps and not gapped:
        print("\n--gaps: the GPU's times need Warp on a CUDA device")
    for size, side, rows in kernels:
        print(f"\n{size} MiB, {side} × {side}: GPU {sum(ms for _, _, ms in rows):.1f} ms\n\n"
              "| kernel or copy | calls | GPU ms |\n|---|---|---|")
        for name, calls, ms in rows:
            print(f"| {name} | {calls} | {ms:.2f} |")
    for size, side, total, marks in gapped:
        print(f"\n{size} MiB, {side} × {side}: the GPU's gaps in one call\n\n{gap_summary(total, marks)}")
    for size, side, total, stamps in timelines:
        print(f"\n{size} MiB, {side} × {side}: one call's host calls, {1e3 * total:.1f} ms\n\n"
              "| start ms | ms | thread | call |\n|---|---|---|---|")
        for begin, seconds, thread, name in stamps:
            print(f"| {1e3 * begin:.1f} | {1e3 * seconds:.1f} | {thread} | {name} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
