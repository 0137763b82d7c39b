"""``OpenCLBackend``: the Backend interface on one OpenCL device, with its own context and queue.

Kernels come from ``programs.py`` (kernels/*.cl); launches round their global size up to a
multiple of ``GROUP``. Device layers are ``OpenCLLayers``, meshes ``OpenCLMesh`` handles (a
host-built BVH, ``fsswarp/backends/bvh.py``, and its buffers).
"""

from __future__ import annotations

import threading
import weakref

import numpy as np
import pyopencl as cl

from ..base import (Backend, DeviceLayers, PreparedLaunch, SonarConstants, beam_edges, fixed_floats,
                    hit_queue_size, mask_items, most_chunks, render_with_room, span_chunks, span_extent)
from ..bvh import FlatBVH, build_bvh
from ..constants import (FRONTAL_VISIBLE, GPU_HIT_QUEUE, MAX_DISTANCE, RAY_CHUNK, RAY_EPSILON,
                         RENDER_THREADS_PER_UNIT)
from ..runtimes import OpenCLDevice
from .programs import GROUP, program

#: Largest layers buffer (bytes) a CPU device keeps between renders.
SCRATCH_BYTES = 1 << 30
#: Most layers buffers a CPU device keeps between renders (``_layers_buffer``).
KEPT_LAYERS = 2
#: Work-group size of ``chunk_offsets``, the prefix sums of a render's chunks (at most the device's).
SCAN_GROUP = 256


