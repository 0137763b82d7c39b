"""Sonar, rig and sea-surface geometry against closed forms and properties (DESIGN §2–3)."""

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from fsswarp.errors import InputError
from fsswarp.rig import (Rig, View, reference_to_world, rotation_x, rotation_y, rotation_z,
                         to_view, world_to_reference)
from fsswarp.sonar import SonarSpec, fan_xy, from_polar, scan_convert, to_polar
from fsswarp.surface import (apparent_returns, mirror_points, mirror_vectors, surface_in_reference,
                             surface_in_views, view_planes)

finite = dict(allow_nan=False, allow_infinity=False)
coords = st.floats(-5, 5, **finite)
point = st.tuples(coords, coords, coords).map(np.array)
depths = st.floats(0.1, 2.0, **finite)
tilts = st.floats(-0.5, 0.5, **finite)
angles = st.floats(-math.pi, math.pi, **finite)


def distorted_sonar(beams=48):
    """A sonar with a cubic (lens-like) beam-angle table."""
    u = np.linspace(-1, 1, beams)
    return SonarSpec(beams=beams, bins=200, azimuth_fov=2 * 0.25, beam_angles=0.25 * (0.8 * u + 0.2 * u**3))


# --- sonar -------------------------------------------------------------------------------

@given(st.floats(0.01, 50, **finite), st.floats(-3.1, 3.1, **finite), st.floats(-1.5, 1.5, **finite))
def test_polar_round_trip(rng, theta, phi):
    p = from_polar(rng, theta, phi)
    r2, t2, f2 = to_polar(p)
    assert r2 == pytest.approx(rng, rel=1e-12)
    assert t2 == pytest.approx(theta, abs=1e-9)
    assert f2 == pytest.approx(phi, abs=1e-9)


def test_polar_closed_form():
    # eq. (1): a point 2 m ahead, 1 m right, 0.5 m up
    r, theta, phi = to_polar([1.0, 2.0, 0.5])
    assert r == pytest.approx(math.sqrt(5.25))
    assert theta == pytest.approx(math.atan2(1, 2))
    assert phi == pytest.approx(math.atan2(0.5, math.sqrt(5)))


def test_linear_beams_and_bins_follow_eq2():
    s = SonarSpec()  # 96 beams, ±14.4°, 512 bins over 1-3 m
    assert s.beam_centres[0] == pytest.approx(-math.radians(14.4))
    assert s.beam_centres[-1] == pytest.approx(math.radians(14.4))
    assert np.diff(s.beam_centres) == pytest.approx(np.full(95, math.radians(28.8) / 95))
    assert s.bin_ranges[0] == 1.0 and s.bin_ranges[-1] == pytest.approx(3.0)
    assert s.range_step == pytest.approx(2.0 / 511)
    b, B, inside = s.beam_bin(s.beam_centres[17], s.bin_ranges[300])
    assert (int(b), int(B), bool(inside)) == (17, 300, True)


@pytest.mark.parametrize("sonar", [SonarSpec(), distorted_sonar()], ids=["linear", "table"])
@given(frac=st.floats(-3, 99, **finite))
@settings(max_examples=60)
def test_beam_coordinate_round_trip(sonar, frac):
    assert sonar.beam_coordinate(sonar.beam_angle(frac)) == pytest.approx(frac, abs=1e-9)


def test_beam_table_centres_and_edges():
    s = distorted_sonar()
    np.testing.assert_allclose(s.beam_coordinate(s.beam_angles), np.arange(48), atol=1e-12)
    # returns half a beam beyond the outer centres are dropped
    c = s.beam_angles
    _, _, inside = s.beam_bin([c[0] - 0.51 * (c[1] - c[0]), c[-1] + 0.51 * (c[-1] - c[-2])], [2.0, 2.0])
    assert not inside.any()


def test_out_of_window_returns_are_dropped():
    s = SonarSpec()
    _, _, inside = s.beam_bin([0.0, 0.0, 0.0, math.radians(15)], [0.99, 3.01, 2.0, 2.0])
    assert inside.tolist() == [False, False, True, False]


