"""Figure drawing in child processes (fsswarp.figures.FigureDrawer) and its setting."""

import os
import re
import time

import pytest
import trimesh
from figure_checks import assert_laid_out, captured_figures

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
    assert figure_workers() == min(8, len(os.sched_getaffinity(0)))
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


# --- what the figures show ------------------------------------------------------------------------

def small_sonar():
    from fsswarp.sonar import SonarSpec

    return SonarSpec.from_degrees(beams=32, bins=128, azimuth_fov_deg=28.8, range_min_m=1.0, range_max_m=3.0)


def test_layers_zoom_on_the_noise_free_echoes_and_share_a_colour_bar(monkeypatch, tmp_path):
    """The noisy data layer fills the window; the zoom follows the clean layers' echo (range
    2.0 m, azimuth 0) all the same, and one colour bar names the scale."""
    import numpy as np

    from fsswarp.figures import layers_figure

    sonar = small_sonar()
    echo = np.zeros((sonar.bins, sonar.beams), np.float32)
    row = int(np.argmin(np.abs(sonar.bin_ranges - 2.0)))
    echo[row - 1: row + 2, 15:17] = 1.0
    noisy = echo + np.random.default_rng(0).uniform(0.05, 0.2, echo.shape).astype(np.float32)
    kept = captured_figures(monkeypatch)
    path = layers_figure({"S0": np.stack([echo, noisy])}, sonar, tmp_path / "layers.png", layers=("object", "data"))
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    fig = kept[0]
    beam_bin = [ax for ax in fig.axes if ax.get_ylabel() == "range (m)"]
    assert len(beam_bin) == 2
    for ax in beam_bin:
        low, high = ax.get_ylim()
        assert 1.7 < low < 2.0 < high < 2.3, (low, high)
        assert ax.xaxis.get_ticklabels()[0].get_fontsize() >= 7
    assert [ax.get_xlabel() for ax in fig.axes if "dB" in ax.get_xlabel()] == ["dB below the brightest pixel of all views"]
    assert all(ax.get_xlabel().endswith(")") for ax in fig.axes if ax.get_xlabel() and "dB" not in ax.get_xlabel())


def fake_views(sonar, count):
    """``count`` EnhancedView-like results with an object, a ghost and a mirror region."""
    import numpy as np

    from fsswarp.enhancement import EnhancedView

    shape = (sonar.bins, sonar.beams)
    views = {}
    for k in range(count):
        region = np.zeros(shape, bool)
        region[60:70, 10:20] = True
        ghost = np.roll(region, 3, axis=0)
        mirror = np.roll(region, 6, axis=1)
        image = np.random.default_rng(k).uniform(0.01, 1.0, shape).astype(np.float32)
        views[f"V{k}"] = (image, EnhancedView(enhanced=image * 0.5, ghost=image * 0.2, synthetic=image,
                                              object_region=region, ghost_region=ghost, mirror_region=mirror,
                                              overlap=region & (ghost | mirror), lut=np.zeros((2, 4)),
                                              background=0.01))
    return views


def test_enhance_names_its_region_colours_and_its_titles_do_not_overlap(monkeypatch, tmp_path):
    from fsswarp.figures import REGIONS, enhance_figure

    sonar = small_sonar()
    views = fake_views(sonar, 3)
    kept = captured_figures(monkeypatch)
    enhance_figure({n: image for n, (image, _) in views.items()}, {n: r for n, (_, r) in views.items()}, sonar,
                   tmp_path / "enhance.png", title="coral-one: ghost removal with a model of a long name, to wrap")
    fig = kept[0]
    legends = [legend for ax in fig.axes for legend in [ax.get_legend()] if legend is not None]
    assert [t.get_text() for t in legends[0].get_texts()] == [name for name, _ in REGIONS.values()]
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    renderer = FigureCanvasAgg(fig).get_renderer()  # the figure is closed: a canvas of its own, same layout
    boxes = [fig._suptitle.get_window_extent(renderer)] + [ax.title.get_window_extent(renderer) for ax in fig.axes
                                                           if ax.get_title()]
    assert len(boxes) == 1 + 3 * 4
    for i, first in enumerate(boxes):
        for second in boxes[i + 1:]:
            assert not first.overlaps(second), (first, second)
    assert_laid_out(fig)


