"""The sensors as priors (fsswarp.pose: Prior, fit_posterior, noise_level, check_start; DESIGN §7)
against closed forms: a synthetic quadratic valley has an analytic Gaussian posterior."""

import math

import numpy as np
import pytest

from fsswarp.compare import PoseSettings
from fsswarp.errors import InputError
from fsswarp.pose import (CARVING_ERROR, POSTERIOR_CELLS, Posterior, Prior, Z95, check_start, fit_posterior,
                          model_lever, noise_level, surface_range, valley_posterior)


#: Each view's deviation pattern (sum 0, sum of squares V − 1), scaled by SIGMA.
PATTERN = np.array([1.2, -0.4, 0.9, -1.3, 0.5, -0.9])
PATTERN = (PATTERN - PATTERN.mean()) * math.sqrt((len(PATTERN) - 1) / np.sum((PATTERN - PATTERN.mean()) ** 2))
SIGMA = 4e-4


class ValleyComparison:
    """A stand-in for ViewComparison whose per-view surrogate is a quadratic valley
    E(x) = ½ (x − c)ᵀ A (x − c) in (m, rad), plus each view's own offset, plus a cell × view
    interaction σ·z_v·h (h = ±1 in a checkerboard over the grid): the views' mean is E, and the
    noise of a cell's mean (``noise_level``) has the closed form of ``expected_noise``, so that
    exp(−(E − min E)/s) × prior is an exact Gaussian."""

    def __init__(self, centre, hessian, sigma=SIGMA):
        self.centre, self.hessian, self.sigma = np.asarray(centre, float), np.asarray(hessian, float), sigma
        self.settings = PoseSettings()
        self.counters = {"grid_cells": 0}

    def surrogate_views(self, depths, tilts, *, cap, samples):
        x = np.stack([depths - self.centre[0], tilts - self.centre[1]], axis=-1)
        value = 0.5 * np.einsum("...i,ij,...j->...", x, self.hessian, x)
        checker = (-1.0) ** np.add.outer(*map(np.arange, depths.shape))
        offsets = np.linspace(0.001, 0.003, len(PATTERN))
        return value[..., None] + offsets + self.sigma * checker[..., None] * PATTERN


def expected_noise(sigma, shape, views=len(PATTERN)):
    """σ_ε/√V of the two-way residuals of ValleyComparison's table on a grid of ``shape``: the
    residual is σ z_v (h − h̄), so σ_ε² = σ² (V − 1) Σ(h − h̄)² / ((G − 1)(V − 1))."""
    checker = (-1.0) ** np.add.outer(*map(np.arange, shape))
    cells = checker.size
    return sigma * math.sqrt(np.sum((checker - checker.mean()) ** 2) / (cells - 1) / views)


def analytic(comparison, prior, shape=(11, 11)):
    """Mean (2,) and covariance (2, 2) of the Gaussian posterior of ``ValleyComparison``."""
    s = expected_noise(comparison.sigma, shape)
    sigma = np.array([prior.depth_sigma, prior.tilt_sigma])
    precision = comparison.hessian / s + np.diag(1.0 / sigma ** 2)
    covariance = np.linalg.inv(precision)
    mean = covariance @ (comparison.hessian / s @ comparison.centre + np.array([prior.depth, prior.tilt]) / sigma ** 2)
    return mean, covariance


