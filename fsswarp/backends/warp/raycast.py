"""Watertight ray casting against a Warp BVH over a mesh's triangles (kernels/bvh.h, raycast.cl).

``nearest_hit`` is the first hit of one ray (the render and frontal kernels use it), the tree
walked nearest child first in native code (``_NEAREST_FIRST``);
``cast_rays_kernel`` is ``Backend.cast_rays``: origins and directions (R,) vec3, distances
(R,) float32 (inf: none), faces (R,) int32 (-1: none).
"""

from __future__ import annotations

import warp as wp

from .sonar import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

_TINY_DIR = wp.constant(1.0e-30)  # stands in for a zero direction component (1/0 -> 1e30, no NaN)


@wp.struct
class RayHit:
    t: float
    face: int


#: ``_nearest_first``'s native code: the tree of ``WarpMesh.bvh`` (Warp's nodes: a box each;
#: leaves list their faces), walked nearest child first. Warp's own ``bvh_query_ray`` pops its
#: nodes in a fixed order and tests one box per node, so a closest-hit search kept visiting boxes
#: behind the hit it had found (the render kernel of a 64 × 64 pose grid 36.9 → 25.4 ms on an
#: H200, the same layers; bench/notes.md). Each inner node's two child boxes get Warp's slab test
#: (``intersect_ray_aabb``, reciprocal of ``qdir``) and are kept while their entry t < best ·
#: 1.000001 (the bound the search applied before, so it tests the same faces that can win); the
#: nearer is taken, the farther pushed with its entry t (at most 64, kernels/bvh.h's
#: FSS_BVH_STACK) and skipped when popped behind a nearer hit. A face is tested watertight (Woop,
#: Benthin & Wald 2013; fss_ray_triangle of kernels/bvh.h, operation for operation, edge values
#: of exactly 0 inside, the module's no-FMA option): a hit in [0, best) becomes the best (a tie on
#: t, which rounding seldom lets through, goes to the lower face). Returns (t, face) as float64,
#: both exact (face -1, t inf: none).
_NEAREST_FIRST = r"""
const wp::BVH tree = wp::bvh_get(bvh);
const wp::vec3 rcp = wp::vec3(1.0f / qdir[0], 1.0f / qdir[1], 1.0f / qdir[2]);
float best = max_t;
int best_face = -1;
int stack[64];
float stack_t[64];
int count = 0;
// whether a box entered at t can hold a hit that wins
auto ahead = [&](float t) { return !(t >= best * 1.000001f); };
// whether the box of node `index` is hit ahead, and where the ray enters it (entry)
auto box_ahead = [&](int index, float& entry) {
    const wp::BVHPackedNodeHalf lo = wp::bvh_load_node(tree.node_lowers, index);
    const wp::BVHPackedNodeHalf hi = wp::bvh_load_node(tree.node_uppers, index);
    return wp::intersect_ray_aabb(org, rcp, wp::vec3(lo.x, lo.y, lo.z), wp::vec3(hi.x, hi.y, hi.z), entry)
           && ahead(entry);
};
float t_root = 0.0f;
int node = box_ahead(*tree.root, t_root) ? *tree.root : -1;
while (node >= 0) {
    const wp::BVHPackedNodeHalf lo = wp::bvh_load_node(tree.node_lowers, node);
    const wp::BVHPackedNodeHalf hi = wp::bvh_load_node(tree.node_uppers, node);
    if (lo.b) {
        for (int k = (int)lo.i; k < (int)hi.i; ++k) {
            const int face = wp::bvh_load_int(tree.primitive_indices, k);
            const wp::vec3 A = wp::index(corners, 3 * face + 0) - org;
            const wp::vec3 B = wp::index(corners, 3 * face + 1) - org;
            const wp::vec3 C = wp::index(corners, 3 * face + 2) - org;
            const float az = A[kz], bz = B[kz], cz = C[kz];
            const float ax = A[kx] - sx * az;
            const float ay = A[ky] - sy * az;
            const float bx = B[kx] - sx * bz;
            const float by = B[ky] - sy * bz;
            const float cx = C[kx] - sx * cz;
            const float cy = C[ky] - sy * cz;
            const float uu = cx * by - cy * bx;
            const float vv = ax * cy - ay * cx;
            const float ww = bx * ay - by * ax;
            if ((uu < 0.0f || vv < 0.0f || ww < 0.0f) && (uu > 0.0f || vv > 0.0f || ww > 0.0f))
                continue;
            float det = uu + vv + ww;
            if (det == 0.0f)
                continue;
            float tt = uu * (sz * az) + vv * (sz * bz) + ww * (sz * cz);
            if (det < 0.0f) {
                det = -det;
                tt = -tt;
            }
            if (!(tt >= 0.0f) || !(tt < best * det))
                continue;
            const float t = tt / det;
            if (!(t >= 0.0f && t < best))
                continue;
            if (t < best || (t == best && best_face >= 0 && face < best_face)) {
                best = t;
                best_face = face;
            }
        }
    } else {
        const int left = (int)lo.i, right = (int)hi.i;
        float tl = 0.0f, tr = 0.0f;
        const bool hl = box_ahead(left, tl);
        const bool hr = box_ahead(right, tr);
        if (hl && hr) {
            const bool left_first = tl <= tr;
            if (count < 64) {
                stack[count] = left_first ? right : left;
                stack_t[count] = left_first ? tr : tl;
                ++count;
            }
            node = left_first ? left : right;
            continue;
        }
        if (hl || hr) {
            node = hl ? left : right;
            continue;
        }
    }
    node = -1;
    while (count > 0) {
        --count;
        if (ahead(stack_t[count])) {
            node = stack[count];
            break;
        }
    }
}
return wp::vec2d((double)(best_face >= 0 ? best : INFINITY), (double)best_face);
"""