def test_scan_conversion_places_a_return_at_eq3():
    s = SonarSpec(beams=32, bins=128)
    image = np.zeros((128, 32), np.float32)
    image[90, 5] = 1.0
    fan, (x0, x1, y0, y1) = scan_convert(image, s, pixel_m=0.005, fill=0.0)
    row, col = np.unravel_index(np.argmax(fan), fan.shape)
    x = x0 + (col + 0.5) * 0.005
    y = y1 - (row + 0.5) * 0.005
    ex, ey = fan_xy(s.beam_centres[5], s.bin_ranges[90])
    assert math.hypot(x - ex, y - ey) < 0.0075
    assert fan.dtype == np.float32 and np.all(np.isfinite(fan))


@pytest.mark.parametrize("kwargs, field", [
    (dict(beams=0), "sonar.beams"),
    (dict(beams=2.5), "sonar.beams"),
    (dict(bins=True), "sonar.bins"),
    (dict(range_min=2.0, range_max=1.0), "sonar.range_max_m"),
    (dict(range_min=float("nan")), "sonar.range_min_m"),
    (dict(elevation_fov=0.0), "sonar.elevation_fov_deg"),
    (dict(azimuth_fov=4.0), "sonar.azimuth_fov_deg"),
    (dict(beams=3, azimuth_fov=0.2, beam_angles=np.array([0.1, 0.0, -0.1])), "sonar.beam_angles_deg"),
    (dict(beams=3, azimuth_fov=0.2, beam_angles=np.array([-0.1, 0.0])), "sonar.beam_angles_deg"),
    (dict(beams=3, azimuth_fov=0.5, beam_angles=np.array([-0.1, 0.0, 0.1])), "sonar.azimuth_fov_deg"),
])
def test_bad_sonar_is_one_line_naming_the_field(kwargs, field):
    with pytest.raises(InputError) as err:
        SonarSpec(**kwargs)
    assert field in str(err.value) and "\n" not in str(err.value)


def test_check_image():
    s = SonarSpec(beams=4, bins=8)
    s.check_image(np.zeros((8, 4), np.float32))
    for bad in (np.zeros((4, 8), np.float32), np.zeros((8, 4)), np.full((8, 4), np.nan, np.float32)):
        with pytest.raises(InputError):
            s.check_image(bad, file="x.tiff")


# --- rig ---------------------------------------------------------------------------------

@given(angles)
def test_rotations_are_proper_and_turn_as_documented(a):
    for rot in (rotation_x(a), rotation_y(a), rotation_z(a)):
        np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(rot) == pytest.approx(1.0)
    if 0 < a < math.pi:
        assert (rotation_x(a) @ [0, 1, 0])[2] > 0    # +Y pitched up toward +Z
        assert (rotation_y(a) @ [1, 0, 0])[2] < 0    # +X (right) turned down
        assert (rotation_z(a) @ [0, 1, 0])[0] < 0    # +Y turned toward -X


def test_world_pose_closed_form():
    view = View("v", position=(1.0, 2.0), heading=0.3, roll=0.4, depth_offset=0.05, tilt_offset=0.01)
    rig = Rig((view,))
    rot, s = rig.world_poses(0.5, 0.2)
    expected = rotation_z(0.3) @ rotation_x(0.21) @ rotation_y(0.4)
    np.testing.assert_allclose(rot[0], expected, atol=1e-12)
    np.testing.assert_allclose(s[0], [1.0, 2.0, -0.55])
    # the viewing axis of an unrolled, unturned sonar rises at the tilt angle
    axis = Rig((View("a"),)).world_poses(0.5, 0.2)[0][0] @ [0, 1, 0]
    assert math.atan2(axis[2], axis[1]) == pytest.approx(0.2)


def paper_rig(n_rolls=8, standoff=2.0):
    rolls = [math.radians(-90 + 22.5 * k) for k in range(n_rolls)]
    views = [View(f"S{k}", (0.0, 0.0), 0.0, r) for k, r in enumerate(rolls)]
    views += [View(f"N{k}", (0.0, 2 * standoff), math.pi, r) for k, r in enumerate(rolls)]
    return Rig(tuple(views))


