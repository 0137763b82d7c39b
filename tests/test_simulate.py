"""fsswarp simulate and render as a user runs them: outputs, determinism, bad input."""

import json
import subprocess
import sys

import numpy as np
import pytest
import tifffile
import trimesh

from fsswarp.dataset import save_scene
from fsswarp.rendering import LAYERS, RenderSettings, RenderWarning, log_compress
from fsswarp.scenes import builtin_scene
from fsswarp.simulation import simulate

FAST = RenderSettings(samples=(1, 16))


def run_cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "fsswarp", "--backend", "opencl", *args],
                          capture_output=True, text=True, cwd=cwd)


@pytest.fixture(scope="module")
def coral(tmp_path_factory):
    from fsswarp.backends import get_backend

    out = tmp_path_factory.mktemp("sim") / "coral"
    return simulate("coral-one", out, seed=3, settings=FAST, backend=get_backend("opencl")), out


def test_simulated_dataset_holds_noisy_images_and_truth_layers(coral):
    dataset, out = coral
    assert len(dataset.images) == 16
    for name in ("S0", "Np67p5"):
        object_ = dataset.truth_layer(name, "object")
        ghost = dataset.truth_layer(name, "ghost")
        assert object_.sum() > 0 and ghost.sum() > 0
        total = sum(dataset.truth_layer(name, c) for c in ("object", "ghost", "mirror", "mirror2"))
        image = dataset.images[name]
        assert not np.array_equal(image, total)          # noise was added
        echo, water = total > 0, total == 0
        background = image[water].mean()                 # exponential floor: 5% of the p99 echo
        assert background == pytest.approx(0.05 * np.percentile(total[echo], 99), rel=0.1)
        # speckle has mean one: over the echo, data ≈ echo + floor
        assert (image[echo].mean() - background) / total[echo].mean() == pytest.approx(1.0, abs=0.15)
    assert (out / "truth" / "model.ply").is_file()
    assert run_cli("check", str(out)).returncode == 0


def test_same_seed_same_images_other_seed_other_images(coral, tmp_path):
    from fsswarp.backends import get_backend

    dataset, _ = coral
    again = simulate("coral-one", tmp_path / "a", seed=3, settings=FAST, backend=get_backend("opencl"))
    other = simulate("coral-one", tmp_path / "b", seed=4, settings=FAST, backend=get_backend("opencl"))
    for name in dataset.images:
        np.testing.assert_array_equal(again.images[name], dataset.images[name])
    assert not np.array_equal(other.images["S0"], dataset.images["S0"])


@pytest.mark.parametrize("label", ["warp-cpu", "opencl-cpu"])
def test_simulate_streams_the_layers_render_gives(label, tmp_path):
    """simulate renders in batches and draws the noise on a worker thread: its images and truth
    layers are bit for bit the one-launch render's layers with add_noise's seeded draws."""
    from conftest import backend_for
    from fsswarp.rendering import add_noise, render
    from fsswarp.rig import world_to_reference
    from fsswarp.simulation import check_scene

    backend = backend_for(label)
    dataset = simulate("coral-one", tmp_path / "s", seed=5, settings=FAST, backend=backend)
    manifest, world = check_scene("coral-one")
    truth = manifest.truth
    model = trimesh.Trimesh(world_to_reference(world.vertices, manifest.rig, truth.depth, truth.tilt), world.faces,
                            process=False)
    views = render(model, manifest.sonar, manifest.rig, truth.depth, truth.tilt, settings=FAST, backend=backend)
    for index, (name, stack) in enumerate(views.items()):
        want = add_noise(stack[LAYERS.index("total")], np.random.default_rng([5, index]))
        np.testing.assert_array_equal(dataset.images[name], want)
        np.testing.assert_array_equal(dataset.truth_layer(name, "ghost"), stack[LAYERS.index("ghost")])


