"""The kernel interface: ``Backend`` and the device-side results it hands out.

``Backend`` is the interface every kernel family goes through; ``WarpBackend``
(``backends/warp/``, NVIDIA Warp on "cpu" or "cuda:N") and ``OpenCLBackend``
(``backends/opencl/``, OpenCL C from the top-level ``kernels/``) implement it.

The public methods of ``Backend`` validate their inputs (``ValueError`` / ``TypeError``
quoting the bad value) and convert them to contiguous float32 arrays; the private ``_name``
methods that subclasses implement receive clean arrays and never validate. All kernels compute
in float32 on the device, except the ICP runs (``icp_runs``), in float64.

Adding a kernel family: a public method here (validation, conversion, the documented
contract) calling an abstract ``_method`` that both backends implement, the Warp kernel in
``backends/warp/<family>.py``, the OpenCL kernel in ``kernels/<family>.cl`` (geometry shared
through ``kernels/sonar.h``), and a NumPy oracle test in ``tests/test_backends.py``.
"""

from __future__ import annotations

import abc
import math
from dataclasses import dataclass
from typing import Any, Callable, Iterator, NamedTuple

import numpy as np

from ..caching import Remembered
from ..errors import is_integer, is_number, real_array
from ..sonar import SonarSpec
from .constants import (CPU_HIT_QUEUE, FIXED_SCALE, GPU_HIT_QUEUE, GPU_ICP_LANES, MAX_DISTANCE, RAY_CHUNK,
                        SPAN_MARGIN)


#: ``SonarConstants``' scalars as one kernel argument: the layout of ``fss_sonar`` (kernels/sonar.h)
#: and the fields of the Warp struct ``KernelSonar``, in this order (32 bytes, no padding).
SONAR_DTYPE = np.dtype([("use_table", np.int32), ("beams", np.int32), ("bins", np.int32),
                        ("half_azimuth", np.float32), ("beam_scale", np.float32), ("range_min", np.float32),
                        ("inv_range_step", np.float32), ("half_elevation", np.float32)])


@dataclass(frozen=True)
class SonarConstants:
    """The float32 constants of one sonar, as every kernel receives them.

    beam_table : (2, beams) float32 when ``use_table``, else a (2, 1) zero dummy (OpenCL
        has no zero-sized buffers). Row 0: the beam centres c_i (rad). Row 1: the inverse
        spacing 1 / (c_{i+1} − c_i) of the segment starting at beam i, the last entry
        repeating the outer spacing for extrapolation. Inverses are rounded once from float64:
        a float32 difference of float32 centres would lose ~1e-6 of the spacing, which far
        extrapolation (hundreds of beams for points behind the sonar) magnifies past 1e-4
        of an index, and kernels need no division (GPU division is not correctly rounded).
    beam_scale = (beams − 1) / (2 W_θ) and inv_range_step = 1 / δR, likewise rounded once.
    """

    beams: int
    bins: int
    use_table: int
    beam_table: np.ndarray
    half_azimuth: float
    beam_scale: float
    range_min: float
    inv_range_step: float
    half_elevation: float

    def record(self) -> np.void:
        """The scalars as one ``SONAR_DTYPE`` record (an OpenCL ``fss_sonar`` argument)."""
        return np.array(tuple(getattr(self, name) for name in SONAR_DTYPE.names), SONAR_DTYPE)[()]

    @classmethod
    def of(cls, sonar: SonarSpec) -> "SonarConstants":
        f32 = lambda x: float(np.float32(x))  # noqa: E731 - the float32 value, as a Python float
        if sonar.beam_angles is None:
            table = np.zeros((2, 1), np.float32)
        else:
            centres = np.asarray(sonar.beam_angles, np.float64)
            inverse = 1.0 / np.diff(centres)
            table = np.ascontiguousarray([centres, np.append(inverse, inverse[-1])], np.float32)
        return cls(beams=int(sonar.beams), bins=int(sonar.bins),
                   use_table=int(sonar.beam_angles is not None), beam_table=table,
                   half_azimuth=f32(sonar.half_azimuth),
                   beam_scale=f32((sonar.beams - 1) / sonar.azimuth_fov),
                   range_min=f32(sonar.range_min), inv_range_step=f32(1.0 / sonar.range_step),
                   half_elevation=f32(sonar.half_elevation))


