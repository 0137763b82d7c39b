"""Built-in target meshes of the paper's scenes (DESIGN §11): two coral rocks and a toy table.

Every mesh is a closed, outward-wound 2-manifold (``mesh.is_volume``) with float64 vertices
in metres, in its own object frame: the origin is the centre of the bounding box, +Z up.
A scene places it in the world with ``[target] position_m`` and ``rotation_deg``.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from .errors import InputError, check_integer, is_finite_number, is_integer


class CoralSpec(NamedTuple):
    """The seed and bounding-box size (x, y, z in m) of a built-in coral."""

    seed: int
    size_m: tuple[float, float, float]


CORAL_ONE = CoralSpec(seed=17, size_m=(0.22, 0.17, 0.15))
CORAL_TWO = CoralSpec(seed=28, size_m=(0.19, 0.24, 0.16))

#: Names accepted by :func:`builtin_mesh` (and by a scene's ``target.builtin``).
BUILTIN_TARGETS = ("coral-one", "coral-two", "table")

# The coral's radius on the unit sphere of directions u:
#   r(u) = 1 + Σ_k a_k exp(κ_k (u·c_k − 1)) − Σ_j b_j exp(λ_j (u·d_j − 1))
# Knobs (a, κ) are broad lumps, the saddles between them and the dents (b, λ) the mild
# concavities. r ≥ 1 − Σ b_j > 0: the surface is the radial graph of r over the icosphere, so
# star-shaped around the sphere's centre, closed and free of self-intersections.
_KNOBS = 10
_KNOB_HEIGHT = (0.20, 0.35)
_KNOB_SHARPNESS = (6.0, 12.0)
_DENTS = 4
_DENT_DEPTH = (0.10, 0.20)
_DENT_SHARPNESS = (8.0, 16.0)

#: How far each table leg reaches up into the top (m), at most half the top's thickness.
LEG_OVERLAP_M = 0.002


def coral_mesh(seed: int, *, size_m=(0.22, 0.18, 0.16), subdivisions: int = 4) -> trimesh.Trimesh:
    """A seeded procedural rock: dominantly convex, with knobs, saddles and shallow dents.

    An icosphere of ``subdivisions`` (20·4^s faces; 5120 for 4) whose vertex radii follow a
    smooth random field of the direction, scaled per axis so that its bounding box is
    ``size_m`` (x, y, z in m) and centred on the origin. The field is drawn from
    ``numpy.random.default_rng(seed)`` alone and does not depend on ``subdivisions``: the
    same seed gives a bit-identical mesh, and a finer mesh of the same rock.
    """
    import trimesh

    check_integer("seed", seed, 0)
    size = _size3("size_m", size_m)
    if not (is_integer(subdivisions) and 1 <= subdivisions <= 6):
        raise InputError("must be an integer from 1 to 6", field="subdivisions", value=subdivisions)

    sphere = trimesh.creation.icosphere(subdivisions=int(subdivisions))
    u = sphere.vertices / np.linalg.norm(sphere.vertices, axis=1, keepdims=True)  # (V, 3)
    rng = np.random.default_rng(int(seed))
    knob_dir = _unit_vectors(rng, _KNOBS)
    knob_height = rng.uniform(*_KNOB_HEIGHT, _KNOBS)
    knob_sharp = rng.uniform(*_KNOB_SHARPNESS, _KNOBS)
    dent_dir = _unit_vectors(rng, _DENTS)
    dent_depth = rng.uniform(*_DENT_DEPTH, _DENTS)
    dent_sharp = rng.uniform(*_DENT_SHARPNESS, _DENTS)
    radius = (1.0
              + np.exp(knob_sharp * (u @ knob_dir.T - 1.0)) @ knob_height
              - np.exp(dent_sharp * (u @ dent_dir.T - 1.0)) @ dent_depth)  # (V,)

    vertices = u * radius[:, None]
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    vertices = (vertices - 0.5 * (low + high)) * (np.asarray(size) / (high - low))
    return trimesh.Trimesh(vertices, sphere.faces, process=False)


def table_mesh(*, top=(0.24, 0.16, 0.02), leg=(0.025, 0.025, 0.14),
               inset: float = 0.015) -> trimesh.Trimesh:
    """A toy wood table: a ``top`` box (x, y, z in m) on four ``leg`` boxes, as one solid.

    Each leg sits ``inset`` m in from a corner of the top, points down (−Z) and reaches
    ``LEG_OVERLAP_M`` (at most half the top's thickness) up into the top, so the union is
    clean; the table is ``top[2] + leg[2] − overlap`` tall. The parts are joined by a boolean
    union (manifold3d, in float64), leaving a deep open concavity between the legs.
    """
    import manifold3d
    import trimesh

    top_size = _size3("top", top)
    leg_size = _size3("leg", leg)
    if not (is_finite_number(inset) and inset >= 0):
        raise InputError("must be a finite number >= 0 (m)", field="inset", value=inset)
    for axis in (0, 1):
        if 2.0 * (inset + leg_size[axis]) >= top_size[axis]:
            raise InputError(f"legs of {'xy'[axis]} width {leg_size[axis]:g} m at inset "
                             f"{inset:g} m do not fit under a top {top_size[axis]:g} m wide",
                             field="leg", value=leg)

    overlap = min(LEG_OVERLAP_M, 0.5 * top_size[2])
    leg_x = 0.5 * top_size[0] - inset - 0.5 * leg_size[0]
    leg_y = 0.5 * top_size[1] - inset - 0.5 * leg_size[1]
    leg_z = overlap - 0.5 * leg_size[2]
    parts = [manifold3d.Manifold.cube(top_size, center=True)
             .translate((0.0, 0.0, 0.5 * top_size[2]))]
    for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
        parts.append(manifold3d.Manifold.cube(leg_size, center=True)
                     .translate((sx * leg_x, sy * leg_y, leg_z)))
    table = manifold3d.Manifold.batch_boolean(parts, manifold3d.OpType.Add).to_mesh64()
    vertices = np.array(table.vert_properties[:, :3], dtype=np.float64)
    vertices -= 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    return trimesh.Trimesh(vertices, np.array(table.tri_verts, dtype=np.int64), process=False)


def builtin_mesh(name: str) -> trimesh.Trimesh:
    """The built-in target ``name`` (one of ``BUILTIN_TARGETS``), a new mesh on every call."""
    if name == "coral-one":
        return coral_mesh(CORAL_ONE.seed, size_m=CORAL_ONE.size_m)
    if name == "coral-two":
        return coral_mesh(CORAL_TWO.seed, size_m=CORAL_TWO.size_m)
    if name == "table":
        return table_mesh()
    raise InputError(f"unknown built-in target; choose one of {', '.join(BUILTIN_TARGETS)}",
                     field="target.builtin", value=name)


def _size3(name: str, value: Any) -> tuple[float, float, float]:
    """``value`` as three finite sizes > 0 (m), or InputError naming ``name``."""
    items = list(value) if isinstance(value, (list, tuple, np.ndarray)) else []
    if not (len(items) == 3 and all(is_finite_number(v) and v > 0 for v in items)):
        raise InputError("must be three finite sizes > 0 (x, y, z in m)", field=name, value=value)
    return (float(items[0]), float(items[1]), float(items[2]))


def _unit_vectors(rng: np.random.Generator, count: int) -> np.ndarray:
    """(count, 3) directions uniform on the unit sphere."""
    v = rng.normal(size=(count, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)
