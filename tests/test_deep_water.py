"""Deep water: datasets without a sea surface in view (no [surface] table; docs/formats.md).

The manifest's rules, the depth the steps place the surface at (closed form), simulation with
the object alone, carving without the surface rule, the shape-only loop, and the commands.
"""

from __future__ import annotations

import json
import math
import re
import tomllib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fsswarp.carving import carve, carve_masks
from fsswarp.cli import main
from fsswarp.dataset import (KnownPose, deep_water_pose, load_dataset, manifest_to_toml, parse_manifest)
from fsswarp.errors import InputError
from fsswarp.holoocean import export_holoocean
from fsswarp.importing import import_recording
from fsswarp.metrics import compare
from fsswarp.reconstruction import NO_POSE_STEP, ReconstructSettings, reconstruct
from fsswarp.rendering import RenderSettings
from fsswarp.scenes import DEEP_WATER_M, builtin_scene
from fsswarp.simulation import simulate
from fsswarp.surface import COMPONENTS

FAST = RenderSettings(samples=(1, 16))
REPO = Path(__file__).resolve().parents[1]


def table() -> dict:
    return {"sonar": {"beams": 8, "bins": 16, "azimuth_fov_deg": 28.8, "elevation_fov_deg": 14.0,
                      "range_min_m": 1.0, "range_max_m": 3.0},
            "rig": {"reference_view": "b", "depth_m": 0.5, "tilt_deg": 10.0},
            "views": [{"name": "a", "position_m": [0.0, 0.0], "heading_deg": 0.0, "roll_deg": 0.0,
                       "depth_offset_m": 0.3},
                      {"name": "b", "position_m": [0.0, 4.0], "heading_deg": 180.0, "roll_deg": 45.0,
                       "depth_offset_m": -0.2, "tilt_offset_deg": 2.0}]}


def test_a_manifest_without_surface_is_deep_water_and_round_trips():
    manifest = parse_manifest(table(), file="dataset.toml")
    assert manifest.deep_water and manifest.surface is None
    assert manifest.known_pose == KnownPose(depth=0.5, tilt=math.radians(10.0))
    text = manifest_to_toml(manifest)
    assert "[surface]" not in text
    assert parse_manifest(tomllib.loads(text), file="again.toml") == manifest


def _edit(path: str, value):
    def edit(t: dict) -> None:
        node, parts = t, path.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        if value is None:
            del node[parts[-1]]
        else:
            node[parts[-1]] = value
    return edit


@pytest.mark.parametrize("edit, field", [
    (_edit("rig.depth_m", None), "rig.depth_m"),
    (lambda t: (t["rig"].pop("depth_m"), t["rig"].pop("tilt_deg")), "surface"),
    (_edit("surface", {"depth_m": 0.5, "tilt_deg": 10.0}), "rig.depth_m"),
    (_edit("truth", {"depth_m": 0.5, "tilt_deg": 10.0}), "truth.depth_m"),
    (_edit("rig.depth_m", -1.0), "rig.depth_m"),
    (_edit("rig.depth_m", 0.1), "views[b].depth_offset_m"),  # view b at 0.1 - 0.2 m: above the surface
], ids=["depth-without-tilt", "neither-surface-nor-known-pose", "surface-and-known-pose", "truth-with-a-depth",
        "negative-depth", "a-view-above-the-surface"])
def test_bad_deep_water_manifests_name_the_field(tmp_path, capsys, edit, field):
    t = table()
    edit(t)
    with pytest.raises(InputError) as caught:
        parse_manifest(t, file="dataset.toml")
    assert caught.value.field == field
    (tmp_path / "scene.toml").write_text(manifest_to_toml(parse_manifest(table(), file=None)).replace(
        "[rig]", "[target]\nbuiltin = \"coral-one\"\nposition_m = [0.0, 2.0, -0.5]\n\n[rig]"))
    assert main(["check", str(tmp_path / "scene.toml")]) == 0
    assert "deep water" in capsys.readouterr().out


def test_the_steps_place_the_surface_beyond_every_range_window():
    """D' = max(known D, range_max + 1 m - the least depth offset): every view's sonar lies at
    least 1 m farther from the surface than its window reaches."""
    manifest = parse_manifest(table(), file=None)
    assert deep_water_pose(manifest) == (3.0 + 1.0 + 0.2, math.radians(10.0))
    deep = replace(manifest, known_pose=KnownPose(depth=30.0, tilt=0.1))
    assert deep_water_pose(deep) == (30.0, 0.1)
    depth, _ = deep_water_pose(manifest)
    assert min(depth + v.depth_offset for v in manifest.rig.views) == pytest.approx(3.0 + 1.0)


@pytest.fixture(scope="module")
def shallow(tmp_path_factory):
    """coral-one's own geometry (true D 0.43 m) simulated with a surface and as deep water,
    noise-free: the same views, with and without the multipath."""
    root = tmp_path_factory.mktemp("deep")
    scene = builtin_scene("coral-one")
    deep = replace(scene, surface=None, truth=None, known_pose=KnownPose(scene.truth.depth, scene.truth.tilt))
    return (simulate(scene, root / "surface", noise=False, settings=FAST),
            simulate(deep, root / "deep", noise=False, settings=FAST))


