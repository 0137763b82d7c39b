"""The comparison of a model's synthetic views with the data (paper §2.4–2.5, eq. 5–7; DESIGN §2,
§3, §7): what the pose step, the shape refinement and the loop's metrics all measure.

:class:`ViewComparison` holds a dataset's side of the comparison, over the views marked
``optimize`` (highlight masks, detection thresholds), and a model located at an estimate
(D m, β rad) (:meth:`ViewComparison.use`): the synthetic layers rendered there stay on the
device, and the data contours (:class:`DataContours`), the anchor views and the detection
shift (rows) are found from them. Queries at any (D, β) then give

- the grid surrogate (:meth:`~ViewComparison.surrogate`): per cell the mean over the views of
  the distance (m) of the synthetic object and mirror contour points to the data's contour,
  saturating at a cap, each data point without a synthetic counterpart counting the cap;
- E_mu of eq. 6 (:meth:`~ViewComparison.exact`, :class:`ExactError`): the ICP motions of the
  synthetic contours (``fsswarp.icp``), carried to the frontal patches (ray casting) and to
  3-D patch motions (``fsswarp.motion.patch_motions``), then μ_m (``fsswarp.metrics.view_errors``);
- CE per view (eq. 5, :meth:`~ViewComparison.contour_errors`).

Contours: the data's is the ``fsswarp.segment`` highlight's first row per beam inside the
view's range window; the synthetic one is the first crossing, between rows, of the data's
detection threshold (:func:`detection_threshold`) by the smoothed synthetic layers (object +
ghost; mirror + double-bounce mirror), shifted by the detection shift. Arrays: layers
(V, 4, bins, beams) float32; contours (V, 2, beams) rows, -1 where a beam has none;
distances (V, 2, bins, beams) float32 m. :func:`view_contours` gives what E_mu compares, for figures.
"""

from __future__ import annotations

import functools
import math
import warnings
from dataclasses import dataclass, field, replace

import numpy as np

from .backends import beams_read, most_launch_views, most_layer_views, rows_read
from .errors import InputError, check_depth_tilt, check_integer, is_finite_number, is_integer, is_number
from .icp import CONTOUR_TOL, icp_many
from .metrics import view_errors
from .motion import patch_motions
from .rendering import RenderSettings, check_mesh
from .segment import SegmentSettings, memoized, normalized, segment_views
from .surface import mirror_points, surface_in_reference, view_planes

#: γ and surface reflection of every synthetic view of a comparison: the renderer's defaults.
ECHO = RenderSettings()


class PoseWarning(UserWarning):
    """A view left out of the pose estimation (the model is not seen in it)."""


@dataclass(frozen=True)
class PoseSettings:
    """Options of the view comparison and of the (D, β) search (``fsswarp.pose``).

    samples : (K_θ, K_φ) sub-rays of the finest grid level's synthetic views; exact_samples :
        those of E_mu and of the located layers that place windows and mirror beams
    coarse_samples : those of the grid levels before the finest
    grid : (cells along D, cells along β) per level
    cap, min_cap : distance (m) at which the surrogate's contour distances saturate: ``cap``
        on the first grid level, halved per level down to ``min_cap`` (used by the detection
        shift and E_mu)
    margin_beams : beams added on each side of a predicted object span
    min_mirror_beams : fewest mirror contour points for a view's mirror term
    window : m added before and after the predicted returns to make a view's range window
    shifts : candidate range shifts (rows) of the synthetic contours (the detection bias)
    polish : nlopt evaluations of E_mu at most (0: no polish)
    patch_rays : elevation rays per beam of the frontal-patch search
    launch_bytes : most device memory (bytes) of one render launch's layers (16 B per
        pixel); a larger grid level is split into several launches
    segment : segmentation of the data
    """

    samples: tuple[int, int] = (2, 64)
    coarse_samples: tuple[int, int] = (1, 32)
    exact_samples: tuple[int, int] = (2, 64)
    grid: tuple[int, int] = (9, 9)
    cap: float = 0.05
    min_cap: float = 0.015
    margin_beams: int = 2
    min_mirror_beams: int = 4
    window: float = 0.1
    shifts: tuple[float, ...] = tuple(0.5 + 0.1 * k for k in range(-20, 21))
    polish: int = 30
    patch_rays: int = 64
    launch_bytes: int = 4 << 30
    segment: SegmentSettings = field(default_factory=SegmentSettings)

    def __post_init__(self) -> None:
        for name in ("samples", "coarse_samples", "exact_samples", "grid"):
            pair = getattr(self, name)
            if len(pair) != 2 or not all(is_integer(k) and k >= 1 for k in pair):
                raise InputError("must be two integers >= 1", field=f"pose.{name}", value=pair)
        if min(self.grid) < 3:
            raise InputError("needs at least 3 cells along each axis", field="pose.grid", value=self.grid)
        for name in ("cap", "min_cap", "window"):
            value = getattr(self, name)
            if not (is_finite_number(value) and value > 0):
                raise InputError("must be a finite number > 0 (m)", field=f"pose.{name}", value=value)
        for name, lowest in (("margin_beams", 0), ("min_mirror_beams", 2), ("polish", 0), ("patch_rays", 1),
                             ("launch_bytes", 1)):
            check_integer(f"pose.{name}", getattr(self, name), lowest)
        if len(self.shifts) == 0 or not all(math.isfinite(s) for s in self.shifts):
            raise InputError("must be a non-empty list of finite shifts (rows)", field="pose.shifts",
                             value=self.shifts)


@dataclass(frozen=True)
class DataContours:
    """The data side of both objectives for the V views where the model is seen, found with
    the model synthesized at the current estimate (``ViewComparison.locate``).

    views : (V,) dataset view indices; names : their names
    threshold : (V, bins) detection threshold per row; windows : (V, 2) rows [lo, hi)
    masks : (V, 2, beams) bool beams of the object (0) and mirror (1) contours
    rows : (V, 2, beams) int first highlight row of each contour, -1 where none
    distances : (V, 2, bins, beams) float32 distance (m) to the contour, saturating at the
        comparison's ``reach``, max(cap, min_cap) (everywhere without a contour)
    """

    views: tuple[int, ...]
    names: tuple[str, ...]
    threshold: np.ndarray
    windows: np.ndarray
    masks: np.ndarray
    rows: np.ndarray
    distances: np.ndarray

    @property
    def counts(self) -> np.ndarray:
        """(V, 2) number of data contour points."""
        return (self.rows >= 0).sum(axis=-1)

    @property
    def mirror_views(self) -> tuple[str, ...]:
        """Names of the views with a mirror term."""
        return tuple(n for n, k in zip(self.names, self.counts[:, 1]) if k > 0)