@pytest.mark.parametrize("slope_m_per_deg", [0.034, 0.0])
def test_a_quadratic_valley_gives_the_analytic_interval(slope_m_per_deg):
    # a valley along D − L·β = const (L = slope in m/rad), stiff across it, flat along it
    slope = slope_m_per_deg * 180.0 / math.pi
    across = np.array([1.0, -slope]) / math.hypot(1.0, slope)
    hessian = 40.0 * np.outer(across, across) + 1e-3 * np.eye(2)
    comparison = ValleyComparison((0.431, math.radians(10.35)), hessian)
    prior = Prior(0.432, math.radians(11.1), 0.003, math.radians(0.6))
    mean, covariance = analytic(comparison, prior)
    axes = np.diag([0.01, math.radians(1.0)])  # a first grid far from the posterior's size: refitted
    post = fit_posterior(comparison, prior, float(mean[0]), float(mean[1]), axes)
    assert post.noise == pytest.approx(expected_noise(SIGMA, (11, 11)), rel=1e-9)
    np.testing.assert_allclose(post.covariance, covariance, rtol=0.03, atol=1e-3 * np.abs(covariance).max())
    for index in (0, 1):
        lo, hi = post.interval(index)
        half = Z95 * math.sqrt(covariance[index, index])
        assert lo == pytest.approx(mean[index] - half, rel=1e-4, abs=0.03 * half)
        assert hi == pytest.approx(mean[index] + half, rel=1e-4, abs=0.03 * half)
    summary = post.summary()
    assert summary["valley"]["slope_m_per_deg"] == pytest.approx(slope_m_per_deg, abs=0.002)
    assert comparison.counters["grid_cells"] in (121, 242, 363)  # refitted to ± 4 sigma at most twice


def test_every_posterior_grid_has_rows_of_one_tilt():
    # a valley along D − L·β: the grids that fit it are tilted; each is sheared so that a row's
    # cells share one tilt bit for bit (the renderer then shares their poses), holding the same
    # ellipse as the tilted grid would
    slope = 0.034 * 180.0 / math.pi
    across = np.array([1.0, -slope]) / math.hypot(1.0, slope)
    comparison = ValleyComparison((0.431, math.radians(10.35)), 40.0 * np.outer(across, across) + 1e-3 * np.eye(2))
    asked = []
    surrogate = comparison.surrogate_views
    comparison.surrogate_views = lambda d, t, **k: asked.append((d, t)) or surrogate(d, t, **k)
    prior = Prior(0.432, math.radians(11.1), 0.003, math.radians(0.6))
    angle = 0.7
    axes = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]]) @ np.diag([0.004, 0.01])
    fit_posterior(comparison, prior, 0.431, math.radians(10.35), axes)
    assert len(asked) >= 2
    for depths, tilts in asked:
        assert np.all(tilts == tilts[:1]) and len(np.unique(tilts)) == POSTERIOR_CELLS
        assert len(np.unique(depths)) == depths.size  # sheared: no column of one depth
    depths, tilts = asked[0]
    first = np.stack([depths[[0, -1, 0], [0, 0, -1]], tilts[[0, -1, 0], [0, 0, -1]]])
    sheared = (first[:, 1:] - first[:, :1]) / 2  # the grid's axes, from its corners
    np.testing.assert_allclose(sheared @ sheared.T, axes @ axes.T, rtol=1e-9)


@pytest.mark.parametrize("fine_first, launches", [(False, 2), (True, 1)])
def test_a_first_grid_that_fits_saves_the_refit(fine_first, launches):
    # the loop starts each pose step's posterior grid from the last step's axes, evaluated
    # finely at once: when they fit, that one launch (else a coarse and a fine one) gives the
    # same posterior as a far first grid refitted
    slope = 0.034 * 180.0 / math.pi
    across = np.array([1.0, -slope]) / math.hypot(1.0, slope)
    hessian = 40.0 * np.outer(across, across) + 1e-3 * np.eye(2)
    prior = Prior(0.432, math.radians(11.1), 0.003, math.radians(0.6))
    far = ValleyComparison((0.431, math.radians(10.35)), hessian)
    post = fit_posterior(far, prior, 0.431, math.radians(10.35), np.diag([0.01, math.radians(1.0)]))
    assert far.counters["grid_cells"] == 3 * POSTERIOR_CELLS ** 2
    near = ValleyComparison((0.431, math.radians(10.35)), hessian)
    again = fit_posterior(near, prior, 0.431, math.radians(10.35), post.axes(), fine_first=fine_first)
    assert near.counters["grid_cells"] == launches * POSTERIOR_CELLS ** 2
    np.testing.assert_allclose(again.covariance, post.covariance, rtol=0.03, atol=1e-3 * np.abs(post.covariance).max())
    wrong = ValleyComparison((0.431, math.radians(10.35)), hessian)  # far axes, finely first: refitted
    refitted = fit_posterior(wrong, prior, 0.431, math.radians(10.35), np.diag([0.01, math.radians(1.0)]),
                             fine_first=fine_first)
    assert wrong.counters["grid_cells"] == 3 * POSTERIOR_CELLS ** 2
    np.testing.assert_allclose(refitted.covariance, post.covariance, rtol=0.03,
                               atol=1e-3 * np.abs(post.covariance).max())


