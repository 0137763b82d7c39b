"""Pieces shared by the profile scripts of bench/ (exact_profile, refine_profile, mesh_profile):
the CPU's name for a record and the per-stage Markdown table of medians."""

from __future__ import annotations


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
