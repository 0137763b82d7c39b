"""Markdown tables and log-log figures of ``fsswarp bench`` runs: ``bench.md`` of one run and
the sections of bench/RESULTS.md (``python bench/report.py``).

A run is the dict of ``run_suite`` (the ``bench.json`` of one run): {schema, date, command,
quick, budget_s, repeat, machine, records}; a record is one timed or skipped point of one
family, kernel, mode, backend and device (fsswarp/benchmark/harness.py). Times in seconds,
throughputs in work units per second.

- ``markdown(run)``: one table per family, each figure beside its physical limit.
- ``machine_markdown(run)``: the machine, the command and every limit profile.
- ``slowest(records)``: the fsswarp kernels furthest from their limits.
- ``plot_family(records, family, path)``: time against size, log-log, limits dashed (PNG).
"""

from __future__ import annotations

from collections.abc import Sequence

from .families import FAMILIES, PEERS
from .harness import format_seconds, format_value

FAMILY_TITLES = {"raycast": "Ray casting (rays/s; fixed ray set, icosphere triangles swept)",
                 "synthesis": "Image synthesis (views/s; coral-one, 96 × 512, samples (2, 64))",
                 "carving": "Space carving (voxel × views/s; 16 views)",
                 "pose": "Depth and tilt grid evaluation (cell × views/s; 16 views)",
                 "reconstruction": "End-to-end reconstruction (coral-one, 16 views)"}


def markdown(run: dict, *, heading: str = "##") -> str:
    """Tables of a run: one per family, every record with its median (min–max), throughput,
    limit and the fraction of it reached."""
    lines = []
    for family in FAMILIES:
        rows = [r for r in run["records"] if r["family"] == family]
        if not rows:
            continue
        lines += ["", f"{heading} {FAMILY_TITLES[family]}", "",
                  "| kernel | mode | backend / device | size | median (min–max), runs | throughput | "
                  "limit (bound) | fraction of limit |", "|---|---|---|---|---|---|---|---|"]
        for r in rows:
            who = f"{r['backend']} {r['device'][:48]}"
            size = f"{r['sweep']} {format_value(r['x'])}" if r.get("x") is not None else "—"
            if r.get("skipped"):
                lines.append(f"| {r['kernel']} | {r['mode']} | {who} | {size} | skipped: {r['skipped']['reason']} "
                             "| — | — | — |")
                continue
            extra = "".join(f"; {format_value(v)} {k}/s" for k, v in r.get("rates", {}).items())
            limit = r["limit"]
            lines.append(f"| {r['kernel']} | {r['mode']} | {who} | {size} | {format_seconds(r['median_s'])} "
                         f"({format_seconds(r['min_s'])}–{format_seconds(r['max_s'])}), {r['repeat']} | "
                         f"{format_value(r['throughput'])} {r['throughput_unit']}{extra} | "
                         f"{format_seconds(limit['limit_s'])} ({limit['bound']}) | {limit['fraction']:.3g} |")
    return "\n".join(lines).lstrip("\n") + "\n"


def machine_markdown(run: dict) -> str:
    """The machine, the command, the date and every limit profile of a run, as Markdown."""
    m = run["machine"]
    cpu = m["cpu"]
    lines = [f"- machine: {m['host']} ({m['system']}), CPU {cpu['model']}, {cpu['logical_cpus']} logical CPUs",
             f"- command: `{run['command']}`", f"- date: {run['date']}",
             f"- budget {run['budget_s']:g} s per point, {run['repeat']} timed runs per figure after a warm-up"
             + (" (quick sizes)" if run["quick"] else ""),
             "- versions: " + ", ".join(f"{k} {v}" for k, v in m["versions"].items()),
             "", "| profile | device | memory bandwidth | peak | host link up / down |", "|---|---|---|---|---|"]
    for key, p in m["profiles"].items():
        bw = f"{p['bandwidth_Bps'] / 1e9:.3g} GB/s ({p['bandwidth_source']}"
        bw += f"; measured copy {p['measured_copy_Bps'] / 1e9:.3g} GB/s)" if "measured_copy_Bps" in p else ")"
        peak = f"{p['peak_ops'] / 1e9:.4g} Gop/s ({p['peak_source']})" if p.get("peak_ops") else "—"
        link = (f"{p['link_up_Bps'] / 1e9:.3g} / {p['link_down_Bps'] / 1e9:.3g} GB/s ({p['link_source']})"
                if p.get("link_up_Bps") else "—")
        lines.append(f"| {key} | {p['name']} | {bw} | {peak} | {link} |")
    return "\n".join(lines) + "\n"


def slowest(records: Sequence[dict], count: int = 3) -> list[dict]:
    """The ``count`` fsswarp kernel families furthest from their limits: per (family, backend,
    device), the lowest fraction of its modes at the largest size measured, lowest first."""
    largest: dict[tuple, dict] = {}
    for r in records:
        if r.get("skipped") or r["backend"] in {peer.name for peer in PEERS} or r["family"] == "reconstruction":
            continue
        key = (r["family"], r["backend"], r["device"])
        best = largest.get(key)
        if best is None or r["x"] > best["x"] or (r["x"] == best["x"]
                                                  and r["limit"]["fraction"] < best["limit"]["fraction"]):
            largest[key] = r
    return sorted(largest.values(), key=lambda r: r["limit"]["fraction"])[:count]


def plot_family(records: Sequence[dict], family: str, path, *, title: str = ""):
    """Log-log time against work size of one family: one line per kernel, mode, backend and
    device (label), its limit dashed in the same colour. Returns the path, or None without
    measured records."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..figures import save_figure

    series: dict[str, list[dict]] = {}
    for r in records:
        if r["family"] == family and not r.get("skipped"):
            device = "PoCL" if "Portable Computing Language" in r["device"] else r["device"][:28]
            series.setdefault(f"{r['backend']} {device}, {r['kernel']} ({r['mode']})", []).append(r)
    if not series:
        return None
    fig, ax = plt.subplots(figsize=(8.5, 5.5))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    styles = ["o", "s", "^", "v", "D", "x", "P", "*"]
    for k, (label, rows) in enumerate(sorted(series.items())):
        rows = sorted(rows, key=lambda r: r["x"])
        x = [r["x"] for r in rows]
        colour = colours[k % len(colours)]
        ax.plot(x, [r["median_s"] for r in rows], marker=styles[k // len(colours) % len(styles)], color=colour,
                label=label)
        ax.plot(x, [r["limit"]["limit_s"] for r in rows], linestyle="--", color=colour, linewidth=0.8)
    sweep_name = next(iter(series.values()))[0]["sweep"]
    if all(r["x"] > 0 for rows in series.values() for r in rows):
        ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(sweep_name)
    ax.set_ylabel("median time (s); dashed: physical limit")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=6, loc="best")
    return save_figure(fig, path, title or FAMILY_TITLES[family])