def test_the_comparison_rows_keep_their_labels_inside_and_apart(monkeypatch, tmp_path):
    """The paper's Figures 10-14 (three views, with and without the initial model's column): one
    colour bar, the labels laid out as :func:`assert_laid_out` checks."""
    from fsswarp.figures import comparison_figure

    sonar = small_sonar()
    views = fake_views(sonar, 3)
    images = {n: image for n, (image, _) in views.items()}
    enhanced = {n: r.enhanced for n, (_, r) in views.items()}
    synthetic = {n: r.synthetic for n, (_, r) in views.items()}

    for initial in (None, synthetic):
        kept = captured_figures(monkeypatch)
        comparison_figure(images, enhanced, synthetic, sonar, tmp_path / "views.png", initial=initial,
                          title="coral-one: the views optimized, with a title long enough to wrap onto two lines")
        columns = 3 if initial is None else 4
        assert len(kept[-1].axes) == 3 * columns + 1
        assert_laid_out(kept[-1])


def test_the_carved_and_the_final_model_have_their_own_shaded_colours(monkeypatch, tmp_path):
    """Orange for the carved model, blue for the final one, each shaded (more than one tone),
    the truth an outline."""
    import numpy as np
    from matplotlib.collections import LineCollection, PolyCollection

    from fsswarp.figures import carve_figure

    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    truth = trimesh.creation.box((0.15, 0.15, 0.15))
    kept = captured_figures(monkeypatch)
    carve_figure(mesh, tmp_path / "carved.png", truth=truth, label="carved")
    carve_figure(mesh, tmp_path / "model.png", truth=truth, label="final")
    for fig, hue in zip(kept, ("orange", "blue")):
        faces = [c for c in fig.axes[0].collections if isinstance(c, PolyCollection)][0].get_facecolors()[:, :3]
        red, blue = faces[:, 0].mean(), faces[:, 2].mean()
        assert (red > 2 * blue) if hue == "orange" else (blue > 1.5 * red), (hue, red, blue)
        assert len(np.unique(faces.round(3), axis=0)) > 10  # shaded, not flat
        outline = [c for c in fig.axes[0].collections if isinstance(c, LineCollection)][0]
        assert len(outline.get_segments()) >= 4  # the box's silhouette seen along z: its four side edges


def test_history_shades_the_intervals_where_the_entries_have_them(monkeypatch, tmp_path):
    import numpy as np
    from matplotlib.collections import PolyCollection

    from fsswarp.figures import history_figure

    history = [{"iteration": k, "depth_m": 0.45 + 0.001 * k, "tilt_deg": 11.0 + 0.1 * k, "E_mu": 0.01 / (k + 1),
                "E_I": 1.0 - 0.1 * k, "E_V": 0.4 - 0.02 * k, "fscore": 0.2 + 0.05 * k} for k in range(4)]
    with_bands = [dict(h, depth_interval_m=[h["depth_m"] - 0.01, h["depth_m"] + 0.02],
                       tilt_interval_deg=[h["tilt_deg"] - 0.3, h["tilt_deg"] + 0.4]) for h in history]
    kept = captured_figures(monkeypatch)
    history_figure(history, tmp_path / "plain.png", best_iteration=3)
    history_figure(with_bands, tmp_path / "bands.png", best_iteration=3, depth_interval_m=[0.44, 0.47])
    plain, bands = kept
    assert len(plain.axes) == 4 and not [c for c in plain.axes[0].collections if isinstance(c, PolyCollection)]
    band = [c for c in bands.axes[0].collections if isinstance(c, PolyCollection)][0]
    low, high = band.get_paths()[0].vertices[:, 1].min(), band.get_paths()[0].vertices[:, 1].max()
    assert np.isclose(low, 0.44) and np.isclose(high, 0.473)
    assert "result's interval" in [t.get_text() for t in bands.legends[0].get_texts()]
    for fig in kept:
        assert_laid_out(fig)