class OpenCLBackend(Backend):
    """One OpenCL device with its own context and queue. Create through
    ``get_backend("opencl", device)``."""

    name = "opencl"

    def __init__(self, found: OpenCLDevice):
        self.device = found.label
        self.is_gpu = found.is_gpu
        self.cl_device = found.device
        self.context = cl.Context([found.device])
        self.queue = cl.CommandQueue(self.context)
        # Kernel objects once: pyopencl makes a new one on every attribute access. Their
        # arguments are state, so launches hold the lock (one backend may serve many threads).
        self._project_kernel = cl.Kernel(program(self.context, "project.cl"), "project_points")
        self._carve_grid_kernel = cl.Kernel(program(self.context, "carve.cl"), "carve_grid")
        self._carve_points_kernel = cl.Kernel(program(self.context, "carve.cl"), "carve_points")
        self._cast_kernel = cl.Kernel(program(self.context, "raycast.cl"), "cast_rays")
        self._render_kernel = cl.Kernel(program(self.context, "render.cl"), "render_views")
        self._direct_hits_kernel = cl.Kernel(program(self.context, "render.cl"), "direct_hits")
        self._sub_rays_kernel = cl.Kernel(program(self.context, "render.cl"), "sub_rays")
        self._fixed_kernel = cl.Kernel(program(self.context, "render.cl"), "fixed_to_float")
        self._hits_kernel = cl.Kernel(program(self.context, "render.cl"), "hit_returns")
        self._view_spans_kernel = cl.Kernel(program(self.context, "render.cl"), "view_spans")
        self._chunk_offsets_kernel = cl.Kernel(program(self.context, "render.cl"), "chunk_offsets")
        self._chunk_views_kernel = cl.Kernel(program(self.context, "render.cl"), "chunk_views")
        self._frontal_rays_kernel = cl.Kernel(program(self.context, "render.cl"), "frontal_rays")
        self._frontal_kernel = cl.Kernel(program(self.context, "pose.cl"), "frontal_contour")
        self._contour_cost_kernel = cl.Kernel(program(self.context, "pose.cl"), "contour_cost")
        self._view_cost_kernel = cl.Kernel(program(self.context, "pose.cl"), "view_cost")
        self.has_float64 = "cl_khr_fp64" in found.device.extensions.split()
        self._icp_kernel = cl.Kernel(program(self.context, "icp.cl"), "icp_runs") if self.has_float64 else None
        self._distances_kernel = cl.Kernel(program(self.context, "closest.cl"), "surface_distances") \
            if self.has_float64 else None
        self._lock = threading.Lock()
        self._held = []  # buffers handed to queued kernels, released after the queue finishes (_finish)
        self._kept_layers = []  # (layers buffer, weak reference to its holder) kept on a CPU device (_layers_buffer)

    @property
    def hit_queue(self) -> float:
        """No queue on a CPU device: render_views deposits each hit's returns at once (PoCL has no
        warps to fill, and the queue made the 24 × 24 pose grid 2–6% slower here)."""
        return GPU_HIT_QUEUE if self.is_gpu else 0.0

    def _input(self, array: np.ndarray) -> cl.Buffer:
        """A buffer holding a copy of ``array``, kept until the queue finishes (``_finish``)."""
        buffer = cl.Buffer(self.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=array)
        self._held.append(buffer)
        return buffer

    def _scratch(self, nbytes: int) -> cl.Buffer:
        """A device buffer of ``nbytes`` for a kernel's results, kept until the queue finishes."""
        buffer = cl.Buffer(self.context, cl.mem_flags.READ_WRITE, size=max(nbytes, 4))
        self._held.append(buffer)
        return buffer

    def _finish(self) -> None:
        """Wait for the queue, then release the buffers its kernels used. NVIDIA's OpenCL makes
        ``clReleaseMemObject`` wait for the kernels that use the buffer, and pyopencl calls it
        holding the GIL: a buffer dropped after its launch stalls every thread until that kernel
        ends (docs/decisions.md, "OpenCL buffers are released after the queue finishes"). Call
        holding ``_lock``: no other thread's launch may be enqueued between the wait and the release."""
        self.queue.finish()
        self._held.clear()

    def _upload(self, array: np.ndarray) -> cl.Buffer:
        return self._input(array)

    def _output(self, shape: tuple[int, ...], dtype) -> tuple[np.ndarray, cl.Buffer]:
        host = np.empty(shape, dtype)
        return host, self._scratch(host.nbytes)

    def _project(self, points, rotations, translations, sonar: SonarConstants):
        n_views, n_points = rotations.shape[0], points.shape[0]
        beam, beam_buf = self._output((n_views, n_points), np.int32)
        bin_, bin_buf = self._output((n_views, n_points), np.int32)
        inside, inside_buf = self._output((n_views, n_points), np.uint8)
        global_size = (-(-n_points // GROUP) * GROUP, n_views)
        with self._lock:
            self._project_kernel(
                self.queue, global_size, None,
                self._input(points), self._input(rotations), self._input(translations),
                self._input(sonar.beam_table), sonar.record(), np.int32(n_points),
                beam_buf, bin_buf, inside_buf)
            for host, buf in ((beam, beam_buf), (bin_, bin_buf), (inside, inside_buf)):
                cl.enqueue_copy(self.queue, host, buf, is_blocking=False)
            self._finish()
        return beam, bin_, inside

    def _prepared_carve(self, integral, rotations, translations, sonar: SonarConstants, voxel_size, radius, origin,
                        shape, centres):
        n_voxels = centres.shape[0] if centres is not None else shape[0] * shape[1] * shape[2]
        seen, seen_buf = self._output((n_voxels,), np.uint8)
        rejected, rejected_buf = self._output((n_voxels,), np.uint8)
        common = (np.int32(n_voxels), self._input(rotations), self._input(translations), self._input(integral),
                  np.int32(rotations.shape[0]), self._input(sonar.beam_table), sonar.record(),
                  np.float32(radius), seen_buf, rejected_buf)
        if centres is not None:
            kernel, args = self._carve_points_kernel, (self._input(centres), *common)
        else:
            kernel = self._carve_grid_kernel
            args = (self._input(origin), np.float32(voxel_size), *(np.int32(n) for n in shape), *common)
        return self._prepared(kernel, (-(-n_voxels // GROUP) * GROUP,), args,
                              ((seen, seen_buf), (rejected, rejected_buf)))

    def _prepared(self, kernel: cl.Kernel, global_size: tuple[int, ...], args: tuple, outputs: tuple) -> PreparedLaunch:
        """A launch of ``kernel`` on ``args`` that waits, reading back ``outputs`` ((host array,
        buffer) pairs) on ``read()``."""
        def launch():
            with self._lock:
                kernel(self.queue, global_size, None, *args)
                self._finish()

        def read():
            with self._lock:
                for host, buf in outputs:
                    cl.enqueue_copy(self.queue, host, buf, is_blocking=False)
                self._finish()
            return tuple(host.copy() for host, _ in outputs)
        return PreparedLaunch(launch, read)

    # --- ray casting and image synthesis --------------------------------------------------------
    def _load_mesh(self, vertices, faces):
        bvh = build_bvh(vertices, faces)
        return OpenCLMesh(bvh, self._input(bvh.node_bounds), self._input(bvh.node_children),
                          self._input(bvh.triangles), self._input(bvh.face_index))

    def _exact_corners(self, mesh, corners):
        """The corners in the BVH's leaf order, and the slack of its float32 boxes (1e-6 of the
        largest |coordinate|)."""
        _check_mesh(mesh)
        buffer = cl.Buffer(self.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                           hostbuf=np.ascontiguousarray(corners[mesh.bvh.face_index].reshape(-1, 9)))
        return buffer, 1.0e-6 * max(float(np.abs(corners).max()), 1.0e-12)

    def _surface_distances(self, mesh, points):
        _check_mesh(mesh)
        corners, slack = mesh.exact
        n_points = points.shape[0]
        distance, distance_buf = self._output((n_points,), np.float64)
        with self._lock:
            self._distances_kernel(self.queue, (-(-n_points // GROUP) * GROUP,), None, mesh.nodes, mesh.children,
                                   corners, self._input(points), np.int32(n_points), np.float64(slack), distance_buf)
            cl.enqueue_copy(self.queue, distance, distance_buf, is_blocking=False)
            self._finish()
        return distance

    def _prepared_cast(self, mesh, origins, directions, max_distance):
        _check_mesh(mesh)
        n_rays = origins.shape[0]
        distance, distance_buf = self._output((n_rays,), np.float32)
        face, face_buf = self._output((n_rays,), np.int32)
        args = (mesh.nodes, mesh.children, mesh.triangles, mesh.face_index, self._input(origins),
                self._input(directions), np.int32(n_rays), np.float32(max_distance), distance_buf, face_buf)
        return self._prepared(self._cast_kernel, (-(-n_rays // GROUP) * GROUP,), args,
                              ((distance, distance_buf), (face, face_buf)))

    # --- copies and the device -------------------------------------------------------------------
    @property
    def device_name(self) -> str:
        return self.cl_device.name.strip()

    def _transfer_calls(self, host):
        flags = cl.mem_flags.READ_WRITE
        source = cl.Buffer(self.context, flags, size=host.nbytes)
        target = cl.Buffer(self.context, flags, size=host.nbytes)
        back = np.empty_like(host)

        def device_to_device():
            cl.enqueue_copy(self.queue, target, source, byte_count=host.nbytes)
            self.queue.finish()

        def host_to_device():
            cl.enqueue_copy(self.queue, source, host, is_blocking=True)

        def device_to_host():
            cl.enqueue_copy(self.queue, back, source, is_blocking=True)
        return device_to_device, host_to_device, device_to_host

    def _frontal_rays(self, mesh, sonar: SonarConstants, rotations, translations, plane_normals, plane_offsets,
                      views, azimuths, rays, mirror):
        _check_mesh(mesh)
        n_items = views.shape[0] * rays
        rng, rng_buf = self._output((views.shape[0], rays), np.float32)
        face, face_buf = self._output((views.shape[0], rays), np.int32)
        with self._lock:
            self._frontal_rays_kernel(
                self.queue, (-(-n_items // GROUP) * GROUP,), None,
                mesh.nodes, mesh.children, mesh.triangles, mesh.face_index, self._input(rotations),
                self._input(translations), self._input(plane_normals), self._input(plane_offsets),
                self._input(views), self._input(azimuths), np.int32(n_items), np.int32(rays),
                self._input(mirror), sonar.record(), np.float32(RAY_EPSILON), np.float32(FRONTAL_VISIBLE), np.float32(MAX_DISTANCE),
                rng_buf, face_buf)
            cl.enqueue_copy(self.queue, rng, rng_buf, is_blocking=False)
            cl.enqueue_copy(self.queue, face, face_buf, is_blocking=False)
            self._finish()
        return rng, face

    def _render(self, mesh, sonar: SonarConstants, beam_widths, rotations, translations,
                plane_normals, plane_offsets, k_theta, k_phi, gamma, surface_reflection, first_rows, rows, spans,
                shared, needed=None, planes=4, *, wait=True):
        _check_mesh(mesh)
        shape = (rotations.shape[0], planes, rows, sonar.beams)
        size = int(np.prod(shape))
        with self._lock:
            layers_buf = self._layers_buffer(4 * size)

            def render_once(share):
                hits = self._enqueue_render(mesh, sonar, beam_widths, rotations, translations, plane_normals,
                                            plane_offsets, k_theta, k_phi, gamma, surface_reflection, first_rows,
                                            spans, shape, layers_buf, shared=shared, needed=needed,
                                            hit_share=share)[1]
                self._finish()
                return None if hits is None else lambda: (int(hits[0][0]), hits[1])

            # waits whatever ``wait`` asks: queued OpenCL launches gained nothing (docs/decisions.md)
            render_with_room(render_once, self.hit_queue)
            layers = OpenCLLayers(self, layers_buf, shape)
            self._kept_layers = [(kept, weakref.ref(layers) if kept is layers_buf else holder)
                                 for kept, holder in self._kept_layers]
        return layers

    def _layers_buffer(self, nbytes: int) -> cl.Buffer:
        """The layers' buffer of a render (its accumulator): on a CPU device one of ``KEPT_LAYERS`` buffers
        kept from earlier renders whose layers are gone (the pose grid renders, reads and drops
        them level after level, beside the comparison's located layers), grown as needed, up to
        ``SCRATCH_BYTES``; else a new one. Call holding ``_lock``; ``_render`` records the holder."""
        if not self.is_gpu and nbytes <= SCRATCH_BYTES:
            for k, (kept, holder) in enumerate(self._kept_layers):
                if holder is None or holder() is None:
                    if kept.size < nbytes:
                        kept.release()
                        kept = cl.Buffer(self.context, cl.mem_flags.READ_WRITE, size=nbytes)
                    self._kept_layers[k] = (kept, None)
                    return kept
            if len(self._kept_layers) < KEPT_LAYERS:
                self._kept_layers.append((cl.Buffer(self.context, cl.mem_flags.READ_WRITE, size=nbytes), None))
                return self._kept_layers[-1][0]
        return cl.Buffer(self.context, cl.mem_flags.READ_WRITE, size=nbytes)

    def _enqueue_render(self, mesh, sonar: SonarConstants, beam_widths, rotations, translations, plane_normals,
                        plane_offsets, k_theta, k_phi, gamma, surface_reflection, first_rows, spans, shape, acc_buf,
                        layers_buf=None, wait_for=None, shared=None, needed=None, hit_share=None):
        """Enqueue the zeroing of acc_buf and the render kernels of the views given (clean
        float32 (n, ...) arrays, their (n, 4) ray spans; ``shared``, their SharedPoses or None,
        first casts the direct legs of the distinct poses; ``needed``, None or the (M, 2, beams)
        uint8 beams read, ``Backend._render``) into acc_buf, the fixed-point int32 layers of
        ``shape`` (n, P, R, beams) (P: 4 layers or 2 components' sums), and with layers_buf
        their floats (``fixed_to_float``), after the events ``wait_for``; ``hit_share``, the
        queue of hits (``hit_queue_size``; None: room for every hit; 0: none, each hit's
        returns at once). Returns the last kernel's event and,
        where anything was cast through a queue with a ``hit_share``, the queue's count (1,)
        int32 (read) and its slots L (a count above L: the queue overflowed and acc_buf lacks
        returns), else None. Call holding ``_lock``."""
        if sonar.use_table:
            centres = np.ascontiguousarray(sonar.beam_table[0], np.float32)
        else:
            centres = (-np.float64(sonar.half_azimuth)
                       + np.arange(sonar.beams) / np.float64(sonar.beam_scale)).astype(np.float32)
        size = int(np.prod(shape))
        zeroed = cl.enqueue_fill_buffer(self.queue, acc_buf, np.int32(0), 0, 4 * size, wait_for=wait_for)
        widest, samples = span_extent(spans)
        hits = None
        if widest:  # else no view reaches the mesh: the layers stay zeros
            count = sonar.beams * k_theta * k_phi
            directions = self._scratch(12 * count)
            self._sub_rays_kernel(self.queue, (-(-count // GROUP) * GROUP,), None, self._input(centres),
                                  self._input(np.ascontiguousarray(beam_widths, np.float32)), sonar.record(),
                                  np.int32(k_theta), np.int32(k_phi), directions)
            poses, hit_range, hit_tri = self._direct_hits(mesh, sonar, directions, shape[0], k_theta, k_phi, shared)
            hit_size = hit_queue_size(shape[0] * widest * k_theta * samples, hit_share)
            counts = self._scratch(4)
            queue = (counts, self._scratch(16 * hit_size), self._scratch(4 * hit_size), np.int32(hit_size))
            views = (self._input(rotations), self._input(translations), self._input(plane_normals),
                     self._input(plane_offsets), directions, self._input(sonar.beam_table), sonar.record(),
                     np.int32(k_theta), np.int32(k_phi), np.float32(1.0 / (k_theta * k_phi)), np.float32(gamma),
                     np.float32(surface_reflection), np.float32(RAY_EPSILON))
            masks = (np.int32(0 if needed is None else needed.shape[0]),
                     self._input(np.ones(1, np.uint8) if needed is None else needed))
            band, first = (np.int32(shape[2]), np.int32(shape[1])), self._input(first_rows)  # rows R, planes P
            counted = [cl.enqueue_fill_buffer(self.queue, counts, np.int32(0), 0, 4)] if hit_size else []
            chunks, threads = self._ray_chunks(mesh, sonar, centres, beam_widths, views[:4], shape[0], k_theta, k_phi,
                                               None if self.is_gpu else spans)
            rendered = self._render_kernel(
                self.queue, (threads,), (GROUP,), mesh.nodes, mesh.children, mesh.triangles, *views,
                np.float32(MAX_DISTANCE), first, *band, *chunks, np.int32(RAY_CHUNK), np.int32(shape[0]), poses,
                hit_range, hit_tri, *masks, acc_buf, *queue, wait_for=[zeroed, *counted])
            done = rendered
            if hit_size:
                served = min(-(-hit_size // GROUP) * GROUP, self._resident_threads())
                done = self._hits_kernel(self.queue, (served,), None, mesh.nodes,
                                         mesh.children, mesh.triangles, *views, first, *band, *masks, *queue[:3],
                                         queue[3], acc_buf, wait_for=[rendered])
            if hit_size and hit_share is not None:  # else the count cannot pass L: nothing to read
                hits = (np.empty(1, np.int32), hit_size)
                cl.enqueue_copy(self.queue, hits[0], counts, wait_for=[done])
        else:
            done = zeroed
        if layers_buf is not None:
            done = self._fixed_kernel(self.queue, (-(-size // GROUP) * GROUP,), None, acc_buf, layers_buf,
                                      np.int32(size))
        return done, hits

    def _ray_chunks(self, mesh, sonar: SonarConstants, centres: np.ndarray, beam_widths, poses, n: int, k_theta: int,
                    k_phi: int, spans=None) -> tuple[tuple[cl.Buffer, cl.Buffer, cl.Buffer, cl.Buffer], int]:
        """render_views' sub-rays (enqueued): ((spans (n, 4) int, chunks (n,), their exclusive
        prefix sums (n,), chunk_views, the view of each chunk), the launch's work-items). Each
        view's span holds the sub-rays that can reach the mesh's box directly or by the surface
        first; the others deposit nothing, so the layers are those of every sub-ray, bit for bit.
        Without ``spans`` they are found on the device (``view_spans``, as
        ``fsswarp.backends.base.ray_spans``), and a GPU launches at most
        ``RENDER_THREADS_PER_UNIT`` work-items per compute unit, each taking several sub-rays in
        turn. A CPU device passes the host's ``spans`` (``Backend._spans``, found when the render
        was planned), chunked on the host (``span_chunks``), and launches a work-item per sub-ray:
        on PoCL the three kernels cost a render of 16 views 2.3 ms (15 %), and the 24 × 24 grid
        ran 1.27× slower with work-items that took several sub-rays. ``poses``: the views'
        rotation, translation, plane normal and offset buffers. Call holding ``_lock``."""
        if spans is not None:  # some view reaches the mesh: the table is not empty
            arrays = (spans, *span_chunks(spans, k_theta))
            return (tuple(self._input(np.ascontiguousarray(a, np.int32)) for a in arrays),
                    -(-arrays[3].size * RAY_CHUNK // GROUP) * GROUP)
        spans, chunks, offsets = self._scratch(16 * n), self._scratch(4 * n), self._scratch(4 * n)
        upper, lower = beam_edges(centres, np.asarray(beam_widths, np.float32))
        self._view_spans_kernel(self.queue, (-(-n // GROUP) * GROUP,), None,
                                self._input(mesh.bounds.astype(np.float32).ravel()), *poses, self._input(upper),
                                self._input(lower), np.int32(sonar.beams), np.float32(sonar.half_elevation),
                                np.int32(k_theta), np.int32(k_phi), np.int32(RAY_CHUNK), np.int32(n), spans, chunks)
        group = min(SCAN_GROUP, self.cl_device.max_work_group_size)
        self._chunk_offsets_kernel(self.queue, (group,), (group,), chunks, np.int32(n), offsets,
                                   cl.LocalMemory(4 * group))
        most = most_chunks(n, sonar.beams, k_theta, k_phi)
        chunk_views = self._scratch(4 * most)
        self._chunk_views_kernel(self.queue, (-(-n // GROUP) * GROUP,), None, chunks, offsets, np.int32(n),
                                 chunk_views)
        threads = min(-(-most * RAY_CHUNK // GROUP) * GROUP, self._resident_threads())
        return (spans, chunks, offsets, chunk_views), threads

    def _resident_threads(self) -> int:
        """Work-items of a launch that takes its items in turn (render_views on a GPU, hit_returns):
        ``RENDER_THREADS_PER_UNIT`` per compute unit, a multiple of ``GROUP``."""
        return -(-self.cl_device.max_compute_units * RENDER_THREADS_PER_UNIT // GROUP) * GROUP

    def _floats(self, acc_buf: cl.Buffer, shape: tuple[int, ...]) -> np.ndarray:
        """The host float32 array of ``shape`` of the fixed-point layers acc_buf (``OpenCLLayers.numpy``)."""
        size = int(np.prod(shape))
        host = np.empty(shape, np.float32)
        if size == 0:
            return host
        with self._lock:
            floats = cl.Buffer(self.context, cl.mem_flags.READ_WRITE, size=4 * size)
            self._fixed_kernel(self.queue, (-(-size // GROUP) * GROUP,), None, acc_buf, floats, np.int32(size))
            cl.enqueue_copy(self.queue, host, floats, is_blocking=True)
            floats.release()
        return host

    def _rows(self, acc_buf: cl.Buffer, shape: tuple[int, int, int, int], start: int, stop: int) -> np.ndarray:
        """Rows [start, stop) of every plane of the (N, P, bins, beams) int32 buffer acc_buf, in one
        rectangular read (``OpenCLLayers.rows``)."""
        n, layers, bins, beams = shape
        host = np.empty((n, layers, stop - start, beams), np.int32)
        if host.size == 0:
            return host
        line = 4 * beams
        with self._lock:
            cl.enqueue_copy(self.queue, host, acc_buf, buffer_origin=(0, start, 0), host_origin=(0, 0, 0),
                            region=(line, stop - start, n * layers), buffer_pitches=(line, line * bins),
                            host_pitches=(line, line * (stop - start)), is_blocking=True)
        return host

    def _direct_hits(self, mesh, sonar: SonarConstants, directions, n_views, k_theta, k_phi,
                     shared) -> tuple[cl.Buffer, cl.Buffer, cl.Buffer]:
        """render_views' poses, hit_range and hit_tri: with ``shared`` (SharedPoses) the direct
        legs of its distinct poses, enqueued; without, poses of -1 for the ``n_views`` views (every
        view casts its own)."""
        if shared is None:
            unused = self._scratch(4)
            return self._input(np.full(n_views, -1, np.int32)), unused, unused
        widest, samples = span_extent(shared.spans)
        count = shared.count * sonar.beams * k_theta * k_phi
        hit_range = self._scratch(4 * count)
        hit_tri = self._scratch(4 * count)
        if widest:
            sub = k_theta * samples
            group = min(GROUP, 1 << (sub - 1).bit_length())
            self._direct_hits_kernel(
                self.queue, (-(-sub // group) * group, widest, shared.count), (group, 1, 1),
                mesh.nodes, mesh.children, mesh.triangles, self._input(shared.rotations),
                self._input(shared.translations), directions, sonar.record(), np.int32(k_theta), np.int32(k_phi),
                np.float32(MAX_DISTANCE), self._input(shared.spans), hit_range, hit_tri)
        return self._input(shared.index), hit_range, hit_tri

    def _render_batches(self, mesh, sonar: SonarConstants, beam_widths, rotations, translations, plane_normals,
                        plane_offsets, k_theta, k_phi, gamma, surface_reflection, batch, spans):
        """Two slots alternate: batch k renders on the backend's queue into slot k % 2 while a
        second queue reads batch k − 1 into the slot's host-allocated (``ALLOC_HOST_PTR``:
        page-locked on NVIDIA) buffer, mapped once; events order the two queues."""
        _check_mesh(mesh)
        n_views = rotations.shape[0]
        shape = (min(batch, n_views), 4, sonar.bins, sonar.beams)
        nbytes = 4 * int(np.prod(shape))
        rw = cl.mem_flags.READ_WRITE
        accs = [cl.Buffer(self.context, rw, size=nbytes) for _ in range(2)]
        layers = [cl.Buffer(self.context, rw, size=nbytes) for _ in range(2)]
        staging = [cl.Buffer(self.context, rw | cl.mem_flags.ALLOC_HOST_PTR, size=nbytes) for _ in range(2)]
        host = [cl.enqueue_map_buffer(self.queue, buf, cl.map_flags.READ | cl.map_flags.WRITE, 0, shape,
                                      np.float32)[0] for buf in staging]
        copier = cl.CommandQueue(self.context)
        first = np.zeros(shape[0], np.int32)
        copied: list = [None, None]  # the event of each slot's last read
        inputs: list = [[], []]  # each slot's last batch's buffers (_held), dropped once it was read
        pending = None  # (start, count, slot) of the batch read last, not yet handed out
        try:
            for k, start in enumerate(range(0, n_views, batch)):
                stop, slot = min(start + batch, n_views), k % 2
                n = stop - start
                with self._lock:
                    rendered = self._enqueue_render(
                        mesh, sonar, beam_widths, rotations[start:stop], translations[start:stop],
                        plane_normals[start:stop], plane_offsets[start:stop], k_theta, k_phi, gamma,
                        surface_reflection, first[:n], spans[start:stop], (n, *shape[1:]), accs[slot], layers[slot],
                        wait_for=None if copied[slot] is None else [copied[slot]],
                        hit_share=None if self.hit_queue else 0.0)[0]
                    self.queue.flush()
                    inputs[slot], self._held = self._held, []  # batch k - 2's: read already
                copied[slot] = cl.enqueue_copy(copier, host[slot][:n], layers[slot], is_blocking=False,
                                               wait_for=[rendered])
                copier.flush()
                if pending is not None:
                    yield _read(host, copied, *pending)
                pending = (start, n, slot)
            if pending is not None:
                yield _read(host, copied, *pending)
        finally:  # a consumer that stops early: no read may land in unmapped memory
            copier.finish()
            for array in host:
                array.base.release(self.queue)
            with self._lock:
                self._finish()
            for buf in accs + layers + staging:
                buf.release()

    # --- frontal contours and their distance to the data's ------------------------------------
    def _contour_cost(self, layers, first_rows, view_index, thresholds, windows, masks, range_weights,
                      beam_weights, distances, cap, shifts):
        n_pairs, beams, n_shifts = view_index.shape[0], distances.shape[3], shifts.shape[0]
        contour = np.empty((n_pairs, 2, beams), np.float32)
        sums, counts = np.empty((n_pairs, 2, n_shifts), np.float32), np.empty((n_pairs, 2), np.int32)
        with self._lock:
            bufs = self._enqueue_contours(layers, first_rows, view_index, thresholds, windows, masks, range_weights,
                                          beam_weights, distances, cap, shifts)
            for host, buf in zip((contour, sums, counts), bufs):
                cl.enqueue_copy(self.queue, host, buf, is_blocking=False)
            self._finish()
        return contour, sums, counts

    def _view_costs(self, layers, first_rows, view_index, thresholds, windows, masks, range_weights,
                    beam_weights, distances, cap, shifts, data_counts, *, wait=True):
        n_pairs, n_shifts = view_index.shape[0], shifts.shape[0]
        costs, costs_buf = self._output((n_pairs, n_shifts), np.float32)
        group = min(GROUP, 1 << (n_shifts - 1).bit_length())
        with self._lock:
            bufs = self._enqueue_contours(layers, first_rows, view_index, thresholds, windows, masks, range_weights,
                                          beam_weights, distances, cap, shifts)
            self._view_cost_kernel(self.queue, (-(-n_shifts // group) * group, n_pairs), (group, 1), bufs[1], bufs[2],
                                   self._input(view_index), self._input(data_counts), np.float32(cap),
                                   np.int32(n_shifts), costs_buf)
            cl.enqueue_copy(self.queue, costs, costs_buf, is_blocking=False)
            self._finish()
        return costs if wait else lambda: costs

    def _enqueue_contours(self, layers, first_rows, view_index, thresholds, windows, masks, range_weights,
                          beam_weights, distances, cap, shifts) -> tuple[cl.Buffer, cl.Buffer, cl.Buffer]:
        """Enqueue ``frontal_contour`` and ``contour_cost``; returns the buffers of their (N, 2,
        beams) contours, (N, 2, S) sums and (N, 2) counts, for the caller to read and release.
        Call holding ``_lock``."""
        n_pairs, bins, beams = view_index.shape[0], distances.shape[2], distances.shape[3]
        n_shifts = shifts.shape[0]
        if isinstance(layers, OpenCLLayers) and layers.backend.context == self.context:
            stack, fixed = layers.buffer, 1
        else:
            stack, fixed = self._input(np.ascontiguousarray(layers.numpy(), np.float32)), 0
        index = self._input(view_index)
        contour_buf = self._scratch(4 * n_pairs * 2 * beams)
        sums_buf = self._scratch(4 * n_pairs * 2 * n_shifts)
        counts_buf = self._scratch(4 * n_pairs * 2)
        cl.enqueue_fill_buffer(self.queue, contour_buf, np.float32(-1.0), 0, 4 * n_pairs * 2 * beams)
        items = mask_items(masks)
        self._frontal_kernel(
            self.queue, (-(-items.shape[1] // GROUP) * GROUP, n_pairs), (GROUP, 1),
            stack, np.int32(fixed), index, self._input(thresholds), self._input(windows), self._input(items),
            np.int32(items.shape[1]), self._input(range_weights), np.int32((range_weights.shape[0] - 1) // 2),
            self._input(beam_weights), np.int32((beam_weights.shape[0] - 1) // 2), np.int32(bins),
            np.int32(beams), self._input(first_rows), np.int32(layers.shape[2]), np.int32(layers.shape[1]),
            contour_buf)
        group = min(GROUP, 1 << (n_shifts - 1).bit_length())
        self._contour_cost_kernel(
            self.queue, (-(-n_shifts // group) * group, 2, n_pairs), (group, 1, 1),
            contour_buf, index, distances.data, np.float32(cap), self._input(shifts), np.int32(n_shifts),
            np.int32(bins), np.int32(beams), sums_buf, counts_buf)
        return contour_buf, sums_buf, counts_buf

    # --- IRLS-ICP runs ----------------------------------------------------------------------
    def _icp_runs(self, source_x, source_y, target_x, target_y, runs, angles, translations, floors, step_tols,
                  max_iterations, max_distance, tuning):
        n_runs, n_points = runs.shape[0], source_x.shape[0]
        flags = cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR
        angle, trans = angles.copy(), translations.copy()
        iterations, converged = np.zeros(n_runs, np.int32), np.zeros(n_runs, np.int32)
        moved_x, moved_y, dist, nearest = np.empty(n_points), np.empty(n_points), np.empty(n_points), \
            np.empty(n_points, np.int32)
        results = (angle, trans, iterations, converged, moved_x, moved_y, nearest, dist)
        buffers = [cl.Buffer(self.context, flags, hostbuf=a) for a in results[:4]]
        buffers += [cl.Buffer(self.context, cl.mem_flags.READ_WRITE, size=a.nbytes) for a in results[4:]]
        work = [cl.Buffer(self.context, cl.mem_flags.READ_WRITE, size=moved_x.nbytes)
                for _ in range(4)]  # anchor_x, anchor_y, room2, scratch
        lanes = self.icp_lanes
        with self._lock:
            self._icp_kernel(
                self.queue, (-(-n_runs * lanes // GROUP) * GROUP,), (GROUP,),
                *(self._input(a) for a in (source_x, source_y, target_x, target_y, runs, floors, step_tols)),
                np.int32(max_iterations), np.float64(max_distance), np.float64(tuning), np.int32(n_runs),
                *buffers, *work, np.int32(lanes))
            for host, buf in zip(results, buffers):
                cl.enqueue_copy(self.queue, host, buf, is_blocking=False)
            self._finish()
        for buf in buffers + work:
            buf.release()
        return results


def _read(host, copied, start, count, slot) -> tuple[int, np.ndarray]:
    copied[slot].wait()
    return start, host[slot][:count]


class OpenCLLayers(DeviceLayers):
    """Rendered layers of ``backend`` as the render's fixed-point accumulator, an OpenCL buffer
    (``.buffer``) of (N, 4, bins, beams) int32 (2^24 = 1), or (N, 4, R, beams) for bands of rows
    (``first_rows``), 2 in place of 4 for the components' sums: the contour kernels read it as it
    is, and ``numpy`` converts it on the device first (``fixed_to_float``: the floats a render to
    float layers gives)."""

    def __init__(self, backend: OpenCLBackend, buffer: cl.Buffer, shape: tuple[int, int, int, int]):
        self.backend = backend
        self.buffer = buffer
        self.shape = shape

    def numpy(self) -> np.ndarray:
        return self.backend._floats(self.buffer, self.shape)

    def rows(self, start: int, stop: int) -> np.ndarray:
        return fixed_floats(self.backend._rows(self.buffer, self.shape, start, stop))


class OpenCLMesh:
    """A mesh uploaded for OpenCLBackend: the host BVH and its device buffers."""

    def __init__(self, bvh: FlatBVH, nodes, children, triangles, face_index):
        self.bvh = bvh
        self.nodes = nodes
        self.children = children
        self.triangles = triangles
        self.face_index = face_index

    def __repr__(self) -> str:
        return f"<OpenCLMesh {self.bvh.n_triangles} triangles, {self.bvh.n_nodes} nodes>"


def _check_mesh(mesh) -> None:
    if not isinstance(mesh, OpenCLMesh):
        raise TypeError(f"mesh must come from OpenCLBackend.load_mesh, got {type(mesh).__name__}")
