"""The paper's built-in scenes (DESIGN §11): targets, view sets and sonar settings.

Each scene is a scene manifest (a dataset manifest with a ``[target]`` and no images). The
sonar looks along +Y from the south position at the origin; the target sits ``STANDOFF_M``
ahead with its top 2 cm below the surface, so that object, ghost and mirror all fall inside
the default 1.0–3.0 m range window and the ±7° elevation aperture.

Sensors (DESIGN §11), ``SENSORS``: ``realistic`` (the default) is the paper's class, a
pressure depth sensor zeroed at the surface (0.1% of a few metres: σ 3 mm, D0 within 3 mm of
the truth) and a tilt sensor good to ±0.6° (β0 0.6–1° off); ``poor`` keeps the starts of the
identifiability study, a depth 3–5 cm off with σ 5 cm and the same tilts with σ 2°.
"""

from __future__ import annotations

import math

import numpy as np

from .dataset import KnownPose, Manifest, SurfaceEstimate, Target, Truth
from .errors import InputError
from .rig import Rig, View
from .sonar import SonarSpec
from .targets import BUILTIN_TARGETS, builtin_mesh

#: Horizontal distance (m) from each sonar position to the target's centre.
STANDOFF_M = 2.0
#: Depth (m) of the target's top below the surface.
TOP_DEPTH_M = 0.02
#: The eight rolls of every position, −90° to 67.5° in steps of 22.5° (rad).
ROLLS = tuple(math.radians(-90.0 + 22.5 * k) for k in range(8))
#: Rolls whose mirror overlaps the object: held out of the optimization (new views).
HELD_OUT_ROLLS_DEG = (-22.5, 0.0, 22.5)
#: How much deeper (m) a deep-water scene puts the rig and the target than the scene's own.
DEEP_WATER_M = 20.0

# name: (true depth m, true tilt deg, measured tilt deg, positions, measured depth m per sensor class)
_SCENES = {
    "coral-one": (0.43, 10.3, 11.1, "SN", {"realistic": 0.432, "poor": 0.47}),
    "coral-two": (0.48, 11.5, 10.8, "SN", {"realistic": 0.4775, "poor": 0.445}),
    "table": (0.45, 10.0, 10.9, "SNEW", {"realistic": 0.4525, "poor": 0.49}),
}
#: Sensor classes of the built-in scenes: (depth σ m, tilt σ deg).
SENSORS = {"realistic": (0.003, 0.6), "poor": (0.05, 2.0)}

#: Horizontal distance (m) from the near-south position ``T`` to the target's centre: a second
#: standoff on the south side. Near 1.2 m but no nearer than every vertex of both corals and
#: its ghost and mirror stay inside the range window, the ±14.4° fan and the ±7° elevation
#: aperture at all eight rolls: from 1.39 m (at 1.2 m the corals leave the aperture at rolls
#: −67.5° to 45° and their mirrors the fan at ±67.5° and −90°); the table fits from 1.62 m.
NEAR_STANDOFF_M = 1.4
# position letter: (x, y) offset (m) from the target's centre, heading (rad)
_POSITIONS = {
    "S": ((0.0, -STANDOFF_M), 0.0),
    "N": ((0.0, STANDOFF_M), math.pi),
    "E": ((STANDOFF_M, 0.0), math.pi / 2),
    "W": ((-STANDOFF_M, 0.0), -math.pi / 2),
    "T": ((0.0, -NEAR_STANDOFF_M), 0.0),
}


