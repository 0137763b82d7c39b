"""How closely the backends agree, and whether their ray casts leak, on this machine.

    python bench/agreement.py [--json FILE]

1. Image synthesis: every available backend renders coral-one's 16 views at the true depth
   and tilt (samples (2, 64)); for every pair, the worst relative L1 difference per layer
   over the views, sum|a − b| / sum|b|.
2. Watertightness: rays aimed exactly at the shared vertices and edge midpoints of a closed
   icosphere (subdivision 4: 2,562 vertices, 7,680 edges) from outside, radially and in 7
   random directions within 60° of the outward normal; a ray whose first hit lies beyond the
   aimed point leaked through the mesh.

Tests assert bounds on both (tests/test_render.py, tests/test_raycast.py); this prints the
measured values for the records.
"""

from __future__ import annotations

import argparse
import itertools
import json

import numpy as np


def available_backends():
    from fsswarp.backends import describe_backends, get_backend

    found = []
    for row in describe_backends():
        if row["available"]:
            found.append(get_backend(row["backend"], row["device"] if row["backend"] == "warp" else row["index"]))
    return found


def label(backend) -> str:
    return f"{backend.name} {backend.device}"


def coral_layers(backend):
    from fsswarp.benchmark import coral_batch

    sonar, mesh, rot, t, n, d = coral_batch(16)
    handle = backend.load_mesh(mesh.vertices, mesh.faces)
    return backend.render(handle, sonar, rot, t, n, d, (2, 64), gamma=1.0, surface_reflection=0.9)


def relative_l1(a: np.ndarray, b: np.ndarray) -> float:
    """Worst over views of sum|a − b| / sum|b|; a, b: (views, bins, beams)."""
    a, b = a.astype(np.float64), b.astype(np.float64)
    return float(np.max(np.abs(a - b).sum(axis=(1, 2)) / np.abs(b).sum(axis=(1, 2))))


def box3(layers: np.ndarray) -> np.ndarray:
    """(views, bins, beams) → the same, each image through a 3 × 3 box filter."""
    from scipy.ndimage import uniform_filter

    return uniform_filter(layers.astype(np.float64), size=(1, 3, 3), mode="constant")


def vertex_and_edge_rays(seed: int = 5, directions: int = 8):
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    centre = np.array([0.2, 2.0, -0.3])
    targets = np.concatenate([sphere.vertices, sphere.vertices[sphere.edges_unique].mean(axis=1)])
    rng = np.random.default_rng(seed)
    origins, dirs, expected = [], [], []
    for k in range(directions):
        out = targets / np.linalg.norm(targets, axis=1, keepdims=True)
        if k:
            jitter = rng.normal(size=out.shape)
            jitter -= np.sum(jitter * out, axis=1, keepdims=True) * out
            jitter /= np.linalg.norm(jitter, axis=1, keepdims=True)
            angle = rng.uniform(0.0, np.radians(60.0), size=(len(out), 1))
            out = np.cos(angle) * out + np.sin(angle) * jitter
        length = rng.uniform(0.3, 2.0, size=len(out))
        origins.append(centre + targets + length[:, None] * out)
        dirs.append(-out)
        expected.append(length)
    return sphere.vertices + centre, sphere.faces, *(np.concatenate(a) for a in (origins, dirs, expected))


def main() -> None:
    from fsswarp.surface import COMPONENTS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    backends = available_backends()
    report = {"render": [], "watertight": []}

    layers = {label(b): coral_layers(b) for b in backends}
    for (name_a, a), (name_b, b) in itertools.combinations(layers.items(), 2):
        worst = {c: relative_l1(a[:, k], b[:, k]) for k, c in enumerate(COMPONENTS)}
        blurred = {c: relative_l1(box3(a[:, k]), box3(b[:, k])) for k, c in enumerate(COMPONENTS)}
        report["render"].append({"a": name_a, "b": name_b, "worst_relative_l1": worst,
                                 "worst_relative_l1_box3": blurred})
        print(f"render  {name_a[:34]:34s} vs {name_b[:34]:34s} " +
              "  ".join(f"{c} {worst[c]:.1e} ({blurred[c]:.1e})" for c in COMPONENTS))

    vertices, faces, origins, dirs, expected = vertex_and_edge_rays()
    for backend in backends:
        dist, _ = backend.cast_rays(backend.load_mesh(vertices, faces), origins, dirs)
        leaked = int(np.sum(dist > expected + 1e-5))
        missed = int(np.sum(~np.isfinite(dist)))
        report["watertight"].append({"backend": label(backend), "rays": len(dist), "leaked": leaked,
                                     "missed": missed})
        print(f"watertight {label(backend)[:40]:40s} {len(dist)} rays: {leaked} leaked, {missed} missed")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(report, handle, indent=2)


if __name__ == "__main__":
    main()
