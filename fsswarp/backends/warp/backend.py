"""``WarpBackend``: the Backend interface on one Warp device ("cpu", "cuda:N").

Kernels live in this package's family modules (sonar geometry, project, raycast, render,
carve, pose, icp) and compile once per process and device (Warp keeps the build in its
kernel cache, ~/.cache/warp). Device layers are ``WarpLayers``, meshes ``WarpMesh`` handles.
"""

from __future__ import annotations

import collections
import threading

import numpy as np
import warp as wp

from ...caching import Remembered
from ..base import (Backend, DeviceLayers, PreparedLaunch, SonarConstants, beam_edges, fixed_floats,
                    hit_queue_size, mask_items, most_chunks, render_with_room, span_chunks, span_extent)
from ..constants import (FIXED_SCALE, FRONTAL_VISIBLE, MAX_DISTANCE, RAY_CHUNK, RAY_EPSILON,
                         RENDER_THREADS_PER_UNIT, WARP_FAR)
from ..runtimes import import_warp
from .carve import carve_grid, carve_points
from .closest import surface_distances_kernel
from .icp import icp_runs_kernel
from .pose import contour_cost_kernel, frontal_contour, view_cost_kernel
from .project import project_points
from .raycast import cast_rays_kernel
from .render import (chunk_views_kernel, direct_hits_kernel, fixed_to_float, frontal_rays_kernel, hits_kernel,
                     render_kernel, sub_rays_kernel, triangle_boxes_kernel, view_spans_kernel)
from .sonar import kernel_sonar

#: Share of a CUDA device's memory that Warp's memory pool keeps after a synchronize instead of
#: handing it back (Warp's default keeps none): the pose grid's launches allocate their layers
#: (gigabytes) again each time, and mapping them again cost the 64 × 64 grid about 20 of its
#: 190 ms on an H100 (docs/decisions.md). Between launches the pool then holds at most this
#: share unused, which other processes on the same GPU cannot have meanwhile.
MEMPOOL_KEEP = 0.25
#: Threads of a render launch that finds its spans on a CPU device (the GPU's path, which the
#: tests force there): a few, so that each takes several sub-rays, as on a GPU.
CPU_THREADS = 1024
#: ``WarpBackend._constant``: inputs up to this size are kept on the device for reuse ...
CONSTANT_BYTES = 1 << 18
#: ... and this many of them (at most 16 MiB).
CONSTANTS = 64
#: Page-locked host memory (bytes) through which a GPU backend's uploads go (``_Staging``); an
#: upload of more than a quarter of it, or under ``STAGED_MIN`` bytes, is copied from pageable
#: memory, as before: the ring's bookkeeping in Python cost the 64 × 64 pose grid's start more than
#: staging its small uploads saved (docs/decisions.md).
STAGING_BYTES = 32 << 20
STAGED_MIN = 64 << 10
#: Held while a backend of this process loads a mesh (``WarpBackend._load_mesh``): Warp's BVH
#: builds are not safe in two threads at once.
_LOAD_LOCK = threading.Lock()


class WarpLayers(DeviceLayers):
    """Rendered layers as the render's fixed-point accumulator, a (N, 4, bins, beams) int32
    ``wp.array`` (``.array``; 2^24 = 1), or (N, 4, R, beams) for bands of rows (``first_rows``),
    2 in place of 4 for the components' sums:
    the contour kernels read it as it is, and ``numpy`` converts it on the device first
    (``fixed_to_float``: the floats a render to float layers gives)."""

    def __init__(self, array: wp.array):
        self.array = array
        self.shape = tuple(array.shape)

    def numpy(self) -> np.ndarray:
        layers = wp.empty(self.shape, dtype=float, device=self.array.device)
        _launch(fixed_to_float, dim=self.array.size, inputs=[self.array.flatten()], outputs=[layers.flatten()],
                device=self.array.device)
        return layers.numpy()

    def rows(self, start: int, stop: int) -> np.ndarray:
        return fixed_floats(self.array[:, :, start:stop].numpy())


class WarpMesh:
    """Handle of a mesh uploaded to one Warp device: a ``wp.Bvh`` over the triangles' (padded)
    boxes and ``corners`` (3F,) vec3, the three corners of each face in turn (the kernels read a
    triangle in one place for the watertight test and its geometric normal; docs/decisions.md),
    kept alive with it."""

    def __init__(self, bvh, corners, lowers, uppers, device):
        self.bvh = bvh
        self.corners = corners
        self.lowers = lowers
        self.uppers = uppers
        self.device = device

    @property
    def id(self):
        return self.bvh.id

    def __repr__(self) -> str:
        return f"<warp mesh: {self.corners.shape[0] // 3} faces on {self.device}>"


