"""OpenCL programs: the C sources of the top-level ``kernels/`` and their builds.

The OpenCL C sources (OpenCL 1.2, float32) ship with the wheel as ``fsswarp/kernels`` (a
hatchling force-include of the repository's top-level ``kernels/``); an editable install
reads them from the repository. Our own ``#include "x.h"`` lines are inlined here before
building, because include paths are not portable across ICDs. Programs are built once per
context and kept; pyopencl's on-disk binary cache stays on (PoCL and NVIDIA cache the builds
themselves), and each build is recorded for ``fsswarp info`` (``backends/builds.py``, read by ``backends/cache.py``).
"""

from __future__ import annotations

import functools
import importlib.resources
import re
import tempfile
import warnings
from pathlib import Path

import pyopencl as cl
from pyopencl.tools import first_arg_dependent_memoize

from ..builds import record_build
from ..constants import opencl_defines

#: Options of every build: the shared constants (``constants.opencl_defines``). No fast-math:
#: results must match the Warp backend.
BUILD_OPTIONS: tuple[str, ...] = opencl_defines()
#: Work-group size the global size of a launch is rounded up to.
GROUP = 64

_INCLUDE = re.compile(r'^[ \t]*#[ \t]*include[ \t]*"([^"]+)"[ \t]*$', re.MULTILINE)


class KernelBuildError(RuntimeError):
    """An OpenCL program failed to build; the message names the file, device, options, the
    build log and a saved copy of the source as built."""


# --- sources -----------------------------------------------------------------------------------
@functools.cache
def kernel_dir() -> Path:
    """The folder holding the .cl/.h sources: ``fsswarp/kernels`` in a wheel, else the
    repository's top-level ``kernels/`` (editable install)."""
    packaged = importlib.resources.files("fsswarp") / "kernels"
    if packaged.is_dir():
        return Path(str(packaged))
    repo = Path(__file__).resolve().parents[3] / "kernels"
    if repo.is_dir():
        return repo
    raise FileNotFoundError(f"fsswarp's OpenCL kernels are missing: neither {packaged} nor {repo} "
                            "exists; reinstall fsswarp")


@functools.cache
def kernel_source(name: str) -> str:
    """Source of ``kernels/<name>`` with our ``#include "x.h"`` lines inlined (once each)."""
    return _inline(name, kernel_dir(), set())


def _inline(name: str, folder: Path, seen: set[str]) -> str:
    path = folder / name
    if not path.is_file():
        raise FileNotFoundError(f"OpenCL source {path} does not exist")
    seen.add(name)
    text = path.read_text(encoding="utf-8")

    def include(match: re.Match) -> str:
        header = match.group(1)
        if header in seen:
            return f"/* {header}: already included */"
        body = _inline(header, folder, seen)
        return f"/* ---- begin {header} ---- */\n{body}\n/* ---- end {header} ---- */"

    return _INCLUDE.sub(include, text)


# --- programs ----------------------------------------------------------------------------------
@first_arg_dependent_memoize
def program(context: cl.Context, name: str, options: tuple[str, ...] = BUILD_OPTIONS) -> cl.Program:
    """``kernels/<name>`` built for ``context`` (memoized per context, name and options), the
    build recorded for ``fsswarp info`` (``builds.record_build``)."""
    built = build(context, kernel_source(name), options, label=name)
    record_build(context.devices, options, kernel_source(name))
    return built


def build(context: cl.Context, source: str, options: tuple[str, ...], *, label: str) -> cl.Program:
    """Build ``source``; on failure raise KernelBuildError with the options, the build log and
    a path to a saved copy of the source. A successful build's log is dropped: vendor
    compilers (NVIDIA's among them) print informational logs that pyopencl would raise as
    ``CompilerWarning``."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", cl.CompilerWarning)
            return cl.Program(context, source).build(options=list(options))
    except cl.Error as err:
        with tempfile.NamedTemporaryFile("w", prefix=f"fsswarp-{Path(label).stem}-", suffix=".cl",
                                         delete=False, encoding="utf-8") as saved:
            saved.write(source)
        devices = "; ".join(d.name.strip() for d in context.devices)
        raise KernelBuildError(
            f"building OpenCL program {label} for {devices} failed "
            f"(options: {' '.join(options) or 'none'}; source saved as {saved.name}):\n{err}"
        ) from None