def test_a_fan_puts_each_cell_at_its_range_and_azimuth_with_labelled_arcs_and_rays():
    """Cell (bin, beam) centres at R (sin θ, cos θ) from the sonar's geometry; arcs in m, rays in deg."""
    import math

    import matplotlib
    import numpy as np

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fsswarp.figures import draw_fan

    sonar = small_sonar()
    fig, ax = plt.subplots()
    mesh = draw_fan(ax, np.zeros((sonar.bins, sonar.beams)), sonar, {"range": (1.8, 2.2), "azimuth": (-6.0, 8.0)})
    corners = mesh.get_coordinates()  # (rows + 1, cols + 1, 2)
    centres = corners.reshape(-1, 2)
    radius = np.hypot(centres[:, 0], centres[:, 1])
    assert radius.min() > 1.8 - sonar.range_step and radius.max() < 2.2 + sonar.range_step
    rows = np.flatnonzero((sonar.bin_ranges + sonar.range_step / 2 > 1.8) & (sonar.bin_ranges - sonar.range_step / 2 < 2.2))
    first_range, first_beam = sonar.bin_ranges[rows[0]], np.flatnonzero(
        np.degrees(sonar.beam_centres) + 0.5 * math.degrees(sonar.beam_widths[0]) > -6.0)[0]
    cell = corners[:2, :2].reshape(-1, 2).mean(axis=0)
    theta = sonar.beam_centres[first_beam]
    assert np.allclose(cell, [first_range * math.sin(theta), first_range * math.cos(theta)], atol=2e-3)
    labels = [t.get_text() for t in ax.texts]
    assert any(re.fullmatch(r"\d\.\d\d m", t) for t in labels) and any(re.fullmatch(r"-?\d+°", t) for t in labels)
    # one white collection of lines: an arc at each labelled range, a ray at each labelled azimuth
    grid, = [c for c in ax.collections if isinstance(c, matplotlib.collections.LineCollection)]
    arcs = [s for s in grid.get_segments() if len(s) > 2]
    rays = [s for s in grid.get_segments() if len(s) == 2]
    ranges = sorted(float(t[:-2]) for t in labels if re.fullmatch(r"\d\.\d\d m", t))
    azimuths = sorted(float(t[:-1]) for t in labels if re.fullmatch(r"-?\d+°", t))
    assert len(arcs) == len(ranges) and len(rays) == len(azimuths)
    assert np.allclose(sorted(np.hypot(*a.T).mean() for a in arcs), ranges, atol=5e-3)
    assert all(np.ptp(np.hypot(*a.T)) < 1e-9 for a in arcs)
    assert np.allclose(sorted(np.degrees(np.arctan2(*np.asarray(r)[1].T)) for r in rays), azimuths)
    assert np.allclose(grid.get_colors()[0], [1.0, 1.0, 1.0, 0.45])
    plt.close(fig)


def test_views_rows_keep_their_labels_inside_the_figure_and_clear_of_each_other(monkeypatch, tmp_path):
    """The report's view rows: four panels a row and one colour bar, laid out as
    :func:`assert_laid_out` checks, with one row and with two under a title."""
    import numpy as np

    from fsswarp.figures import views_figure

    sonar = small_sonar()
    views = fake_views(sonar, 2)
    rows = {name: {"data": image, "ghost-free data": result.enhanced, "carved model at D0 0.432 m": result.synthetic,
                   "final model at D 0.433 m": np.roll(result.synthetic, 2, axis=0)}
            for name, (image, result) in views.items()}
    for shown, title in (({"V0": rows["V0"]}, ""), (rows, "coral-one: two views with a title")):
        kept = captured_figures(monkeypatch)
        views_figure(shown, sonar, tmp_path / "views.png", title=title)
        assert len(kept[-1].axes) == 4 * len(shown) + 1
        assert_laid_out(kept[-1])


def test_the_carved_model_figure_keeps_its_labels_inside_and_apart(monkeypatch, tmp_path):
    from fsswarp.figures import carve_figure

    kept = captured_figures(monkeypatch)
    carve_figure(trimesh.creation.box((0.3, 0.1, 0.05)), tmp_path / "carved.png",
                 truth=trimesh.creation.icosphere(radius=0.06), title="coral-one: carved model (iteration 0)")
    assert len(kept[-1].axes) == 3
    assert_laid_out(kept[-1])


def test_pose_levels_keep_their_tick_labels_apart(monkeypatch, tmp_path):
    """The first pose step's levels of coral-one's demo (9 × 9 cells, 2.25 mm × 0.45° and finer):
    laid out on the fixed grid, their depth tick labels do not run into each other."""
    import math
    from types import SimpleNamespace

    import numpy as np

    from fsswarp.figures import pose_figure

    levels = []
    for centre, step, tilt_step in ((0.432, 2.25e-3, 0.45), (0.4342, 1.125e-3, 0.225), (0.4342, 0.5625e-3, 0.1125)):
        depths = centre + step * np.arange(-4, 5)
        tilts = np.radians(10.7 + tilt_step * np.arange(-4, 5))
        costs = (depths[:, None] - 0.4336) ** 2 * 1e3 + (tilts[None, :] - math.radians(10.69)) ** 2 + 0.015
        levels.append(SimpleNamespace(depths=depths, tilts=tilts, costs=costs))
    result = SimpleNamespace(levels=levels, depth0=0.432, tilt0=math.radians(11.1), depth=0.4336,
                             tilt=math.radians(10.69))
    kept = captured_figures(monkeypatch)
    pose_figure(result, tmp_path / "pose.png", truth=(0.43, math.radians(10.3)),
                title="first pose step: the (D, tilt) grid search around the measured values")
    assert len(kept[0].axes) == 6  # three levels, each with its colour bar
    assert_laid_out(kept[0])