@pytest.mark.parametrize("axes", [np.zeros((2, 2)), np.eye(3), np.array([[1.0, math.nan], [0.0, 1.0]]),
                                  np.array([[0.01, 0.02], [0.001, 0.002]])])
def test_estimate_pose_refuses_axes_that_span_no_area(coral_one, axes):
    from fsswarp.pose import estimate_pose

    with pytest.raises(InputError, match="posterior_axes = .*: must be \\(2, 2\\) finite axes spanning an area") \
            as info:
        estimate_pose(coral_one.truth_mesh(), coral_one, posterior_axes=axes)
    assert "\n" not in str(info.value)


def test_identified_means_half_the_prior_interval():
    comparison = ValleyComparison((0.43, 0.18), np.diag([1e-9, 1e-9]))  # flat: no data
    prior = Prior(0.43, 0.18, 0.003, 0.01)
    post = fit_posterior(comparison, prior, 0.43, 0.18, np.diag([0.012, 0.04]))
    assert post.identified() == {"depth": False, "tilt": False}
    (d0, d1), (t0, t1) = post.interval(0), post.interval(1)
    assert d1 - d0 == pytest.approx(2 * Z95 * 0.003, rel=0.03) and t1 - t0 == pytest.approx(2 * Z95 * 0.01, rel=0.03)
    stiff = ValleyComparison((0.43, 0.18), np.diag([1e4, 1e4]))
    assert fit_posterior(stiff, prior, 0.43, 0.18, np.diag([0.012, 0.04])).identified() == {"depth": True,
                                                                                            "tilt": True}


def test_noise_level_removes_the_views_own_offsets():
    comparison = ValleyComparison((0.43, 0.18), np.diag([30.0, 2.0]))
    depths, tilts = np.meshgrid(np.linspace(0.42, 0.44, 7), np.linspace(0.17, 0.19, 5), indexing="ij")
    table = comparison.surrogate_views(depths, tilts, cap=None, samples=None)
    assert noise_level(table) == pytest.approx(expected_noise(SIGMA, (7, 5)), rel=1e-9)
    assert noise_level(table + np.linspace(0.0, 0.05, len(PATTERN))) == pytest.approx(noise_level(table), rel=1e-9)
    with_nan = table.copy()
    with_nan[0, 0, 2] = np.nan  # a view without a value in one cell is left out
    assert noise_level(with_nan) == pytest.approx(noise_level(np.delete(table, 2, axis=-1)), rel=1e-12)
    values = np.array([1.0, 2.0, 4.0, np.nan])  # one cell: the standard error of its values
    assert noise_level(values) == pytest.approx(np.std([1.0, 2.0, 4.0], ddof=1) / math.sqrt(3))
    assert noise_level(np.array([0.002])) == 0.002 and noise_level(np.zeros(4)) == 1e-6


def test_a_prior_with_infinite_sigma_adds_nothing():
    prior = Prior(0.43, 0.18, math.inf, math.inf)
    assert prior.penalty(np.array([0.1, 5.0]), np.array([0.0, 1.0])).tolist() == [0.0, 0.0]


@pytest.mark.parametrize("field, change, shown", [
    ("surface.depth_sigma_m", dict(depth_sigma=0.0), "0.0"),
    ("surface.tilt_sigma_deg", dict(tilt_sigma=0.0), "0.0")])
