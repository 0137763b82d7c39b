"""Host-side BVH for the OpenCL ray caster: a linear BVH (LBVH) built in vectorised NumPy.

Triangles are sorted by the 30-bit Morton code of their centroid; the sorted range is split
top-down, one tree level at a time (no Python loop over nodes or triangles), at the highest
Morton bit in which the range's first and last codes differ (Karras 2012), or at the middle
when all codes of a range are equal. Ranges of at most ``LEAF_SIZE`` triangles become leaves.
The boxes are then found bottom up, each inner child's from the two boxes its node holds.

Layout (``kernels/bvh.h`` reads it): a binary tree whose every node stores the boxes of its two
children, so that one node fetch tests both children. Node 0 is the root. Child references:
``c >= 0`` an inner node index; ``c < 0`` a leaf, ``~c = (first << 3) | count`` with ``first``
the index of its first triangle in the reordered triangle array and ``count <= 4``
(``count == 0``: an empty child, whose box is inverted so no ray enters it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FlatBVH", "build_bvh", "LEAF_SIZE"]

#: Most triangles of one leaf.
LEAF_SIZE = 4


@dataclass(frozen=True)
class FlatBVH:
    """A flattened BVH.

    node_bounds : (Nn, 2, 2, 4) float32
        ``[node, child, 0 (lo) | 1 (hi), xyz + pad]``: the boxes of each node's two children.
    node_children : (Nn, 2) int32
        Child references (see the module docstring).
    triangles : (Nf, 9) float32
        Vertices v0, v1, v2 (xyz each) of the triangles in leaf order.
    face_index : (Nf,) int32
        Original face index of each reordered triangle.
    """

    node_bounds: np.ndarray
    node_children: np.ndarray
    triangles: np.ndarray
    face_index: np.ndarray

    @property
    def n_nodes(self) -> int:
        return int(self.node_children.shape[0])

    @property
    def n_triangles(self) -> int:
        return int(self.face_index.shape[0])


def _leaf(first: np.ndarray, count: np.ndarray) -> np.ndarray:
    return ~((first.astype(np.int64) << 3) | count.astype(np.int64))


def decode_leaf(ref) -> tuple[np.ndarray, np.ndarray]:
    """(first, count) of leaf references (``ref < 0``)."""
    e = ~np.asarray(ref, np.int64)
    return e >> 3, e & 7


def _expand_bits(v: np.ndarray) -> np.ndarray:
    """Spread the low 10 bits of v so that two zero bits separate each (uint64 math)."""
    v = v.astype(np.uint64) & np.uint64(0x3FF)
    v = (v | (v << np.uint64(16))) & np.uint64(0x030000FF)
    v = (v | (v << np.uint64(8))) & np.uint64(0x0300F00F)
    v = (v | (v << np.uint64(4))) & np.uint64(0x030C30C3)
    v = (v | (v << np.uint64(2))) & np.uint64(0x09249249)
    return v


def triangle_bounds(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Nf, 3) lower and upper corners of the triangles' boxes, of vertices (Nv, 3) and faces
    (Nf, 3): the corners' element-wise minimum and maximum (as ``min(axis=1)`` on the (Nf, 3, 3)
    triangles, 6x faster; ``np.take`` gathers the corners faster than indexing does)."""
    a, b, c = (np.take(vertices, faces[:, k], axis=0) for k in range(3))
    return np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c)


