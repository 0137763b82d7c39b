"""HoloOcean-style folders (fsswarp.holoocean): export, import, and the conventions NeuSIS reads.

Oracles: hand-computed sensor-to-world matrices (HoloOcean's x forward, y left, z up), NeuSIS's
own pixel formulas (rpl-cmu/neusis helpers.get_arcs: row i at RangeMin + i·ΔR, column j at
-Azimuth/2 + j·Δθ, θ toward +y), trimesh's ray caster for the vertices a view sees, and closed
forms for the resampled beams.
"""

from __future__ import annotations

import json
import math
import pickle
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

from fsswarp.cli import main
from fsswarp.dataset import Dataset, load_dataset, save_dataset
from fsswarp.errors import InputError
from fsswarp.holoocean import CONFIG, TABLE_KEYS, export_holoocean, holoocean_dataset
from fsswarp.importing import import_recording
from fsswarp.rendering import RenderSettings
from fsswarp.rig import Rig, View
from fsswarp.scenes import builtin_scene
from fsswarp.simulation import simulate
from fsswarp.sonar import SonarSpec

REPO = Path(__file__).resolve().parents[1]
FAST = RenderSettings(samples=(1, 16))


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """coral-one simulated with noise (a surface dataset with a truth) and its deep-water twin."""
    root = tmp_path_factory.mktemp("holoocean")
    return {"surface": simulate("coral-one", root / "surface", seed=2, settings=FAST),
            "deep": simulate(builtin_scene("coral-one", deep_water=True), root / "deep", seed=2, settings=FAST)}


def world_poses(dataset, depth, tilt):
    return dataset.rig.world_poses(depth, tilt)


@pytest.mark.parametrize("kind", ["surface", "deep"])
def test_exported_then_imported_datasets_round_trip(simulated, kind, tmp_path):
    original = simulated[kind]
    export_holoocean(original, tmp_path / "holo")
    back = import_recording(tmp_path / "holo", tmp_path / "again")
    a, b = original.manifest, back.manifest
    assert (a.surface, a.known_pose, a.truth, a.rig.names, a.rig.reference) == \
        (b.surface, b.known_pose, b.truth, b.rig.names, b.rig.reference)
    assert [v.optimize for v in a.rig.views] == [v.optimize for v in b.rig.views]
    for key in ("beams", "bins", "azimuth_fov", "elevation_fov", "range_min", "range_max"):
        assert getattr(b.sonar, key) == pytest.approx(getattr(a.sonar, key), rel=1e-12, abs=1e-12)
    for depth, tilt in ((0.43, math.radians(10.3)), (5.0, math.radians(-20.0))):  # poses at any (D, β)
        (ra, sa), (rb, sb) = world_poses(original, depth, tilt), world_poses(back, depth, tilt)
        assert np.abs(ra - rb).max() < 1e-9 and np.abs(sa - sb).max() < 1e-9
    for name, image in original.images.items():  # float32 rounding, twice: x/s, then (x/s)·s
        np.testing.assert_allclose(back.images[name], image, rtol=3e-7, atol=0)
        assert back.images[name].dtype == np.float32
    mesh_a, mesh_b = original.truth_mesh(), back.truth_mesh()
    world = trimesh.load_mesh(tmp_path / "holo" / "gt.ply").vertices  # PLY holds float32 (trimesh)
    bound = 2 * np.finfo(np.float32).eps * (np.abs(world).max() + np.abs(mesh_a.vertices).max())
    assert np.abs(mesh_a.vertices - mesh_b.vertices).max() <= bound
    assert np.array_equal(mesh_a.faces, mesh_b.faces)


