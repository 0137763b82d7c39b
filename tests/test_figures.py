"""Figure drawing in child processes (fsswarp.figures.FigureDrawer) and its setting."""

import os
import time

import pytest
import trimesh

from fsswarp.atomic import write_bytes
from fsswarp.cli import main
from fsswarp.errors import InputError
from fsswarp.figures import FigureDrawer, FigureWarning, carve_figure, draw_here, figure_workers


@pytest.fixture(scope="module")
def drawer():
    drawer = FigureDrawer(2)
    yield drawer
    drawer.close()


def test_figures_drawn_in_processes_equal_those_drawn_here(drawer, tmp_path):
    """The same PNG bytes, whichever process draws; the batch waits for every figure."""
    meshes = [trimesh.creation.icosphere(subdivisions=2, radius=r) for r in (0.1, 0.15, 0.2)]
    truth = trimesh.creation.box((0.2, 0.25, 0.3))
    for k, mesh in enumerate(meshes):
        carve_figure(mesh, tmp_path / f"here{k}.png", truth=truth, title=f"mesh {k}")
    with drawer.batch() as draw:
        for k, mesh in enumerate(meshes):
            draw(carve_figure, mesh, tmp_path / "drawn" / f"{k}.png", truth=truth, title=f"mesh {k}")
    for k in range(len(meshes)):
        drawn = (tmp_path / "drawn" / f"{k}.png").read_bytes()
        assert drawn[:8] == b"\x89PNG\r\n\x1a\n" and drawn == (tmp_path / f"here{k}.png").read_bytes()
    assert (tmp_path / "here0.png").read_bytes() != (tmp_path / "here1.png").read_bytes()


def test_a_failed_figure_raises_its_error_after_the_others_are_drawn(drawer, tmp_path):
    (tmp_path / "folder.png").mkdir()
    with pytest.raises(InputError, match="folder.png: is a folder"):
        with drawer.batch() as draw:
            draw(write_bytes, tmp_path / "folder.png", b"x")
            draw(write_bytes, tmp_path / "fine.png", b"y")
    assert (tmp_path / "fine.png").read_bytes() == b"y"
    with drawer.batch() as draw:  # the processes carry on
        draw(write_bytes, tmp_path / "after.png", b"z")
    assert (tmp_path / "after.png").read_bytes() == b"z"


def test_an_error_in_the_batch_leaves_no_figure_running(drawer, tmp_path):
    """Leaving by an error cancels the figures not started and waits for the ones being drawn:
    afterwards no process writes into the (removed) output folder."""
    with pytest.raises(RuntimeError, match="stop"):
        with drawer.batch() as draw:
            for k in range(8):
                draw(write_bytes, tmp_path / f"{k}.bin", bytes(2 ** 20))
            raise RuntimeError("stop")
    written = sorted(os.listdir(tmp_path))
    time.sleep(0.5)
    assert sorted(os.listdir(tmp_path)) == written and not any(name.endswith(".tmp") for name in written)


def test_workers_setting(monkeypatch):
    monkeypatch.setenv("FSSWARP_FIGURE_WORKERS", "0")
    assert figure_workers() == 0
    with FigureDrawer().batch() as draw:  # no process: figures are drawn at once, here
        assert draw is draw_here
    monkeypatch.setenv("FSSWARP_FIGURE_WORKERS", " 3 ")
    assert figure_workers() == 3
    monkeypatch.delenv("FSSWARP_FIGURE_WORKERS")
    assert figure_workers() == min(4, len(os.sched_getaffinity(0)))
    for bad in ("-1", "two", "1.5", "65"):
        monkeypatch.setenv("FSSWARP_FIGURE_WORKERS", bad)
        with pytest.raises(InputError, match=f"FSSWARP_FIGURE_WORKERS = '{bad}': must be an integer from 0 to 64"):
            figure_workers()


def test_a_bad_workers_setting_is_a_user_mistake(monkeypatch, tmp_path, capsys, coral_one):
    monkeypatch.setenv("FSSWARP_FIGURE_WORKERS", "many")
    assert main(["-q", "reconstruct", str(coral_one.root), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert err == "fsswarp: error: FSSWARP_FIGURE_WORKERS = 'many': must be an integer from 0 to 64\n"
    assert not (tmp_path / "r").exists()



def test_figures_are_drawn_here_where_processes_cannot_start(monkeypatch, tmp_path):
    """A system where the pool's semaphores or processes are not available (an OSError): one
    warning, and the figures are drawn in this process."""
    import concurrent.futures

    def refuse(*args, **kwargs):
        raise OSError(38, "Function not implemented")

    monkeypatch.setattr(concurrent.futures, "ProcessPoolExecutor", refuse)
    with pytest.warns(FigureWarning, match=r"figure processes could not start \(\[Errno 38\] Function not "
                                           r"implemented\); drawing the figures in this process"):
        drawer = FigureDrawer(2)
    with drawer.batch() as draw:
        assert draw is draw_here
        draw(write_bytes, tmp_path / "a.bin", b"a")
    assert (tmp_path / "a.bin").read_bytes() == b"a"
    drawer.close()