def test_a_prior_needs_a_positive_sigma(coral_one, field, change, shown):
    import dataclasses

    manifest = coral_one.manifest
    spoilt = dataclasses.replace(coral_one, manifest=dataclasses.replace(
        manifest, surface=dataclasses.replace(manifest.surface, **change)))
    with pytest.raises(InputError, match=f"dataset.toml: {field} = {shown}: must be > 0") as info:
        Prior.of(spoilt)
    assert "\n" not in str(info.value)


def test_starts_that_cannot_be_right_are_refused(coral_one):
    surface = coral_one.manifest.surface
    check_start(coral_one, surface.depth + 0.01, surface.tilt + math.radians(2.0))  # within 5 sigma
    with pytest.raises(InputError, match=r"--depth = 47.0: is .* sigma from the measured 0.432 m"):
        check_start(coral_one, 47.0, surface.tilt)  # centimetres typed as metres
    with pytest.raises(InputError, match=r"--tilt = 0.19: is .* sigma from the measured 11.1 deg"):
        check_start(coral_one, surface.depth, math.radians(0.19))  # radians typed as degrees
    # the surface beyond every beam's range: no ghost or mirror can be seen
    assert surface_range(coral_one, surface.depth, surface.tilt) < coral_one.sonar.range_max
    far = surface_range(coral_one, 3.5, surface.tilt)
    assert far > coral_one.sonar.range_max
    import dataclasses

    wide = dataclasses.replace(coral_one, manifest=dataclasses.replace(coral_one.manifest, surface=dataclasses.replace(
        surface, depth_sigma=1.0)))
    with pytest.raises(InputError, match="--depth = 3.5: puts the sea surface .* beyond the range window"):
        check_start(wide, 3.5, surface.tilt)


def test_surface_range_is_the_closed_form_for_a_level_sonar(coral_one):
    # one view, no roll: the top edge of the elevation aperture meets the plane at D / sin(β + W_φ)
    import dataclasses

    from fsswarp.rig import Rig

    level = dataclasses.replace(coral_one.rig.views[0], roll=0.0, heading=0.0, depth_offset=0.0, tilt_offset=0.0)
    one = dataclasses.replace(coral_one, manifest=dataclasses.replace(coral_one.manifest, rig=Rig((level,), 0)))
    depth, tilt = 0.5, math.radians(5.0)
    expected = depth / math.sin(tilt + coral_one.sonar.elevation_fov / 2)
    assert surface_range(one, depth, tilt) == pytest.approx(expected, rel=1e-9)


def _height_only(seed: int, lever: float = 2.0, sensors=(0.003, 0.6)):
    """A pose step whose likelihood fixes only the height h = D − L·β: N(aᵀθ; g, v), a =
    (1, −L), with the sensors' prior; its conditional Posterior in closed form, and the exact
    Gaussian posterior (mean, covariance) written out by hand."""
    rng = np.random.default_rng(seed)
    prior = Prior(0.432 + rng.normal(0, 0.002), math.radians(11.0 + rng.normal(0, 0.3)), sensors[0],
                  math.radians(sensors[1]))
    a = np.array([1.0, -lever])
    g, v = 0.43 - lever * math.radians(10.3) + rng.normal(0, 0.002), rng.uniform(0.5, 3.0) * 1e-3 ** 2
    precision0 = np.diag([prior.depth_sigma ** -2, prior.tilt_sigma ** -2])
    covariance = np.linalg.inv(precision0 + np.outer(a, a) / v)
    mean = covariance @ (precision0 @ np.array([prior.depth, prior.tilt]) + a * g / v)
    conditional = Posterior(float(mean[0]), float(mean[1]), covariance, prior, math.nan, math.nan, 1e-4)
    return prior, a, g, v, conditional, mean, covariance


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_valley_posterior_of_a_height_only_likelihood_is_the_closed_form(seed):
    """Without the carving error, a conditional posterior that already is prior × N(aᵀθ; g, v)
    comes back unchanged, and the valley is the line D = g + L·β."""
    lever = 1.9 + 0.1 * seed
    prior, a, g, v, conditional, mean, covariance = _height_only(seed, lever)
    found = valley_posterior(conditional, lever, carving_error=np.zeros((2, 2)))
    assert np.allclose([found.depth, found.tilt], mean, rtol=0, atol=1e-10)
    assert np.allclose(found.covariance, covariance, rtol=1e-8)
    assert found.valley_slope == lever
    assert found.valley_depth == pytest.approx(g + lever * found.tilt, abs=1e-10)