def build_bvh(vertices: np.ndarray, faces: np.ndarray) -> FlatBVH:
    """LBVH of a triangle mesh: vertices (Nv, 3) float32, faces (Nf, 3) int32 (Nf >= 1)."""
    verts = np.ascontiguousarray(vertices, np.float32)
    faces = np.ascontiguousarray(faces, np.int64)
    n = faces.shape[0]
    if n == 0:
        raise ValueError("build_bvh needs at least one triangle")
    if n >= 2**28:
        raise ValueError(f"too many triangles for the BVH layout ({n})")
    tri_lo, tri_hi = triangle_bounds(verts, faces)
    centroid = (tri_lo.astype(np.float64) + tri_hi) * 0.5

    # Morton codes of the box centres (30 bits)
    c_lo = centroid.min(axis=0)
    extent = centroid.max(axis=0) - c_lo
    scale = np.where(extent > 0, 1023.0 / np.where(extent > 0, extent, 1.0), 0.0)
    q = np.clip(((centroid - c_lo) * scale).astype(np.int64), 0, 1023)
    codes = (_expand_bits(q[:, 0]) << np.uint64(2)) | (_expand_bits(q[:, 1]) << np.uint64(1)) \
        | _expand_bits(q[:, 2])
    codes = codes.astype(np.int64)
    order = np.argsort(codes, kind="stable")
    codes = np.take(codes, order)

    if n <= LEAF_SIZE:
        node_bounds = np.zeros((1, 2, 2, 4), np.float32)
        node_bounds[0, 0, 0, :3] = tri_lo.min(axis=0)
        node_bounds[0, 0, 1, :3] = tri_hi.max(axis=0)
        node_bounds[0, 1] = np.array([[np.inf] * 3 + [0.0], [-np.inf] * 3 + [0.0]], np.float32)  # empty
        node_children = np.array([[_leaf(np.array(0), np.array(n)), _leaf(np.array(0), np.array(0))]], np.int32)
    else:
        node_bounds, node_children = _tree(codes, np.take(tri_lo, order, axis=0), np.take(tri_hi, order, axis=0))
    triangles = np.take(verts, np.take(faces, order, axis=0).reshape(-1), axis=0).reshape(n, 9)
    return FlatBVH(node_bounds, node_children, triangles, order.astype(np.int32))


def _tree(codes: np.ndarray, tri_lo: np.ndarray, tri_hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(node_bounds (Nn, 2, 2, 4), node_children (Nn, 2)) of n > LEAF_SIZE triangles sorted by
    their (n,) Morton ``codes``, with their (n, 3) box corners in that order. The ranges split top
    down, one level at a time (node ids level after level); the boxes are then found bottom up:
    each leaf's over its triangles (one reduction over the n), each inner child's from the two
    boxes its node holds (the same minima and maxima as over its triangles, in O(n) in all)."""
    n = codes.size
    lo, hi = np.array([0], np.int64), np.array([n], np.int64)  # ranges to split at this level
    levels, next_id = [], 0  # (first id, children's first triangles, their refs) per level
    while lo.size:
        m = lo.size
        first, last = codes[lo], codes[hi - 1]
        x = first ^ last
        bit = np.frexp(x.astype(np.float64))[1] - 1  # highest differing bit
        target = ((first >> np.maximum(bit, 0)) | 1) << np.maximum(bit, 0)
        split = np.searchsorted(codes, target, side="left")
        split = np.where(x == 0, (lo + hi) // 2, split)
        split = np.clip(split, lo + 1, hi - 1)
        c_lo = np.stack([lo, split], axis=1).reshape(-1)  # children's ranges, (left, right) per node
        c_hi = np.stack([split, hi], axis=1).reshape(-1)
        count = c_hi - c_lo
        inner = count > LEAF_SIZE
        ref = _leaf(c_lo, count)
        ref[inner] = next_id + m + np.arange(int(inner.sum()))
        levels.append((next_id, c_lo, ref))
        next_id += m
        lo, hi = c_lo[inner], c_hi[inner]
    children = np.concatenate([ref for _, _, ref in levels])  # (2 Nn,), child slot 2 id + side
    boxes = np.zeros((next_id * 2, 2, 3), np.float32)  # [slot, lo | hi, xyz]
    leaf = np.flatnonzero(children < 0)
    starts = np.concatenate([c_lo for _, c_lo, _ in levels])[leaf]
    by_start = np.argsort(starts)  # the leaves partition the n triangles
    boxes[leaf[by_start], 0] = np.minimum.reduceat(tri_lo, starts[by_start], axis=0)
    boxes[leaf[by_start], 1] = np.maximum.reduceat(tri_hi, starts[by_start], axis=0)
    for first_id, _, ref in reversed(levels):  # an inner child's node lies one level deeper
        slots = 2 * first_id + np.flatnonzero(ref >= 0)
        node = 2 * children[slots]
        boxes[slots, 0] = np.minimum(boxes[node, 0], boxes[node + 1, 0])
        boxes[slots, 1] = np.maximum(boxes[node, 1], boxes[node + 1, 1])
    node_bounds = np.zeros((next_id, 2, 2, 4), np.float32)
    node_bounds[..., :3] = boxes.reshape(next_id, 2, 2, 3)
    return node_bounds, np.ascontiguousarray(children.reshape(next_id, 2), np.int32)
