"""The rig: view poses in the world and relative to the reference view (DESIGN §2).

World frame: origin on the sea surface, +Z up (the surface is z = 0). Every view shares the
sonar depth D (m below the surface) and tilt β (rad, positive = pitched up toward the
surface); view m adds known offsets. ``R_m^W = Rz(ψ_m) · Rx(β + δβ_m) · Ry(ω_m)`` and
``s_m = (x_m, y_m, -(D + δD_m))``. Relative poses map view-frame points into the reference
frame: ``P_ref = R_m @ P_view + t_m``; they change with β.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from .errors import InputError, degrees_shown


def rotation_x(angle) -> np.ndarray:
    """(..., 3, 3) right-handed rotation about +X; pitches +Y up toward +Z for angle > 0."""
    c, s = np.cos(angle), np.sin(angle)
    o, i = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([i, o, o], -1), np.stack([o, c, -s], -1), np.stack([o, s, c], -1)], -2)


def rotation_y(angle) -> np.ndarray:
    """(..., 3, 3) right-handed rotation about +Y (the viewing axis); turns +X down for angle > 0."""
    c, s = np.cos(angle), np.sin(angle)
    o, i = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, o, s], -1), np.stack([o, i, o], -1), np.stack([-s, o, c], -1)], -2)


def rotation_z(angle) -> np.ndarray:
    """(..., 3, 3) right-handed rotation about +Z; turns +Y toward -X for angle > 0."""
    c, s = np.cos(angle), np.sin(angle)
    o, i = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, -s, o], -1), np.stack([s, c, o], -1), np.stack([o, o, i], -1)], -2)


@dataclass(frozen=True)
class View:
    """One sonar view's known pose values (radians, metres) and its image file.

    position : (x, y) horizontal position in the world frame (m)
    heading, roll : ψ and ω (rad); depth_offset, tilt_offset : δD (m) and δβ (rad)
    optimize : whether the view takes part in the optimization (else a held-out view)
    """

    name: str
    position: tuple[float, float] = (0.0, 0.0)
    heading: float = 0.0
    roll: float = 0.0
    depth_offset: float = 0.0
    tilt_offset: float = 0.0
    optimize: bool = True
    image: str | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name or not _safe_name(self.name):
            raise InputError("must be a non-empty name of letters, digits, '-', '_' or '.'",
                             field="views.name", value=self.name)
        values = (*self.position, self.heading, self.roll, self.depth_offset, self.tilt_offset)
        if len(self.position) != 2 or not all(math.isfinite(v) for v in values):
            raise InputError("pose values must be finite numbers", field=f"views[{self.name}]",
                             value=values)


@dataclass(frozen=True)
class Rig:
    """The views of a dataset and which one is the reference (index into ``views``)."""

    views: tuple[View, ...]
    reference: int = 0

    def __post_init__(self) -> None:
        if len(self.views) == 0:
            raise InputError("at least one view is required", field="views", value=[])
        names = [v.name for v in self.views]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise InputError("view names must be unique", field="views.name", value=duplicates[0])
        if not 0 <= self.reference < len(self.views):
            raise InputError("no such view", field="rig.reference_view", value=self.reference)

    @property
    def names(self) -> list[str]:
        return [v.name for v in self.views]

    def index(self, name: str) -> int:
        """Index of the view called ``name``."""
        try:
            return self.names.index(name)
        except ValueError:
            raise InputError("no view of that name", field="view", value=name) from None

    def _arrays(self):
        v = self.views
        return (np.array([x.position for x in v], dtype=np.float64),
                np.array([x.heading for x in v]), np.array([x.roll for x in v]),
                np.array([x.depth_offset for x in v]), np.array([x.tilt_offset for x in v]))

    def world_poses(self, depth, tilt):
        """World poses of every view for shared ``depth`` (m) and ``tilt`` (rad).

        ``depth`` and ``tilt`` may be arrays of one shape G (a grid of candidates).
        Returns ``(R, s)``: (*G, V, 3, 3) rotations view → world and (*G, V, 3) positions.
        """
        depth, tilt = np.broadcast_arrays(np.asarray(depth, np.float64), np.asarray(tilt, np.float64))
        tilts, inverse = np.unique(tilt, return_inverse=True)  # a (D, β) grid repeats each tilt
        rot = self._world_rotations(tilts)[inverse.reshape(-1)].reshape(tilt.shape + (len(self.views), 3, 3))
        return rot, self._world_positions(depth)

    def _world_positions(self, depth: np.ndarray) -> np.ndarray:
        """(*G, V, 3) positions of every view at the (*G,) depths."""
        pos, _, _, d_off, _ = self._arrays()
        z = -(depth[..., None] + d_off)
        return np.concatenate([np.broadcast_to(pos, z.shape + (2,)), z[..., None]], axis=-1)

    def _world_rotations(self, tilts: np.ndarray) -> np.ndarray:
        """(T, V, 3, 3) rotations view → world of every view at each of the (T,) tilts."""
        _, heading, roll, _, t_off = self._arrays()
        beta = tilts[:, None] + t_off
        return rotation_z(np.broadcast_to(heading, beta.shape)) @ rotation_x(beta) @ \
            rotation_y(np.broadcast_to(roll, beta.shape))

    def reference_pose(self, depth, tilt):
        """World pose of the reference frame: the reference view with zero roll.

        Returns ``(R, s)`` of shapes (*G, 3, 3) and (*G, 3); read-only for one candidate
        (``_one``)."""
        return self._one("_reference_pose", depth, tilt)

    def _reference_pose(self, depth, tilt):
        return self._reference_rotations(tilt), self._reference_positions(depth)

    def _reference_rotations(self, tilt: np.ndarray) -> np.ndarray:
        """(*G, 3, 3) rotations of the reference frame at the (*G,) tilts."""
        ref = self.views[self.reference]
        return rotation_z(np.full(tilt.shape, ref.heading)) @ rotation_x(tilt + ref.tilt_offset)

    def _reference_positions(self, depth: np.ndarray) -> np.ndarray:
        """(*G, 3) positions of the reference frame at the (*G,) depths."""
        ref = self.views[self.reference]
        return np.stack([np.full(depth.shape, ref.position[0]), np.full(depth.shape, ref.position[1]),
                         -(depth + ref.depth_offset)], axis=-1)

    def relative_poses(self, depth, tilt):
        """Every view's pose in the reference frame: ``P_ref = R @ P_view + t``.

        ``R_m = (R_ref^W)ᵀ R_m^W`` and ``t_m = (R_ref^W)ᵀ (s_m - s_ref)``; both depend on β alone (the
        depth D cancels in s_m − s_ref, and is not used), and ``R_m = Ry(ω_m)`` (taken exactly) for
        views with the reference's heading and tilt offset.
        Returns ``(R, t)``: (*G, V, 3, 3) and (*G, V, 3); read-only for one candidate (``_one``,
        remembered by its tilt alone)."""
        depth, tilt = np.broadcast_arrays(np.asarray(depth, np.float64), np.asarray(tilt, np.float64))
        return self._one("_relative_poses", np.zeros(depth.shape), tilt)

    def _one(self, method: str, depth, tilt):
        """The result of the method named ``method`` (``_reference_pose`` or ``_relative_poses``)
        for broadcast (*G,) depths and tilts; one candidate (G of size 1, a pose step asks for
        each several times) is remembered (``_remembered``)."""
        depth, tilt = np.broadcast_arrays(np.asarray(depth, np.float64), np.asarray(tilt, np.float64))
        if depth.size == 1:
            return self._remembered(method, depth.shape, float(depth.flat[0]), float(tilt.flat[0]))
        return getattr(self, method)(depth, tilt)

    @functools.lru_cache(maxsize=256)
    def _remembered(self, method: str, shape: tuple, depth: float, tilt: float):
        """The read-only result of ``_one`` for one candidate of ``shape``."""
        result = getattr(self, method)(np.full(shape, depth), np.full(shape, tilt))
        for array in result:
            array.setflags(write=False)
        return result

    def _relative_poses(self, depth, tilt):
        # a relative pose depends on β alone (D cancels in s_m − s_ref): found once per distinct
        # tilt (the same operations per tilt, so the same bits as one candidate's), then spread
        # over the candidates; a (D, β) grid renders every depth of a tilt from the same poses
        tilts, inverse = np.unique(tilt, return_inverse=True)
        rt = np.swapaxes(self._reference_rotations(tilts), -1, -2)[..., None, :, :]
        rot = rt @ self._world_rotations(tilts)
        # a view with the reference's heading and tilt offset turns by its roll alone, Ry(ω), at
        # every (D, β): exact, so that renders on a (D, β) grid find its pose the same bit for bit
        _, heading, roll, _, tilt_offset = self._arrays()
        ref = self.views[self.reference]
        level = (heading == ref.heading) & (tilt_offset == ref.tilt_offset)
        rot[..., level, :, :] = rotation_y(roll[level])
        at_surface = np.zeros(1)  # s_m − s_ref at D = 0: (Δx, Δy, δD_ref − δD_m), (1, V, 3)
        apart = self._world_positions(at_surface) - self._reference_positions(at_surface)[:, None, :]
        t = (rt @ apart[..., None])[..., 0]
        inverse = inverse.reshape(-1)
        return rot[inverse].reshape(tilt.shape + rot.shape[1:]), t[inverse].reshape(tilt.shape + t.shape[1:])


def with_rolls(rig: Rig, rolls, *, at: str | None = None) -> tuple[Rig, list[str]]:
    """``rig`` plus one new view per roll (rad) at the position, heading and offsets of view
    ``at`` (default: the reference view), named ``roll<degrees>`` (e.g. ``roll45``,
    ``roll-22.5``; 6 significant digits). Rolls lie in [-180, 180] degrees, as in a manifest;
    a roll given twice makes one view, and two rolls that share a name are refused. Returns
    the extended rig (same reference) and the new views' names."""
    base = rig.views[rig.reference if at is None else rig.index(at)]
    names, added = [], []
    for roll in rolls:
        if not (math.isfinite(roll) and abs(roll) <= math.pi):
            raise InputError("must be a finite angle in [-180, 180] degrees", field="--roll",
                             value=degrees_shown(roll))
        name = f"roll{math.degrees(roll):g}"
        if name in rig.names:
            raise InputError("the dataset already has a view of that name", field="--roll", value=name)
        if name in names:
            if added[names.index(name)].roll != roll:
                raise InputError(f"differs from another --roll only beyond the 6 digits of the view name {name}",
                                 field="--roll", value=degrees_shown(roll))
            continue
        names.append(name)
        added.append(View(name, base.position, base.heading, roll, base.depth_offset,
                          base.tilt_offset, optimize=False))
    return Rig(rig.views + tuple(added), rig.reference), names


def world_to_reference(points, rig: Rig, depth: float, tilt: float) -> np.ndarray:
    """(..., 3) world points expressed in the reference frame for (depth, tilt)."""
    rot, s = rig.reference_pose(depth, tilt)
    return (np.asarray(points, np.float64) - s) @ rot


def reference_to_world(points, rig: Rig, depth: float, tilt: float) -> np.ndarray:
    """(..., 3) reference-frame points expressed in the world frame for (depth, tilt)."""
    rot, s = rig.reference_pose(depth, tilt)
    return np.asarray(points, np.float64) @ rot.T + s


def to_view(points, rotation, translation) -> np.ndarray:
    """(..., 3) reference-frame points in a view frame: ``Rᵀ (P - t)``."""
    return (np.asarray(points, np.float64) - translation) @ rotation


def _safe_name(name: str) -> bool:
    return all(ch.isalnum() or ch in "-_." for ch in name) and not name.startswith(".")