@wp.func_native(_NEAREST_FIRST)
def _nearest_first(bvh: wp.uint64, corners: wp.array(dtype=wp.vec3), org: wp.vec3, qdir: wp.vec3, kx: int, ky: int,
                   kz: int, sx: float, sy: float, sz: float, max_t: float) -> wp.vec2d:
    """(t, face) of the nearest hit (``_NEAREST_FIRST``), float64."""
    ...


@wp.func
def nearest_hit(bvh: wp.uint64, corners: wp.array(dtype=wp.vec3), org: wp.vec3, dir: wp.vec3, max_t: float):
    """Nearest watertight hit of the ray in [0, max_t), the BVH over the triangles' boxes walked
    nearest child first (``_NEAREST_FIRST``; face -1 and t = inf: none). corners (3F,): the
    corners of face f at 3f, 3f + 1, 3f + 2 (``WarpMesh.corners``)."""
    # dominant axis, shear constants (fss_make_ray)
    ax = wp.abs(dir[0])
    ay = wp.abs(dir[1])
    az = wp.abs(dir[2])
    kz = int(2)
    if ax > ay:
        if ax > az:
            kz = 0
    else:
        if ay > az:
            kz = 1
    kx = kz + 1
    if kx == 3:
        kx = 0
    ky = kx + 1
    if ky == 3:
        ky = 0
    dz = dir[kz]
    if dz < 0.0:
        tmp = kx
        kx = ky
        ky = tmp
    sx = dir[kx] / dz
    sy = dir[ky] / dz
    sz = 1.0 / dz
    # the slab test takes 1/dir: keep zero components finite so it has no 0·inf NaN
    qdir = dir
    for k in range(3):
        if qdir[k] == 0.0:
            qdir[k] = _TINY_DIR
    found = _nearest_first(bvh, corners, org, qdir, kx, ky, kz, sx, sy, sz, max_t)
    hit = RayHit()
    hit.t = float(found[0])
    hit.face = int(found[1])
    return hit


@wp.kernel
def cast_rays_kernel(mesh: wp.uint64, corners: wp.array(dtype=wp.vec3), origins: wp.array(dtype=wp.vec3),
                     directions: wp.array(dtype=wp.vec3), max_distance: float,
                     distance_out: wp.array(dtype=float), face_out: wp.array(dtype=wp.int32)):
    """Thread i: nearest hit of ray i within max_distance (inf and -1 if none)."""
    i = wp.tid()
    hit = nearest_hit(mesh, corners, origins[i], directions[i], max_distance)
    distance_out[i] = hit.t
    face_out[i] = hit.face