def test_a_deep_water_simulation_holds_the_object_alone(shallow):
    """The deep-water images are the surface simulation's object layers (the ghost, mirror and
    double-bounce gone), and truth/ holds object layers only."""
    surface, deep = shallow
    assert deep.manifest.truth.depth is None and deep.truth_mesh() is not None
    assert deep.check_truth_layers() == len(deep.rig.names)
    for name in deep.rig.names:
        object_layer = surface.truth_layer(name, "object")
        np.testing.assert_array_equal(deep.images[name], object_layer)
        np.testing.assert_array_equal(deep.truth_layer(name, "object"), object_layer)
        assert not (deep.root / "truth" / f"{name}_ghost.tiff").exists()
    assert any(surface.truth_layer(n, c).any() for n in surface.rig.names for c in COMPONENTS[1:])


def test_carving_deep_water_keeps_no_surface_rule(shallow):
    """Deep-water carving is carving with no plane at the views' true relative poses (the
    working depth does not move them), and keeps voxels that the surface rule removes."""
    surface, deep = shallow
    known = deep.manifest.known_pose
    result = carve(deep, resolution=40)
    masks = np.stack([result.segmentation[n].feasible for n in result.views])
    index = [deep.rig.index(n) for n in result.views]
    rotations, translations = (a[index] for a in deep.rig.relative_poses(known.depth, known.tilt))
    plain = carve_masks(masks, rotations, translations, deep.sonar, resolution=40, plane=None)
    assert np.array_equal(plain.occupancy, result.voxels.occupancy)
    np.testing.assert_allclose(plain.origin, result.voxels.origin, atol=1e-12)
    with_surface = carve(surface, surface.manifest.truth.depth, surface.manifest.truth.tilt, resolution=40,
                         masks={n: result.segmentation[n].feasible for n in result.views}, views=result.views)
    assert with_surface.mesh.volume < result.mesh.volume


@pytest.mark.slow
def test_reconstructing_an_imported_deep_water_dataset(tmp_path):
    """simulate (deep water, noisy) -> export -> import -> reconstruct: no pose step, the known
    depth and tilt, and a model whose E_V is no worse than the carving's (iteration 0: carving
    without the surface layers)."""
    scene = builtin_scene("coral-one", deep_water=True)
    dataset = simulate(scene, tmp_path / "sim", seed=3, settings=RenderSettings(samples=(2, 32)))
    export_holoocean(dataset, tmp_path / "holo")
    imported = import_recording(tmp_path / "holo", tmp_path / "ds")
    assert imported.manifest.deep_water
    result = reconstruct(imported, settings=ReconstructSettings(iterations=4, resolution=80))
    summary = result.summary()
    assert summary["surface"] is None and summary["pose_step"] == NO_POSE_STEP == "skipped: no sea surface in the dataset"
    assert (summary["depth_m"], summary["tilt_deg"]) == pytest.approx((0.43 + DEEP_WATER_M, 10.3))
    assert all(entry["depth_m"] == summary["depth_m"] for entry in summary["history"])
    carved = carve(imported, resolution=80).mesh
    e_v = compare(result.model, imported.truth_mesh())["E_V"]
    assert summary["history"][0]["E_V"] == pytest.approx(compare(carved, imported.truth_mesh())["E_V"], abs=1e-9)
    assert e_v <= summary["history"][0]["E_V"]
    assert summary["history"][result.best_iteration]["E_V"] == pytest.approx(e_v)
    with pytest.raises(InputError, match="--depth"):
        reconstruct(imported, depth0=0.5)


@pytest.mark.slow
def test_the_commands_on_a_deep_water_dataset(tmp_path, capsys):
    run = lambda *args: main(["--quiet", *map(str, args)])  # noqa: E731
    scene, data = tmp_path / "deep.toml", tmp_path / "ds"
    assert run("scene", "coral-one", "--deep-water", "--out", scene) == 0
    assert "[surface]" not in scene.read_text() and "[truth]" not in scene.read_text()
    assert run("simulate", scene, "--out", data, "--samples", 1, 8) == 0
    assert run("carve", data, "--out", tmp_path / "carve", "--resolution", 24) == 0
    assert json.loads((tmp_path / "carve" / "carve.json").read_text())["depth_tilt_source"] == "known"
    assert run("reconstruct", data, "--out", tmp_path / "rec", "--iterations", 0, "--resolution", 16) == 0
    record = json.loads((tmp_path / "rec" / "result.json").read_text())
    assert record["surface"] is None and record["pose_step"] == NO_POSE_STEP
    documented = set(re.findall(r"`([^`\s]+)`", (REPO / "docs" / "formats.md").read_text()))
    assert not (set(record) | set(record["history"][0])) - documented
    assert run("render", data / "truth" / "model.ply", "--dataset", data, "--out", tmp_path / "r", "--view", "S0",
               "--samples", 1, 8) == 0
    import tifffile
    total, obj = (tifffile.imread(tmp_path / "r" / f"S0_{layer}.tiff") for layer in ("total", "object"))
    assert obj.any() and np.array_equal(total, obj)
    capsys.readouterr()
    for args in (("reconstruct", data, "--out", tmp_path / "x", "--depth", 1.0),
                 ("pose", data, "--model", data / "truth" / "model.ply", "--out", tmp_path / "p"),
                 ("enhance", data, "--model", data / "truth" / "model.ply", "--out", tmp_path / "e"),
                 ("demo", scene, "--out", tmp_path / "d")):
        assert main([*map(str, args)]) == 2, args[0]
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and ("deep water" in err or "deep-water" in err or "no sea surface" in err), err
    assert load_dataset(data).manifest.known_pose.depth == pytest.approx(0.43 + DEEP_WATER_M)