@dataclass(frozen=True)
class ExactError:
    """E_mu at one (D, β) and what it came from.

    value : E_mu (m); per_view : (V,) μ_m (NaN: no object patch); shift : the detection-bias
    shift used (rows); object_patches, mirror_patches : patches with a 3-D motion
    """

    value: float
    per_view: np.ndarray
    shift: float
    object_patches: int
    mirror_patches: int


# --- the comparison ---------------------------------------------------------------------------

class ViewComparison:
    """The synthetic views of a model against a dataset's data views (the module docstring).

    dataset : fsswarp.dataset.Dataset; settings : PoseSettings (contours, costs, samples);
    backend : where the kernels run (default ``get_backend()``). :meth:`use` places a model
    (reference frame) at an estimate (D m, β rad); every query needs one in use.
    Raises InputError when no view is marked optimize.
    """

    def __init__(self, dataset, *, settings: PoseSettings = PoseSettings(), backend=None):
        from .backends import get_backend

        self.dataset, self.settings = dataset, settings
        self.sonar, self.rig = dataset.sonar, dataset.rig
        self.backend = backend or get_backend()
        self.smoothing = (_gaussian(settings.segment.sigma_bins), _gaussian(settings.segment.sigma_beams))
        self.shifts = np.asarray(settings.shifts, np.float64)
        self.reach = max(settings.cap, settings.min_cap)
        self.counters = {"grid_cells": 0, "surrogate_cells": 0, "exact": 0}
        self.views = [i for i, v in enumerate(self.rig.views) if v.optimize]
        if not self.views:
            raise InputError("no view takes part in the optimization: every view has optimize = false",
                             file=dataset.root, field="views.optimize", value=False)
        self.highlight, self.threshold = dataset.derived(
            ("pose views", tuple(self.views), settings.segment),
            lambda: _view_highlights(dataset, self.views, settings.segment))
        self.model = self.estimate = None
        self._unseen: set[str] = set()
        self._anchored: frozenset[int] | None = None  # rig views of poses that depend on neither D nor β
        self._errors_here = None  # contour_errors at the located estimate
        self._data_distances = None  # _data_distances_of's last (key, maps): their device copy is in use
        self._no_distances = self.backend.device_distances(  # locating reads the contours alone: any distances do
            np.zeros((len(self.views), 2, self.sonar.bins, self.sonar.beams), np.float32))

    def use(self, model, depth: float, tilt: float) -> "ViewComparison":
        """Compare ``model`` (trimesh-like, reference frame) located at (depth m, tilt rad): the
        model is loaded unless it is the one in use (the same object, or equal vertices and
        faces), and located unless it is located there already, so that the layers and contours
        found there are kept. Returns self. Raises InputError when the model is seen in none of
        the views."""
        check_depth_tilt(depth, tilt)
        if model is not self.model:
            same_faces = self.model is not None and np.array_equal(np.asarray(getattr(model, "faces", ())), self.faces)
            vertices, faces = check_mesh(model, name="model", judge_watertight=not same_faces)  # judged at its load
            if not (same_faces and np.array_equal(vertices, self.vertices)):  # the copies loaded, whatever changed
                self.mesh = self.backend.load_mesh(vertices, faces)
                self.vertices, self.faces = vertices.copy(), faces.copy()
                self.estimate, self._unseen = None, set()
            self.model = model
        if self.estimate != (float(depth), float(tilt)):
            self.locate(depth, tilt)
        return self

    def locate(self, depth: float, tilt: float) -> None:
        """Find the data contours (``data``), the anchor views and the detection shift
        (``anchors``, ``shift``) with the model in use synthesized at (depth m, tilt rad), the
        current estimate; ``estimate`` records it. The layers rendered there (exact samples)
        stay on the device for the costs at the estimate; ``predicted`` reads them on first use."""
        check_depth_tilt(depth, tilt)
        made = self._data_distances
        self.data, self._layers, self._keep, self._predicted = self._data_contours(depth, tilt)
        self._errors_here = None
        if self._data_distances is not made:  # new data contours: their device maps, ICP goals
            self._distances = self.backend.device_distances(self.data.distances)  # read at every cap
            self._goals = self._data_points(self.data)
        self.anchors, self.shift = self._detection_shift(depth, tilt)
        self.estimate = (float(depth), float(tilt))

    @property
    def unseen(self) -> tuple[str, ...]:
        """Names of the views to optimize where the model is not seen at the located estimate."""
        return tuple(self.rig.views[i].name for i in self.views if self.rig.views[i].name not in self.data.names)

    def restart(self, *, stacklevel: int = 2) -> None:
        """Zero ``counters`` and warn (PoseWarning) about the views where the model is not seen
        at the located estimate; a later ``locate`` warns only about views not seen before."""
        self.counters = dict.fromkeys(self.counters, 0)
        self._unseen = set(self.unseen)
        if self._unseen:
            self.warn_unseen(self._unseen, *self.estimate, stacklevel=stacklevel + 1)

    @property
    def predicted(self) -> np.ndarray:
        """(V, 4, bins, beams) float32 layers of the data views at the located estimate (exact
        samples), read from the device on first use."""
        if self._predicted is None:
            self._predicted = _kept(self._layers.numpy(), self._keep)
        return self._predicted

    def predicted_rows(self, start: int, stop: int) -> np.ndarray:
        """Rows [start, stop) of :attr:`predicted`, (V, 4, stop − start, beams) float32: from the
        device alone where ``predicted`` has not been read (the shape step's overshoot term reads
        the rows its votes reach, not 12.6 MB per update on coral-one)."""
        if self._predicted is not None:
            return self._predicted[:, :, start:stop]
        return _kept(self._layers.rows(start, stop), self._keep)

    # --- data contours ---------------------------------------------------------------------
    def _data_contours(self, depth: float, tilt: float):
        """(DataContours of the views where the model is seen, the device layers synthesized at
        (depth, tilt) of every view to optimize, the (V,) positions of the views seen among
        them, their (V, 4, bins, beams) host copy or None). On a CPU device the host copy is
        read, and the predicted contours are scanned from the row before the smoothing can
        first see a return (every layer of a view is 0 above its first echo row, so no row there
        crosses the threshold): the same contours as a scan from row 0, which a GPU does
        instead, leaving the copy until ``predicted`` is read."""
        sonar, st, views, threshold = self.sonar, self.settings, self.views, self.threshold
        names = [self.rig.views[i].name for i in views]
        every = np.ones((len(views), 2, sonar.beams), bool)
        layers = self.render_pairs(views, np.array([depth]), np.array([tilt]), st.exact_samples)
        predicted = None if self.backend.is_gpu else layers.numpy()
        first = np.zeros(len(views), np.int64) if predicted is None else scan_start(predicted, len(self.smoothing[0]))
        scan = np.stack([first, np.full(len(views), sonar.bins)], axis=1)
        contour, _, _ = self.backend.contour_cost(layers, np.arange(len(views)), threshold, scan, every,
                                                  self._no_distances, [0.0], self.smoothing)
        seen = (contour[:, 0] >= 0).any(axis=1)
        if not seen.any():
            raise InputError(f"the model is seen in none of the views to optimize at depth {depth:.3f} m, tilt "
                             f"{math.degrees(tilt):.2f} deg: it must be in the reference frame of the dataset",
                             field="model", value=f"{len(self.faces)} faces")
        unseen = {n for n, s in zip(names, seen) if not s} - self._unseen
        if unseen:
            self._unseen |= unseen
            self.warn_unseen(unseen, depth, tilt, stacklevel=5)
        keep = np.flatnonzero(seen)
        pad = int(math.ceil(st.window / sonar.range_step))
        windows, masks, rows = _data_windows(contour[keep], _kept(self.highlight, keep), pad, st.margin_beams,
                                             st.min_mirror_beams)
        seen_views = tuple(views[k] for k in keep)
        data = DataContours(seen_views, tuple(names[k] for k in keep), threshold[keep], windows, masks, rows,
                            self._data_distances_of(seen_views, rows))
        return data, layers, keep, None if predicted is None else _kept(predicted, keep)

    def warn_unseen(self, names, depth: float, tilt: float, *, stacklevel: int = 2) -> None:
        """PoseWarning that the model is not seen in the views ``names`` at (depth m, tilt rad)."""
        warnings.warn(f"views {', '.join(sorted(names))}: the model is not seen in them at depth {depth:.3f} m, "
                      f"tilt {math.degrees(tilt):.2f} deg; the pose estimation leaves them out", PoseWarning,
                      stacklevel=stacklevel)

    def _detection_shift(self, depth: float, tilt: float):
        """(anchor view names, shift in rows or None): the views whose pose relative to the
        reference depends neither on D nor on β (at the reference position), and the shift of
        ``settings.shifts`` (refined by a parabola through its neighbours) that minimizes their
        object term; None without anchor views (each cell then takes its own best shift), from
        the located layers (``_located_costs``)."""
        data = self.data
        if self._anchored is None:  # a property of the rig: found at the first estimate located
            pose_a = self.rig.relative_poses(depth, tilt)
            pose_b = self.rig.relative_poses(depth + 0.01, tilt + 0.01)
            self._anchored = frozenset(v for v in self.views if all(np.allclose(a[v], b[v], rtol=0, atol=1e-12)
                                                                    for a, b in zip(pose_a, pose_b)))
        fixed = [k for k, v in enumerate(data.views) if v in self._anchored]
        if not fixed:
            return (), None
        _, sums, counts = self._located_costs(self.shifts, self.settings.min_cap)
        sums, counts = sums[fixed], counts[fixed]
        sums[:, 1], counts[:, 1] = 0.0, 0
        counts_data = data.counts[fixed]
        counts_data[:, 1] = 0
        cost = _view_cost(sums[None], counts[None], counts_data, self.settings.min_cap)[0].mean(axis=0)
        return tuple(data.names[k] for k in fixed), _parabola_minimum(self.shifts, cost)

    def _data_points(self, data: DataContours) -> dict[tuple[int, int], np.ndarray]:
        """{(component, view k): (M, 2) fan-plane points of the data's contour} for the contours of
        two points or more (the ICP goals of ``align``)."""
        theta, sonar = self.sonar.beam_centres, self.sonar
        goals = {}
        for k, c in zip(*np.nonzero(data.counts >= 2)):
            target = np.flatnonzero(data.rows[k, c] >= 0)
            goal = fan_points(theta[target], sonar.bin_range(data.rows[k, c, target]))
            goal.setflags(write=False)
            goals[int(c), int(k)] = goal
        return goals

    def _located_costs(self, shifts, cap: float):
        """``Backend.contour_cost`` (contours, sums, counts) of the data views' layers at the
        located estimate, from the device layers of every view to optimize: every pair is
        costed where it lies (a view left out against data view 0, then dropped) rather than
        the data views' layers uploaded again; a pair's cost does not depend on the others."""
        data = self.data
        found = self.backend.contour_cost(self._layers, self._located_index(), data.threshold, data.windows,
                                          data.masks, self._distances, shifts, self.smoothing, cap)
        return tuple(a[self._keep] for a in found)

    def _located_index(self) -> np.ndarray:
        """(pairs of the located layers,) int64 data view of each pair: a view left out is
        compared with data view 0 (and its pair dropped)."""
        index = np.zeros(self._layers.shape[0], np.int64)
        index[self._keep] = np.arange(len(self._keep))
        return index

    def _data_distances_of(self, views: tuple[int, ...], rows: np.ndarray) -> np.ndarray:
        """(V, 2, bins, beams) float32 distance maps (:meth:`_distance`) of the data contours'
        ``rows`` (V, 2, beams) in the dataset ``views``, read-only: the last call's maps (the same
        object) where the views and rows are the last call's, as they mostly are from one locate
        to the next, so that ``locate`` keeps their device copy and ICP goals too."""
        key = (views, rows.tobytes())
        if self._data_distances is None or self._data_distances[0] != key:
            sonar = self.sonar
            distances = np.empty((len(rows), 2, sonar.bins, sonar.beams), np.float32)
            for i, row in enumerate(rows):
                for c, r in enumerate(row):
                    distances[i, c] = self._distance(r)
            distances.setflags(write=False)
            self._data_distances = (key, distances)
        return self._data_distances[1]

    def _distance(self, rows: np.ndarray) -> np.ndarray:
        """(bins, beams) distance (m) of every pixel to the contour pixels (row per beam), at
        most ``reach``: the range axis in δR, the beam axis in arc length at the contour's
        median range."""
        sonar = self.sonar
        beams = np.flatnonzero(rows >= 0)
        arc = float(np.median(sonar.bin_range(rows[beams]))) * float(np.mean(np.diff(sonar.beam_centres))) \
            if beams.size else 1.0
        return _remembered_distance(np.ascontiguousarray(rows, np.int64).tobytes(), sonar.bins, sonar.range_step,
                                    arc, self.reach)

    # --- synthesis and the surrogate -------------------------------------------------------
    def view_poses(self, views, depths: np.ndarray, tilts: np.ndarray):
        """(G, V) poses and planes of cells (G,) in the dataset views ``views``."""
        poses = view_planes(self.rig, depths, tilts)
        if tuple(views) == tuple(range(poses[0].shape[1])):
            return poses  # every view, in order
        v = list(views)
        return tuple(a[:, v] for a in poses)

    @property
    def prediction_settings(self) -> RenderSettings:
        """The render settings of ``predicted``: the exact samples, with ``ECHO``'s γ and
        surface reflection."""
        return replace(ECHO, samples=tuple(self.settings.exact_samples))

    def render_pairs(self, views, depths: np.ndarray, tilts: np.ndarray, samples, rows=None, beams=None,
                     components: bool = False):
        """DeviceLayers (G·V, 4, bins, beams) of cells (G,) in the dataset views ``views``, or
        bands of rows, the beams read and the components' sums: ``rows``, ``beams`` and
        ``components`` as ``Backend.render_device`` takes them."""
        return self._render_planned(self.plan_pairs(views, depths, tilts, samples, rows, beams, components))

    def plan_pairs(self, views, depths: np.ndarray, tilts: np.ndarray, samples, rows=None, beams=None,
                   components: bool = False):
        """The host half of :meth:`render_pairs` (``Backend.plan_render``): a RenderPlan, made
        without the device (thread-safe). A pair's pose depends on its cell's tilt alone
        (``view_planes``): the pairs of one tilt and view are one pose group."""
        rot, t, n, d = self.view_poses(views, depths, tilts)
        if np.any(d <= 0):
            raise InputError("the sonar must lie below the surface in every view", field="depth",
                             value=float(np.min(depths)))
        tilt_index = np.unique(np.asarray(tilts, np.float64).reshape(-1), return_inverse=True)[1].reshape(-1)
        groups = tilt_index[:, None] * d.shape[-1] + np.arange(d.shape[-1])
        return self.backend.plan_render(self.mesh, self.sonar, rot.reshape(-1, 3, 3), t.reshape(-1, 3),
                                        n.reshape(-1, 3), d.reshape(-1), samples, rows=rows, beams=beams,
                                        components=components, pose_groups=groups.reshape(-1))

    def _render_planned(self, plan, wait: bool = True):
        return self.backend.render_planned(self.mesh, self.sonar, plan, gamma=ECHO.gamma,
                                           surface_reflection=ECHO.surface_reflection, wait=wait)

    def grid_launches(self, samples=None) -> tuple[np.ndarray, int, np.ndarray, int]:
        """How :meth:`view_costs` renders the data views: (first (V,), R, read (V, 2, beams), cells per
        launch): the band of R rows from ``first`` that holds what each view's window reads
        (``rows_read``, the widest view's R, started lower where it would pass the last row), the
        beams its masks read (``beams_read``), and the most cells (at least one) whose layers (8 B
        per pixel of the bands: the two components' int32 sums) fit ``settings.launch_bytes`` and
        one launch's 2^31 values, and, with ``samples`` (K_θ, K_φ), whose sub-rays stay below 2^31."""
        data, sonar = self.data, self.sonar
        need_lo, need_hi = rows_read(data.windows, len(self.smoothing[0]), sonar.bins)
        rows = int(np.max(need_hi - need_lo))
        values = 2 * rows * sonar.beams * len(data.views)  # a cell's
        bounds = [self.settings.launch_bytes // (4 * values),
                  most_layer_views(rows, sonar.beams, 2) // len(data.views)]
        if samples is not None:
            bounds.append(most_launch_views(sonar.beams, *samples) // len(data.views))
        per = max(1, min(bounds))
        return np.minimum(need_lo, sonar.bins - rows), rows, beams_read(data.masks, len(self.smoothing[1])), per

    def view_costs(self, depths: np.ndarray, tilts: np.ndarray, samples, cap: float, *, contours: bool = True):
        """(G, V, S) surrogate view costs of cells (G,) at the detection shift (S = 1) or, without
        one, at every candidate shift; and (G, V, 2, beams) synthetic contours, or None with
        ``contours`` false (the costs are then combined on the device, ``Backend.view_costs``,
        and only they are read back). One launch unless the layers would exceed
        ``settings.launch_bytes`` or its sub-rays 2^31.

        Each pair renders only the band of rows its view's window reads and the beams its masks
        read, into the two components' sums (:meth:`grid_launches`; ``render_device``'s ``rows``,
        ``beams`` and ``components``): the contours and costs are those of full layers, bit for
        bit. One cell at the located estimate with
        the exact samples reads the layers rendered there, on the device (``_located_index``; no
        render: the same pixels). On a GPU the host work of each launch after the first
        (:meth:`plan_pairs`) is done in a thread while the launch before it runs, and the first
        launch is short (:func:`_launches`); without ``contours`` every launch is then queued on
        the device, its costs read back after the last (a render whose queue of hits overflowed
        is made again then, ``Backend.render_planned``)."""
        data = self.data
        n_views = len(data.views)
        layout = self.grid_launches(samples)
        per = layout[3]
        shifts = self.shifts if self.shift is None else [self.shift]
        ahead = self.backend.is_gpu
        launches = _launches(len(depths), per, ahead)
        queued = ahead and not contours

        def plan(launch: slice):
            cell_d, cell_t = depths[launch], tilts[launch]
            if len(cell_d) == 1 and (float(cell_d[0]), float(cell_t[0])) == self.estimate \
                    and tuple(samples) == tuple(self.settings.exact_samples):
                return None  # the located layers
            return self.plan_pairs(data.views, cell_d, cell_t, samples, **grid_render_options(layout, len(cell_d)))

        def launch_costs(g: int, planned, wait: bool):
            """(the launch's costs (g, V, S), or with ``wait`` false a function that returns them;
            None, or a function that says whether its render dropped hits: ``DeviceLayers.overflowed``)."""
            if planned is None:
                layers, index, keep = self._layers, self._located_index(), self._keep
            else:
                layers = self._render_planned(planned, wait=wait)
                index, keep = np.tile(np.arange(n_views), g), slice(None)
            arguments = (layers, index, data.threshold, data.windows, data.masks, self._distances, shifts,
                         self.smoothing)
            if contours:
                contour, sums, counts = (a[keep] for a in self.backend.contour_cost(*arguments, cap))
                found.append(contour.reshape(g, n_views, 2, -1))
                return _view_cost(sums.reshape(g, n_views, 2, -1), counts.reshape(g, n_views, 2), data.counts,
                                  cap), None
            found_costs = self.backend.view_costs(*arguments, data.counts, cap, wait=wait)
            if wait:
                return found_costs[keep].reshape(g, n_views, -1), None
            return (lambda: found_costs()[keep].reshape(g, n_views, -1)), layers.overflowed  # not the layers

        costs, found, checks = [], [], []
        for launch, planned in zip(launches, _planned(plan, launches, ahead=ahead)):
            cost, overflowed = launch_costs(launch.stop - launch.start, planned, not queued)
            costs.append(cost)
            checks.append(overflowed)
        if queued:  # after the last launch: a launch whose render dropped hits is planned and made again, waiting
            costs = [launch_costs(launch.stop - launch.start, plan(launch), True)[0]
                     if overflowed is not None and overflowed() else cost()
                     for launch, cost, overflowed in zip(launches, costs, checks)]
        self.counters["surrogate_cells"] += len(depths)
        return np.concatenate(costs), np.concatenate(found) if contours else None

    def surrogate(self, depths, tilts, *, cap: float | None = None, samples=None) -> np.ndarray:
        """Surrogate cost (m) of cells: depths (m), tilts (rad) of one shape -> that shape, the
        mean over the views of :meth:`surrogate_views`."""
        return self.surrogate_views(depths, tilts, cap=cap, samples=samples).mean(axis=-1)

    def surrogate_views(self, depths, tilts, *, cap: float | None = None, samples=None) -> np.ndarray:
        """Per-view surrogate costs (m) of cells: depths (m), tilts (rad) of one shape -> that
        shape + (V,): each view's object + mirror contour terms at the detection shift (or,
        without anchor views, at the cell's best shift, the least mean over the views).
        cap : saturation distance (default ``settings.cap``), at most ``reach``, max(cap,
            min_cap), up to which the data's distances are kept; samples : default
            ``settings.samples``."""
        if cap is not None and not (is_number(cap) and 0 < cap <= self.reach):
            raise InputError(f"must be a distance in (0, {self.reach}] m", field="cap", value=cap)
        depths, tilts = np.broadcast_arrays(np.asarray(depths, np.float64), np.asarray(tilts, np.float64))
        costs, _ = self.view_costs(depths.reshape(-1), tilts.reshape(-1), samples or self.settings.samples,
                                    self.settings.cap if cap is None else cap, contours=False)
        costs = costs.astype(np.float64)
        shift = np.argmin(costs.mean(axis=1), axis=-1)
        per_view = np.take_along_axis(costs, shift[:, None, None], axis=-1)[..., 0]
        return per_view.reshape(depths.shape + (costs.shape[1],))

    # --- E_mu --------------------------------------------------------------------------------
    def exact(self, depth: float, tilt: float) -> ExactError:
        """E_mu (eq. 6) at (depth m, tilt rad), with its per-view μ_m."""
        check_depth_tilt(depth, tilt)
        self.counters["exact"] += 1
        data = self.data
        contour, shift = self.synthetic_contours(depth, tilt)
        rot, t, n_view, d_view = (a[0] for a in self.view_poses(data.views, np.array([depth]), np.array([tilt])))
        normal, offset = surface_in_reference(self.rig, depth, tilt)
        n_views = len(data.views)
        aligned = [(c, k, beams, result.motions) for c, k, beams, _, _, result in self.align(contour, shift)]
        component, view, face, vectors = self.frontal_motions(rot, t, n_view, d_view, aligned)
        if not np.any(component == 0):
            return ExactError(math.nan, np.full(n_views, np.nan), shift, 0, 0)
        faces, column = np.unique(face, return_inverse=True)
        centres = self.vertices[self.faces[faces]].mean(axis=1)
        # the mean 2-D motion of each (component, face, view): sums in the beams' order
        cell, shape = (component * len(faces) + column) * n_views + view, (2, len(faces), n_views)
        counts = np.bincount(cell, minlength=math.prod(shape)).reshape(shape)
        sums = np.stack([np.bincount(cell, vectors[:, a], math.prod(shape)) for a in (0, 1)], axis=-1)
        seen = counts > 0
        mean = np.where(seen[..., None], sums.reshape(shape + (2,)) / np.maximum(counts, 1)[..., None], np.nan)
        fields = list(zip(mean, seen))
        obj = patch_motions(centres, *fields[0], rot, t).motion
        object_seen = fields[0][1].any(axis=1)
        if not object_seen.all():  # mirror-only patches: the nearest object patch's motion
            from scipy.spatial import cKDTree

            _, nearest = cKDTree(centres[object_seen]).query(centres[~object_seen])
            obj[~object_seen] = obj[object_seen][nearest]
        mirror_seen = fields[1][1]
        mirror = {}
        if mirror_seen.any():
            virtual = mirror_points(centres, normal, offset)
            mir = patch_motions(virtual, *fields[1], rot, t, surface=(normal, offset)).motion
            mirror = dict(mirror_motion=np.where(mirror_seen.any(axis=1)[:, None], mir, 0.0),
                          mirror_frontal=mirror_seen.T, normal=normal)
        per_view = view_errors(obj, fields[0][1].T, **mirror)
        finite = per_view[np.isfinite(per_view)]
        return ExactError(float(finite.mean()) if finite.size else math.nan, per_view, shift,
                          int(object_seen.sum()), int(mirror_seen.any(axis=1).sum()))

    def synthetic_contours(self, depth: float, tilt: float) -> tuple[np.ndarray, float]:
        """The synthetic contours (V, 2, beams) (rows, -1: none) at (depth m, tilt rad) with the
        exact samples, and the detection shift (rows) that aligns them with the data's: the
        anchor views' or, without anchors, the candidate shift of least cost."""
        costs, contours = self.view_costs(np.array([depth]), np.array([tilt]), self.settings.exact_samples,
                                           self.settings.min_cap)
        shift = self.shift if self.shift is not None else _parabola_minimum(self.shifts, costs[0].mean(axis=0))
        return contours[0], float(shift)

    def contour_errors(self, depth: float, tilt: float) -> np.ndarray:
        """(V,) CE (m) of the views ``data.views``: the error of the ICP of the synthetic object
        contour at (depth m, tilt rad) to the data's (paper eq. 9); NaN where a view has fewer
        than two points in either."""
        here = self.estimate == (float(depth), float(tilt))
        if here and self._errors_here is not None:  # found once per location (refinement's last CE, then E_I's)
            return self._errors_here.copy()
        contour, shift = self.synthetic_contours(depth, tilt)
        errors = np.full(len(self.data.views), math.nan)
        for _, k, _, _, _, result in self.align(contour, shift, (0,)):
            errors[k] = result.error
        if here:
            self._errors_here = errors.copy()
        return errors

    def align(self, contours: np.ndarray, shift: float, components=(0, 1)) -> list[tuple]:
        """ICP of the synthetic contours (V, 2, beams) (rows, -1: none; the detection ``shift``
        added) to the data's, in the fan plane, for every view and component with two points or
        more in both, all in lockstep, on the backend's device when it has float64 (one
        thread per run; else on the host): (component, view, beams, source (N, 2), goal (M, 2),
        ICPResult) each."""
        data, sonar = self.data, self.sonar
        order = list(components)
        # (C, V, beams): the beams of each synthetic contour that its data mask keeps, in request order
        kept = ((contours[:, order] >= 0) & data.masks[:, order]).transpose(1, 0, 2)
        sizes = kept.sum(axis=-1)
        used = (sizes >= 2) & (data.counts[:, order].T >= 2)
        pair_c, pair_k = np.nonzero(used)
        point_c, point_k, beam = np.nonzero(kept & used[..., None])  # pairs in order, each its beams in order
        component = np.asarray(order)[point_c]
        sources = fan_points(sonar.beam_centres[beam], sonar.bin_range(contours[point_k, component, beam] + shift))
        ends = np.cumsum(sizes[used]).tolist()
        requests = [(order[c], k, beam[a:b], sources[a:b], self._goals[order[c], k])
                    for c, k, a, b in zip(pair_c.tolist(), pair_k.tolist(), [0] + ends[:-1], ends)]
        results = icp_many([(source, goal) for *_, source, goal in requests], tol=CONTOUR_TOL,
                           backend=self.backend if self.backend.has_float64 else None)
        return [request + (result,) for request, result in zip(requests, results)]

    def frontal_motions(self, rot, t, n, d, motions):
        """Every beam whose frontal patch is found, for ``motions``: (component k, view k, beams,
        (beams, 2) 2-D motions) per contour; one ``frontal_faces`` call for both components.
        Returns (component (M,), view (M,), face (M,), 2-D motion (M, 2)), components in order,
        then the contours' and beams' order. rot (V, 3, 3), t (V, 3), n (V, 3), d (V,) : every
        view's pose and surface plane, indexed by k."""
        ordered = [m for c in (0, 1) for m in motions if m[0] == c]
        if not ordered:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2))
        component, v = (np.array([m[i] for m in ordered], np.int64) for i in (0, 1))
        sizes = [len(beams) for _, _, beams, _ in ordered]
        found = np.concatenate(self.frontal_faces(rot[v], t[v], n[v], d[v],
                                                  [self.sonar.beam_centres[beams] for _, _, beams, _ in ordered],
                                                  mirror=component == 1))
        ok = found >= 0
        vectors = np.concatenate([np.asarray(vectors, np.float64).reshape(-1, 2) for *_, vectors in ordered])
        return (np.repeat(component, sizes)[ok], np.repeat(v, sizes)[ok], found[ok].astype(np.int64), vectors[ok])

    def frontal_faces(self, rot, t, n, d, thetas, *, mirror) -> list[np.ndarray]:
        """Per view k: (len(thetas[k]),) face of the frontal patch of each beam azimuth, -1 where
        none: the hit at the shortest range (object), or at the shortest mirror range
        (|P| + |P'|)/2 over the beam's elevation rays that meet the surface first (mirror,
        DESIGN §3); ``Backend.frontal_faces``, all views' beams in one launch.

        rot (V, 3, 3), t (V, 3) : the views' poses; n (V, 3), d (V,) : their surface planes;
        thetas : V arrays of beam azimuths (rad); mirror : a bool for every view, or (V,) bools."""
        if not len(thetas):
            return []
        sizes = [len(theta) for theta in thetas]
        views = np.repeat(np.arange(len(thetas)), sizes)
        azimuths = np.concatenate([np.asarray(theta, np.float64) for theta in thetas])
        flags = np.asarray(mirror, bool)
        found = self.backend.frontal_faces(self.mesh, self.sonar, rot, t, n, d, views, azimuths,
                                           self.settings.patch_rays, mirror=flags if flags.ndim == 0 else flags[views])
        return np.split(found, np.cumsum(sizes)[:-1])