def _launch(kernel, dim, **kwargs) -> None:
    """``wp.launch`` at the threads per block that the kernel's module names in its options
    (``render.RAY_BLOCK`` for the ray-casting module, Warp's 256 for the others): the variant
    each module is compiled for, and the one ``fsswarp info``'s cache check looks for."""
    wp.launch(kernel, dim=dim, block_dim=kernel.module.options["block_dim"], **kwargs)


class _Staging:
    """A ring of page-locked host memory for one CUDA device's uploads: an upload copies its bytes
    into the ring and queues an asynchronous copy on the device's current stream, so the host
    never waits for the stream to drain, as a copy from pageable memory can (the pose grid planned
    its next launch's uploads while the last one rendered; docs/decisions.md). A region is written
    again only after the copy that read it has ended (an event recorded after each copy).
    Thread-safe: the answer's thread uploads beside the loop's."""

    #: The dtypes staged: the NumPy dtype each converts its host data to first (as ``wp.array``
    #: does); a vector or matrix of float32 takes the trailing axes of its data.
    SCALARS = {wp.float32: np.float32, float: np.float32, wp.int32: np.int32, wp.float64: np.float64}

    def __init__(self, device, size: int, smallest: int = STAGED_MIN):
        self.device, self.size, self.smallest = device, int(size), max(int(smallest), 1)
        self.buffer = self.host = None  # allocated at the first upload staged
        self.head = 0
        self.pending = collections.deque()  # (start, stop, event) of the copies not yet known to have ended
        self.lock = threading.Lock()

    def upload(self, data, dtype) -> wp.array | None:
        """``data`` (a NumPy array) as a new array of ``dtype`` on the device, its copy queued;
        None where it is not staged (another type, or too large): the caller copies it itself."""
        scalar = self.SCALARS.get(dtype)
        inner = ()
        if scalar is None and getattr(dtype, "_wp_scalar_type_", None) is wp.float32:
            scalar, inner = np.float32, tuple(dtype._shape_)
        if scalar is None or not isinstance(data, np.ndarray):
            return None
        shape = data.shape[:data.ndim - len(inner)]
        size = data.size * np.dtype(scalar).itemsize  # judged before converting: most uploads are small
        if not shape or data.shape[len(shape):] != inner or not self.smallest <= size <= self.size // 4:
            return None
        host = np.ascontiguousarray(data, scalar)
        with self.lock:
            if self.buffer is None:
                self.buffer = wp.empty(self.size, dtype=wp.uint8, device="cpu", pinned=True)
                self.host = self.buffer.numpy()
            start = tail = -(-self.head // 16) * 16  # aligned for every dtype
            if start + size > self.size:  # wrapped: the tail [tail, end) is left, after its copies
                start = 0
            stop = start + size
            # the regions ahead of the head, in the ring's order, hold the oldest copies
            while self.pending and ((self.pending[0][0] < stop and start < self.pending[0][1])
                                    or (start == 0 < tail <= self.pending[0][0])):
                wp.synchronize_event(self.pending.popleft()[2])
            self.head = stop
            self.host[start:stop] = host.reshape(-1).view(np.uint8)
            source = wp.array(ptr=self.buffer.ptr + start, dtype=dtype, shape=shape, device="cpu", pinned=True)
            target = wp.empty(shape, dtype=dtype, device=self.device)
            wp.copy(target, source)
            self.pending.append((start, stop, wp.get_stream(self.device).record_event()))
        return target


class WarpBackend(Backend):
    """Warp on one device ("cpu", "cuda:N"). Create through ``get_backend("warp", device)``."""

    name = "warp"

    def __init__(self, device: str):
        import_warp()  # initialized quietly
        self._device = wp.get_device(device)
        self.device = str(self._device.alias)
        self.is_gpu = bool(self._device.is_cuda)
        if self.is_gpu and wp.is_mempool_enabled(self._device):
            wp.set_mempool_release_threshold(self._device, MEMPOOL_KEEP)
        self.has_float64 = True
        self._constants = Remembered(CONSTANTS)  # _constant's uploads
        self._staging = _Staging(self._device, STAGING_BYTES) if self.is_gpu else None

    def _array(self, data: np.ndarray, dtype) -> wp.array:
        staged = None if self._staging is None else self._staging.upload(data, dtype)
        return wp.array(data, dtype=dtype, device=self._device) if staged is None else staged

    def _constant(self, data: np.ndarray, dtype) -> wp.array:
        """``_array`` of a kernel input that no kernel writes, reused while the same bytes come
        again: a pose step passes the same thresholds, windows, masks, weights and beam tables
        to hundreds of launches, and each upload waits for its copy. Inputs above
        ``CONSTANT_BYTES`` are uploaded each time; the last ``CONSTANTS`` are kept."""
        data = np.ascontiguousarray(data)
        if data.nbytes > CONSTANT_BYTES:
            return self._array(data, dtype)
        key = (dtype, data.shape, data.dtype.str, data.tobytes())
        return self._constants.get(key, lambda: self._array(data, dtype))

    def _arrays(self, *items) -> list[wp.array]:
        """``_array`` of each (host array, dtype) pair, the dtypes float32 scalars, vectors or
        matrices (the host arrays' trailing axes their shape), in one upload: views of one
        buffer (each upload costs ~0.1 ms of Warp's Python, and the loop makes thousands)."""
        host = [np.asarray(data, np.float32) for data, _ in items]
        buffer = self._array(np.concatenate([h.ravel() for h in host]), float)
        views = (view.reshape(h.shape) for view, h in zip(_views(buffer, [h.size for h in host]), host))
        return [view if dtype is float else view.view(dtype) for view, (_, dtype) in zip(views, items)]

    def _upload(self, array: np.ndarray) -> wp.array:
        return self._array(array, float)

    def _project(self, points, rotations, translations, sonar: SonarConstants):
        n_views, n_points = rotations.shape[0], points.shape[0]
        with wp.ScopedDevice(self._device):
            beam = wp.empty((n_views, n_points), dtype=wp.int32)
            bin_ = wp.empty((n_views, n_points), dtype=wp.int32)
            inside = wp.empty((n_views, n_points), dtype=wp.uint8)
            _launch(project_points, dim=(n_views, n_points),
                    inputs=[self._array(points, wp.vec3), self._array(rotations, wp.mat33),
                            self._array(translations, wp.vec3), self._constant(sonar.beam_table, float),
                            kernel_sonar(sonar)],
                    outputs=[beam, bin_, inside])
            wp.synchronize_device(self._device)
            return beam.numpy(), bin_.numpy(), inside.numpy()

    # --- ray casting and image synthesis ------------------------------------------------------
    def _load_mesh(self, vertices, faces):
        """The float32 corners and each triangle's box, padded so that boxes of axis-aligned
        triangles have volume (and rounding never loses one) by 1e-6 × (the largest |vertex
        coordinate|, at least 1e-12) + 1e-6 × the box's longest side, made on the device
        (``triangle_boxes_kernel``, float32 throughout). One load at a time in a process
        (``_LOAD_LOCK``): BVHs built by two threads at once on an H200 made renders fail with
        illegal memory accesses in 4 of 5 runs (docs/decisions.md, "Threads")."""
        n_faces = faces.shape[0]
        extent = float(np.max(np.abs(vertices))) if len(vertices) else 1.0
        with _LOAD_LOCK, wp.ScopedDevice(self._device):
            corners = wp.empty(3 * n_faces, dtype=wp.vec3)
            lowers, uppers = wp.empty(n_faces, dtype=wp.vec3), wp.empty(n_faces, dtype=wp.vec3)
            _launch(triangle_boxes_kernel, dim=n_faces,
                    inputs=[self._array(np.asarray(vertices, np.float32), wp.vec3), self._array(faces.reshape(-1),
                            wp.int32), float(np.float32(1.0e-6 * max(extent, 1.0e-12)))],
                    outputs=[corners, lowers, uppers])
            bvh = wp.Bvh(lowers, uppers)
        return WarpMesh(bvh, corners, lowers, uppers, self.device)

    def _exact_corners(self, mesh, corners):
        return self._array(corners.reshape(-1, 3), wp.vec3d)

    def _surface_distances(self, mesh, points):
        """The BVH's search (``closest.py``) from a cube of half-side 1/1024 of the mesh's box
        diagonal, doubled until it holds the nearest triangle."""
        mesh = self._check_mesh(mesh)
        lower, upper = mesh.bounds
        with wp.ScopedDevice(self._device):
            distance = wp.empty(points.shape[0], dtype=wp.float64)
            _launch(surface_distances_kernel, dim=points.shape[0],
                    inputs=[mesh.id, mesh.exact, wp.vec3d(*lower), wp.vec3d(*upper),
                            wp.float64(max(float(np.linalg.norm(upper - lower)) / 1024.0, 1.0e-12)),
                            self._array(points, wp.vec3d)],
                    outputs=[distance])
            return distance.numpy()

    def _check_mesh(self, mesh) -> "WarpMesh":
        if not isinstance(mesh, WarpMesh):
            raise TypeError(f"mesh must be a handle from this backend's load_mesh, got {type(mesh).__name__}")
        if mesh.device != self.device:
            raise ValueError(f"mesh was loaded on {mesh.device!r}, this backend runs on {self.device!r}")
        return mesh

    def _prepared_cast(self, mesh, origins, directions, max_distance):
        mesh = self._check_mesh(mesh)
        n_rays = origins.shape[0]
        with wp.ScopedDevice(self._device):
            inputs = [mesh.id, mesh.corners, self._array(origins, wp.vec3),
                      self._array(directions, wp.vec3), float(np.float32(min(max_distance, WARP_FAR)))]
            distance = wp.empty(n_rays, dtype=float)
            face = wp.empty(n_rays, dtype=wp.int32)

        def launch():
            _launch(cast_rays_kernel, dim=n_rays, inputs=inputs, outputs=[distance, face], device=self._device)
            wp.synchronize_device(self._device)
        return PreparedLaunch(launch, lambda: (distance.numpy(), face.numpy()))

    def _frontal_rays(self, mesh, sonar: SonarConstants, rotations, translations, plane_normals, plane_offsets,
                      views, azimuths, rays, mirror):
        mesh = self._check_mesh(mesh)
        shape = (views.shape[0], rays)
        with wp.ScopedDevice(self._device):
            rng = wp.empty(shape, dtype=float)
            face = wp.empty(shape, dtype=wp.int32)
            *poses, azimuth = self._poses(rotations, translations, plane_normals, plane_offsets, azimuths)
            _launch(frontal_rays_kernel, dim=shape,
                    inputs=[mesh.id, mesh.corners, *poses, self._constant(views, wp.int32), azimuth,
                            self._constant(mirror, wp.uint8), kernel_sonar(sonar),
                            float(np.float32(RAY_EPSILON)),
                            float(np.float32(FRONTAL_VISIBLE)), float(np.float32(MAX_DISTANCE))],
                    outputs=[rng, face])
            wp.synchronize_device(self._device)
            return rng.numpy(), face.numpy()

    def _render(self, mesh, sonar: SonarConstants, beam_widths, rotations, translations,
                plane_normals, plane_offsets, k_theta, k_phi, gamma, surface_reflection, first_rows, rows, spans,
                shared, needed=None, planes=4, *, wait=True):
        mesh = self._check_mesh(mesh)
        shape = (rotations.shape[0], planes, rows, sonar.beams)
        with wp.ScopedDevice(self._device):
            poses = self._poses(rotations, translations, plane_normals, plane_offsets)
            acc = wp.empty(shape, dtype=wp.int32)
            first = self._constant(first_rows, wp.int32)

            def render_once(share):
                acc.zero_()
                hits = self._render_into(mesh, sonar, beam_widths, poses, k_theta, k_phi, gamma, surface_reflection,
                                         first, spans, acc, shared=shared, needed=needed, hit_share=share)
                return None if hits is None else lambda: (int(hits[0].numpy()[0]), hits[1])  # waits

            layers = WarpLayers(acc)
            layers.overflowed = render_with_room(render_once, self.hit_queue, wait=wait)
            if wait:
                wp.synchronize_device(self._device)
            return layers

    def _poses(self, rotations, translations, plane_normals, plane_offsets, *more) -> list[wp.array]:
        """The (N,) views of a render on the device: rotations, translations, plane normals,
        offsets, and ``more`` float arrays (one upload)."""
        return self._arrays((rotations, wp.mat33), (translations, wp.vec3), (plane_normals, wp.vec3),
                            (plane_offsets, float), *((extra, float) for extra in more))

    def _render_into(self, mesh, sonar: SonarConstants, beam_widths, poses, k_theta, k_phi, gamma,
                     surface_reflection, first_rows, spans, acc, layers=None, shared=None, needed=None,
                     hit_share=None) -> tuple[wp.array, int] | None:
        """Launch the render kernels of the views ``poses`` ((n,) device arrays of ``_poses``) on
        the device's current stream: acc (n, P, R, beams) int32 (P: 4 layers or 2 components'
        sums), zeroed, receives the deposits, and layers of its shape float32, if given, their
        floats; first_rows (n,) int32 on the
        device; spans (n, 4) int32 on the host (``Backend._render``: nothing is cast where they
        are all empty, and the queue of hits is sized on them; a CPU device packs them, a GPU
        finds its own on the device, ``_ray_chunks``); shared, the views' SharedPoses
        (or None), whose distinct poses' direct legs are cast first; needed, None or the (M, 2,
        beams) uint8 beams read (``Backend._render``); hit_share, the queue of hits
        (``hit_queue_size``; None: room for every hit). Returns without waiting: the queue's count
        (1,) int32 on the device and its slots L (a count above L: the queue overflowed and acc
        lacks returns), or None where nothing was cast."""
        if sonar.use_table:
            centres = np.ascontiguousarray(sonar.beam_table[0], np.float32)
        else:  # the centres of SonarSpec.beam_centres
            half = float(sonar.half_azimuth)
            centres = (-half + np.arange(sonar.beams) * (2.0 * half / max(sonar.beams - 1, 1))).astype(np.float32)
        weight = float(np.float32(1.0 / (k_theta * k_phi)))
        widest, samples = span_extent(spans)
        if widest:  # else no view reaches the mesh: the layers stay zeros
            widths = np.asarray(beam_widths, np.float32)
            directions = wp.empty((sonar.beams, k_theta, k_phi), dtype=wp.vec3)
            _launch(sub_rays_kernel, dim=directions.shape,
                    inputs=[self._constant(centres, float), self._constant(widths, float), kernel_sonar(sonar)],
                    outputs=[directions])
            hits = self._direct_hits(mesh, directions, acc.shape[0], shared)
            size = hit_queue_size(acc.shape[0] * widest * k_theta * samples, hit_share)
            queue = (wp.zeros(1, dtype=wp.int32), wp.empty(size, dtype=wp.vec4i), wp.empty(size, dtype=float))
            table, masks = (self._constant(sonar.beam_table, float),
                            self._constant(np.ones((1, 1, 1), np.uint8) if needed is None else needed, wp.uint8))
            chunks, threads = self._ray_chunks(mesh, sonar, centres, widths, poses, acc.shape[0], k_theta, k_phi,
                                               None if self.is_gpu else spans)
            _launch(render_kernel, dim=threads,
                    inputs=[mesh.id, mesh.corners, *poses, directions, kernel_sonar(sonar), int(k_theta),
                            weight, float(gamma), float(surface_reflection), first_rows, *chunks, RAY_CHUNK, threads,
                            *hits, int(needed is not None), masks],
                    outputs=[acc, *queue])
            served = min(size, self._resident_threads())
            _launch(hits_kernel, dim=served,
                    inputs=[mesh.id, mesh.corners, *poses, directions, table, kernel_sonar(sonar), weight,
                            float(gamma), float(surface_reflection), first_rows, int(needed is not None), masks,
                            *queue, served],
                    outputs=[acc])
        if layers is not None:
            _launch(fixed_to_float, dim=acc.size, inputs=[acc.flatten()], outputs=[layers.flatten()])
        return (queue[0], size) if widest else None

    def _ray_chunks(self, mesh, sonar: SonarConstants, centres: np.ndarray, widths: np.ndarray, poses, n: int,
                    k_theta: int, k_phi: int, spans=None) -> tuple[tuple[wp.array, wp.array, wp.array, wp.array], int]:
        """render_kernel's sub-rays: ((spans (n, 4) int32, chunks (n,), their exclusive prefix
        sums (n,), chunk_views, the view of each chunk), the launch's threads), for the n views
        ``poses`` (``_poses``). Each view's span holds the sub-rays that can reach the mesh's box
        directly or by the surface first; the others deposit nothing, so the layers are those of
        every sub-ray, bit for bit. Without ``spans`` they are found on the device
        (``view_spans_kernel``, as ``fsswarp.backends.base.ray_spans``) and the launch's threads
        each take several in turn; a CPU device passes the host's ``spans`` (found when the render
        was planned), chunked on the host (``span_chunks``), a thread per sub-ray."""
        if spans is not None:  # some view reaches the mesh: the table is not empty
            arrays = (spans, *span_chunks(spans, k_theta))
            return tuple(self._array(np.ascontiguousarray(a, np.int32), wp.int32) for a in arrays), \
                int(arrays[3].size) * RAY_CHUNK
        lower, upper = (wp.vec3(*bound.astype(np.float32)) for bound in mesh.bounds)
        spans, chunks, offsets = (wp.empty(shape, dtype=wp.int32) for shape in ((n, 4), n, n))
        _launch(view_spans_kernel, dim=n,
                inputs=[lower, upper, *poses, *(self._constant(edges, float) for edges in beam_edges(centres, widths)),
                        float(sonar.half_elevation), int(k_theta), int(k_phi), RAY_CHUNK],
                outputs=[spans, chunks])
        wp.utils.array_scan(chunks, offsets, inclusive=False)
        most = most_chunks(n, sonar.beams, k_theta, k_phi)
        chunk_views = wp.empty(most, dtype=wp.int32)
        _launch(chunk_views_kernel, dim=n, inputs=[chunks, offsets], outputs=[chunk_views])
        return (spans, chunks, offsets, chunk_views), min(most * RAY_CHUNK, self._resident_threads())

    def _resident_threads(self) -> int:
        """Threads of a launch that takes its items in turn (render_kernel, hits_kernel): about
        as many as the device keeps running at once (one thread runs a CPU launch anyway)."""
        return int(self._device.sm_count) * RENDER_THREADS_PER_UNIT if self._device.is_cuda else CPU_THREADS

    def _direct_hits(self, mesh, directions, n_views, shared) -> tuple[wp.array, wp.array, wp.array]:
        """render_kernel's poses, hit_range and hit_face: with ``shared`` (SharedPoses) the direct
        legs of its distinct poses along the (beams, K_θ, K_φ) sub-ray ``directions``, launched;
        without, poses of -1 (every view casts its own)."""
        if shared is None:
            return (self._constant(np.full(n_views, -1, np.int32), wp.int32),
                    wp.empty((1, 1, 1, 1), dtype=float), wp.empty((1, 1, 1, 1), dtype=wp.int32))
        shape = (shared.count, *directions.shape)
        hit_range, hit_face = wp.empty(shape, dtype=float), wp.empty(shape, dtype=wp.int32)
        widest, samples = span_extent(shared.spans)
        _launch(direct_hits_kernel, dim=(shape[0], widest, shape[2] * samples),
                inputs=[mesh.id, mesh.corners, self._array(shared.rotations, wp.mat33),
                        self._array(shared.translations, wp.vec3), directions, shape[2],
                        self._array(shared.spans, wp.int32)],
                outputs=[hit_range, hit_face])
        return self._array(shared.index, wp.int32), hit_range, hit_face

    def _render_batches(self, mesh, sonar: SonarConstants, beam_widths, rotations, translations, plane_normals,
                        plane_offsets, k_theta, k_phi, gamma, surface_reflection, batch, spans):
        """On CUDA two slots alternate: batch k renders on the device's stream into slot k % 2
        while a copy stream takes batch k − 1 to its page-locked host buffer (events order
        them); on the CPU the layers are host memory already and come as they are."""
        mesh = self._check_mesh(mesh)
        n_views = rotations.shape[0]
        shape = (min(batch, n_views), 4, sonar.bins, sonar.beams)
        slots = 2 if self.is_gpu else 1
        with wp.ScopedDevice(self._device):
            poses = self._poses(rotations, translations, plane_normals, plane_offsets)
            accs = [wp.empty(shape, dtype=wp.int32) for _ in range(slots)]
            layers = [wp.empty(shape, dtype=float) for _ in range(slots)]
            first = self._constant(np.zeros(shape[0], np.int32), wp.int32)
        host = [wp.empty(shape, dtype=float, device="cpu", pinned=True) for _ in range(slots)] if self.is_gpu else None
        copier = wp.Stream(self._device) if self.is_gpu else None
        copied: list = [None] * slots  # the event of each slot's last copy
        pending = None  # (start, count, slot) of the batch copied last, not yet handed out
        try:
            for k, start in enumerate(range(0, n_views, batch)):
                stop, slot = min(start + batch, n_views), k % slots
                n = stop - start
                with wp.ScopedDevice(self._device):
                    if copied[slot] is not None:  # the slot's layers went to the host first
                        wp.get_stream(self._device).wait_event(copied[slot])
                    acc, out = accs[slot][:n], layers[slot][:n]
                    acc.zero_()
                    self._render_into(mesh, sonar, beam_widths, tuple(p[start:stop] for p in poses), k_theta,
                                      k_phi, gamma, surface_reflection, first[:n], spans[start:stop], acc, out)
                    if self.is_gpu:
                        copier.wait_event(wp.get_stream(self._device).record_event())
                        wp.copy(host[slot][:n], out, stream=copier)
                        copied[slot] = copier.record_event()
                if not self.is_gpu:  # launches on the CPU return when done
                    yield start, out.numpy()
                    continue
                if pending is not None:
                    yield self._copied(host, copied, *pending)
                pending = (start, n, slot)
            if pending is not None:
                yield self._copied(host, copied, *pending)
        finally:  # a consumer that stops early: no copy may land in freed buffers
            if copier is not None:
                wp.synchronize_stream(copier)

    @staticmethod
    def _copied(host, copied, start, count, slot) -> tuple[int, np.ndarray]:
        wp.synchronize_event(copied[slot])
        return start, host[slot].numpy()[:count]

    # --- voxel space carving -------------------------------------------------------------------
    def _prepared_carve(self, integral, rotations, translations, sonar: SonarConstants, voxel_size, radius, origin,
                        shape, centres):
        n_voxels = centres.shape[0] if centres is not None else shape[0] * shape[1] * shape[2]
        with wp.ScopedDevice(self._device):
            seen = wp.empty(n_voxels, dtype=wp.uint8)
            rejected = wp.empty(n_voxels, dtype=wp.uint8)
            common = [self._array(rotations, wp.mat33), self._array(translations, wp.vec3),
                      self._array(integral, wp.int32), self._constant(sonar.beam_table, float),
                      kernel_sonar(sonar), radius]
            if centres is not None:
                kernel, inputs = carve_points, [self._array(centres, wp.vec3), *common]
            else:
                kernel = carve_grid
                inputs = [wp.vec3(*(float(x) for x in origin)), voxel_size, shape[1], shape[2], *common]

        def launch():
            _launch(kernel, dim=n_voxels, inputs=inputs, outputs=[seen, rejected], device=self._device)
            wp.synchronize_device(self._device)
        return PreparedLaunch(launch, lambda: (seen.numpy(), rejected.numpy()))

    # --- copies and the device -------------------------------------------------------------------
    @property
    def device_name(self) -> str:
        return self._device.name

    def _transfer_calls(self, host):
        with wp.ScopedDevice(self._device):
            source = self._array(host, float)
            target = wp.empty_like(source)
        staging = wp.array(host, dtype=float, device="cpu")
        back = np.empty_like(host)

        def device_to_device():
            wp.copy(target, source)
            wp.synchronize_device(self._device)

        def host_to_device():
            wp.copy(source, staging)
            wp.synchronize_device(self._device)

        def device_to_host():
            back[:] = source.numpy()
        return device_to_device, host_to_device, device_to_host

    # --- frontal contours and their distance to the data's (kernels after the class) ---------
    def _contour_cost(self, layers, first_rows, view_index, thresholds, windows, masks, range_weights,
                      beam_weights, distances, cap, shifts):
        with wp.ScopedDevice(self._device):
            contour, sums, counts = self._contour_launch(layers, first_rows, view_index, thresholds, windows, masks,
                                                         range_weights, beam_weights, distances, cap, shifts)
            wp.synchronize_device(self._device)
            return contour.numpy(), sums.numpy(), counts.numpy()

    def _view_costs(self, layers, first_rows, view_index, thresholds, windows, masks, range_weights,
                    beam_weights, distances, cap, shifts, data_counts, *, wait=True):
        with wp.ScopedDevice(self._device):
            _, sums, counts = self._contour_launch(layers, first_rows, view_index, thresholds, windows, masks,
                                                   range_weights, beam_weights, distances, cap, shifts)
            costs = wp.empty((view_index.shape[0], shifts.shape[0]), dtype=float)
            _launch(view_cost_kernel, dim=costs.shape,
                    inputs=[sums, counts, self._constant(view_index, wp.int32), self._constant(data_counts, wp.int32),
                            float(np.float32(cap))],
                    outputs=[costs])
            return costs.numpy() if wait else costs.numpy  # numpy waits for the launches

    def _contour_launch(self, layers, first_rows, view_index, thresholds, windows, masks, range_weights,
                        beam_weights, distances, cap, shifts) -> tuple[wp.array, wp.array, wp.array]:
        """Launch ``frontal_contour`` and ``contour_cost_kernel`` on the current device's stream;
        returns their (N, 2, beams) contours, (N, 2, S) sums and (N, 2) counts without waiting."""
        n_pairs, beams = view_index.shape[0], distances.shape[3]
        if isinstance(layers, WarpLayers) and layers.array.device == self._device:
            stack, scale = layers.array, 1.0 / FIXED_SCALE
        else:
            stack, scale = self._array(np.ascontiguousarray(layers.numpy(), np.float32), float), 1.0
        index = self._constant(view_index, wp.int32)
        contour = wp.full((n_pairs, 2, beams), -1.0, dtype=float)
        items = mask_items(masks)
        _launch(frontal_contour, dim=(n_pairs, items.shape[1]),
                inputs=[stack, scale, self._constant(first_rows, wp.int32), index, self._constant(thresholds, float),
                        self._constant(windows, wp.int32),
                        self._constant(items, wp.int32), self._constant(range_weights, float),
                        (range_weights.shape[0] - 1) // 2, self._constant(beam_weights, float),
                        (beam_weights.shape[0] - 1) // 2],
                outputs=[contour])
        sums = wp.empty((n_pairs, 2, shifts.shape[0]), dtype=float)
        counts = wp.empty((n_pairs, 2), dtype=wp.int32)
        _launch(contour_cost_kernel, dim=(n_pairs, 2, shifts.shape[0]),
                inputs=[contour, index, distances.data, float(np.float32(cap)), self._constant(shifts, float)],
                outputs=[sums, counts])
        return contour, sums, counts

    # --- IRLS-ICP runs (kernels after the class) ------------------------------------------------
    def _icp_runs(self, source_x, source_y, target_x, target_y, runs, angles, translations, floors, step_tols,
                  max_iterations, max_distance, tuning):
        """Three uploads and two read-backs (Warp's Python costs ~0.1 ms each, and the loop runs
        ~200 of these): the read-only float64 inputs in one array, the transforms (read and
        written) with the float64 outputs and scratch in another, the integers in a third; the
        kernel gets views of them."""
        n_runs, n_points = runs.shape[0], source_x.shape[0]
        sizes = (n_points, n_points, target_x.shape[0], target_y.shape[0], n_runs, n_runs)
        read = np.concatenate([source_x, source_y, target_x, target_y, floors, step_tols]).astype(np.float64)
        written = np.concatenate([angles, np.ravel(translations), np.zeros(7 * n_points)]).astype(np.float64)
        # angle, trans, moved_x, moved_y, dist (read back), then scratch; iterations, converged, nearest
        float_sizes, int_sizes = (n_runs, 2 * n_runs) + (n_points,) * 7, (n_runs, n_runs, n_points)
        with wp.ScopedDevice(self._device):
            sx, sy, tx, ty, floor, tol = _views(self._array(read, wp.float64), sizes)
            io = self._array(written, wp.float64)
            angle, trans, moved_x, moved_y, dist, anchor_x, anchor_y, room2, scratch = _views(io, float_sizes)
            counters = wp.zeros(sum(int_sizes), dtype=wp.int32)
            iterations, converged, nearest = _views(counters, int_sizes)
            lanes = self.icp_lanes
            _launch(icp_runs_kernel, dim=n_runs * lanes,
                    inputs=[sx, sy, tx, ty, self._array(runs, wp.int32), floor, tol, max_iterations,
                            wp.float64(max_distance), wp.float64(tuning)],
                    outputs=[angle, trans.reshape((n_runs, 2)), iterations, converged, moved_x, moved_y, nearest,
                             dist, anchor_x, anchor_y, room2, scratch, lanes])
            wp.synchronize_device(self._device)
            floats = io[:sum(float_sizes[:5])].numpy()
            ints = counters.numpy()
        angle, trans, moved_x, moved_y, dist = np.split(floats, np.cumsum(float_sizes[:4]))
        iterations, converged, nearest = np.split(ints, np.cumsum(int_sizes[:2]))
        return angle, trans.reshape(n_runs, 2), iterations, converged, moved_x, moved_y, nearest, dist


def _views(array: wp.array, sizes) -> list[wp.array]:
    """Consecutive 1-D views of ``array`` of the given sizes (an empty array for a size of 0,
    which Warp does not slice)."""
    ends = np.cumsum(sizes)
    return [array[int(end - size):int(end)] if size else wp.empty(0, dtype=array.dtype, device=array.device)
            for end, size in zip(ends, sizes)]