def test_the_files_follow_holoocean(simulated, tmp_path):
    """Config.json's last sensor of the agent is the ImagingSonar; each pkl a dict of a float32
    (RangeBins, AzimuthBins) image in [0, 1] (1 at the brightest pixel of all views) and a 4 x 4
    pose; the pickles name no NumPy module but ``numpy`` itself (NumPy 1 and 2 read them)."""
    dataset = simulated["surface"]
    out = export_holoocean(dataset, tmp_path / "holo")
    config = json.loads((out / CONFIG).read_text())
    sonar = config["agents"][0]["sensors"][-1]
    assert sonar["sensor_type"] == "ImagingSonar"
    settings = sonar["configuration"]
    assert set(settings) == {"Azimuth", "Elevation", "RangeMin", "RangeMax", "RangeBins", "AzimuthBins"}
    assert (settings["RangeBins"], settings["AzimuthBins"]) == (512, 96)
    assert settings["Elevation"] == pytest.approx(14.0)
    assert settings["Azimuth"] == pytest.approx(28.8 * 96 / 95)  # edge to edge: beams × beam spacing
    step = 2.0 / 511
    assert (settings["RangeMin"], settings["RangeMax"]) == pytest.approx((1.0 - step / 2, 3.0 + step / 2))
    files = sorted((out / "Data").iterdir())
    assert [f.name for f in files] == [f"{i:06d}.pkl" for i in range(16)]
    peaks = []
    for path in files:
        raw = path.read_bytes()
        assert b"numpy._core" not in raw and b"numpy.core" not in raw
        record = pickle.loads(raw)
        image, pose = record["ImagingSonar"], record["PoseSensor"]
        assert image.dtype == np.float32 and image.shape == (512, 96) and image.min() >= 0
        assert image.flags.writeable  # NeuSIS zeroes pixels in place
        assert pose.shape == (4, 4) and np.array_equal(pose[3], [0, 0, 0, 1])
        peaks.append(image.max())
    assert max(peaks) == 1.0
    assert set(config["fsswarp"]) == set(TABLE_KEYS)


def test_pose_sensor_matrices_against_hand_computed_axes(tmp_path):
    """Columns of a PoseSensor rotation: HoloOcean's forward, left and up in the world."""
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    cases = {  # view: (forward, left, up, position)
        "east": (View("east", position=(1.0, 2.0), heading=math.radians(90)), (-1, 0, 0), (0, -1, 0), (0, 0, 1)),
        "up30": (View("up30", tilt_offset=math.radians(30)), (0, c, s), (-1, 0, 0), (0, -s, c)),
        "roll90": (View("roll90", roll=math.radians(90)), (0, 1, 0), (0, 0, 1), (1, 0, 0)),
    }
    rig = Rig(tuple(case[0] for case in cases.values()))
    manifest = builtin_scene("coral-one", deep_water=True)
    manifest = replace(manifest, target=None, rig=rig, known_pose=replace(manifest.known_pose, depth=3.0, tilt=0.0))
    sonar = SonarSpec(beams=8, bins=16)
    manifest = replace(manifest, sonar=sonar)
    images = {name: np.ones((16, 8), np.float32) for name in cases}
    out = export_holoocean(Dataset(manifest, images), tmp_path / "holo")
    for index, (view, forward, left, up) in enumerate(cases.values()):
        with open(out / "Data" / f"{index:06d}.pkl", "rb") as handle:
            pose = pickle.load(handle)["PoseSensor"]
        np.testing.assert_allclose(pose[:3, :3], np.array([forward, left, up]).T, atol=1e-15)
        assert pose[:3, 3] == pytest.approx([*view.position, -3.0])