def _data_windows(contour: np.ndarray, highlight: np.ndarray, pad: int, margin: int, min_mirror: int):
    """(windows (K, 2) int64, masks (K, 2, beams) bool, rows (K, 2, beams) int64) of K views whose
    predicted contours ``contour`` (K, 2, beams) (rows, -1: none) show the object (component 0)
    in some beam, with their data highlights (K, bins, beams) bool. A view's window: the rows of
    its predicted contour points widened by ``pad`` rows each side, within the image. Its data
    rows: per beam the first highlight row in the window (-1: none); the object's where the
    predicted object spans the beam (``margin`` beams more each side), the mirror's on the side
    beyond it with more such rows, where at least ``min_mirror`` beams have one (else none)."""
    beams = contour.shape[2]
    bins = highlight.shape[1]
    point = contour >= 0
    lo = np.floor(np.where(point, contour, np.inf).min(axis=(1, 2))).astype(np.int64) - pad
    hi = np.ceil(np.where(point, contour, -np.inf).max(axis=(1, 2))).astype(np.int64) + pad + 1
    windows = np.stack([np.maximum(lo, 0), np.minimum(hi, bins)], axis=1)
    top, bottom = int(windows[:, 0].min()), int(windows[:, 1].max())  # the rows any window holds
    row = np.arange(top, bottom)
    inside = (row >= windows[:, :1]) & (row < windows[:, 1:])  # (K, rows)
    lit = highlight[:, top:bottom] & inside[:, :, None]
    first_row = np.where(lit.any(axis=1), lit.argmax(axis=1) + top, -1)  # (K, beams)
    index = np.arange(beams)
    span = point[:, 0]
    start = span.argmax(axis=1)[:, None] - margin
    stop = beams - 1 - span[:, ::-1].argmax(axis=1)[:, None] + margin
    obj, left, right = (index >= start) & (index <= stop), index < start, index > stop
    found = first_row >= 0
    mirror = np.where(((found & left).sum(axis=1) > (found & right).sum(axis=1))[:, None], left, right)
    mirror &= ((found & mirror).sum(axis=1) >= min_mirror)[:, None]
    rows = np.stack([np.where(obj, first_row, -1), np.where(mirror, first_row, -1)], axis=1)
    return windows, np.stack([obj, mirror], axis=1), rows