def test_relative_pose_of_reference_is_its_roll():
    """Views at the reference's position, heading and tilt offset: R = Ry(ω), t = 0, exactly at
    every (D, β) (a render on a (D, β) grid shares their poses bit for bit); a view with its own
    tilt offset δβ turns by Rx(δβ) Ry(ω)."""
    rig = Rig(paper_rig().views + (View("off", (0.0, 0.0), 0.0, 0.3, tilt_offset=0.05),))
    rot, t = rig.relative_poses(np.array([0.40, 0.43, 0.50]), np.array([0.0, 0.18, 0.31]))
    for k in range(8):
        for g in range(3):
            np.testing.assert_array_equal(rot[g, k], rotation_y(rig.views[k].roll))
            np.testing.assert_array_equal(t[g, k], 0.0)
    np.testing.assert_allclose(rot[:, 16], np.broadcast_to(rotation_x(0.05) @ rotation_y(0.3), (3, 3, 3)), atol=1e-12)


def test_tilt_moves_the_opposite_view():
    """The N view, 4 m ahead at the same depth: t_N = Rx(β)ᵀ (0, 4, 0) = (0, 4 cos β, -4 sin β)."""
    rig = paper_rig()
    for beta in (0.0, 0.1, 0.2):
        rot, t = rig.relative_poses(0.43, beta)
        np.testing.assert_allclose(t[8], [0, 4 * math.cos(beta), -4 * math.sin(beta)], atol=1e-12)
        # unrolled N view looks back along the reference's axis, pitched by 2β about X
        np.testing.assert_allclose(rot[12], rotation_x(-beta) @ rotation_z(math.pi) @ rotation_x(beta), atol=1e-12)
    t_a = rig.relative_poses(0.43, 0.18)[1][8]
    t_b = rig.relative_poses(0.43, 0.18 + math.radians(1))[1][8]
    assert np.linalg.norm(t_a - t_b) > 0.06      # 1° of tilt moves it about 7 cm
    t_c = rig.relative_poses(0.50, 0.18)[1][8]   # depth alone moves nothing relative
    np.testing.assert_allclose(t_a, t_c, atol=1e-12)


@given(point, depths, tilts)
@settings(max_examples=50)
def test_relative_poses_agree_with_world_poses(p_world, depth, tilt):
    rig = paper_rig()
    rot_w, s_w = rig.world_poses(depth, tilt)
    rot, t = rig.relative_poses(depth, tilt)
    p_ref = world_to_reference(p_world, rig, depth, tilt)
    np.testing.assert_allclose(reference_to_world(p_ref, rig, depth, tilt), p_world, atol=1e-9)
    for m in (3, 9, 15):
        p_view = (p_world - s_w[m]) @ rot_w[m]
        np.testing.assert_allclose(rot[m] @ p_view + t[m], p_ref, atol=1e-9)
        np.testing.assert_allclose(to_view(p_ref, rot[m], t[m]), p_view, atol=1e-9)


def test_grid_of_candidates_broadcasts():
    rig = paper_rig()
    depths, tilts = np.meshgrid(np.linspace(0.4, 0.5, 3), np.linspace(0.1, 0.2, 4), indexing="ij")
    rot, t = rig.relative_poses(depths, tilts)
    assert rot.shape == (3, 4, 16, 3, 3) and t.shape == (3, 4, 16, 3)
    one_rot, one_t = rig.relative_poses(depths[2, 1], tilts[2, 1])
    np.testing.assert_allclose(rot[2, 1], one_rot)
    np.testing.assert_allclose(t[2, 1], one_t)
    n, d = surface_in_views(rig, depths, tilts)
    assert n.shape == (3, 4, 16, 3) and d.shape == (3, 4, 16)