def test_truth_vertices_land_on_the_returns_by_neusis_conventions(tmp_path):
    """A noise-free deep-water simulation, exported: every truth vertex that a view sees (the
    first hit along its ray, facing the sonar, cos > 0.2, inside the elevation aperture) lies
    within one range bin and one azimuth bin of a return, by NeuSIS's pixel formulas applied to
    PoseSensor and gt.ply; with the columns mirrored, many do not."""
    dataset = simulate(builtin_scene("coral-one", deep_water=True), tmp_path / "ds", noise=False,
                       settings=RenderSettings(samples=(2, 512)))
    out = export_holoocean(dataset, tmp_path / "holo")
    settings = json.loads((out / CONFIG).read_text())["agents"][0]["sensors"][-1]["configuration"]
    hfov, vfov = math.radians(settings["Azimuth"]), math.radians(settings["Elevation"])
    rows, cols = settings["RangeBins"], settings["AzimuthBins"]
    r_min, r_step = settings["RangeMin"], (settings["RangeMax"] - settings["RangeMin"]) / rows
    truth = trimesh.load_mesh(out / "gt.ply")
    caster = trimesh.ray.ray_triangle.RayMeshIntersector(truth)
    seen = landed = landed_mirrored = 0
    for path in sorted((out / "Data").glob("*.pkl")):
        with open(path, "rb") as handle:
            record = pickle.load(handle)
        image, pose = record["ImagingSonar"], record["PoseSensor"]
        local = (truth.vertices - pose[:3, 3]) @ pose[:3, :3]  # sensor frame: x forward, y left, z up
        rng = np.linalg.norm(local, axis=1)
        theta, phi = np.arctan2(local[:, 1], local[:, 0]), np.arcsin(local[:, 2] / rng)
        row, col = (rng - r_min) / r_step, (theta + hfov / 2) / (hfov / cols)  # NeuSIS: r = i·ΔR + r_min
        inside = np.flatnonzero((np.abs(phi) < vfov / 2) & (row >= 0) & (row <= rows - 1) & (col >= 0)
                                & (col <= cols - 1))
        origins = np.repeat(pose[None, :3, 3], len(inside), axis=0)
        rays = (truth.vertices[inside] - origins) / rng[inside, None]
        hits, index, _ = caster.intersects_location(origins, rays, multiple_hits=False)
        first = np.full(len(inside), np.inf)
        first[index] = np.linalg.norm(hits - origins[index], axis=1)
        facing = -np.einsum("ij,ij->i", truth.vertex_normals[inside], rays) > 0.2
        visible = inside[(first > rng[inside] - 1e-4) & facing]
        seen += len(visible)
        for picture, counter in ((image, "landed"), (image[:, ::-1], "mirrored")):
            near = np.zeros(len(visible), bool)
            for di in (-1, 0, 1, 2):
                for dj in (-1, 0, 1, 2):
                    i, j = np.floor(row[visible]).astype(int) + di, np.floor(col[visible]).astype(int) + dj
                    ok = (np.abs(i - row[visible]) <= 1) & (np.abs(j - col[visible]) <= 1)
                    ok &= (i >= 0) & (i < rows) & (j >= 0) & (j < cols)
                    near |= ok & (picture[np.clip(i, 0, rows - 1), np.clip(j, 0, cols - 1)] > 0)
            if counter == "landed":
                landed += int(near.sum())
            else:
                landed_mirrored += int(near.sum())
    assert seen > 10_000
    assert landed >= 0.999 * seen  # the misses: silhouette vertices exactly on a bin edge
    assert landed_mirrored < 0.8 * seen


def test_a_beam_angle_table_is_resampled_to_uniform_bins(tmp_path):
    """A table from -10 to 14 deg: uniform bins at ±14 deg; an image linear in azimuth comes
    back linear (interpolation is exact on it), and 0 where no beam looked."""
    angles = np.radians(np.linspace(-10.0, 14.0, 9) + 0.5 * np.sin(np.arange(9)))  # uneven spacing
    sonar = SonarSpec(beams=9, bins=4, azimuth_fov=float(angles[-1] - angles[0]), beam_angles=angles)
    manifest = replace(builtin_scene("coral-one", deep_water=True), target=None, sonar=sonar,
                       rig=Rig((View("a"),)))
    image = np.repeat((1.0 + angles)[None, :], 4, axis=0).astype(np.float32)  # value 1 + θ (rad)
    out = export_holoocean(Dataset(manifest, {"a": image}), tmp_path / "holo")
    config = json.loads((out / CONFIG).read_text())
    settings, table = config["agents"][0]["sensors"][-1]["configuration"], config["fsswarp"]
    edge = float(np.degrees(np.max(np.abs(angles[[0, -1]]))))
    assert settings["Azimuth"] == pytest.approx(2 * edge * 9 / 8)
    assert table["azimuth_resampled"] is True
    with open(out / "Data" / "000000.pkl", "rb") as handle:
        exported = pickle.load(handle)["ImagingSonar"] * table["intensity_scale"]
    theta = -np.radians(np.linspace(-edge, edge, 9))  # HoloOcean column j looks at θ_H = -(fsswarp's θ)
    reach = (angles[0] - (angles[1] - angles[0]) / 2, angles[-1] + (angles[-1] - angles[-2]) / 2)
    looked = (theta >= reach[0]) & (theta <= reach[1])
    expected = np.where(looked, 1.0 + np.clip(theta, angles[0], angles[-1]), 0.0)
    np.testing.assert_allclose(exported, np.repeat(expected[None, :], 4, axis=0), rtol=1e-6, atol=1e-7)
    assert not looked.all()