def test_the_valley_posterior_drops_the_tilt_a_fixed_shape_claims():
    """A conditional posterior that pins β too (a fixed shape) keeps only what it says about the
    height: the tilt interval is the prior's narrowed by the depth sensor through the valley."""
    lever = 2.0
    prior, a, g, v, _, _, _ = _height_only(4, lever, sensors=(0.05, 2.0))
    sharp = np.diag([0.001, math.radians(0.05)]) ** 2  # a fixed shape: both pinned
    conditional = Posterior(0.43, math.radians(10.3), sharp, prior, math.nan, math.nan, 1e-4)
    found = valley_posterior(conditional, lever, carving_error=np.zeros((2, 2)))
    v_c, v_0 = a @ sharp @ a, a @ np.diag([prior.depth_sigma, prior.tilt_sigma]) ** 2 @ a
    v_h = 1 / (1 / v_c - 1 / v_0)
    expected = np.linalg.inv(np.diag([prior.depth_sigma ** -2, prior.tilt_sigma ** -2]) + np.outer(a, a) / v_h)
    assert np.allclose(found.covariance, expected, rtol=1e-8)
    # the poor sensors (5 cm, 2°) at a 2 m standoff: 1/σ_β² = 1/(2°)² + (L/5 cm)², not identified
    tilt_sigma = math.degrees(math.sqrt(found.covariance[1, 1]))
    assert tilt_sigma == pytest.approx((0.25 + (lever * math.pi / 180 / 0.05) ** 2) ** -0.5, rel=0.01)
    assert found.identified() == {"depth": False, "tilt": False}  # D = h + L·β: as loose as β


def test_the_carving_error_widens_the_interval_toward_the_prior():
    prior, a, g, v, conditional, _, _ = _height_only(5)
    widths = [valley_posterior(conditional, 2.0, carving_error=scale * CARVING_ERROR).covariance[1, 1]
              for scale in (0.0, 1.0, 1e9)]
    assert widths[0] < widths[1] < widths[2] <= prior.tilt_sigma ** 2 * (1 + 1e-6)
    assert widths[2] == pytest.approx(prior.tilt_sigma ** 2, rel=1e-3)


def test_a_conditional_that_adds_nothing_on_the_height_leaves_the_prior():
    prior = Prior(0.45, math.radians(10.9), 0.003, math.radians(0.6))
    same = Posterior(0.45, math.radians(10.9), np.diag([0.003, math.radians(0.6)]) ** 2, prior, math.nan, math.nan,
                     1e-4)
    found = valley_posterior(same, 2.0)
    assert np.allclose([found.depth, found.tilt], [prior.depth, prior.tilt], atol=1e-12)
    assert np.allclose(found.covariance, same.covariance, rtol=1e-9)


def test_the_lever_is_the_horizontal_distance_to_the_model(coral_one):
    """For the usual reference, −∂(D − n(β)·c)/∂β = c_y cos β − c_z sin β: the centroid's
    horizontal distance ahead of the reference sonar (closed form, n = (0, sin β, cos β))."""
    import trimesh

    tilt = math.radians(10.3)
    ahead = np.array([0.0, 2.0 * math.cos(tilt) + 0.3 * math.sin(tilt), 0.3 * math.cos(tilt) - 2.0 * math.sin(tilt)])
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    box.apply_translation(ahead)
    lever = model_lever(box, coral_one.rig, 0.43, tilt)
    assert lever == pytest.approx(ahead[1] * math.cos(tilt) - ahead[2] * math.sin(tilt), rel=1e-6)
    assert lever == pytest.approx(2.0, rel=1e-6)
