"""Device fixtures shared by the test modules.

``backend`` runs a test once per backend and device: warp-cpu, opencl-cpu, and (marked
``gpu``) warp-cuda and opencl-gpu; a device this machine lacks is skipped with the reason.
``backend_for_label("opencl-cpu")`` gives one by label (tests comparing two backends).
``wp_device`` runs a test once per Warp device ("cpu", and "cuda:0" marked ``gpu``). The names
``device``, ``platform`` and ``ctx_factory`` belong to pyopencl's test helpers: do not use them.
"""

from __future__ import annotations

import functools

import pytest
from hypothesis import settings

from fsswarp.backends import describe_backends, get_backend

# Property tests draw the same examples on every run and machine (the suite is deterministic;
# raise max_examples locally to search wider), with no example database and no deadline
# (CI machines are slow and shared).
settings.register_profile("fsswarp", derandomize=True, database=None, deadline=None)
settings.load_profile("fsswarp")


def pytest_sessionstart(session):
    """Compile the package's bytecode once: the suite starts hundreds of child processes (the
    command line; mesh, figure and truth workers), and where Python writes no bytecode
    (PYTHONDONTWRITEBYTECODE, as on this project's CI-class machine) each compiled every module
    it imported (~0.2-0.3 s a start there)."""
    import compileall
    from pathlib import Path

    import fsswarp

    compileall.compile_dir(Path(fsswarp.__file__).parent, quiet=1)


#: Labels of the ``backend`` fixture: "<backend>-<device kind>".
BACKEND_LABELS = [
    pytest.param("warp-cpu", id="warp-cpu"),
    pytest.param("opencl-cpu", id="opencl-cpu"),
    pytest.param("warp-cuda", id="warp-cuda", marks=pytest.mark.gpu),
    pytest.param("opencl-gpu", id="opencl-gpu", marks=pytest.mark.gpu),
]


@functools.cache
def _rows() -> tuple[dict, ...]:
    return tuple(describe_backends())


def backend_for(label: str):
    """The backend a label names ("warp-cpu", "opencl-gpu", ...), or skip the test."""
    name, where = label.split("-")
    kind = "cpu" if where == "cpu" else "gpu"
    for row in _rows():
        if row["backend"] == name and row["kind"] == kind and row["available"]:
            return get_backend(name, row["device"] if name == "warp" else row["index"])
    notes = "; ".join(r["note"] for r in _rows() if r["backend"] == name and r["note"])
    pytest.skip(f"no {label} device here" + (f" ({notes})" if notes else ""))


@pytest.fixture(scope="session")
def backend_for_label():
    """``backend_for`` as a fixture: label -> backend, or skip (for tests that need two)."""
    return backend_for


@pytest.fixture(scope="session", params=BACKEND_LABELS)
def backend(request):
    """Every backend and device kind (kernels compile once per session)."""
    return backend_for(request.param)


@pytest.fixture(scope="session", params=["cpu", pytest.param("cuda:0", marks=pytest.mark.gpu)])
def wp_device(request) -> str:
    """Every Warp device alias ("cpu", "cuda:0")."""
    rows = [r for r in _rows() if r["backend"] == "warp" and r["available"]]
    if not rows:
        pytest.skip("warp-lang is not installed")
    if request.param not in {r["device"] for r in rows}:
        pytest.skip(f"no Warp device {request.param} here")
    return request.param


@pytest.fixture(scope="session")
def coral_one(tmp_path_factory):
    """coral-one simulated once per session with noise (seed 1, default render settings, the
    OpenCL backend when present): the loaded Dataset (its ``root`` is the folder)."""
    from fsswarp.simulation import simulate

    return simulate("coral-one", tmp_path_factory.mktemp("carve") / "coral-one", seed=1, backend=_simulating_backend())


@pytest.fixture(scope="session")
def coral_south(tmp_path_factory):
    """coral-one seen from its south position alone (8 views, 5 of them optimized; seed 1, as
    ``coral_one``): for the tests of commands' plumbing, whose runs then take about half as long."""
    from fsswarp.scenes import builtin_scene
    from fsswarp.simulation import simulate

    return simulate(builtin_scene("coral-one", positions="S"), tmp_path_factory.mktemp("carve") / "coral-south",
                    seed=1, backend=_simulating_backend())


def _simulating_backend():
    """The session datasets' backend: OpenCL on a CPU device where present, else fsswarp's choice."""
    rows = [r for r in _rows() if r["backend"] == "opencl" and r["kind"] == "cpu" and r["available"]]
    return get_backend("opencl", rows[0]["index"]) if rows else get_backend()
