"""The built-in scenes: view sets, placement, and that object, ghost and mirror are imaged."""

import math

import numpy as np
import pytest

from fsswarp.dataset import Target, load_scene, save_scene
from fsswarp.errors import InputError
from fsswarp.rig import to_view, world_to_reference
from fsswarp.scenes import NEAR_STANDOFF_M, STANDOFF_M, TOP_DEPTH_M, builtin_scene, target_world_mesh
from fsswarp.sonar import to_polar
from fsswarp.surface import apparent_returns, surface_in_views


@pytest.mark.parametrize("name, count", [("coral-one", 16), ("coral-two", 16), ("table", 32)])
def test_view_sets_follow_the_paper(name, count):
    scene = builtin_scene(name)
    views = scene.rig.views
    assert len(views) == count
    rolls = sorted({round(math.degrees(v.roll), 6) for v in views})
    assert rolls == [-90 + 22.5 * k for k in range(8)]
    held = {round(math.degrees(v.roll), 6) for v in views if not v.optimize}
    assert held == {-22.5, 0.0, 22.5}
    assert scene.rig.views[scene.rig.reference].position == (0.0, 0.0)
    truth, measured = scene.truth, scene.surface
    # realistic sensors (DESIGN §11): a pressure depth sensor, a tilt sensor good to 0.6 deg
    assert abs(measured.depth - truth.depth) <= 0.003 and measured.depth_sigma == 0.003
    assert math.radians(0.6) <= abs(measured.tilt - truth.tilt) <= math.radians(1.0)
    assert measured.tilt_sigma == pytest.approx(math.radians(0.6))
    poor = builtin_scene(name, sensors="poor").surface
    assert 0.03 <= abs(poor.depth - truth.depth) <= 0.05 and poor.depth_sigma == 0.05
    assert poor.tilt == measured.tilt and poor.tilt_sigma == pytest.approx(math.radians(2.0))


def test_scene_command_writes_the_poor_sensors_on_request(tmp_path):
    from fsswarp.cli import main
    from fsswarp.dataset import load_scene

    assert main(["scene", "coral-two", "--sensors", "poor", "--out", str(tmp_path / "poor.toml")]) == 0
    assert load_scene(tmp_path / "poor.toml").surface == builtin_scene("coral-two", sensors="poor").surface
    with pytest.raises(InputError, match="--sensors = 'bad': must be one of realistic, poor"):
        builtin_scene("table", sensors="bad")


@pytest.mark.parametrize("name", ["coral-one", "coral-two", "table"])
def test_target_sits_just_below_the_surface_ahead_of_the_sonar(name):
    mesh = target_world_mesh(builtin_scene(name).target)
    lo, hi = mesh.bounds
    assert hi[2] == pytest.approx(-TOP_DEPTH_M)
    assert mesh.centroid[1] == pytest.approx(STANDOFF_M, abs=0.03)
    assert mesh.is_watertight


@pytest.mark.parametrize("name, positions", [("coral-one", None), ("coral-two", None), ("table", None),
                                             ("coral-one", "SNEW"), ("coral-two", "WE"),
                                             ("coral-one", "ST"), ("coral-two", "ST")])
def test_object_ghost_and_mirror_fall_in_every_view(name, positions):
    """Every vertex lies inside the window and apertures; its ghost and mirror returns land in
    the window; at roll 0 the mirror falls on the object, at ±67.5° it moves five beams or more."""
    scene = builtin_scene(name, positions)
    sonar, rig, truth = scene.sonar, scene.rig, scene.truth
    points = world_to_reference(target_world_mesh(scene.target).vertices, rig, truth.depth, truth.tilt)
    rot, t = rig.relative_poses(truth.depth, truth.tilt)
    n, d = surface_in_views(rig, truth.depth, truth.tilt)
    for m, view in enumerate(rig.views):
        p = to_view(points, rot[m], t[m])
        rng, theta, phi = to_polar(p)
        assert sonar.in_elevation(phi).all(), view.name
        returns = apparent_returns(p, n[m], d[m])
        for component, (az, r) in returns.items():
            _, _, inside = sonar.beam_bin(az, r)
            assert inside.all(), (view.name, component)
        shift = np.degrees(np.median(np.abs(returns["mirror"][0] - returns["object"][0])))
        roll = round(math.degrees(view.roll), 6)
        if roll == 0:
            assert shift < 0.3
        if abs(roll) == 67.5:
            assert shift > 1.5   # five 0.3° beams