def _view_highlights(dataset, views, settings: SegmentSettings):
    """(read-only (V, bins, beams) highlight masks, read-only (V, bins) detection thresholds) of
    the data images of the rig views ``views`` (indices)."""
    names = [dataset.rig.views[i].name for i in views]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # views without a highlight get no contour
        segmented = segment_views({n: dataset.images[n] for n in names}, settings, label="images/{}")
    highlight = np.stack([segmented[n].highlight for n in names])
    threshold = np.stack([detection_threshold(dataset.images[n], settings) for n in names])
    highlight.setflags(write=False)
    threshold.setflags(write=False)
    return highlight, threshold


def view_contours(model, dataset, depth: float, tilt: float, *, at=(), settings: PoseSettings = PoseSettings(),
                  backend=None) -> dict[str, dict]:
    """What E_mu compares, per view, for figures: ``model`` (reference frame) against
    ``dataset`` with the data contours found at (depth m, tilt rad), the synthetic ones there
    and at each (depth, tilt) of ``at``. Returns {view name: {"data": (2, beams) range (m) of
    the data's object (0) and mirror (1) contour per beam, "synthetic": [(2, beams) ranges at
    (depth, tilt), then at each of ``at``], "mu": [μ_m (m) at the same poses]}}, NaN where a
    beam has no contour point (or a view no μ_m), for the views where the model is seen."""
    comparison = ViewComparison(dataset, settings=settings, backend=backend).use(model, depth, tilt)
    data, sonar = comparison.data, comparison.sonar
    out = {name: {"data": np.where(data.rows[k] >= 0, sonar.bin_range(data.rows[k]), np.nan),
                  "synthetic": [], "mu": []} for k, name in enumerate(data.names)}
    for pose in [(depth, tilt), *at]:
        contours, shift = comparison.synthetic_contours(*pose)
        mu = comparison.exact(*pose).per_view
        for k, name in enumerate(data.names):
            out[name]["synthetic"].append(np.where(contours[k] >= 0, sonar.bin_range(contours[k] + shift), np.nan))
            out[name]["mu"].append(float(mu[k]))
    return out