def test_one_candidate_is_remembered_read_only_and_equals_the_grid():
    """A pose step asks for the poses of one (D, β) several times: the result for one
    candidate (a scalar or a (1,) array) is remembered, read-only, and equals that cell of a
    grid bit for bit; a new candidate gets its own."""
    rig = paper_rig()
    depths, tilts = np.array([0.41, 0.43, 0.47]), np.array([0.15, 0.18, 0.2])
    grid_rot, grid_t = rig.relative_poses(depths, tilts)
    grid_ref = rig.reference_pose(depths, tilts)
    for i in range(3):
        for d, t in ((depths[i], tilts[i]), (depths[i:i + 1], tilts[i:i + 1])):
            rot, trans = rig.relative_poses(d, t)
            assert rot.shape == grid_rot.shape[1:] if np.ndim(d) == 0 else rot.shape == (1, 16, 3, 3)
            np.testing.assert_array_equal(rot.reshape(16, 3, 3), grid_rot[i])
            np.testing.assert_array_equal(trans.reshape(16, 3), grid_t[i])
            for mine, grid in zip(rig.reference_pose(d, t), grid_ref):
                np.testing.assert_array_equal(mine.reshape(grid[i].shape), grid[i])
            assert rig.relative_poses(d, t)[0] is rot  # remembered
            with pytest.raises(ValueError, match="read-only"):
                rot[..., 0, 0] = 2.0
    assert rig.relative_poses(0.41, 0.15)[0] is not rig.relative_poses(0.41, 0.16)[0]
    assert rig.relative_poses(0.52, 0.15)[0] is rig.relative_poses(0.41, 0.15)[0]  # by the tilt alone
    grid = rig.relative_poses(depths, tilts)[0]
    assert grid.flags.writeable and grid is not grid_rot  # grids are computed each time


def test_a_grid_that_repeats_its_tilts_equals_each_candidate():
    """A (D, β) grid repeats each tilt along D (its rotations are found once per tilt): every
    cell's world and relative poses and surface equal, bit for bit, those of that candidate
    alone, in grids of several shapes (and in one whose tilts all differ); the relative poses
    and the surface normals do not move with the depth at all, even for a view with depth and
    tilt offsets (the same bits); ``view_planes`` gives the same poses and planes at once."""
    rig = Rig(paper_rig().views + (View("off", (0.3, 0.1), 0.2, 0.3, depth_offset=0.07, tilt_offset=0.05),))
    depths, tilts = np.meshgrid(np.linspace(0.38, 0.52, 5), np.radians([8.0, 9.5, 11.0, 9.5]), indexing="ij")
    for d, t in ((depths, tilts), (depths.ravel(), tilts.ravel()), (depths[:, :1], tilts),
                 (depths[:, 0], np.radians([8.0, 8.5, 9.0, 9.5, 10.0]))):
        d, t = np.broadcast_arrays(d, t)
        grid = (*rig.relative_poses(d, t), *rig.world_poses(d, t), *surface_in_views(rig, d, t))
        at_once = view_planes(rig, d, t)
        for mine, theirs in zip(at_once, grid[:2] + grid[4:]):
            np.testing.assert_array_equal(mine, theirs)
        if d.ndim == 2:  # depth along the first axis
            for same_tilt in (grid[0], grid[1], grid[4]):
                np.testing.assert_array_equal(same_tilt, np.broadcast_to(same_tilt[:1], same_tilt.shape))
        for cell in np.ndindex(d.shape):
            alone = (*rig.relative_poses(float(d[cell]), float(t[cell])),
                     *rig.world_poses(float(d[cell]), float(t[cell])),
                     *surface_in_views(rig, float(d[cell]), float(t[cell])))
            for mine, whole in zip(alone, grid):
                np.testing.assert_array_equal(mine, whole[cell])