def _write_folder(root: Path, records, config=None) -> Path:
    """A HoloOcean folder written with plain pickle (NumPy's own reduction), as HoloOcean users do."""
    (root / "Data").mkdir(parents=True)
    settings = {"Azimuth": 30.0, "Elevation": 12.0, "RangeMin": 1.0, "RangeMax": 5.0, "RangeBins": 8,
                "AzimuthBins": 6}
    config = config or {"agents": [{"agent_name": "auv0", "sensors": [
        {"sensor_type": "ImagingSonar", "configuration": settings}, {"sensor_type": "PoseSensor"}]}]}
    (root / CONFIG).write_text(json.dumps(config))
    for name, record in records.items():
        (root / "Data" / name).write_bytes(pickle.dumps(record))
    return root


def _pose(rotation, position):
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, position
    return pose


def test_a_plain_holoocean_folder_imports_as_deep_water(tmp_path):
    """No fsswarp table: views named after the files (2 before 10), deep water at the first
    view's depth and tilt; the world poses equal the PoseSensor matrices (HoloOcean's axes
    taken back), the columns mirrored, RangeMin/Max the bins' outer edges."""
    rng = np.random.default_rng(4)
    ang = math.radians(20)
    forward_up = np.array([[1, 0, 0], [0, math.cos(ang), -math.sin(ang)], [0, math.sin(ang), math.cos(ang)]])
    pitch_up = np.array([[math.cos(ang), 0, -math.sin(ang)], [0, 1, 0], [math.sin(ang), 0, math.cos(ang)]])
    poses = {"10.pkl": _pose(np.eye(3), (1.0, 2.0, -6.0)), "2.pkl": _pose(pitch_up, (0.0, 0.0, -4.0)),
             "3.pkl": _pose(forward_up, (3.0, -1.0, -5.0))}
    images = {name: rng.random((8, 6), dtype=np.float32) for name in poses}
    folder = _write_folder(tmp_path / "holo", {n: {"ImagingSonar": images[n], "PoseSensor": poses[n],
                                                   "DepthSensor": np.float32(-1)} for n in poses})
    dataset, mesh, record = holoocean_dataset(folder)
    assert dataset.rig.names == ["2", "3", "10"] and mesh is None
    assert dataset.manifest.deep_water and record["fsswarp_table"] is False
    known = dataset.manifest.known_pose
    assert (known.depth, known.tilt) == pytest.approx((4.0, math.radians(20)))
    rotations, positions = dataset.rig.world_poses(known.depth, known.tilt)
    axes = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # HoloOcean's x, y, z in fsswarp's frame
    for k, name in enumerate(["2.pkl", "3.pkl", "10.pkl"]):
        np.testing.assert_allclose(rotations[k] @ axes, poses[name][:3, :3], atol=1e-12)
        np.testing.assert_allclose(positions[k], poses[name][:3, 3], atol=1e-12)
        np.testing.assert_array_equal(dataset.images[name[:-4]], images[name][:, ::-1])
    sonar = dataset.sonar
    assert (sonar.range_min, sonar.range_max) == pytest.approx((1.25, 4.75))
    assert math.degrees(sonar.azimuth_fov) == pytest.approx(25.0)


def _spoiled(tmp_path, **change):
    good = _pose(np.eye(3), (0.0, 0.0, -3.0))
    record = {"ImagingSonar": np.ones((8, 6), np.float32), "PoseSensor": good}
    record.update(change)
    return _write_folder(tmp_path / "holo", {"000000.pkl": record, "000001.pkl": {**record, "PoseSensor": good}})