class Backend(abc.ABC):
    """A device that runs fsswarp's kernels.

    name : "warp" or "opencl"
    device : the device, e.g. "cpu" or "cuda:0" (Warp), "<platform>: <device name>" (OpenCL)
    is_gpu : whether the device is a GPU
    has_float64 : whether its kernels can compute in float64 (``icp_runs`` and ``surface_distances`` need it)
    device_name : the device's own name (property)
    icp_lanes : threads given to each ICP run (property: ``GPU_ICP_LANES`` on a GPU, else 1)
    hit_queue : the render's queue of hits, its slots per thread of a launch (property:
        ``GPU_HIT_QUEUE`` on a GPU, ``CPU_HIT_QUEUE`` on a CPU; OpenCL on a CPU: 0, no queue)

    For timing kernels without their transfers: ``prepared_cast``, ``prepared_carve`` (launches
    on inputs uploaded once) and ``transfer_calls`` (copies).
    """

    name: str
    device: str
    is_gpu: bool
    has_float64: bool

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name} on {self.device!r}>"

    @property
    def icp_lanes(self) -> int:
        return GPU_ICP_LANES if self.is_gpu else 1

    @property
    def hit_queue(self) -> float:
        return GPU_HIT_QUEUE if self.is_gpu else CPU_HIT_QUEUE

    # --- projection (voxel carving) -----------------------------------------------------------
    def project(self, points, rotations, translations, sonar: SonarSpec):
        """Nearest beam and bin of every point in every view.

        points : (P, 3) float
            Points in the reference frame (m).
        rotations : (V, 3, 3) float, translations : (V, 3) float
            View poses, ``P_ref = R @ P_view + t``; a point is seen at ``Rᵀ (P_ref − t)``.
        sonar : SonarSpec

        Returns ``(beam, bin, inside)``: (V, P) int32 nearest column and row, by the rule of
        ``SonarSpec.beam_bin`` (floor(coordinate + 0.5); with a beam-angle table the
        fractional beam interpolates linearly between beam centres and extrapolates with the
        outer spacing), clamped to ±2^30 for points absurdly far away; and (V, P) bool
        ``inside``: the return lands in the image (0 <= beam < beams, 0 <= bin < bins) and its
        elevation lies in the aperture (|φ| <= W_φ).

        Computed in float32 on the device: results differ from the float64 NumPy rule
        (``to_view``, ``to_polar``, ``SonarSpec.beam_bin``, ``SonarSpec.in_elevation``) only
        for points that float32 cannot place: within about 1e-4 of an index (or two float32
        ulps of θ or R, whichever is larger; at 3 m one ulp of R is 6e-5 of a 3.9 mm bin) of
        a half-index boundary, or within ~1e-6 rad of the elevation edge. Backends agree
        with each other on the same terms.
        """
        pts = real_array("points", points, ("P", 3))
        rot, trans = _view_poses(rotations, translations, sonar)
        if pts.shape[0] >= 2**31 - 2**10:
            raise ValueError(f"too many points for one launch ({pts.shape[0]}); split them")
        n_views, n_points = rot.shape[0], pts.shape[0]
        if n_views == 0 or n_points == 0:
            empty = np.zeros((n_views, n_points), np.int32)
            return empty, empty.copy(), np.zeros((n_views, n_points), bool)
        beam, bin_, inside = self._project(pts, rot, trans, SonarConstants.of(sonar))
        return beam, bin_, inside != 0

    @abc.abstractmethod
    def _project(self, points: np.ndarray, rotations: np.ndarray, translations: np.ndarray,
                 sonar: SonarConstants) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Kernel launch of ``project``: clean float32 C-contiguous (P, 3), (V, 3, 3), (V, 3)
        arrays with P, V >= 1. Returns (V, P) int32 beam, int32 bin, uint8 inside (0 or 1)."""

    def carve(self, masks, rotations, translations, sonar: SonarSpec, voxel_size: float, *,
              origin=None, shape=None, centres=None):
        """Space carving: how many views see each voxel and how many reject it (DESIGN §6).

        masks : (V, bins, beams) bool or integer, nonzero = the view's feasible region
        rotations : (V, 3, 3) float, translations : (V, 3) float
            View poses, ``P_ref = R @ P_view + t`` (V <= 255).
        sonar : SonarSpec
        voxel_size : h (m), the side of every voxel (a cube)
        origin (3,) float and shape (nx, ny, nz) : a regular grid, voxel (i, j, k) centred
            at ``origin + h·(i, j, k)`` (computed in float32), flattened in C order; or
        centres : (P, 3) float, explicit voxel centres (the fine levels of coarse-to-fine)

        Returns ``(seen, rejected)``, (P,) uint8. A view sees a voxel when its window holds
        the whole voxel (its bounding sphere inside the elevation aperture, and the box of
        beams and bins it projects into, by the rounding rule of ``project``, inside the
        image); it rejects it when it sees it and its feasible mask is empty in that box.
        Views are taken in order and the first rejection ends a voxel's loop: ``rejected`` is
        1 when a view rejects the voxel, else 0; ``seen`` counts the views that see it up to
        and including that view (all of them for a voxel no view rejects). fsswarp/carving.py
        explains the rule and why it is conservative; ``fsswarp.carving.carve_reference`` is
        the float64 oracle.
        Float32 on the device: decisions differ from the oracle only where a bound lies
        within float32 rounding of a half-index boundary or of the elevation edge.
        """
        feasible, rot, trans, size = _carve_views(masks, rotations, translations, sonar, voxel_size)
        grid = origin is not None or shape is not None
        if grid == (centres is not None) or (grid and (origin is None or shape is None)):
            raise ValueError("give either origin and shape (a grid) or centres")
        if centres is not None:
            points = real_array("centres", centres, ("P", 3))
            n_voxels, start, dims = points.shape[0], None, None
        else:
            start = real_array("origin", np.asarray(origin).reshape(-1), (3,))
            dims = tuple(shape) if isinstance(shape, (tuple, list, np.ndarray)) else ()
            if len(dims) != 3 or any(not is_integer(n) or n < 0
                                     for n in dims):
                raise ValueError(f"shape must be three integers >= 0, got {shape!r}")
            dims = tuple(int(n) for n in dims)
            n_voxels, points = dims[0] * dims[1] * dims[2], None
        if n_voxels >= 2**31 - 2**10:
            raise ValueError(f"too many voxels for one launch ({n_voxels}); split them")
        if n_voxels == 0 or rot.shape[0] == 0:
            return np.zeros(n_voxels, np.uint8), np.zeros(n_voxels, np.uint8)
        launch = self._prepared_carve(_summed_area(feasible, sonar), rot, trans, SonarConstants.of(sonar),
                                      float(np.float32(size)), _circumradius(size), start, dims, points)
        launch()
        return launch.read()

    def prepared_carve(self, masks, rotations, translations, sonar: SonarSpec, voxel_size: float, origin,
                       side: int) -> "PreparedLaunch":
        """``carve`` of the cubic grid of side³ voxels at ``origin`` (``shape = (side,) * 3``),
        with its inputs uploaded once, for timing the kernel alone: the summed-area tables of
        the masks and the poses go to the device now; each call of the returned
        ``PreparedLaunch`` launches the carve-grid kernel and waits, and its ``read()`` gives the
        last call's ``(seen, rejected)``, (side³,) uint8, as ``carve`` returns them.

        masks, rotations, translations, sonar, voxel_size, origin : as ``carve`` (V >= 1)
        side : voxels along each axis, >= 1
        """
        feasible, rot, trans, size = _carve_views(masks, rotations, translations, sonar, voxel_size)
        start = real_array("origin", np.asarray(origin).reshape(-1), (3,))
        if not is_integer(side) or side < 1 or int(side) ** 3 >= 2**31 - 2**10:
            raise ValueError(f"side must be an integer >= 1 with side**3 < 2^31 - 2^10 voxels, got {side!r}")
        if rot.shape[0] == 0:
            raise ValueError("give at least one view")
        return self._prepared_carve(_summed_area(feasible, sonar), rot, trans, SonarConstants.of(sonar),
                                    float(np.float32(size)), _circumradius(size), start, (int(side),) * 3, None)

    @abc.abstractmethod
    def _prepared_carve(self, integral: np.ndarray, rotations: np.ndarray, translations: np.ndarray,
                        sonar: SonarConstants, voxel_size: float, radius: float, origin: np.ndarray | None,
                        shape: tuple[int, int, int] | None, centres: np.ndarray | None) -> "PreparedLaunch":
        """Inputs of a ``carve`` launch uploaded once: integral (V, bins + 1, beams + 1) int32
        summed-area tables of the masks, clean float32 poses, the float32 voxel size and
        circumradius, and either a grid (origin (3,) float32, shape) or centres (P, 3) float32,
        P, V >= 1. Its ``read()`` gives (P,) uint8 seen and rejected counts."""


    # --- ray casting and image synthesis ------------------------------------------------------
    def load_mesh(self, vertices, faces, *, exact: bool = False) -> Any:
        """Upload a triangle mesh once for many launches; returns an opaque handle.

        vertices : (Nv, 3) float, faces : (Nf, 3) int, indices into vertices (Nf >= 1)
        The handle keeps the device copy (Warp: a ``wp.Bvh`` and the triangles' corners; OpenCL:
        a flattened BVH, ``fsswarp.backends.bvh``) and the vertices' box, ``bounds`` (2, 3)
        float64 (lower, upper). ``exact`` (a device with float64): it also keeps the corners in
        float64, for :meth:`surface_distances`."""
        verts = real_array("vertices", vertices, ("Nv", 3))
        tris = np.asarray(faces)
        if tris.ndim != 2 or tris.shape[1] != 3 or tris.shape[0] == 0 or tris.dtype.kind not in "iu":
            raise ValueError(f"faces must be a non-empty (Nf, 3) integer array, got {tris.shape} {tris.dtype}")
        if tris.min() < 0 or tris.max() >= verts.shape[0]:
            raise ValueError(f"faces index vertices 0..{verts.shape[0] - 1}, got {tris.min()}..{tris.max()}")
        if exact and not self.has_float64:
            raise ValueError(f"exact meshes need float64, which {self!r} lacks")
        tris = np.ascontiguousarray(tris, dtype=np.int32)
        handle = self._load_mesh(verts, tris)
        handle.bounds = np.stack([verts.min(axis=0), verts.max(axis=0)]).astype(np.float64)  # for ray_spans
        handle.exact = None
        if exact:
            corners = real_array("vertices", vertices, ("Nv", 3), np.float64)[tris]
            handle.exact = self._exact_corners(handle, corners)
        return handle

    def surface_distances(self, mesh, points) -> np.ndarray:
        """(N,) float64: the distance from each of ``points`` (N, 3) float to the nearest triangle
        of ``mesh`` (a handle of ``load_mesh(..., exact=True)``), exact in float64 (the closest
        point by the triangle's Voronoi regions; kernels/closest.cl)."""
        pts = real_array("points", points, ("N", 3), np.float64)
        if getattr(mesh, "exact", None) is None:
            raise ValueError("mesh must be loaded with load_mesh(..., exact=True)")
        if pts.shape[0] == 0:
            return np.zeros(0, np.float64)
        return self._surface_distances(mesh, pts)

    def cast_rays(self, mesh, origins, directions, max_distance: float = MAX_DISTANCE):
        """First hit of every ray: ``(distance, face)``, (R,) float32 and (R,) int32.

        origins : (R, 3) float, directions : (R, 3) float unit vectors
        A ray that hits nothing within ``max_distance`` gives distance inf and face -1.
        Watertight: a ray through a shared edge or vertex never leaks through the mesh."""
        org, dirs = _rays(origins, directions)
        if org.shape[0] == 0:
            return np.zeros(0, np.float32), np.zeros(0, np.int32)
        launch = self._prepared_cast(mesh, org, dirs, float(max_distance))
        launch()
        return launch.read()

    def prepared_cast(self, mesh, origins, directions, max_distance: float = MAX_DISTANCE) -> "PreparedLaunch":
        """``cast_rays`` with the rays uploaded once, for timing the kernel alone: origins and
        directions (R, 3) float (R >= 1) go to the device now; each call of the returned
        ``PreparedLaunch`` launches the cast kernel on them and waits, and its ``read()`` gives
        the last call's ``(distance, face)`` as ``cast_rays`` returns them."""
        org, dirs = _rays(origins, directions)
        if org.shape[0] == 0:
            raise ValueError("origins must hold at least one ray")
        return self._prepared_cast(mesh, org, dirs, float(max_distance))

    def transfer_calls(self, nbytes: int) -> tuple[Callable[[], None], Callable[[], None], Callable[[], None]]:
        """Three blocking copies of ``nbytes`` (rounded down to whole float32 values, >= 4),
        for timing the device's memory and host link: device to device, host to device and
        device to host (pageable host memory). Buffers are allocated once, here."""
        if not is_integer(nbytes) or nbytes < 4:
            raise ValueError(f"nbytes must be an integer >= 4, got {nbytes!r}")
        return self._transfer_calls(np.ones(int(nbytes) // 4, np.float32))

    @property
    @abc.abstractmethod
    def device_name(self) -> str:
        """The device's own name (a GPU model, an OpenCL device's name, Warp's "cpu")."""

    @abc.abstractmethod
    def _transfer_calls(self, host: np.ndarray) -> tuple[Callable[[], None], Callable[[], None], Callable[[], None]]:
        """``transfer_calls`` of the (n,) float32 ``host`` array: device-to-device,
        host-to-device and device-to-host copies of its bytes, each waiting until done."""

    def frontal_faces(self, mesh, sonar: SonarSpec, rotations, translations, plane_normals, plane_offsets,
                      views, azimuths, rays: int, *, mirror) -> np.ndarray:
        """Face of the frontal patch of every beam, -1 where none (the patches that E_mu and
        shape refinement move, fsswarp/compare.py): over the beam's ``rays`` elevation rays
        φ_j = −W_φ + (j + ½) · 2W_φ / rays, the face seen at the shortest range. ``mirror``: a
        bool for every beam, or (B,) bools, one per beam (both kinds in one launch).

        mirror False: a ray's first hit before it meets the surface, at its distance.
        mirror True: a ray that meets the surface at Q (s = d / (n·u), before any hit) is
        reflected there; its first hit P, cast from ε = RAY_EPSILON past Q, counts when P
        lies in the fan (|elevation| <= W_φ, |azimuth| <= W_θ) and the first hit from the sonar
        toward P is not nearer than |P| − FRONTAL_VISIBLE; it is seen at (|P| + s + |P − Q|) / 2.

        rotations (V, 3, 3), translations (V, 3) : view poses (``P_ref = R @ P_view + t``);
        plane_normals (V, 3), plane_offsets (V,) : the surface ``n·P = d`` in each view frame;
        views (B,) int in [0, V) and azimuths (B,) float (rad) : the beams; rays >= 1.
        Returns (B,) int32. One thread per ray, float32; the host keeps each beam's nearest (the
        first of equal ranges): where two rays' ranges tie within rounding, another ray's face
        may win than in float64."""
        _check_sonar(sonar)
        rot, trans, normals, offsets = _view_planes(rotations, translations, plane_normals, plane_offsets)
        theta = real_array("azimuths", np.asarray(azimuths).reshape(-1), ("B",))
        index = _view_index("views", views, rot.shape[0])
        if index.shape != theta.shape:
            raise ValueError(f"views must be ({theta.shape[0]},) like azimuths, got {index.shape}")
        if not is_integer(rays) or rays < 1:
            raise ValueError(f"rays must be a positive integer, got {rays!r}")
        flags = np.asarray(mirror)
        if flags.dtype != bool or flags.shape not in ((), theta.shape):
            raise ValueError(f"mirror must be a bool or ({theta.shape[0]},) bools, got {flags.dtype} {flags.shape}")
        if theta.shape[0] == 0:
            return np.zeros(0, np.int32)
        if theta.shape[0] * rays >= 2**31 - 2**10:
            raise ValueError(f"too many rays for one launch ({theta.shape[0]} beams x {rays}); split them")
        ranges, faces = self._frontal_rays(mesh, SonarConstants.of(sonar), rot, trans, normals, offsets, index,
                                           theta, int(rays), np.broadcast_to(flags, theta.shape).astype(np.uint8))
        nearest = np.argmin(ranges, axis=1)  # the first of equal ranges
        beams = np.arange(len(nearest))
        return np.where(np.isfinite(ranges[beams, nearest]), faces[beams, nearest], -1).astype(np.int32)

    def render(self, mesh, sonar: SonarSpec, rotations, translations, plane_normals, plane_offsets,
               samples: tuple[int, int], *, gamma: float, surface_reflection: float) -> np.ndarray:
        """Noise-free multipath layers of N views, one launch (the contract of fsswarp.rendering).

        rotations (N, 3, 3), translations (N, 3): view poses (``P_ref = R @ P_view + t``);
        plane_normals (N, 3), plane_offsets (N,): the surface ``n·P = d`` in each VIEW frame.
        samples = (K_θ, K_φ) sub-rays per beam. Returns (N, 4, bins, beams) float32: the
        layers object, ghost, mirror, mirror2 (``fsswarp.surface.COMPONENTS``)."""
        return self.render_device(mesh, sonar, rotations, translations, plane_normals, plane_offsets,
                                  samples, gamma=gamma, surface_reflection=surface_reflection).numpy()

    def render_device(self, mesh, sonar: SonarSpec, rotations, translations, plane_normals,
                      plane_offsets, samples: tuple[int, int], *, gamma: float,
                      surface_reflection: float, rows=None, beams=None, components: bool = False) -> "DeviceLayers":
        """``render`` with the layers left on the device (for kernels that consume them there,
        and for timing the synthesis without the read-back). Returns once the layers are
        complete; ``.numpy()`` copies them to the host.

        rows : None (default), the full (N, 4, bins, beams) layers; or ``(first, count)``, a
            band of rows per view: first (N,) integers, count an integer R >= 1, with
            0 <= first[n] and first[n] + R <= bins. View n then renders only the bins
            first[n] <= B < first[n] + R, into layers of shape (N, 4, R, beams) whose row k
            is the image's row first[n] + k; returns landing outside the band are dropped.
            Every pixel of the band equals, bit for bit, the same pixel of the full layers
            (fixed-point integer accumulation: a pixel's value does not depend on which other
            pixels are rendered), and less memory is filled, converted and allocated.
            ``contour_cost`` consumes banded layers. The result's ``first_rows`` is the (N,)
            int array first (None for full layers); ``.numpy()`` copies the band as it is,
            (N, 4, R, beams).
        beams : None (default), every beam; or (N, 2, beams) bools, the beams that will be read
            of each view's two components (0: the object and ghost layers, 1: the mirror and
            mirror2 layers); or (M, 2, beams) with M dividing N, view n's at row n % M (a batch
            of cells × M views, cell by cell: each cell's views read the same beams). A
            component's pixels at a beam not read stay zero, and the legs whose returns land
            only there are not cast (the pose grid passes its views' masks, :func:`beams_read`);
            every other pixel equals, bit for bit, the same pixel of the full layers.
        components : False (default), the four layers; True, the two components' sums
            (``COMPONENTS`` of fsswarp.surface: object + ghost, mirror + mirror2), (N, 2, R,
            beams), half the memory: what ``contour_cost`` reads. Each pixel is, in the
            accumulator's fixed point, exactly the sum of the two layers' pixels, so the
            contours and costs are those of the four layers, bit for bit.
        """
        return self.render_planned(mesh, sonar, self.plan_render(mesh, sonar, rotations, translations, plane_normals,
                                                                 plane_offsets, samples, rows=rows, beams=beams,
                                                                 components=components),
                                   gamma=gamma, surface_reflection=surface_reflection)

    def plan_render(self, mesh, sonar: SonarSpec, rotations, translations, plane_normals, plane_offsets,
                    samples: tuple[int, int], *, rows=None, beams=None, components: bool = False,
                    pose_groups=None) -> "RenderPlan":
        """The host half of ``render_device`` (arguments as there): the inputs checked and made
        clean, the bands, the beams read, the sub-ray spans and the shared poses, without the
        device. Thread-safe: a caller may plan its next launch while this one renders
        (``fsswarp.compare.ViewComparison.view_costs``). ``pose_groups``: None, or (N,) ints >= 0
        that give views of one pose, where the caller knows them (:func:`shared_poses`' groups:
        checked, and the same plan as without them)."""
        rot, trans, normals, offsets = _view_planes(rotations, translations, plane_normals, plane_offsets)
        k_theta, k_phi = (int(k) for k in samples)
        if k_theta < 1 or k_phi < 1:
            raise ValueError(f"samples must be two positive counts, got {tuple(samples)}")
        n_views = rot.shape[0]
        first, count = _row_bands(rows, n_views, sonar.bins)
        needed = _needed_beams(beams, n_views, sonar.beams)
        if not isinstance(components, (bool, np.bool_)):
            raise ValueError(f"components must be True or False, got {components!r}")
        planes = 2 if components else 4
        if n_views > most_layer_views(count, sonar.beams, planes):
            raise ValueError(f"{n_views} views of {planes} x {count} x {sonar.beams} exceed one launch's "
                             f"2^31 pixels; split the batch")
        _check_sub_rays(n_views, sonar.beams, k_theta, k_phi)
        spans = shared = None
        if n_views:
            spans = self._spans(mesh, sonar, rot, trans, normals, offsets, k_phi)
            shared = shared_poses(rot, trans, spans, sonar.beams * k_theta * k_phi,
                                  _pose_groups(pose_groups, n_views))
        return RenderPlan(rot, trans, normals, offsets, k_theta, k_phi, first, count, rows is not None, needed, spans,
                          shared, planes)

    def render_planned(self, mesh, sonar: SonarSpec, plan: "RenderPlan", *, gamma: float,
                       surface_reflection: float, wait: bool = True) -> "DeviceLayers":
        """The device half of ``render_device``: render the views of ``plan`` (``plan_render``
        of the same mesh and sonar). With ``wait`` false a GPU backend may only queue the render
        (Warp CUDA does; OpenCL waits, docs/decisions.md): the layers are then complete unless
        their ``overflowed`` (``DeviceLayers``), which waits for the render, says that its queue
        of hits overflowed; render again, waiting, where it does."""
        if plan.rotations.shape[0] == 0:
            return HostLayers(np.zeros((0, plan.planes, plan.count, sonar.beams), np.float32),
                              plan.first if plan.banded else None)
        layers = self._render(mesh, SonarConstants.of(sonar), sonar.beam_widths, plan.rotations, plan.translations,
                              plan.normals, plan.offsets, plan.k_theta, plan.k_phi, float(gamma),
                              float(surface_reflection), plan.first, plan.count, plan.spans, plan.shared, plan.needed,
                              plan.planes, wait=wait)
        layers.first_rows = plan.first.copy() if plan.banded else None
        return layers

    def render_batches(self, mesh, sonar: SonarSpec, rotations, translations, plane_normals, plane_offsets,
                       samples: tuple[int, int], *, gamma: float, surface_reflection: float,
                       batch: int = 256) -> Iterator[tuple[int, np.ndarray]]:
        """``render`` of N views streamed to the host in batches of ``batch`` views: yields
        ``(start, layers)`` for each batch in order, layers the (n, 4, bins, beams) float32
        layers of views start .. start + n − 1, bit for bit those of ``render``.

        ``layers`` is a view of a staging buffer that the next batch reuses: it is valid until
        the next batch is asked for (copy what you keep). On a GPU the staging buffers are
        page-locked host memory and the copy of batch k runs on its own stream or queue while
        batch k + 1 renders (Warp CUDA: pinned ``wp.array`` and a copy stream ordered by events;
        OpenCL: ``ALLOC_HOST_PTR`` buffers mapped once and a second queue ordered by events).
        On a CPU device the layers are rendered in host memory and come without a copy (Warp
        "cpu") or through a host-allocated buffer (OpenCL). Arguments as ``render``; batch >= 1
        views, with batch × 4 × bins × beams < 2^31. Inputs are checked when this is called,
        not when the first batch is asked for.
        """
        rot, trans, normals, offsets = _view_planes(rotations, translations, plane_normals, plane_offsets)
        _check_sonar(sonar)
        k_theta, k_phi = (int(k) for k in samples)
        if k_theta < 1 or k_phi < 1:
            raise ValueError(f"samples must be two positive counts, got {tuple(samples)}")
        if not is_integer(batch) or batch < 1 or batch > most_layer_views(sonar.bins, sonar.beams):
            raise ValueError(f"batch must be an integer >= 1 with batch x 4 x {sonar.bins} x {sonar.beams} "
                             f"< 2^31 pixels, got {batch!r}")
        _check_sub_rays(min(int(batch), rot.shape[0]), sonar.beams, k_theta, k_phi)
        if rot.shape[0] == 0:
            return (batch for batch in ())
        return self._render_batches(mesh, SonarConstants.of(sonar), sonar.beam_widths, rot, trans, normals,
                                    offsets, k_theta, k_phi, float(gamma), float(surface_reflection), int(batch),
                                    self._spans(mesh, sonar, rot, trans, normals, offsets, k_phi))

    def _spans(self, mesh, sonar: SonarSpec, rotations, translations, plane_normals, plane_offsets,
               k_phi: int) -> np.ndarray:
        """The (N, 4) sub-rays each view casts: :func:`ray_spans` on a CPU device; every sub-ray on
        a GPU, where the spans' host work outweighed what they save (measured on an H100,
        docs/decisions.md). The renders launch only for the sub-rays in spans, packed in chunks
        (``_ray_chunks``): a GPU finds its spans on the device, a CPU device packs these
        (:func:`span_chunks`). These also size the queue of hits and the shared poses' direct
        legs."""
        if self.is_gpu:
            return np.tile(np.array([[0, sonar.beams, 0, k_phi]], np.int32), (rotations.shape[0], 1))
        return ray_spans(mesh.bounds, sonar, rotations, translations, plane_normals, plane_offsets, k_phi)

    @abc.abstractmethod
    def _render_batches(self, mesh, sonar: SonarConstants, beam_widths: np.ndarray, rotations: np.ndarray,
                        translations: np.ndarray, plane_normals: np.ndarray, plane_offsets: np.ndarray,
                        k_theta: int, k_phi: int, gamma: float, surface_reflection: float,
                        batch: int, spans: np.ndarray) -> Iterator[tuple[int, np.ndarray]]:
        """Generator of ``render_batches``: clean float32 arrays of N >= 1 views, batch >= 1, spans
        as ``_render``'s; yields (start, (n, 4, bins, beams) float32 host layers) per batch, valid
        until the next."""

    @abc.abstractmethod
    def _load_mesh(self, vertices: np.ndarray, faces: np.ndarray) -> Any:
        """Device copy of a clean (Nv, 3) float32 / (Nf, 3) int32 mesh."""

    @abc.abstractmethod
    def _exact_corners(self, mesh, corners: np.ndarray) -> Any:
        """The device copy of ``mesh``'s float64 corners (Nf, 3, 3), faces in ``load_mesh``'s
        order, as ``_surface_distances`` reads them."""

    @abc.abstractmethod
    def _surface_distances(self, mesh, points: np.ndarray) -> np.ndarray:
        """``surface_distances`` of clean (N, 3) float64 points, N >= 1."""

    @abc.abstractmethod
    def _prepared_cast(self, mesh, origins: np.ndarray, directions: np.ndarray,
                       max_distance: float) -> "PreparedLaunch":
        """Rays of a ``cast_rays`` launch uploaded once: clean (R, 3) float32 arrays, R >= 1. Its
        ``read()`` gives (R,) float32 distance (inf: no hit) and (R,) int32 face."""

    @abc.abstractmethod
    def _frontal_rays(self, mesh, sonar: SonarConstants, rotations: np.ndarray, translations: np.ndarray,
                      plane_normals: np.ndarray, plane_offsets: np.ndarray, views: np.ndarray,
                      azimuths: np.ndarray, rays: int, mirror: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Kernel launch of ``frontal_faces``, one thread per ray: clean float32 (V, 3, 3), (V, 3),
        (V, 3), (V,) arrays, (B,) int32 views in range, (B,) float32 azimuths and (B,) uint8 mirror
        flags, B >= 1. Returns
        every ray's (B, rays) float32 range (inf: none) and int32 face (-1: none)."""

    @abc.abstractmethod
    def _render(self, mesh, sonar: SonarConstants, beam_widths: np.ndarray, rotations: np.ndarray,
                translations: np.ndarray, plane_normals: np.ndarray, plane_offsets: np.ndarray,
                k_theta: int, k_phi: int, gamma: float, surface_reflection: float,
                first_rows: np.ndarray, rows: int, spans: np.ndarray,
                shared: "SharedPoses | None", needed: np.ndarray | None = None, planes: int = 4, *,
                wait: bool = True) -> "DeviceLayers":
        """Kernel launch of ``render_device`` (the algorithm: fsswarp/rendering.py's docstring);
        beam_widths: (beams,) float32 Δθ_b; first_rows (N,) int32 and rows R: view n keeps
        the bins first_rows[n] <= B < first_rows[n] + R (zeros and bins for full layers),
        valid; spans (N, 4) int32 (:func:`ray_spans`): view n casts only the sub-rays (i, j) of
        beams spans[n, 0] <= b < spans[n, 1] with spans[n, 2] <= j < spans[n, 3] (the others
        reach nothing); shared (:func:`shared_poses`): views whose direct legs are cast once per
        distinct pose (the same float operations, so the same pixels), or None; needed: None or
        (M, 2, beams) uint8, M dividing N, ``render_device``'s ``beams`` (0/1, C order; view n's
        at row n % M); planes: 4, the layers, or 2, the components' sums (``render_device``'s
        ``components``). Returns the (N, planes, R, beams) float32 layers, complete, on the
        device (the caller sets ``first_rows``); with ``wait`` false, as ``render_planned`` says."""

    # --- frontal contours and their distance to the data's (the (D, β) grid search) ----------
    def contour_cost(self, layers, view_index, thresholds, windows, masks, distances, shifts,
                     smoothing, cap: float = math.inf) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Frontal contours of N synthetic views and their distances to the data's contours
        (the grid surrogate of fsswarp/compare.py; kernels/pose.cl states the rule exactly).

        layers : (N, 4, bins, beams) float32, a ``DeviceLayers`` of this backend's
            ``render_device`` (read where it lies) or a host array (full layers), or (N, 2, bins,
            beams), the components' sums (``render_device(..., components=True)``); or banded
            layers, a ``DeviceLayers`` of shape (N, 4 or 2, R, beams) whose ``first_rows`` (N,)
            places row k of pair n at image row first_rows[n] + k (``render_device(...,
            rows=...)``; ``HostLayers(array, first_rows)`` on the host). The band of pair n
            must hold every row its window reads, [max(lo − rB, 0), min(hi + rB, bins)) of
            its view's window [lo, hi), else ValueError; the results are then bit for bit
            those of the full layers (the smoothing clamps rows to the image, not the band)
        view_index : (N,) int, the data view 0 <= v < V that pair n is compared with
        thresholds : (V, bins) float, the data view's detection threshold of every row
        windows : (V, 2) int, rows [lo, hi) scanned, 0 <= lo < hi <= bins
        masks : (V, 2, beams) bool, beams where the object (0) and mirror (1) contours count
        distances : (V, 2, bins, beams) float >= 0, each pixel's distance (m) to the data's
            object and mirror contour; or a ``DeviceDistances`` of this backend's
            ``device_distances`` (checked and uploaded once for many calls)
        shifts : (S,) float, range shifts (rows) at which the distances are read
        smoothing : (range_weights (2 rB + 1,), beam_weights (2 rb + 1,)) float, odd lengths
        cap : > 0 (m), the distances read as min(distance, cap) in float32 (a pose step reads
            one upload of the maps at several caps); default none

        Returns ``(contours, sums, counts)``: (N, 2, beams) float32 fractional row of the first
        threshold crossing of the smoothed object + ghost (0) and mirror + double-bounce (1)
        layers, -1 where none; (N, 2, S) float32 sums of the distances over the contour
        points; (N, 2) int32 their counts. Float32 on the device, summed in beam order.
        """
        args = self._contour_inputs(layers, view_index, thresholds, windows, masks, distances, shifts, smoothing,
                                    cap)
        n_pairs, n_shifts, beams = args[2].shape[0], args[10].shape[0], args[8].shape[3]
        if n_pairs == 0:
            return (np.zeros((0, 2, beams), np.float32), np.zeros((0, 2, n_shifts), np.float32),
                    np.zeros((0, 2), np.int32))
        return self._contour_cost(*args)

    def view_costs(self, layers, view_index, thresholds, windows, masks, distances, shifts, smoothing,
                   data_counts, cap: float, *, wait: bool = True) -> np.ndarray | Callable[[], np.ndarray]:
        """The grid surrogate's view cost of N synthetic views (fsswarp/compare.py), contours and
        sums left on the device: ``contour_cost``'s (sums, counts) combined per pair n and shift s
        into ``Σ_c (sums[n, c, s] + cap · max(0, m − k)) / max(k, m)``, k = counts[n, c], m =
        data_counts[view_index[n], c], a term 0 where k = m = 0 (kernels/pose.cl ``view_cost``).

        The arguments as ``contour_cost``'s, and data_counts : (V, 2) int >= 0, the data's
        contour points per view and component; cap : > 0 (m), finite. Returns (N, S) float32,
        the only array read back; with ``wait`` false a function that returns it (a GPU backend
        may then queue the kernels and read them back when it is called: Warp CUDA does).
        """
        args = self._contour_inputs(layers, view_index, thresholds, windows, masks, distances, shifts, smoothing,
                                    cap)
        n_views = args[3].shape[0]
        counts = np.asarray(data_counts)
        if counts.dtype.kind not in "iu" or counts.shape != (n_views, 2) or (counts.size and counts.min() < 0):
            raise ValueError(f"data_counts must be ({n_views}, 2) integers >= 0, got {counts.dtype} {counts.shape}")
        if not math.isfinite(cap):
            raise ValueError(f"cap must be a finite distance (m) for view costs, got {cap!r}")
        n_pairs, n_shifts = args[2].shape[0], args[10].shape[0]
        if n_pairs == 0:
            costs = np.zeros((0, n_shifts), np.float32)
            return costs if wait else lambda: costs
        return self._view_costs(*args, np.ascontiguousarray(counts, np.int32), wait=wait)

    def _contour_inputs(self, layers, view_index, thresholds, windows, masks, distances, shifts, smoothing,
                        cap) -> tuple:
        """``contour_cost``'s arguments checked and converted: (layers, first_rows, view_index,
        thresholds, windows, masks, range_weights, beam_weights, distances, cap, shifts), as
        ``_contour_cost`` takes them, or raise."""
        thr = real_array("thresholds", thresholds, ("V", "bins"))
        if isinstance(distances, DeviceDistances):
            if distances.backend is not self:
                raise ValueError(f"distances were uploaded by {distances.backend!r}, not by this backend")
            dist = distances
        else:
            dist = self.device_distances(distances)
        n_views, bins, beams = thr.shape[0], thr.shape[1], dist.shape[3]
        if dist.shape[0] != n_views or dist.shape[2] != bins:
            raise ValueError(f"distances must have shape (V, 2, bins, beams) = ({n_views}, 2, {bins}, "
                             f"beams) like thresholds, got {dist.shape}")
        mask = np.asarray(masks)
        if mask.dtype != np.bool_ or mask.shape != (n_views, 2, beams):
            raise ValueError(f"masks must be a bool array of shape ({n_views}, 2, {beams}), got "
                             f"{mask.dtype} {mask.shape}")
        win = np.asarray(windows)
        if win.dtype.kind not in "iu" or win.shape != (n_views, 2) or np.any(win[:, 0] < 0) \
                or np.any(win[:, 1] > bins) or np.any(win[:, 0] >= win[:, 1]):
            raise ValueError(f"windows must be ({n_views}, 2) integers with 0 <= lo < hi <= {bins}, got {win!r}")
        index = _view_index("view_index", view_index, n_views)
        steps = real_array("shifts", shifts, ("S",))
        if steps.shape[0] == 0:
            raise ValueError("shifts must hold at least one shift")
        if not (is_number(cap) and cap > 0):  # NaN fails too
            raise ValueError(f"cap must be a distance > 0 (m), got {cap!r}")
        weights = [real_array(name, w, ("K",)) for name, w in zip(("range weights", "beam weights"),
                                                                      smoothing)]
        if len(smoothing) != 2 or any(w.shape[0] % 2 == 0 for w in weights):
            raise ValueError("smoothing must be two 1-D weight arrays of odd lengths")
        if not isinstance(layers, DeviceLayers):
            layers = HostLayers(real_array("layers", layers, ("N", "P", bins, beams)))
        first = getattr(layers, "first_rows", None)
        shape = tuple(layers.shape)
        if first is None:
            if len(shape) != 4 or shape[0] != index.shape[0] or shape[1] not in (4, 2) or shape[2] != bins \
                    or shape[3] != beams:
                raise ValueError(f"layers must have shape (N, 4 or 2, bins, beams) = ({index.shape[0]}, 4 or 2, "
                                 f"{bins}, {beams}), got {shape}")
            first = np.zeros(index.shape[0], np.int32)
        else:
            if len(shape) != 4 or shape[0] != index.shape[0] or shape[1] not in (4, 2) or shape[3] != beams:
                raise ValueError(f"banded layers must have shape (N, 4 or 2, R, beams) = ({index.shape[0]}, 4 or 2, "
                                 f"R, {beams}), got {shape}")
            first, _ = _row_bands((first, shape[2]), index.shape[0], bins)
            need_lo, need_hi = rows_read(win[index], weights[0].shape[0], bins)
            bad = np.flatnonzero((first > need_lo) | (first + shape[2] < need_hi))
            if bad.size:
                n = int(bad[0])
                raise ValueError(f"the band of pair {n}, rows [{first[n]}, {first[n] + shape[2]}), misses rows "
                                 f"its window needs, [{need_lo[n]}, {need_hi[n]}) (window {tuple(win[index[n]])} "
                                 f"of view {index[n]}, ± {(weights[0].shape[0] - 1) // 2} rows of smoothing)")
        return (layers, first, index, thr, np.ascontiguousarray(win, np.int32), np.ascontiguousarray(mask, np.uint8),
                weights[0], weights[1], dist, float(cap), steps)

    @abc.abstractmethod
    def _contour_cost(self, layers: "DeviceLayers", first_rows: np.ndarray, view_index: np.ndarray,
                      thresholds: np.ndarray, windows: np.ndarray, masks: np.ndarray,
                      range_weights: np.ndarray, beam_weights: np.ndarray, distances: "DeviceDistances",
                      cap: float, shifts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Kernel launches of ``contour_cost``: layers a DeviceLayers of this backend or any
        other (read back with ``.numpy()``), (N, 4 or 2, R, beams), with first_rows (N,) int32 the
        image row of each pair's row 0 (zeros and R = bins for full layers; every band holds
        the rows its window reads), distances this backend's, clean C-contiguous int32 /
        float32 / uint8 arrays, N >= 1.
        Returns (N, 2, beams) float32 contours, (N, 2, S) float32 sums, (N, 2) int32 counts."""

    @abc.abstractmethod
    def _view_costs(self, layers: "DeviceLayers", first_rows: np.ndarray, view_index: np.ndarray,
                    thresholds: np.ndarray, windows: np.ndarray, masks: np.ndarray, range_weights: np.ndarray,
                    beam_weights: np.ndarray, distances: "DeviceDistances", cap: float, shifts: np.ndarray,
                    data_counts: np.ndarray, *, wait: bool = True) -> np.ndarray | Callable[[], np.ndarray]:
        """Kernel launches of ``view_costs``: ``_contour_cost``'s arguments and data_counts (V, 2)
        int32. Returns (N, S) float32 costs, or with ``wait`` false a function that returns them;
        contours, sums and counts stay on the device."""

    def device_distances(self, distances) -> "DeviceDistances":
        """``contour_cost``'s distance maps, (V, 2, bins, beams) float >= 0, checked and
        uploaded once for many calls (a pose step reads the same maps in every E_mu: 3.9 MB
        for coral-one's 10 views)."""
        dist = real_array("distances", distances, ("V", 2, "bins", "beams"))
        if np.any(dist < 0):
            raise ValueError("distances must be >= 0")
        return DeviceDistances(self, self._upload(dist), dist.shape)

    @abc.abstractmethod
    def _upload(self, array: np.ndarray) -> Any:
        """A device copy of a C-contiguous float32 array (Warp: ``wp.array``; OpenCL: a
        read-only buffer)."""

    # --- IRLS-ICP of 2-D contours (fsswarp/icp.py), float64 ------------------------------------
    def icp_runs(self, source_x, source_y, target_x, target_y, runs, angles, translations, floors, step_tols,
                 *, max_iterations: int, max_distance: float, tuning: float) -> "ICPRuns":
        """R IRLS-ICP runs of fsswarp/icp.py, one thread each (of ``icp_lanes``), in float64: every iteration
        matches each moved source point to its nearest target (brute force; the first of
        equal distances), weighs the pairs with Cauchy weights at the robust scale
        σ = max(median distance / √(2 ln 2), floor), solves the weighted Procrustes problem
        from the original points, and stops when no point moves more than the run's step
        tolerance, when the weights sum to 0, or after ``max_iterations``.

        source_x, source_y (F,) : every run's source points, run after run (a run's own copy);
        target_x, target_y (M,) : the targets; runs (R, 3) int : each run's first target, its
            number of targets (>= 1) and of source points (>= 1), the sources' first point
            being the sum of the earlier runs' counts
        angles (R,), translations (R, 2) : each run's start transform ``p -> rot(angle) p + t``
        floors (R,) > 0 : the floors of σ; step_tols (R,) >= 0 : the tolerances (plane units)
        max_distance : pairs farther than this (> 0; inf: none) get weight 0 and distance inf
        tuning : the Cauchy constant c > 0
        Returns an ICPRuns. Needs a device with float64 (``has_float64``)."""
        sx, sy, tx, ty = (real_array(name, value, ("F",), np.float64) for name, value in (
            ("source_x", source_x), ("source_y", source_y), ("target_x", target_x), ("target_y", target_y)))
        table = np.asarray(runs)
        if table.dtype.kind not in "iu" or table.ndim != 2 or table.shape[1] != 3:
            raise ValueError(f"runs must be an (R, 3) integer array, got {table.dtype} {table.shape}")
        n_runs = table.shape[0]
        if sx.shape != sy.shape or tx.shape != ty.shape:
            raise ValueError("source_x/source_y and target_x/target_y must have equal lengths")
        if n_runs and (table[:, 1:].min() < 1 or table[:, 0].min() < 0
                       or (table[:, 0] + table[:, 1]).max() > tx.shape[0]):
            raise ValueError(f"runs must name targets within 0..{tx.shape[0]} and count >= 1 targets and sources")
        if int(table[:, 2].sum()) != sx.shape[0]:
            raise ValueError(f"the runs' source counts sum to {int(table[:, 2].sum())}, not to the "
                             f"{sx.shape[0]} source points")
        angle = real_array("angles", angles, (n_runs,), np.float64)
        move = real_array("translations", translations, (n_runs, 2), np.float64)
        floor = real_array("floors", floors, (n_runs,), np.float64)
        tol = real_array("step_tols", step_tols, (n_runs,), np.float64)
        if np.any(floor <= 0) or np.any(tol < 0):
            raise ValueError("floors must be > 0 and step_tols >= 0")
        if not (is_integer(max_iterations) and max_iterations >= 1):
            raise ValueError(f"max_iterations must be an integer >= 1, got {max_iterations!r}")
        if not (max_distance > 0 and math.isfinite(tuning) and tuning > 0):
            raise ValueError(f"max_distance and tuning must be > 0, got {max_distance!r}, {tuning!r}")
        if not self.has_float64:
            raise RuntimeError(f"{self!r} has no float64 (cl_khr_fp64): run the ICP on the host")
        if n_runs == 0:
            return ICPRuns(np.zeros(0), np.zeros((0, 2)), np.zeros(0, np.int32), np.zeros(0, bool),
                           np.zeros((0, 2)), np.zeros(0, np.int32), np.zeros(0))
        first = np.ascontiguousarray(np.cumsum(table[:, 2]) - table[:, 2], np.int32)
        info = np.ascontiguousarray(np.column_stack([first, table]), np.int32)  # (R, 4)
        angle, move, iterations, converged, moved_x, moved_y, nearest, dist = self._icp_runs(
            sx, sy, tx, ty, info, angle, move, floor, tol, int(max_iterations), float(max_distance), float(tuning))
        return ICPRuns(angle, move, iterations, converged.astype(bool), np.column_stack([moved_x, moved_y]),
                       nearest, np.where(dist >= 0.0, dist, np.inf))

    @abc.abstractmethod
    def _icp_runs(self, source_x: np.ndarray, source_y: np.ndarray, target_x: np.ndarray, target_y: np.ndarray,
                  runs: np.ndarray, angles: np.ndarray, translations: np.ndarray, floors: np.ndarray,
                  step_tols: np.ndarray, max_iterations: int, max_distance: float, tuning: float) -> tuple:
        """Kernel launch of ``icp_runs``: clean C-contiguous float64 arrays, runs (R, 4) int32
        (first source point, first target, targets, source points), R >= 1. Returns the final
        (R,) angles and (R, 2) translations, the (R,) int32 iterations and converged (0/1), and
        per source point (F,) its moved x and y, its nearest target (int32) and its distance
        to it (-1 where not usable)."""


class RenderPlan(NamedTuple):
    """``Backend.plan_render``'s host work for one render: clean float32 ``rotations`` (N, 3, 3),
    ``translations`` (N, 3), ``normals`` (N, 3), ``offsets`` (N,); the samples ``k_theta``,
    ``k_phi``; the bands' ``first`` rows (N,) and row ``count`` (``banded``: whether bands
    were asked for); the beams read, ``needed`` (M, 2, beams) uint8 (view n's at row n % M)
    or None; the ``spans`` (N, 4) and the ``shared`` poses (SharedPoses or None; both None
    for N = 0); ``planes``, 4 layers or 2 components' sums."""

    rotations: np.ndarray
    translations: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray
    k_theta: int
    k_phi: int
    first: np.ndarray
    count: int
    banded: bool
    needed: np.ndarray | None
    spans: np.ndarray | None
    shared: "SharedPoses | None"
    planes: int


class PreparedLaunch:
    """A kernel launch on inputs already on the device (``Backend.prepared_cast``,
    ``Backend.prepared_carve``): calling it launches the kernel and waits until it is done,
    returning None; ``read()`` copies the last call's outputs to the host."""

    def __init__(self, launch: Callable[[], None], read: Callable[[], tuple]):
        self._launch = launch
        self._read = read

    def __call__(self) -> None:
        self._launch()

    def read(self) -> tuple[np.ndarray, ...]:
        return self._read()


class ICPRuns(NamedTuple):
    """What ``Backend.icp_runs`` leaves: per run, the final ``angles`` (R,) and
    ``translations`` (R, 2), ``iterations`` (R,) run and whether it ``converged`` (R,); per
    source point (run after run), its ``moved`` position (F, 2), its ``nearest`` target (F,)
    (an index into the targets) and ``distances`` (F,) to it after the last move (inf beyond
    ``max_distance``)."""

    angles: np.ndarray
    translations: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    moved: np.ndarray
    nearest: np.ndarray
    distances: np.ndarray


class DeviceLayers(abc.ABC):
    """Rendered layers in a backend's device memory; ``shape`` = (N, 4, bins, beams) float32,
    or (N, 4, R, beams) for a band of rows per view (``render_device(..., rows=...)``), or 2 in
    place of 4 for the components' sums (``render_device(..., components=True)``).

    first_rows : None for full layers; for banded ones the (N,) int array of the image row
        that each view's row 0 holds (row k of view n is image row first_rows[n] + k).
    """

    shape: tuple[int, int, int, int]
    first_rows: np.ndarray | None = None
    #: None for complete layers; for those of ``Backend.render_planned(wait=False)`` a function
    #: that waits for the render and says whether its queue of hits overflowed (then the layers
    #: lack returns); it holds no reference to the layers
    overflowed: Callable[[], bool] | None = None

    @abc.abstractmethod
    def numpy(self) -> np.ndarray:
        """A host copy of ``shape`` float32 (for banded layers the band as it is)."""

    def rows(self, start: int, stop: int) -> np.ndarray:
        """A host copy of rows [start, stop) of every layer, (N, P, stop − start, beams) float32:
        ``numpy()[:, :, start:stop]``, the same values, without copying the other rows."""
        return self.numpy()[:, :, start:stop]


class DeviceDistances:
    """Distance maps in a backend's device memory (``Backend.device_distances``): ``shape``
    (V, 2, bins, beams) float32, checked once; ``data`` the backend's device copy."""

    def __init__(self, backend: Backend, data: Any, shape: tuple[int, int, int, int]):
        self.backend = backend
        self.data = data
        self.shape = tuple(shape)


class HostLayers(DeviceLayers):
    """Layers already on the host (an empty batch; or host layers given to ``contour_cost``,
    with ``first_rows`` for banded ones)."""

    def __init__(self, array: np.ndarray, first_rows: np.ndarray | None = None):
        self.array = array
        self.shape = array.shape
        self.first_rows = None if first_rows is None else np.asarray(first_rows)

    def numpy(self) -> np.ndarray:
        return self.array


def fixed_floats(acc: np.ndarray) -> np.ndarray:
    """The float32 layers of a render's int32 fixed-point accumulator (2^24 = 1): the values the
    kernels' ``fixed_to_float`` gives (the nearest float32, scaled by an exact power of two)."""
    return acc.astype(np.float32) * np.float32(1.0 / FIXED_SCALE)


def rows_read(windows, range_taps: int, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """The image rows [lo, hi) that ``contour_cost`` reads for (N, 2) windows [lo, hi) with a
    range smoothing of ``range_taps`` (odd) taps: each window widened by the smoothing's
    radius, clipped to the image [0, bins). Returns (N,) lo and (N,) hi, int64; a band of
    rows that holds them gives the full layers' results (``render_device``'s ``rows``)."""
    windows = np.asarray(windows, np.int64)
    radius = (range_taps - 1) // 2
    return np.maximum(windows[:, 0] - radius, 0), np.minimum(windows[:, 1] + radius, bins)


def beams_read(masks, beam_taps: int) -> np.ndarray:
    """The beams that ``contour_cost`` reads for (N, 2, beams) bool ``masks`` with a beam smoothing
    of ``beam_taps`` (odd) taps: each component's mask widened by the smoothing's radius,
    clipped to the image. Returns (N, 2, beams) bool; layers rendered with these ``beams``
    (``render_device``) give the full layers' results."""
    masks = np.asarray(masks, bool)
    radius = (beam_taps - 1) // 2
    read = masks.copy()
    for shift in range(1, min(radius, masks.shape[-1] - 1) + 1):
        read[..., shift:] |= masks[..., :-shift]
        read[..., :-shift] |= masks[..., shift:]
    return read


def mask_items(masks: np.ndarray) -> np.ndarray:
    """The contours each view's ``frontal_contour`` threads find: for (V, 2, beams) bool
    ``masks``, (V, K) int32 items c · beams + b of the masked (component c, beam b) of each view
    in that order, padded with -1; K the most of any view (at least 1). A thread per item, not
    per beam: a view's masks keep 17-42 of 96 beams of each component on coral-one, and a warp
    of 32 beams then ran mostly idle lanes (bench/notes.md)."""
    flat = np.asarray(masks, bool).reshape(len(masks), -1)
    counts = flat.sum(axis=1)
    items = np.full((len(flat), max(1, int(counts.max(initial=0)))), -1, np.int32)
    view, item = np.nonzero(flat)
    items[view, np.arange(len(item)) - np.repeat(np.cumsum(counts) - counts, counts)] = item
    return items


def ray_spans(bounds: np.ndarray, sonar: SonarSpec, rotations: np.ndarray, translations: np.ndarray,
              plane_normals: np.ndarray, plane_offsets: np.ndarray, k_phi: int) -> np.ndarray:
    """(N, 4) int32 spans of the sub-rays that can reach a mesh inside the box ``bounds`` (2, 3)
    (reference frame) in each of N views (``render``'s poses and planes), directly or by the
    surface first (toward the box's mirror image in the surface): beams [first, end) and
    elevation samples j [first, end) of ``k_phi``, the hull of the box's and the image's. A
    sub-ray's azimuth is its beam's centre ± half its width whatever its elevation, and the
    azimuths of a convex set ahead of the sonar (y > 0) lie between its corners'; its elevation
    atan(z/ρ) lies between the corners' least and most z over the least ρ (>= the least y) or
    the most; ± SPAN_MARGIN. Every sub-ray of a box not wholly ahead; zeros where none is
    reached. About 0.5 µs a view."""
    corners = np.array(np.meshgrid(*np.asarray(bounds, np.float32).T, indexing="ij")).reshape(3, -1).T  # (8, 3)
    rot = np.asarray(rotations, np.float32)  # float32 as the kernels: far inside SPAN_MARGIN
    normal, offset = np.asarray(plane_normals, np.float32), np.asarray(plane_offsets, np.float32)
    origin = np.einsum("nji,nj->ni", rot, np.asarray(translations, np.float32))  # Rᵀ t
    # the corners lead and the views run along the last axis: the reductions over the 8 corners
    # are then elementwise over long rows
    x, y, z = boxes = np.empty((3, 2, 8, rot.shape[0]), np.float32)  # the box, its image
    boxes[:, 0] = (np.tensordot(rot, corners, axes=([1], [1])) - origin[:, :, None]).transpose(1, 2, 0)
    height = x[0] * normal[:, 0] + y[0] * normal[:, 1] + z[0] * normal[:, 2] - offset  # (8, N)
    boxes[:, 1] = boxes[:, 0] - 2.0 * normal.T[:, None, :] * height
    ahead = np.all(y > 0.0, axis=1)  # (2, N): the box ahead of the sonar
    np.copyto(y, np.float32(1.0), where=~ahead[:, None])
    slopes = x / y  # tan(azimuth)
    lo = np.where(ahead, np.arctan(slopes.min(axis=1)) - SPAN_MARGIN, -np.inf)
    hi = np.where(ahead, np.arctan(slopes.max(axis=1)) + SPAN_MARGIN, np.inf)
    uppers, lowers = beam_edges(np.asarray(sonar.beam_centres, np.float64), np.asarray(sonar.beam_widths, np.float64))
    first, end = np.searchsorted(uppers, lo, side="left"), np.searchsorted(lowers, hi, side="right")
    near, far = y.min(axis=1), np.sqrt(x * x + y * y).max(axis=1)  # bounds of ρ per box
    low, high = z.min(axis=1), z.max(axis=1)
    down = np.arctan(low / np.where(low < 0.0, near, far)) - SPAN_MARGIN
    up = np.arctan(high / np.where(high > 0.0, near, far)) + SPAN_MARGIN
    step = 2.0 * sonar.half_elevation / k_phi  # sample j at −half_elevation + (j + 0.5) step
    j_first = np.where(ahead, np.ceil((down + sonar.half_elevation) / step - 0.5), 0).clip(0, k_phi)
    j_end = np.where(ahead, np.floor((up + sonar.half_elevation) / step - 0.5) + 1, k_phi).clip(0, k_phi)
    reached = (first < end) & (j_first < j_end)  # (2, N) the box, the mirror image
    most = np.iinfo(np.int64).max
    spans = np.stack([np.where(reached, first, most).min(axis=0), np.where(reached, end, 0).max(axis=0),
                      np.where(reached, j_first, most).min(axis=0), np.where(reached, j_end, 0).max(axis=0)], axis=1)
    spans[~reached.any(axis=0)] = 0
    return spans.astype(np.int32)


def beam_edges(centres: np.ndarray, widths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (beams,) edges of beams ``centres`` ± ``widths``/2 made monotone for the spans'
    searches: (upper, lower), upper[b] the highest upper edge of beams 0..b (the first beam that
    reaches an angle), lower[b] the lowest lower edge of beams b.. (past the last beam that
    starts below one); both nondecreasing, in the inputs' dtype."""
    upper = np.maximum.accumulate(centres + 0.5 * widths)
    lower = np.minimum.accumulate((centres - 0.5 * widths)[::-1])[::-1]
    return upper, np.ascontiguousarray(lower)


def span_chunks(spans: np.ndarray, k_theta: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The render's chunks of ``RAY_CHUNK`` sub-rays over (N, 4) spans (the layout of the
    device's ``view_spans`` kernels): (chunks (N,), their exclusive prefix sums (N,), the view of
    each chunk), int32; a view's span holds (end − first beam) K_θ (end − first sample) sub-rays."""
    counts = (spans[:, 1] - spans[:, 0]).astype(np.int64) * k_theta * (spans[:, 3] - spans[:, 2])
    chunks = -(-counts // RAY_CHUNK)
    return (chunks.astype(np.int32), (np.cumsum(chunks) - chunks).astype(np.int32),
            np.repeat(np.arange(len(spans), dtype=np.int32), chunks))


def most_chunks(n_views: int, beams: int, k_theta: int, k_phi: int) -> int:
    """The most chunks of ``RAY_CHUNK`` sub-rays that ``n_views`` views can have (every sub-ray
    of every view): the size of a render's chunk table found on the device."""
    return n_views * -(-beams * k_theta * k_phi // RAY_CHUNK)


@dataclass(frozen=True)
class SharedPoses:
    """The P distinct poses of a render's N views: view n has pose ``index[n]`` (N,) int32, the
    pose p ``rotations[p]`` (P, 3, 3) and ``translations[p]`` (P, 3) float32, contiguous, and
    ``spans[p]`` (P, 4) int32, the hull of the ray spans of its views (zeros where none reaches
    the mesh)."""

    index: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    spans: np.ndarray

    @property
    def count(self) -> int:
        """P, the distinct poses."""
        return int(self.rotations.shape[0])


#: Most direct-leg hits (float and int each) that a render keeps for its shared poses.
SHARED_HITS = 2**27
#: Odd multipliers of the pose hash, one per float of a pose (fixed: the same poses, the same keys).
_POSE_HASH = np.random.default_rng(20261126).integers(1, 2**63, size=12, dtype=np.uint64) | np.uint64(1)


def shared_poses(rotations: np.ndarray, translations: np.ndarray, spans: np.ndarray,
                 sub_rays: int, groups: np.ndarray | None = None) -> SharedPoses | None:
    """The views among (N, 3, 3) rotations and (N, 3) translations (float32) that share a pose
    bit for bit, whose direct legs (the first hit along each sub-ray, which the surface does not
    change) a render casts once per pose: on a (D, β) grid the depth never moves a pose, and
    views at the reference's position keep theirs at every tilt. None where every pose differs,
    or where the P poses' ``sub_rays`` hits each would pass ``SHARED_HITS``. Poses are told
    apart by a 64-bit hash of their bits, checked exactly (a collision: None). ``groups``: None,
    or (N,) ints >= 0 that the caller knows to give views of one pose (a (D, β) grid: the tilt
    and the view); the hash then runs over one view of each group (a launch of 1,800 cells of
    16 views hashes 1,024 poses, not 28,800), and the grouping is checked bit for bit (where it
    fails, every view is hashed)."""
    n = rotations.shape[0]
    rows = np.ascontiguousarray(np.concatenate([rotations.reshape(n, 9), translations], axis=1), np.float32)
    hashed, of = np.arange(n), None  # the views hashed, and each view's row among them
    if groups is not None:
        last = np.full(int(groups.max()) + 1, -1, np.int64)
        last[groups] = np.arange(n)  # one view of each group
        present = last >= 0
        if np.array_equal(rows[last[groups]], rows):
            hashed, of = last[present], (np.cumsum(present) - 1)[groups]
    keys = rows[hashed].view(np.uint32).astype(np.uint64) @ _POSE_HASH  # (mod 2^64: in any order, the same)
    order = np.argsort(keys)  # grouped by key; within a pose any order (its rows are the same bits)
    ordered = keys[order]
    new_key = np.r_[True, ordered[1:] != ordered[:-1]]
    starts = np.flatnonzero(new_key)
    if starts.size == n or starts.size * sub_rays > SHARED_HITS:
        return None
    index = np.empty(hashed.size, np.int64)
    index[order] = np.cumsum(new_key) - 1  # the rank of the pose's key
    first = hashed[order[starts]]
    if not np.array_equal(rows[first][index], rows[hashed]):
        return None
    if of is not None:
        index = index[of]
    hull = np.zeros((first.size, 4), np.int64)  # poses none of whose views reach the mesh: zeros
    if np.all(spans == spans[0]):  # every view casts the same sub-rays (a GPU's: all of them)
        hull[:] = spans[0] if spans[0, 1] > spans[0, 0] else 0
    else:
        grouped = np.argsort(index, kind="stable")
        reached = grouped[spans[grouped, 1] > spans[grouped, 0]]  # grouped by pose
        pose = index[reached]
        starts = np.flatnonzero(np.r_[True, pose[1:] != pose[:-1]]) if pose.size else pose
        for k, combine in enumerate((np.minimum, np.maximum, np.minimum, np.maximum)):
            if pose.size:
                hull[pose[starts], k] = combine.reduceat(spans[reached, k], starts)
    return SharedPoses(index.astype(np.int32).reshape(n), np.ascontiguousarray(rows[first, :9].reshape(-1, 3, 3)),
                       np.ascontiguousarray(rows[first, 9:]), hull.astype(np.int32))


def span_extent(spans: np.ndarray) -> tuple[int, int]:
    """A render launch's extent over (N, 4) :func:`ray_spans`: the widest beam span and the
    most elevation samples of any view (0 beams: no view reaches the mesh, nothing to cast)."""
    return int(np.max(spans[:, 1] - spans[:, 0])), int(np.max(spans[:, 3] - spans[:, 2]))


def hit_queue_size(threads: int, share: float | None) -> int:
    """The slots of a render's queue of hits (``Backend.hit_queue``) over a launch of ``threads``
    threads: ``share`` of them, at least one (0 for a share of 0: no queue), or with ``share``
    None one each (a thread queues at most one hit: the queue cannot overflow)."""
    if share is None:
        return threads
    return 0 if share == 0 else max(1, min(threads, math.ceil(share * threads)))


def render_with_room(render_once: Callable[[float | None], Callable[[], tuple[int, int]] | None], share: float, *,
                     wait: bool = True) -> Callable[[], bool] | None:
    """``render_once(share)``: a render through a queue of hits of ``share`` (``hit_queue_size``)
    that returns a function giving the queue's (count, slots) once the render is done, or None
    where it queued nothing. Where the count passed the slots (hits were dropped), the render is
    made again with room for every hit (``render_once(None)``, which cannot overflow). With
    ``wait`` false nothing is read: returns None or a function that says, once the render is
    done, whether it dropped hits (``DeviceLayers.overflowed``)."""
    filled = render_once(share)
    if filled is None:
        return None

    def overflowed() -> bool:
        count, slots = filled()
        return count > slots

    if not wait:
        return overflowed
    if overflowed():
        render_once(None)
    return None


def most_launch_views(beams: int, k_theta: int, k_phi: int) -> int:
    """The most views one render launch holds: their sub-rays, views × ``beams`` × K_θ × K_φ, stay
    below 2^31 (the render kernels count them in int32)."""
    return (2**31 - 1) // (beams * k_theta * k_phi)


def most_layer_views(rows: int, beams: int, planes: int = 4) -> int:
    """The most views whose layers one launch holds: their pixels, views × ``planes`` (4 layers,
    or 2 components' sums) × ``rows`` × ``beams``, stay below 2^31 (the kernels index them in
    int32)."""
    return (2**31 - 1) // (planes * rows * beams)


def _check_sub_rays(n_views: int, beams: int, k_theta: int, k_phi: int) -> None:
    """Raise unless ``n_views`` fit one render launch (:func:`most_launch_views`)."""
    if n_views > most_launch_views(beams, k_theta, k_phi):
        raise ValueError(f"{n_views} views of {beams} beams x ({k_theta}, {k_phi}) sub-rays exceed one launch's "
                         f"2^31 sub-rays; split the batch")


def _needed_beams(beams, n_views: int, n_beams: int) -> np.ndarray | None:
    """``render_device``'s ``beams`` as (M, 2, beams) uint8 0/1 (C order), M dividing N, None for
    every beam, or raise."""
    if beams is None:
        return None
    beams = np.asarray(beams)
    if beams.dtype != bool or beams.ndim != 3 or beams.shape[1:] != (2, n_beams) or beams.shape[0] < 1 \
            or n_views % beams.shape[0]:
        raise ValueError(f"beams must be None or an (M, 2, {n_beams}) bool array with M dividing the {n_views} "
                         f"views, got {beams.dtype} {beams.shape}")
    return np.ascontiguousarray(beams, np.uint8)


def _pose_groups(groups, n_views: int) -> np.ndarray | None:
    """``plan_render``'s ``pose_groups`` as (N,) int64, or None, or raise."""
    if groups is None:
        return None
    groups = np.asarray(groups)
    if groups.dtype.kind not in "iu" or groups.shape != (n_views,) or (groups.size and groups.min() < 0):
        raise ValueError(f"pose_groups must be None or ({n_views},) integers >= 0, got {groups.dtype} {groups.shape}")
    return groups.astype(np.int64, copy=False)


def _row_bands(rows, n_views: int, bins: int) -> tuple[np.ndarray, int]:
    """(first (N,) int32, count) of ``render_device``'s ``rows`` (None: zeros and bins), or raise."""
    if rows is None:
        return np.zeros(n_views, np.int32), int(bins)
    try:
        first, count = rows
    except (TypeError, ValueError):
        raise ValueError(f"rows must be None or (first (N,) ints, count), got {rows!r}") from None
    first = np.asarray(first)
    if first.dtype.kind not in "iu" or first.shape != (n_views,):
        raise ValueError(f"rows: first must be a ({n_views},) integer array, got {first.dtype} {first.shape}")
    if not is_integer(count) or not 1 <= count <= bins:
        raise ValueError(f"rows: count must be an integer in [1, {bins}], got {count!r}")
    count = int(count)
    if first.size and (first.min() < 0 or first.max() > bins - count):
        raise ValueError(f"rows: every band [first, first + {count}) must lie in [0, {bins}), got first "
                         f"{first.min()}..{first.max()}")
    return np.ascontiguousarray(first, np.int32), count


def _carve_views(masks, rotations, translations, sonar, voxel_size):
    """``carve``'s views and voxel size: (V, bins, beams) masks, (V, 3, 3) and (V, 3) float32
    poses and the voxel size as a float, V <= 255, or raise."""
    rot, trans = _view_poses(rotations, translations, sonar)
    feasible = np.asarray(masks)
    if feasible.dtype.kind not in "biu":
        raise TypeError(f"masks must be bool or integer, got dtype {feasible.dtype}")
    if feasible.shape != (rot.shape[0], sonar.bins, sonar.beams):
        raise ValueError(f"masks must have shape (V, bins, beams) = ({rot.shape[0]}, {sonar.bins}, "
                         f"{sonar.beams}), got {feasible.shape}")
    if rot.shape[0] > 255:
        raise ValueError(f"at most 255 views per launch (uint8 counts), got {rot.shape[0]}")
    size = float(voxel_size) if is_number(voxel_size) else np.nan
    if not (np.isfinite(np.float32(size)) and np.float32(size) > 0):
        raise ValueError(f"voxel_size must be a finite number > 0, got {voxel_size!r}")
    return feasible, rot, trans, size


#: ``_summed_area``'s tables by the digest of their masks (read-only; the last 4): a carving
#: passes the same masks to its five launches, and every carving of a dataset the same.
_SUMMED_AREAS = Remembered(4)


def _summed_area(feasible: np.ndarray, sonar: SonarSpec) -> np.ndarray:
    """(V, bins + 1, beams + 1) int32 summed-area tables of (V, bins, beams) masks: element
    [v, B, b] counts the nonzero pixels in rows < B and columns < b (read-only, remembered by
    the masks' digest: hashing takes ~0.02 ms where the tables took ~6 ms for coral-one's views)."""
    import xxhash

    masks = np.ascontiguousarray(feasible != 0)
    key = xxhash.xxh3_128_digest(masks) + repr(masks.shape).encode()

    def table() -> np.ndarray:
        integral = np.zeros((masks.shape[0], sonar.bins + 1, sonar.beams + 1), np.int32)
        np.cumsum(np.cumsum(masks, axis=1, dtype=np.int32), axis=2, out=integral[:, 1:, 1:])
        integral.setflags(write=False)
        return integral
    return _SUMMED_AREAS.get(key, table)


def _circumradius(size: float) -> float:
    """The float32 circumradius h·√3/2 of a cube of side h."""
    return float(np.float32(size * np.sqrt(3.0) / 2.0))


def _rays(origins, directions) -> tuple[np.ndarray, np.ndarray]:
    """(R, 3) float32 origins and directions of the same R rays, or raise."""
    org = real_array("origins", origins, ("R", 3))
    dirs = real_array("directions", directions, ("R", 3))
    if org.shape != dirs.shape:
        raise ValueError(f"origins and directions must have the same shape, got {org.shape} and {dirs.shape}")
    return org, dirs


def _view_poses(rotations, translations, sonar) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3, 3) and (V, 3) float32 view poses of the same V views, with ``sonar`` a SonarSpec,
    or raise."""
    rot = real_array("rotations", rotations, ("V", 3, 3))
    trans = real_array("translations", translations, ("V", 3))
    if rot.shape[0] != trans.shape[0]:
        raise ValueError(f"rotations and translations must describe the same views, got "
                         f"{rot.shape[0]} rotations and {trans.shape[0]} translations")
    _check_sonar(sonar)
    return rot, trans


def _check_sonar(sonar) -> None:
    if not isinstance(sonar, SonarSpec):
        raise TypeError(f"sonar must be a fsswarp.sonar.SonarSpec, got {type(sonar).__name__}")


def _view_planes(rotations, translations, plane_normals, plane_offsets):
    """(N, 3, 3), (N, 3), (N, 3) and (N,) float32 poses and surface planes of the same N views
    (``render_device``, ``frontal_faces``), or raise."""
    rot = real_array("rotations", rotations, ("N", 3, 3))
    trans = real_array("translations", translations, ("N", 3))
    normals = real_array("plane_normals", plane_normals, ("N", 3))
    offsets = real_array("plane_offsets", np.asarray(plane_offsets).reshape(-1, 1), ("N", 1))
    if not (rot.shape[0] == trans.shape[0] == normals.shape[0] == offsets.shape[0]):
        raise ValueError("rotations, translations, plane_normals and plane_offsets must describe "
                         f"the same views, got {rot.shape[0]}, {trans.shape[0]}, {normals.shape[0]}, "
                         f"{offsets.shape[0]}")
    return rot, trans, normals, np.ascontiguousarray(offsets[:, 0])


def _view_index(name: str, value, n_views: int) -> np.ndarray:
    """(K,) int32 indices of views 0 <= v < n_views, or raise."""
    index = np.asarray(value)
    if index.dtype.kind not in "iu" or index.ndim != 1 or (index.size and (index.min() < 0
                                                                         or index.max() >= n_views)):
        raise ValueError(f"{name} must be a 1-D integer array of views 0..{n_views - 1}")
    return np.ascontiguousarray(index, np.int32)