def test_new_rolls_lie_in_a_turn_and_each_name_is_one_roll():
    """``with_rolls`` (render --roll): a roll given twice makes one view; rolls beyond ±180°
    (a manifest's range) and two rolls that share a 6-digit name are refused, naming --roll
    in degrees; depth and tilt are checked with their options' names, the tilt in degrees."""
    from fsswarp.errors import check_depth_tilt
    from fsswarp.rig import with_rolls

    rig = paper_rig()
    extended, names = with_rolls(rig, [math.radians(10.0), math.radians(10.0), math.radians(-180.0)])
    assert names == ["roll10", "roll-180"] and len(extended.views) == len(rig.views) + 2
    for degrees, text in ((200.0, r"--roll = 200\.0.*\[-180, 180\]"), (1e6, r"--roll = 1000000\.0"),
                          (float("nan"), "--roll = nan")):
        with pytest.raises(InputError, match=text):
            with_rolls(rig, [math.radians(degrees)])
    with pytest.raises(InputError, match=r"--roll = 0\.10000000001: differs .* roll0\.1"):
        with_rolls(rig, [math.radians(0.1), math.radians(0.10000000001)])
    with pytest.raises(InputError, match=r"--tilt = 95\.0: must be a finite tilt in \(-90, 90\) degrees"):
        check_depth_tilt(0.4, np.float64(math.radians(95.0)))
    with pytest.raises(InputError, match=r"--depth = nan"):
        check_depth_tilt(float("nan"), 0.1)
    with pytest.raises(InputError, match=r"--depth = 'deep'"):
        check_depth_tilt("deep", 0.1)


def test_rig_errors():
    with pytest.raises(InputError, match="unique"):
        Rig((View("a"), View("a")))
    with pytest.raises(InputError):
        Rig(())
    with pytest.raises(InputError):
        View("a", heading=float("nan"))
    with pytest.raises(InputError):
        View("../evil")


# --- surface -----------------------------------------------------------------------------

@given(depths, tilts)
def test_surface_in_reference_closed_form(depth, tilt):
    n, d = surface_in_reference(paper_rig(), depth, tilt)
    np.testing.assert_allclose(n, [0, math.sin(tilt), math.cos(tilt)], atol=1e-12)
    assert d == pytest.approx(depth)


@given(depths, tilts, st.floats(-0.2, 0.2, **finite))
@settings(max_examples=50)
def test_surface_in_views_is_the_world_plane(depth, tilt, depth_offset):
    views = tuple(View(f"v{k}", (0.3 * k, 1.0 - k), 0.7 * k, 0.4 * k - 1, depth_offset * (k % 2), 0.02 * k)
                  for k in range(4))
    rig = Rig(views, reference=1)
    n, d = surface_in_views(rig, depth, tilt)
    rot_w, s_w = rig.world_poses(depth, tilt)
    for m, view in enumerate(views):
        # the distance from each sonar to the surface is its own depth
        assert d[m] == pytest.approx(depth + view.depth_offset, abs=1e-9)
        # world points with z = 0 satisfy the view-frame plane equation
        for xy in ((0.0, 0.0), (1.5, -2.0)):
            p_view = (np.array([*xy, 0.0]) - s_w[m]) @ rot_w[m]
            assert float(n[m] @ p_view) == pytest.approx(d[m], abs=1e-9)


@given(point, st.tuples(coords, coords, coords), st.floats(-3, 3, **finite))
def test_mirror_is_an_involution(p, raw_normal, offset):
    n = np.array(raw_normal)
    if np.linalg.norm(n) < 1e-3:
        n = np.array([0.0, 0.0, 1.0])
    n = n / np.linalg.norm(n)
    q = mirror_points(p, n, offset)
    np.testing.assert_allclose(mirror_points(q, n, offset), p, atol=1e-9)
    assert float(n @ q - offset) == pytest.approx(-float(n @ p - offset), abs=1e-9)
    v = mirror_vectors(p, n)
    assert np.linalg.norm(v) == pytest.approx(np.linalg.norm(p))
    np.testing.assert_allclose(mirror_vectors(v, n), p, atol=1e-9)


def test_apparent_returns_closed_form():
    """Level sonar (β = 0) at depth 0.5 m, point 2 m ahead, 0.1 m above the sonar."""
    n, d = np.array([0.0, 0.0, 1.0]), 0.5
    r = apparent_returns(np.array([0.0, 2.0, 0.1]), n, d)
    direct, surface = math.hypot(2.0, 0.1), math.hypot(2.0, 0.9)
    assert r["object"][1] == pytest.approx(direct)
    assert r["ghost"][1] == pytest.approx(0.5 * (direct + surface))
    assert r["mirror"][1] == pytest.approx(0.5 * (direct + surface))
    assert r["mirror2"][1] == pytest.approx(surface)
    for name in r:
        assert r[name][0] == pytest.approx(0.0)


