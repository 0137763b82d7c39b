"""Kernel benchmarks of ``fsswarp bench`` (DESIGN §12; method in docs/benchmarks.md).

``harness``: timing, size sweeps under a budget, records, the machine probe and physical
limits; ``families``: what each family launches and its operation counts, and ``run_suite``;
``report``: the Markdown tables and figures of a run and of bench/RESULTS.md.
"""

from .families import FAMILIES, check_options, coral_batch, run_suite
from .harness import cpu_info
from .report import machine_markdown, markdown, plot_family, slowest

__all__ = ["FAMILIES", "check_options", "coral_batch", "cpu_info", "machine_markdown", "markdown", "plot_family",
           "run_suite", "slowest"]