def test_stream_views_hands_every_view_in_order_and_raises_the_consumers_error():
    from conftest import backend_for
    from fsswarp.rendering import render, rig_poses, stream_views
    from fsswarp.rig import world_to_reference
    from fsswarp.simulation import check_scene

    backend = backend_for("warp-cpu")
    manifest, world = check_scene("coral-one")
    truth = manifest.truth
    model = trimesh.Trimesh(world_to_reference(world.vertices, manifest.rig, truth.depth, truth.tilt), world.faces,
                            process=False)
    names = manifest.rig.names[:5]
    poses = rig_poses(manifest.rig, truth.depth, truth.tilt, names)
    want = render(model, manifest.sonar, manifest.rig, truth.depth, truth.tilt, views=names, settings=FAST,
                  backend=backend)
    seen = []
    stream_views(model, manifest.sonar, *poses, lambda k, stack: seen.append((k, stack)), settings=FAST,
                 backend=backend, batch=2, queued=1)
    assert [k for k, _ in seen] == list(range(5))
    for k, stack in seen:  # copies: the staging buffer was reused by the later batches
        np.testing.assert_array_equal(stack, want[names[k]])

    def fail(k, stack):
        if k == 2:
            raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        stream_views(model, manifest.sonar, *poses, fail, settings=FAST, backend=backend, batch=2, queued=1)


def test_render_command_writes_every_layer(coral, tmp_path):
    _, out = coral
    done = run_cli("render", str(out / "truth" / "model.ply"), "--dataset", str(out), "--out",
                   str(tmp_path / "r"), "--view", "S0", "--view", "Sp45", "--samples", "1", "16")
    assert done.returncode == 0, done.stderr
    names = sorted(p.name for p in (tmp_path / "r").iterdir())
    assert names == sorted([f"{v}_{layer}.tiff" for v in ("S0", "Sp45") for layer in LAYERS]
                           + ["layers.png", "render.json"])
    stack = [tifffile.imread(tmp_path / "r" / f"Sp45_{layer}.tiff") for layer in LAYERS]
    np.testing.assert_allclose(stack[-1], sum(stack[:-1]), rtol=1e-5, atol=1e-7)
    assert json.loads((tmp_path / "r" / "render.json").read_text())["views"] == ["S0", "Sp45"]


def test_render_at_new_rolls(coral, tmp_path):
    """--roll 45 at the reference position reproduces the dataset's own 45° view there (Sp45),
    and a new roll gets its own files; clashing names and unknown --at views exit 2."""
    _, out = coral
    model = str(out / "truth" / "model.ply")
    common = ["--dataset", str(out), "--samples", "1", "16"]
    done = run_cli("render", model, *common, "--out", str(tmp_path / "r"), "--view", "Sp45",
                   "--roll", "45", "--roll", "90")
    assert done.returncode == 0, done.stderr
    report = json.loads((tmp_path / "r" / "render.json").read_text())
    assert report["views"] == ["Sp45", "roll45", "roll90"]
    assert report["new_views"]["roll90"] == {"roll_deg": 90.0, "at": "Sm90"}
    for layer in LAYERS:
        np.testing.assert_array_equal(tifffile.imread(tmp_path / "r" / f"roll45_{layer}.tiff"),
                                      tifffile.imread(tmp_path / "r" / f"Sp45_{layer}.tiff"))
    roll90 = tifffile.imread(tmp_path / "r" / "roll90_total.tiff")
    assert roll90.sum() > 0 and not np.array_equal(roll90, tifffile.imread(tmp_path / "r" / "roll45_total.tiff"))
    for extra, field in ((["--roll", "45", "--at", "nowhere"], "view = 'nowhere'"),
                         (["--roll", "nan"], "--roll")):
        bad = run_cli("render", model, *common, "--out", str(tmp_path / "bad"), *extra)
        assert bad.returncode == 2 and field in bad.stderr and len(bad.stderr.strip().splitlines()) == 1, bad.stderr
        assert not (tmp_path / "bad").exists()


def scene_file(tmp_path, **changes):
    import dataclasses

    manifest = builtin_scene("coral-one")
    manifest = dataclasses.replace(manifest, **changes)
    return save_scene(manifest, tmp_path / "scene.toml")


def test_empty_mesh_exits_2(tmp_path):
    import dataclasses

    (tmp_path / "empty.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nelement face 0\n"
                                        "property list uchar int vertex_indices\nend_header\n")
    target = dataclasses.replace(builtin_scene("coral-one").target, builtin=None, mesh="empty.ply")
    path = scene_file(tmp_path, target=target)
    done = run_cli("simulate", str(path), "--out", str(tmp_path / "out"))
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "target.mesh" in done.stderr and not (tmp_path / "out").exists()