class Evil:
    def __reduce__(self):
        return (print, ("this must never run",))


@pytest.mark.parametrize("change, field", [
    (dict(ImagingSonar=-np.ones((8, 6), np.float32)), "ImagingSonar"),
    (dict(ImagingSonar=np.ones((8, 5), np.float32)), "AzimuthBins"),
    (dict(PoseSensor=np.diag([2.0, 1.0, 1.0, 1.0])), "PoseSensor"),
    (dict(PoseSensor=_pose(np.eye(3), (0.0, 0.0, 0.5))), "PoseSensor[2][3]"),
    (dict(ImagingSonar=Evil()), "pickle"),
], ids=["negative-image", "wrong-azimuth-bins", "not-a-rotation", "above-the-surface", "code-in-the-pickle"])
def test_bad_folders_are_one_line_errors_naming_file_and_field(tmp_path, capsys, change, field):
    folder = _spoiled(tmp_path, **change)
    with pytest.raises(InputError) as caught:
        holoocean_dataset(folder)
    assert field in str(caught.value) and str(folder) in str(caught.value)
    assert main(["import", str(folder), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr()
    assert "this must never run" not in err.out
    assert err.err.count("\n") == 1 and err.err.startswith("fsswarp: error: ") and field in err.err
    assert not (tmp_path / "out").exists()


def test_config_without_an_imaging_sonar_is_refused(tmp_path):
    folder = _write_folder(tmp_path / "holo", {"0.pkl": {"ImagingSonar": np.ones((8, 6), np.float32),
                                                         "PoseSensor": _pose(np.eye(3), (0, 0, -2))}},
                           config={"agents": [{"sensors": [{"sensor_type": "PoseSensor"}]}]})
    with pytest.raises(InputError, match="ImagingSonar"):
        holoocean_dataset(folder)


def test_export_and_import_from_the_command_line(simulated, tmp_path, capsys):
    dataset = simulated["deep"]
    assert main(["--quiet", "export", str(dataset.root), "--format", "holoocean", "--out", str(tmp_path / "h")]) == 0
    assert main(["--quiet", "import", str(tmp_path / "h"), "--out", str(tmp_path / "ds")]) == 0
    assert load_dataset(tmp_path / "ds").manifest.known_pose == dataset.manifest.known_pose
    source = json.loads((tmp_path / "ds" / "source.json").read_text())
    assert source["format"] == "HoloOcean"
    assert main(["import", str(tmp_path / "h"), "--out", str(tmp_path / "ds"), "--depth", "3"]) == 2
    assert "--depth" in capsys.readouterr().err


def test_export_refuses_a_window_that_starts_within_half_a_bin(simulated, tmp_path):
    dataset = simulated["deep"]
    sonar = replace(dataset.sonar, range_min=0.001, range_max=3.0)
    images = {n: np.zeros((sonar.bins, sonar.beams), np.float32) for n in dataset.rig.names}
    with pytest.raises(InputError, match="range_min_m"):
        export_holoocean(Dataset(replace(dataset.manifest, sonar=sonar), images), tmp_path / "holo")
    assert not (tmp_path / "holo").exists()


def test_every_key_written_is_documented(simulated, tmp_path):
    formats = (REPO / "docs" / "formats.md").read_text()
    documented = set(re.findall(r"`([^`\s]+)`", formats))
    out = export_holoocean(simulated["surface"], tmp_path / "holo")
    _, _, record = holoocean_dataset(out)
    table = json.loads((out / CONFIG).read_text())["fsswarp"]
    keys = set(record) | set(table) | set(table["views"][0]) | set(table["poses_at"]) | set(table["surface"])
    assert not sorted(keys - documented)


def test_a_resaved_import_keeps_its_truth(simulated, tmp_path):
    """The imported dataset is an ordinary one: save_dataset copies it whole."""
    export_holoocean(simulated["deep"], tmp_path / "holo")
    back = import_recording(tmp_path / "holo", tmp_path / "ds")
    save_dataset(back, tmp_path / "copy")
    assert load_dataset(tmp_path / "copy").truth_mesh() is not None