below = st.tuples(st.floats(-1.0, 1.0, **finite), st.floats(0.5, 3.0, **finite), st.floats(0.01, 0.6, **finite))


@given(below, depths, tilts)
def test_ghost_is_farther_than_the_object_below_the_surface(point_spec, depth, tilt):
    """Sonar and point below the surface: |P'| > |P|, so ghost and mirror lie behind the object."""
    rig = Rig((View("s"),))
    n, d = surface_in_views(rig, depth, tilt)
    x, y, depth_below_surface = point_spec
    # a point of the reference frame at the given depth below the surface
    p = np.array([x, y, 0.0])
    p = p + (d[0] - depth_below_surface - float(n[0] @ p)) * n[0]
    r = apparent_returns(p, n[0], d[0])
    assert r["ghost"][1] > r["object"][1]
    assert r["mirror"][1] == pytest.approx(r["ghost"][1])
    assert r["mirror2"][1] > r["ghost"][1]
    assert r["ghost"][0] == r["object"][0]


def rolled_returns(roll, depth, tilt, p_ref):
    rig = Rig((View("ref"), View("rolled", roll=roll)))
    rot, t = rig.relative_poses(depth, tilt)
    n, d = surface_in_views(rig, depth, tilt)
    return apparent_returns(to_view(p_ref, rot[1], t[1]), n[1], d[1])


near_axis = st.tuples(st.floats(-0.05, 0.05, **finite), st.floats(1.5, 2.5, **finite),
                      st.floats(-0.1, 0.1, **finite))


near_surface = st.floats(0.2, 0.6, **finite)
sensor_tilts = st.floats(math.radians(5), math.radians(15), **finite)


@given(near_axis, near_surface, sensor_tilts)
def test_mirror_falls_on_the_ghost_at_zero_roll(p, depth, tilt):
    """Zero roll: the mirror stays in the point's vertical plane (same X), at the ghost's
    range; for a level sonar it coincides exactly, and near the axis it is within one 0.3°
    beam (the paper's sensor class: D 0.2–0.6 m, β 5–15°)."""
    p = np.array(p)
    rig = Rig((View("s"),))
    n, d = surface_in_views(rig, depth, tilt)
    assert mirror_points(p, n[0], d[0])[0] == pytest.approx(p[0], abs=1e-12)
    r = rolled_returns(0.0, depth, tilt, p)
    assert r["mirror"][1] == pytest.approx(r["ghost"][1])
    assert np.sign(r["mirror"][0]) == np.sign(r["ghost"][0]) or abs(r["ghost"][0]) < 1e-12
    assert abs(r["mirror"][0] - r["ghost"][0]) < math.radians(0.3)
    level = rolled_returns(0.0, depth, 0.0, p)
    assert level["mirror"][0] == pytest.approx(level["ghost"][0], abs=1e-12)


@given(near_axis, st.floats(0.3, 1.0, **finite), st.floats(0.05, 0.3, **finite))
def test_mirror_separates_when_rolled(p, depth, tilt):
    """At 45° roll the surface normal gains an azimuth component: the mirror moves away from
    the ghost by about atan(2h·sin45°·cos β / R), many beams for a point near the axis."""
    p_ref = np.array(p)
    r = rolled_returns(math.radians(45), depth, tilt, p_ref)
    n, d = surface_in_reference(Rig((View("r"),)), depth, tilt)
    h = d - float(n @ p_ref)   # the point's depth below the surface
    assume(h > 0.1)
    separation = abs(r["mirror"][0] - r["ghost"][0])
    assert separation > 0.5 * math.atan(2 * h * math.sin(math.radians(45)) * math.cos(tilt) / 3.5)
    assert separation > math.radians(3 * 0.3)   # at least three 0.3° beams