def test_positions_put_a_scene_on_another_rig(tmp_path):
    """``positions`` sets the sonar positions (eight rolls each, in the order given); the
    scene's own views come first and unchanged with SNEW, and every view looks at the
    target's centre (azimuth 0 at zero roll)."""
    own, four = builtin_scene("coral-one"), builtin_scene("coral-one", "snew")
    assert [v.name[0] for v in four.rig.views] == [c for c in "SNEW" for _ in range(8)]
    assert four.rig.views[:16] == own.rig.views and four.target == own.target and four.truth == own.truth
    assert builtin_scene("table", "SNEW") == builtin_scene("table")
    west = builtin_scene("coral-two", "WS")
    assert west.rig.views[west.rig.reference].name == "Wm90" and len(west.rig.views) == 16
    truth = four.truth
    centre = world_to_reference(np.array([four.target.position]), four.rig, truth.depth, truth.tilt)
    rot, t = four.rig.relative_poses(truth.depth, truth.tilt)
    for m, view in enumerate(four.rig.views):
        if view.roll == 0:
            _, theta, _ = to_polar(to_view(centre, rot[m], t[m]))
            assert abs(math.degrees(theta[0])) < 1e-6, view.name
    assert load_scene(save_scene(four, tmp_path / "four.toml")) == four


def test_near_south_is_a_second_standoff_on_the_south_side():
    """T: eight rolls at NEAR_STANDOFF_M (1.4 m, near 1.2 m where the corals still fit)
    south of the target's centre, heading north like S; ST keeps S's views and reference."""
    two, south = builtin_scene("coral-one", "st"), builtin_scene("coral-one", "S")
    views = two.rig.views
    assert NEAR_STANDOFF_M == 1.4 and views[:8] == south.rig.views and two.rig.reference == 0
    assert [v.name for v in views[8:]] == ["Tm90", "Tm67p5", "Tm45", "Tm22p5", "T0", "Tp22p5", "Tp45", "Tp67p5"]
    assert len({v.name for v in views}) == 16
    cx, cy, _ = two.target.position
    for view in views:
        distance = math.hypot(view.position[0] - cx, view.position[1] - cy)
        assert view.position[0] == cx and view.position[1] < cy and view.heading == 0.0
        assert distance == pytest.approx(NEAR_STANDOFF_M if view.name[0] == "T" else STANDOFF_M, abs=1e-12)
    assert [v.optimize for v in views[8:]] == [v.optimize for v in views[:8]]


def test_scene_command_writes_two_standoffs(tmp_path):
    from fsswarp.cli import main

    assert main(["scene", "coral-two", "--positions", "ST", "--out", str(tmp_path / "st.toml")]) == 0
    scene = load_scene(tmp_path / "st.toml")
    assert scene == builtin_scene("coral-two", "ST") and len(scene.rig.views) == 16


@pytest.mark.parametrize("positions", ["", "SX", "SS", "S N", "TT", 5, None])
def test_bad_positions_are_one_line(positions):
    if positions is None:  # None means the scene's own
        assert builtin_scene("coral-one", positions) == builtin_scene("coral-one")
        return
    with pytest.raises(InputError, match="--positions") as err:
        builtin_scene("coral-one", positions)
    assert "\n" not in str(err.value)


def test_scene_file_round_trip(tmp_path):
    scene = builtin_scene("table")
    assert load_scene(save_scene(scene, tmp_path / "table.toml")) == scene


def test_unknown_scene_is_one_line():
    with pytest.raises(InputError, match="reef") as err:
        builtin_scene("reef")
    assert "\n" not in str(err.value)


def test_mesh_file_target_is_scaled_rotated_and_placed(tmp_path):
    import trimesh

    trimesh.creation.box(extents=(2.0, 1.0, 0.5)).export(tmp_path / "box.ply")
    target = Target(position=(1.0, 2.0, -0.5), mesh="box.ply", scale=0.1, rotation=(0.0, 0.0, math.pi / 2))
    mesh = target_world_mesh(target, base=tmp_path)
    np.testing.assert_allclose(mesh.extents, [0.1, 0.2, 0.05], atol=1e-12)
    np.testing.assert_allclose(mesh.bounds.mean(axis=0), [1.0, 2.0, -0.5], atol=1e-12)
    (tmp_path / "bad.ply").write_text("not a mesh")
    with pytest.raises(InputError, match="target.mesh"):
        target_world_mesh(Target(position=(0, 0, -1), mesh="bad.ply"), base=tmp_path)