@pytest.mark.parametrize("content, scale, field, message", [
    (b"#!/bin/sh\n", 1.0, "target.mesh", "cannot read mesh"),            # trimesh: NotImplementedError
    ("truncated", 1.0, "target.mesh", "cannot read mesh"),                 # trimesh: IndexError
    ("cube", 1e300, "target.scale_m", "float32"),                          # vertices of inf
])
def test_a_scene_whose_mesh_cannot_be_read_or_placed_is_refused_by_check_and_simulate(tmp_path, content, scale,
                                                                                       field, message):
    """``check`` reads and places a scene's target mesh as ``simulate`` does: whatever trimesh
    raises for an unreadable file, or a scale that overflows float32, is one line naming the
    scene file and the field, exit 2, nothing written."""
    import dataclasses

    import trimesh

    mesh = tmp_path / ("target.sh" if isinstance(content, bytes) else "target.ply")
    if isinstance(content, bytes):
        mesh.write_bytes(content)
    else:
        trimesh.creation.box(extents=(0.1, 0.1, 0.1)).export(mesh)
    if content == "truncated":
        mesh.write_bytes(mesh.read_bytes()[:100])
    target = dataclasses.replace(builtin_scene("coral-one").target, builtin=None, mesh=mesh.name, scale=scale)
    path = scene_file(tmp_path, target=target)
    for args in (("check", str(path)), ("simulate", str(path), "--out", str(tmp_path / "out"))):
        done = run_cli(*args)
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 2 and len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
        assert lines[0].startswith(f"fsswarp: error: {path}: {field}") and message in lines[0]
    assert not (tmp_path / "out").exists()


def test_a_view_offset_that_lifts_the_sonar_above_the_surface_is_refused(tmp_path):
    """A view's depth offset that puts its sonar above the surface (at the measured or the
    true depth) names the view's field in the scene file, in check as in simulate."""
    path = scene_file(tmp_path)
    text = path.read_text()
    assert "depth_offset_m = 0.0" in text
    path.write_text(text.replace("depth_offset_m = 0.0", "depth_offset_m = -0.5", 1))
    for args in (("check", str(path)), ("simulate", str(path), "--out", str(tmp_path / "out"))):
        done = run_cli(*args)
        assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
        assert f"{path}: views[" in done.stderr and "].depth_offset_m = -0.5: puts the sonar above" in done.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("edit, field", [
    (("range_min_m = 1.0", "range_min_m = 3.0"), "range_max_m"),   # empty window
    (("range_max_m = 3.0", "range_max_m = 0.5"), "range_max_m"),   # inverted window
    (("heading_deg = 0.0", "heading_deg = nan"), "heading_deg"),   # NaN pose
])
def test_bad_scene_values_exit_2(tmp_path, edit, field):
    path = scene_file(tmp_path)
    text = path.read_text()
    assert edit[0] in text
    path.write_text(text.replace(edit[0], edit[1], 1))
    done = run_cli("simulate", str(path), "--out", str(tmp_path / "out"))
    assert done.returncode == 2 and field in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "out").exists()


def test_open_mesh_and_missed_window_warn(tmp_path):
    import dataclasses

    from fsswarp.backends import get_backend
    from fsswarp.sonar import SonarSpec

    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    box.update_faces(np.arange(len(box.faces)) != 0)   # a hole
    box.export(tmp_path / "open.ply")
    target = dataclasses.replace(builtin_scene("coral-one").target, builtin=None, mesh="open.ply")
    manifest = dataclasses.replace(builtin_scene("coral-one"), target=target,
                                   sonar=SonarSpec(range_min=2.5, range_max=4.0))
    path = save_scene(manifest, tmp_path / "scene.toml")
    with pytest.warns(RenderWarning) as caught:
        simulate(path, tmp_path / "out", settings=FAST, backend=get_backend("opencl"))
    text = " ".join(str(w.message) for w in caught)
    assert "not watertight" in text and "outside the range window" in text


def test_log_compression_maps_decades_linearly():
    image = np.array([[1.0, 0.1, 0.001, 0.0]], np.float32)
    out = log_compress(image, dynamic_range_db=60)
    assert out.dtype == np.uint8
    assert out.tolist() == [[255, 170, 0, 0]]