def builtin_scene(name: str, positions: str | None = None, sensors: str = "realistic", *,
                  deep_water: bool = False) -> Manifest:
    """The scene manifest of a built-in target: ``coral-one``, ``coral-two`` or ``table``.

    positions : the sonar positions around the target, distinct letters of ``SNEWT`` (south,
        north, east, west at ``STANDOFF_M``; ``T`` near-south, the south side again at
        ``NEAR_STANDOFF_M``: two standoffs on one side, ``ST``); eight rolls at each, the first
        position's first view the reference; default the scene's own (DESIGN §11: ``SN`` for
        the corals, ``SNEW`` for the table). The corals with ``SNEW`` see their south–north
        extent in azimuth too.
    sensors : a class of ``SENSORS`` (module docstring).
    deep_water : the same rig and target ``DEEP_WATER_M`` deeper, without a surface: no
        [surface] and no [truth] table; the true depth and tilt are the known [rig] ones."""
    if name not in _SCENES:
        raise InputError(f"unknown built-in scene; choose one of {', '.join(BUILTIN_TARGETS)}",
                         field="scene", value=name)
    if sensors not in SENSORS:
        raise InputError(f"must be one of {', '.join(SENSORS)}", field="--sensors", value=sensors)
    depth, tilt_deg, tilt0_deg, own, measured = _SCENES[name]
    depth0, (depth_sigma, tilt_sigma_deg) = measured[sensors], SENSORS[sensors]
    positions = check_positions(positions) or own
    height = float(builtin_mesh(name).extents[2])
    drop = DEEP_WATER_M if deep_water else 0.0
    centre = (0.0, STANDOFF_M, -(drop + TOP_DEPTH_M + 0.5 * height))
    views = []
    for letter in positions:
        (dx, dy), heading = _POSITIONS[letter]
        xy = (centre[0] + dx, centre[1] + dy)
        for roll in ROLLS:
            roll_deg = round(math.degrees(roll), 6)
            views.append(View(name=f"{letter}{_roll_label(roll_deg)}", position=xy, heading=heading,
                              roll=roll, optimize=roll_deg not in HELD_OUT_ROLLS_DEG))
    rig, target = Rig(tuple(views), reference=0), Target(position=centre, builtin=name)
    if deep_water:
        return Manifest(sonar=SonarSpec(), surface=None, rig=rig, target=target,
                        known_pose=KnownPose(depth=drop + depth, tilt=math.radians(tilt_deg)))
    return Manifest(
        sonar=SonarSpec(),
        surface=SurfaceEstimate(depth=depth0, tilt=math.radians(tilt0_deg), depth_sigma=depth_sigma,
                                tilt_sigma=math.radians(tilt_sigma_deg)),
        rig=rig,
        truth=Truth(depth=depth, tilt=math.radians(tilt_deg)),
        target=target,
    )


def check_positions(positions) -> str | None:
    """``positions`` (a string of distinct letters of ``SNEWT``, upper or lower case) in upper
    case, None for None (a scene's own); InputError (field ``--positions``) otherwise."""
    if positions is None:
        return None
    letters = positions.upper() if isinstance(positions, str) else None
    if not letters or any(c not in _POSITIONS for c in letters) or len(set(letters)) != len(letters):
        raise InputError("must be distinct letters of S, N, E, W, T (sonar positions south, north, east, west of the "
                         "target, T near-south), e.g. SN, SNEW or ST", field="--positions", value=positions)
    return letters


def target_world_mesh(target: Target, *, base=None, file=None):
    """The target mesh placed in the world frame: scaled, rotated (x, then y, then z, about
    the mesh origin) and moved to ``target.position``. ``base`` folder resolves ``target.mesh``;
    ``file`` (the scene file) is named in the InputError of a mesh that cannot be read or
    whose placed vertices leave float32's range (the kernels' precision)."""
    import trimesh

    from .dataset import read_mesh, vertices_beyond_float32
    from .rig import rotation_x, rotation_y, rotation_z

    if target.builtin is not None:
        mesh = builtin_mesh(target.builtin)
    else:
        mesh = read_mesh(target.mesh_path(base if base is not None else "."), field="target.mesh", file=file,
                         value=target.mesh)
    rx, ry, rz = target.rotation
    rot = rotation_z(rz) @ rotation_y(ry) @ rotation_x(rx)
    with np.errstate(over="ignore", invalid="ignore"):
        vertices = (np.asarray(mesh.vertices) * target.scale) @ rot.T + np.asarray(target.position)
    if vertices_beyond_float32(vertices):
        raise InputError("places the target's vertices beyond float32's range", file=file, field="target.scale_m",
                         value=target.scale)
    return trimesh.Trimesh(vertices=vertices, faces=np.asarray(mesh.faces), process=False)


def _roll_label(roll_deg: float) -> str:
    text = f"{abs(roll_deg):g}".replace(".", "p")
    return ("m" if roll_deg < 0 else "p") + text if roll_deg else "0"