def detection_threshold(image, settings: SegmentSettings = SegmentSettings()) -> np.ndarray:
    """(bins,) linear intensity at which the segmentation's hysteresis low threshold lies in
    each row of a (bins, beams) image, less the background: ``(m + low·s − 1)·level(B)``
    (``fsswarp.segment.normalized``, steps 0–2: the same clipped spikes, background level, median m
    and spread s)."""
    array = np.asarray(image, np.float64)
    return memoized("detection_threshold", array, settings, lambda: _detection_threshold(array, settings))


def _detection_threshold(array: np.ndarray, settings: SegmentSettings) -> np.ndarray:
    level, _, centre, spread = normalized(array, settings)
    return np.maximum(centre + settings.low * spread - 1.0, 0.0) * level


def scan_start(layers: np.ndarray, taps: int) -> np.ndarray:
    """(N,) the first row from which ``contour_cost`` must scan (N, 4, bins, beams) ``layers``,
    smoothed along range over ``taps`` rows, to find every threshold crossing: the row before
    the smoothing first reaches a return of any layer and beam (above it the smoothed image
    is 0 and cannot exceed a threshold >= 0), at least 0, at most bins − 1."""
    bins = layers.shape[2]
    echo = layers.any(axis=(1, 3))  # (N, bins): rows holding a return
    first = np.where(echo.any(axis=1), echo.argmax(axis=1), bins)
    return np.clip(first - (taps - 1) // 2 - 1, 0, bins - 1)


def contour_distance(rows: np.ndarray, bins: int, range_step: float, arc: float, reach: float) -> np.ndarray:
    """(bins, beams) float32 distance (m) of every pixel to the contour pixels (row, beam) of
    ``rows`` (beams,) (first row per beam, -1: none), saturating at ``reach`` (m): the range
    axis in ``range_step``, the beam axis in ``arc`` (m). Exact below ``reach``, as scipy's
    ``distance_transform_edt`` with that sampling, but only the contour pixels within
    ``reach`` are visited (±reach/arc beams, ±reach/range_step rows)."""
    n_beams = len(rows)
    out = np.full((bins, n_beams), reach * reach)
    beams = np.flatnonzero(rows >= 0)
    if beams.size:
        lo = max(int(rows[beams].min() - reach / range_step) - 1, 0)
        hi = min(int(rows[beams].max() + reach / range_step) + 2, bins)
        band = out[lo:hi]
        dr = (np.arange(lo, hi)[:, None] - rows[beams][None, :]) * range_step  # (rows, contour points)
        dr2 = dr * dr
        for offset in range(-int(reach / arc), int(reach / arc) + 1):
            target = beams + offset
            inside = (target >= 0) & (target < n_beams)
            cols = target[inside]
            band[:, cols] = np.minimum(band[:, cols], dr2[:, inside] + (offset * arc) ** 2)
    return np.sqrt(out).astype(np.float32)  # out starts at reach² and only falls


@functools.lru_cache(maxsize=128)
def _remembered_distance(rows: bytes, bins: int, range_step: float, arc: float, reach: float) -> np.ndarray:
    """:func:`contour_distance` of the int64 ``rows`` bytes, read-only, for the 128 latest
    arguments: the loop locates again and again on data contours that rarely change."""
    out = contour_distance(np.frombuffer(rows, np.int64), bins, range_step, arc, reach)
    out.setflags(write=False)
    return out


def _gaussian(sigma: float) -> np.ndarray:
    """scipy.ndimage.gaussian_filter's 1-D weights for ``sigma`` (truncate 4), (2r + 1,)."""
    radius = int(4.0 * sigma + 0.5)
    if radius == 0:
        return np.ones(1)
    x = np.arange(-radius, radius + 1)
    w = np.exp(-0.5 * (x / sigma) ** 2)
    return w / w.sum()


#: With launches planned ahead, the first launch holds this share of a full one (at least
#: ``FIRST_LAUNCH_CELLS`` cells), so that the device starts while the next is planned: 450 of
#: the 3,603 cells of coral-one's 4 GiB launches, whose plan takes ~4 ms on an H200's host.
FIRST_LAUNCH_SHARE = 0.125
FIRST_LAUNCH_CELLS = 64


def grid_render_options(layout: tuple, cells: int) -> dict:
    """The ``rows``, ``beams`` and ``components`` of ``ViewComparison.render_pairs`` (and
    ``plan_pairs``) with which :meth:`ViewComparison.view_costs` renders ``cells`` cells of every
    data view, from its ``grid_launches()`` ``layout`` (first, R, read, per): each pair's band of R
    rows from its view's first row, the beams its contours read, the components' sums."""
    first, rows, read, _ = layout
    return dict(rows=(np.tile(first, cells), rows), beams=read, components=True)


def _launches(cells: int, per: int, ahead: bool) -> list[slice]:
    """The cells of each launch of :meth:`ViewComparison.view_costs`: ``per`` at a time; with
    ``ahead`` (plans made while the device renders), a first launch of ``FIRST_LAUNCH_SHARE``
    of ``min(per, cells)`` where that is at least ``FIRST_LAUNCH_CELLS`` cells, and each next one
    twice the one before, up to ``per``: a launch's plan then mostly takes less time than the
    render before it (on an H200 the 64 × 64 grid's GPU waited 1–3 ms in all for its host)."""
    size = min(per, cells)
    if ahead and size * FIRST_LAUNCH_SHARE >= FIRST_LAUNCH_CELLS:
        size = max(1, int(size * FIRST_LAUNCH_SHARE))
    launches, start = [], 0
    while start < cells:
        launches.append(slice(start, min(start + size, cells)))
        start, size = start + size, min(per, 2 * size)
    return launches


def _planned(plan, items, *, ahead: bool):
    """``plan(item)`` of each of ``items``, in order; with ``ahead``, the next item's is made in a
    thread while the caller uses this one (host work beside a GPU's; on a CPU device the kernels
    use every core, so nothing runs beside them)."""
    items = list(items)
    if not ahead or len(items) < 2:
        yield from (plan(item) for item in items)
        return
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(1, thread_name_prefix="fsswarp-plan") as pool:
        coming = pool.submit(plan, items[0])
        for item in items[1:]:
            current, coming = coming.result(), pool.submit(plan, item)
            yield current
        yield coming.result()


def _kept(layers: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The (V, ...) ``layers`` of the views at the sorted, distinct positions ``keep``: the array
    itself where every view is kept (no 12.6 MB copy per locate on coral-one), else a copy."""
    return layers if len(keep) == len(layers) else layers[keep]


def _parabola_minimum(x: np.ndarray, y: np.ndarray) -> float:
    """Where the parabola through the smallest of the (S,) values ``y`` at uniform ``x`` and its
    two neighbours is smallest (the end point itself at an end, or where flat)."""
    i = int(np.argmin(y))
    if i == 0 or i == len(y) - 1:
        return float(x[i])
    curvature = y[i - 1] - 2.0 * y[i] + y[i + 1]
    if curvature <= 0:
        return float(x[i])
    return float(x[i] + 0.5 * (x[1] - x[0]) * (y[i - 1] - y[i + 1]) / curvature)


def _view_cost(sums: np.ndarray, counts: np.ndarray, data_counts: np.ndarray, cap: float) -> np.ndarray:
    """(G, V, S) object + mirror terms from (G, V, 2, S) sums, (G, V, 2) counts and the data's
    (V, 2) counts: ``(Σ d + cap · max(0, n_data − n)) / max(n, n_data)``, 0 for empty terms."""
    n = counts[..., None].astype(np.float64)
    n_data = data_counts[None, :, :, None].astype(np.float64)
    total = sums + cap * np.maximum(n_data - n, 0.0)
    terms = np.divide(total, np.maximum(n, n_data), out=np.zeros(total.shape), where=np.maximum(n, n_data) > 0)
    return terms.sum(axis=2)


def fan_points(theta, rng) -> np.ndarray:
    """(N, 2) fan-plane points R (sin θ, cos θ) (paper eq. 3)."""
    return np.stack([rng * np.sin(theta), rng * np.cos(theta)], axis=1)
