"""Voxel space carving (paper §2.2, DESIGN §6): feasible masks -> voxels -> the closed mesh S0.

:func:`carve` segments the views of a dataset (``fsswarp.segment``), carves, and meshes:
it returns a :class:`CarveResult` (mesh, voxels, segmentation, timings). :func:`carve_masks`
carves given feasible masks; :func:`carve_reference` is the float64 NumPy oracle of the kernel
(``Backend.carve``: kernels/carve.cl and its Warp twin); :func:`voxel_mesh` meshes the voxels.

The rule. A voxel is a cube of side h (m) centred at c. A view *sees* it when the cube's
bounding sphere lies wholly in its window, and *rejects* it when the box of beams and bins the
sphere projects into holds no feasible pixel (a summed-area table answers in four reads). A
voxel is kept when at least ``min_views`` views see it, none rejects it, and it does not lie
wholly above the estimated sea surface plus ``surface_margin`` (deep water: no surface rule).

Grid. Pass 1 carves the region every view sees (reference frame, below the surface, ∩ an
optional ``box``, (2, 3) m) at ``domain_resolution`` voxels along its longest side; pass 2
carves the box of the survivors' major components coarse-to-fine, from at most ``coarse``
voxels across to the finest voxel, the box's longest side / ``resolution``.

Mesh. Holes filled, components under 1% of the largest dropped, marching cubes (scikit-image,
Lewiner) at ``MC_LEVEL``, Taubin smoothing (``smooth`` iterations), and decimation to at most
``faces`` triangles by manifold3d's ``simplify``: a closed, outward-oriented, watertight
trimesh in the reference frame of (depth m, tilt rad). :class:`MeshJob` makes it in a worker
process (:func:`mesh_workers`) while the caller goes on.

Masks: view name -> (bins, beams) bool. Why each rule: docs/decisions.md ("Space carving").
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from .dataset import deep_water_pose
from .errors import InputError, check_depth_tilt, check_integer, is_finite_number, is_integer
from .rendering import signed_volume
from .rig import to_view
from .segment import Segmentation, SegmentSettings, segment_views
from .sonar import SonarSpec, from_polar, to_polar
from .surface import surface_in_reference


#: Marching-cubes level on the 0/1 occupancy: just under 1/2, so that no saddle of a face or
#: cube ties with it (at exactly 1/2 the Lewiner tables resolve ties inconsistently and leave
#: non-manifold edges: 200 of 200 random 12³ solids; none at this level).
MC_LEVEL = 0.5 - 1.0 / 64.0


class CarveWarning(UserWarning):
    """Carving went ahead without something it would have used (a view, smoothing, decimation)."""


@dataclass(frozen=True)
class CarveSettings:
    """Options of :func:`carve` (the module docstring explains each).

    domain_resolution : voxels along the longest side of the domain in pass 1
    coarse : at most this many voxels along the longest side of pass 2's first level
    min_views : a voxel fewer views see is removed
    surface_margin : m above the estimated sea surface that voxels may reach
    smooth : Taubin smoothing iterations of the mesh (0: none)
    faces : decimate the mesh to at most this many triangles (0: keep every triangle)
    segment : segmentation options
    """

    domain_resolution: int = 96
    coarse: int = 16
    min_views: int = 2
    surface_margin: float = 0.0
    smooth: int = 10
    faces: int = 20_000
    segment: SegmentSettings = field(default_factory=SegmentSettings)

    def __post_init__(self) -> None:
        for name, lowest in (("domain_resolution", 8), ("coarse", 2), ("min_views", 1), ("smooth", 0),
                             ("faces", 0)):
            check_integer(name, getattr(self, name), lowest)
        if not is_finite_number(self.surface_margin):
            raise InputError("must be a finite number (m)", field="surface_margin", value=self.surface_margin)


@dataclass
class VoxelCarving:
    """Kept voxels of one carving at the finest level.

    occupancy : (nx, ny, nz) bool; voxel (i, j, k) is centred at ``origin + voxel_size·(i, j, k)``
    domain : (2, 3) lower and upper corner of the region carved (reference frame, m)
    tested : voxels tested (each against the views up to the first that rejects it)
    """

    occupancy: np.ndarray
    origin: np.ndarray
    voxel_size: float
    domain: np.ndarray
    tested: int

    @property
    def kept(self) -> int:
        return int(self.occupancy.sum())

    def centres(self) -> np.ndarray:
        """(K, 3) centres of the kept voxels."""
        return self.origin + self.voxel_size * np.argwhere(self.occupancy)


@dataclass
class CarveResult:
    """What :func:`carve` made.

    mesh : trimesh.Trimesh, closed and outward-oriented, in the reference frame of (depth, tilt)
    voxels : the kept voxels
    depth, tilt : the D (m) and β (rad) used; views : the view names carved
    segmentation : view name -> Segmentation; timings : stage -> seconds
    backend, device : where the kernels ran
    """

    mesh: object
    voxels: VoxelCarving
    depth: float
    tilt: float
    views: tuple[str, ...]
    segmentation: dict[str, Segmentation]
    timings: dict[str, float]
    backend: str
    device: str


def carve(dataset, depth: float | None = None, tilt: float | None = None, *, resolution: int = 128,
          box=None, settings: CarveSettings = CarveSettings(), views=None, masks=None,
          backend=None, mesh: bool = True) -> CarveResult:
    """Segment the views of ``dataset``, carve, and extract the mesh S0.

    depth (m), tilt (rad) : default the dataset's measured values (``manifest.surface``); for
        deep water (no surface) ``fsswarp.dataset.deep_water_pose``, and no surface constraint
    resolution : voxels along the longest side of the carving box at the finest level
    box : optional (2, 3) lower and upper corner (reference frame, m) limiting the domain
    views : names to carve with (default all); masks : optional {view: (bins, beams) bool}
        feasible masks used instead of segmenting (e.g. the true ones)
    backend : default ``get_backend("auto")``
    mesh : False leaves ``CarveResult.mesh`` None and no mesh_s timing, for the caller to mesh
        the voxels (:func:`voxel_mesh`, or a :class:`MeshJob` in a mesh process)
    Views without any highlight are left out with a CarveWarning (they would remove every
    voxel they see). Raises InputError when fewer than two views remain, when the views see
    nothing in common, or when no voxel survives.
    """
    from .backends import get_backend

    timings: dict[str, float] = {}
    surface = dataset.manifest.surface
    default = deep_water_pose(dataset.manifest) if surface is None else (surface.depth, surface.tilt)
    depth = default[0] if depth is None else float(depth)
    tilt = default[1] if tilt is None else float(tilt)
    check_depth_tilt(depth, tilt)
    rig = dataset.rig
    names = rig.names if views is None else [rig.views[rig.index(n)].name for n in views]
    missing = [n for n in names if masks is not None and n not in masks]
    if missing:
        raise InputError("no feasible mask given for this view", field="masks", value=missing[0])

    start = time.perf_counter()
    segmentation: dict[str, Segmentation] = {}
    if masks is not None:
        feasible = {name: np.asarray(masks[name], bool) for name in names}
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # reported once below, as a CarveWarning
            segmentation = dict(dataset.derived(  # a reconstruction carves the same images at many poses
                ("segment", tuple(names), settings.segment),
                lambda: segment_views({name: dataset.images[name] for name in names}, settings.segment,
                                      label="images/{}")))
        feasible = {name: segmentation[name].feasible for name in names}
    timings["segment_s"] = time.perf_counter() - start
    empty = [n for n in names if not feasible[n].any()]
    if empty:
        warnings.warn(f"views {', '.join(empty)}: no object highlight found; carving without them",
                      CarveWarning, stacklevel=2)
    used = [n for n in names if n not in empty]
    if len(used) < max(2, settings.min_views):
        raise InputError(f"carving needs at least {max(2, settings.min_views)} views with an object highlight, "
                         f"{len(used)} have one", file=dataset.root, field="views", value=used)

    backend = backend or get_backend()
    index = [rig.index(n) for n in used]
    rotations, translations = (a[index] for a in rig.relative_poses(depth, tilt))
    plane = None  # deep water: no surface rule
    if surface is not None:
        normal, offset = surface_in_reference(rig, depth, tilt)
        plane = (normal, float(offset) + settings.surface_margin)
    stack = np.stack([feasible[n] for n in used])
    voxels = carve_masks(stack, rotations, translations, dataset.sonar, resolution=resolution, box=box,
                         plane=plane, settings=settings,
                         backend=backend, timings=timings, source=dataset.root)
    surface_mesh = None
    if mesh:
        start = time.perf_counter()
        surface_mesh = voxel_mesh(voxels, smooth=settings.smooth, faces=settings.faces)
        timings["mesh_s"] = time.perf_counter() - start
    return CarveResult(mesh=surface_mesh, voxels=voxels, depth=depth, tilt=tilt, views=tuple(used),
                       segmentation=segmentation, timings=timings, backend=backend.name, device=backend.device)


def check_box(box) -> np.ndarray:
    """``box`` as (2, 3) float64 lower and upper corners (m), or InputError (field --box)."""
    user = np.asarray(box, np.float64)
    if user.shape != (2, 3) or not np.all(np.isfinite(user)) or np.any(user[1] <= user[0]):
        raise InputError("must be finite lower and upper corners (x0 y0 z0 x1 y1 z1) with x0 < x1, "
                         "y0 < y1, z0 < z1", field="--box", value=user.ravel().tolist())
    return user


def carve_masks(masks, rotations, translations, sonar: SonarSpec, *, resolution: int = 128, box=None,
                plane=None, settings: CarveSettings = CarveSettings(), backend=None,
                timings: dict | None = None, source=None) -> VoxelCarving:
    """Carve with given feasible masks (V, bins, beams) and view poses (V, 3, 3), (V, 3).

    plane : optional (normal (3,), offset): voxels wholly above ``normal·P = offset`` are removed
    box : optional (2, 3) corners limiting the domain; resolution, settings : as in :func:`carve`
    ``timings`` (a dict) receives domain_s and carve_s; ``source`` names the data in errors.
    """
    from .backends import get_backend

    if not is_integer(resolution) or not 8 <= resolution <= 1024:
        raise InputError("must be an integer in 8..1024", field="--resolution", value=resolution)
    backend = backend or get_backend()
    timings = {} if timings is None else timings
    start = time.perf_counter()
    domain = common_region(sonar, rotations, translations, plane=plane)
    if domain is None:
        raise InputError("the views see no region in common (below the sea surface): check the "
                         "views' positions, headings and the depth/tilt", file=source, field="views",
                         value=len(rotations))
    if box is not None:
        user = check_box(box)
        domain = np.stack([np.maximum(domain[0], user[0]), np.minimum(domain[1], user[1])])
        if np.any(domain[1] <= domain[0]):
            raise InputError("lies outside the region the views see in common", field="--box",
                             value=user.ravel().tolist())
    timings["domain_s"] = time.perf_counter() - start

    start = time.perf_counter()
    run = _Carver(backend, masks, rotations, translations, sonar, plane, settings.min_views)
    size = domain[1] - domain[0]
    h = float(size.max()) / settings.domain_resolution
    shape = tuple(int(n) for n in np.maximum(np.ceil(size / h - 1e-9), 1))
    first = run.grid(domain[0] + 0.5 * h, h, shape)
    if not first.any():
        raise InputError("every voxel was carved away: the views disagree about the object (wrong "
                         "depth/tilt, or no object in the images)", file=source, field="views", value=len(rotations))
    kept = np.argwhere(_major_components(first))
    lo = np.maximum(domain[0] + h * (kept.min(axis=0) - 1), domain[0])
    hi = np.minimum(domain[0] + h * (kept.max(axis=0) + 2), domain[1])

    size = hi - lo
    h = float(size.max()) / resolution
    levels = max(0, math.ceil(math.log2(resolution / settings.coarse)))
    unit = h * 2**levels
    shape = tuple(int(n) for n in np.maximum(np.ceil(size / unit - 1e-9), 1))
    occupancy = run.grid(lo + 0.5 * unit, unit, shape)
    offsets = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)])
    for level in range(levels - 1, -1, -1):
        step = h * 2**level
        interior = _interior(occupancy)
        parents = np.argwhere(occupancy & ~interior)
        children = (2 * parents[:, None, :] + offsets[None]).reshape(-1, 3)
        refined = interior.repeat(2, 0).repeat(2, 1).repeat(2, 2)
        if len(children):
            keep = run.points(lo + step * (children + 0.5), step)
            refined[tuple(children[keep].T)] = True
        occupancy = refined
    timings["carve_s"] = time.perf_counter() - start
    if not occupancy.any():
        raise InputError("every voxel was carved away: the views disagree about the object (wrong "
                         "depth/tilt, or no object in the images)", file=source, field="views", value=len(rotations))
    return VoxelCarving(occupancy=occupancy, origin=lo + 0.5 * h, voxel_size=h, domain=domain, tested=run.tested)


class _Carver:
    """Backend.carve with the keep rule (views, surface) applied; counts the voxels tested."""

    def __init__(self, backend, masks, rotations, translations, sonar, plane, min_views):
        self.backend, self.masks, self.rotations, self.translations = backend, masks, rotations, translations
        self.sonar, self.plane, self.min_views = sonar, plane, min_views
        self.tested = 0

    def _keep(self, seen, rejected, centres, size) -> np.ndarray:
        keep = (seen >= self.min_views) & (rejected == 0)
        if self.plane is not None:
            normal, offset = self.plane
            keep &= centres @ np.asarray(normal, np.float64) - size * math.sqrt(3.0) / 2.0 <= offset
        self.tested += len(seen)
        return keep

    def grid(self, origin, size, shape) -> np.ndarray:
        seen, rejected = self.backend.carve(self.masks, self.rotations, self.translations, self.sonar, size,
                                            origin=origin, shape=shape)
        axes = [origin[a] + size * np.arange(shape[a]) for a in range(3)]
        centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        return self._keep(seen, rejected, centres, size).reshape(shape)

    def points(self, centres, size) -> np.ndarray:
        seen, rejected = self.backend.carve(self.masks, self.rotations, self.translations, self.sonar, size,
                                            centres=centres)
        return self._keep(seen, rejected, centres, size)


def _interior(occupancy: np.ndarray) -> np.ndarray:
    """Kept voxels whose 26 neighbours are all kept (the grid's edge counts as removed)."""
    from scipy import ndimage

    return ndimage.binary_erosion(occupancy, structure=np.ones((3, 3, 3), bool), border_value=0)


def _major_components(occupancy: np.ndarray) -> np.ndarray:
    """The kept voxels of the 26-connected components holding at least 1% of the largest's
    voxels (drops specks: the shadowed slabs that only views from one side judge, noise)."""
    from scipy import ndimage

    labels, count = ndimage.label(occupancy, structure=np.ones((3, 3, 3), bool))
    if count <= 1:
        return occupancy
    sizes = np.bincount(labels.ravel())[1:]
    return np.isin(labels, 1 + np.flatnonzero(sizes >= 0.01 * sizes.max()))


def common_region(sonar: SonarSpec, rotations, translations, *, plane=None, samples: int = 64):
    """(2, 3) box around the region that every view sees (the project rule), below ``plane``
    (normal, offset) if given; None if there is none.

    The views' frustum boxes (caps sampled 33 × 17 in azimuth and elevation) bound the search;
    a lattice of ``samples`` points along its longest side finds the common region, whose box
    is grown by one lattice step (and clipped to the frustum boxes)."""
    rotations = np.asarray(rotations, np.float64)
    translations = np.asarray(translations, np.float64)
    theta = sonar.beam_angle(np.linspace(-0.5, sonar.beams - 0.5, 33))
    phi = np.linspace(-sonar.half_elevation, sonar.half_elevation, 17)
    ranges = np.array([max(sonar.range_min - 0.5 * sonar.range_step, 0.0), sonar.range_max + 0.5 * sonar.range_step])
    caps = from_polar(ranges[:, None, None], theta[None, :, None], phi[None, None, :]).reshape(-1, 3)
    world = np.einsum("vij,pj->vpi", rotations, caps) + translations[:, None, :]
    lo, hi = world.min(axis=1).max(axis=0), world.max(axis=1).min(axis=0)
    if np.any(hi <= lo):
        return None
    step = float((hi - lo).max()) / samples
    axes = [np.arange(lo[a] + 0.5 * step, hi[a], step) for a in range(3)]
    if any(len(a) == 0 for a in axes):
        return None
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    if plane is not None:
        points = points[points @ np.asarray(plane[0], np.float64) <= plane[1]]
    for rot, t in zip(rotations, translations):  # each view tests only the points that all before it see
        points = points[sonar.in_window(*to_polar(to_view(points, rot, t)))]
    if not len(points):
        return None
    return np.stack([np.maximum(points.min(axis=0) - step, lo), np.minimum(points.max(axis=0) + step, hi)])


def carve_reference(masks, rotations, translations, sonar: SonarSpec, voxel_size: float, *, origin=None,
                    shape=None, centres=None):
    """The float64 NumPy oracle of ``Backend.carve`` (same arguments, same result): (P,) uint8
    seen counts (up to the first rejecting view) and rejected flags. Grid centres are formed
    in float32 as the kernels do."""
    masks = np.asarray(masks) != 0
    rotations = np.asarray(rotations, np.float64)
    translations = np.asarray(translations, np.float64)
    if centres is None:
        o = np.asarray(origin, np.float32).reshape(3)
        h = np.float32(voxel_size)
        idx = np.stack(np.meshgrid(*(np.arange(n, dtype=np.float32) for n in shape), indexing="ij"), -1)
        centres = (o + h * idx).reshape(-1, 3)
    points = np.asarray(centres, np.float32).astype(np.float64)
    radius = float(np.float32(float(voxel_size) * math.sqrt(3.0) / 2.0))
    integral = np.zeros((len(masks), sonar.bins + 1, sonar.beams + 1), np.int64)
    integral[:, 1:, 1:] = masks.cumsum(axis=1).cumsum(axis=2)
    seen = np.zeros(len(points), np.int64)
    rejected = np.zeros(len(points), bool)
    for v in range(len(rotations)):
        q = to_view(points, rotations[v], translations[v])
        rng, theta, phi = to_polar(q)
        rho = np.hypot(q[:, 0], q[:, 1])
        with np.errstate(invalid="ignore", divide="ignore"):
            d_phi = np.arcsin(np.minimum(radius / rng, 1.0))
            d_theta = np.arcsin(np.minimum(radius / rho, 1.0))
        b_lo = np.floor(sonar.beam_coordinate(theta - d_theta) + 0.5)
        b_hi = np.floor(sonar.beam_coordinate(theta + d_theta) + 0.5)
        bin_lo = np.floor(sonar.bin_coordinate(rng - radius) + 0.5)
        bin_hi = np.floor(sonar.bin_coordinate(rng + radius) + 0.5)
        whole = ((radius < rho) & (np.abs(phi) + d_phi <= sonar.half_elevation)
                 & (b_lo >= 0) & (b_hi < sonar.beams) & (bin_lo >= 0) & (bin_hi < sonar.bins))
        count = np.ones(len(points), np.int64)
        w = np.flatnonzero(whole)
        b0, b1 = b_lo[w].astype(np.int64), b_hi[w].astype(np.int64) + 1
        r0, r1 = bin_lo[w].astype(np.int64), bin_hi[w].astype(np.int64) + 1
        table = integral[v]
        count[w] = table[r1, b1] - table[r0, b1] - table[r1, b0] + table[r0, b0]
        seen += whole & ~rejected
        rejected |= whole & (count == 0)
    return seen.astype(np.uint8), rejected.astype(np.uint8)


def within(voxels: VoxelCarving, mesh) -> VoxelCarving:
    """``voxels`` keeping only the voxels whose centres lie inside the closed ``mesh`` (same
    frame): a model held to the space that the views see (``fsswarp.metrics.inside_grid``)."""
    from .metrics import inside_grid

    inside = inside_grid(mesh, voxels.origin, voxels.voxel_size, voxels.occupancy.shape)
    return dataclasses.replace(voxels, occupancy=voxels.occupancy & inside)


#: A triangle nearer than this many voxel sizes before a voxel's centre does not hide it (:func:`held`).
UNSEEN_MARGIN = 1.5


def held(voxels: VoxelCarving, mesh, rotations, translations, sonar: SonarSpec, backend) -> VoxelCarving:
    """The closed ``mesh`` held to the carving ``voxels`` (same frame): the kept voxels whose
    centres lie inside it (:func:`within`), and those that no view sees past it, where the
    views cannot tell full from empty. A view sees a centre where it lies in the view's
    window (its nearest beam and bin in the image, its elevation in the aperture) and the line
    from the view's origin to it meets ``mesh`` no nearer than ``UNSEEN_MARGIN`` voxels before
    it. rotations (V, 3, 3), translations (V, 3): the views' poses in the voxels' frame (the
    carving's views); a ray launch per view, for the centres that no view before it saw."""
    inside = within(voxels, mesh)
    outside = np.argwhere(voxels.occupancy & ~inside.occupancy)
    centres = voxels.origin + voxels.voxel_size * outside
    unseen = np.ones(len(centres), bool)
    handle = backend.load_mesh(mesh.vertices, mesh.faces) if len(centres) else None
    for rotation, origin in zip(np.asarray(rotations, np.float64), np.asarray(translations, np.float64)):
        left = np.flatnonzero(unseen)
        rays = centres[left] - origin
        rng, theta, phi = to_polar(rays @ rotation)
        look = sonar.in_window(rng, theta, phi)
        if not look.any():
            continue
        hit, _ = backend.cast_rays(handle, np.broadcast_to(origin, (int(look.sum()), 3)), rays[look] / rng[look, None])
        unseen[left[look][~(hit < rng[look] - UNSEEN_MARGIN * voxels.voxel_size)]] = False
    occupancy = inside.occupancy.copy()
    occupancy[tuple(outside[unseen].T)] = True
    return dataclasses.replace(inside, occupancy=occupancy)


def voxel_mesh(voxels: VoxelCarving, *, smooth: int = 10, faces: int = 20_000, timings: dict | None = None):
    """The closed, outward-oriented, watertight surface of the kept voxels (module docstring:
    Mesh). Smoothing or decimation that would break watertightness is skipped with a
    CarveWarning. ``timings`` (a dict) receives each stage's seconds: fill_s, components_s,
    marching_cubes_s, orient_s, smooth_s, smooth_check_s, decimate_s, decimate_check_s and
    trimesh_s (making the Trimesh)."""
    import trimesh
    from skimage.measure import marching_cubes

    timings = {} if timings is None else timings
    clock = time.perf_counter()

    def lap(stage: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[stage] = now - clock
        clock = now

    occupied, lower = _crop(voxels.occupancy)
    filled = _fill_holes(occupied)
    lap("fill_s")
    solid = _major_components(filled)
    lap("components_s")
    h = voxels.voxel_size
    padded = np.pad(solid, 1).astype(np.float32)
    with warnings.catch_warnings():  # scikit-image <= 0.25 sets .shape of its tables (NumPy 2.5 deprecates it)
        warnings.filterwarnings("ignore", "Setting the shape on a NumPy array", DeprecationWarning)
        vertices, triangles, _, _ = marching_cubes(padded, level=MC_LEVEL, method="lewiner", allow_degenerate=False)
    # Lewiner's vertices: grid index + 31/64 or 33/64 along an edge, exact in float32, so that
    # adding the crop's corner and scaling as marching_cubes(spacing=h) scales give the whole
    # grid's vertices bit for bit; distinct (0.68 h or more apart) and all used, so trimesh's
    # process (merging vertices) would change nothing
    vertices = ((vertices + lower.astype(np.float32)) * np.full(3, h)).astype(np.float32)
    lap("marching_cubes_s")
    vertices = vertices + (voxels.origin - h)
    triangles = triangles.astype(np.int64)
    if signed_volume(vertices[triangles]) < 0:
        triangles = np.ascontiguousarray(triangles[:, ::-1])
    if not _closed(triangles):
        raise RuntimeError(f"marching cubes gave a mesh that is not watertight and consistently wound "
                           f"({len(triangles)} faces)")
    lap("orient_s")
    if smooth:
        smoothed = _taubin(vertices, triangles, int(smooth))
        lap("smooth_s")
        if _accept(smoothed, triangles, "Taubin smoothing", closed=True):  # the faces did not change
            vertices = smoothed
        lap("smooth_check_s")
    if faces and len(triangles) > faces:
        decimated = _decimate(vertices, triangles, faces, 2.0 * h)
        lap("decimate_s")
        if _accept(*decimated, "decimation"):
            vertices, triangles = decimated
        lap("decimate_check_s")
        if len(triangles) > faces:
            warnings.warn(f"decimation stopped at {len(triangles)} faces, above the {faces} asked for: it moves "
                          "the surface by at most 2 voxels", CarveWarning, stacklevel=2)
    mesh = trimesh.Trimesh(vertices, triangles, process=False)
    lap("trimesh_s")
    return mesh


#: Most processes that mesh carvings ahead (:func:`mesh_workers`).
MAX_MESH_WORKERS = 3


def mesh_workers() -> int:
    """Processes that make carvings' meshes while the reconstruction goes on (:class:`MeshJob`):
    the environment variable FSSWARP_MESH_WORKERS (0: each mesh is made in this process when it
    is needed), else :func:`default_mesh_workers` of the CPUs that this process may use."""
    from .processes import worker_count
    from .system import usable_cpus

    return worker_count("FSSWARP_MESH_WORKERS", default_mesh_workers(usable_cpus()))


def default_mesh_workers(cpus: int) -> int:
    """Mesh processes for ``cpus`` CPUs: one per 4 less one, at most ``MAX_MESH_WORKERS``: none
    on fewer than 8, whose cores the loop's kernels and the truth metrics use; 3 on a 16-core
    GPU host."""
    return min(MAX_MESH_WORKERS, max(0, cpus // 4 - 1))


#: The mesh processes of this Python process, made on first use: {workers: WorkerProcesses or
#: None where they could not start}. They serve every reconstruction run here and stop at exit.
_MESH_PROCESSES: dict = {}


def start_mesh_workers():
    """The mesh processes (:func:`mesh_workers` of them; None for none), started now if they are
    not running, so that their imports (~1 s) are done before the first mesh comes. Where they
    cannot start, a CarveWarning, once, and meshes are made in this process."""
    workers = mesh_workers()
    if workers == 0:
        return None
    if workers not in _MESH_PROCESSES:
        import atexit

        from .processes import WorkerProcesses

        if not _MESH_PROCESSES:
            atexit.register(_stop_mesh_workers)
        try:
            _MESH_PROCESSES[workers] = WorkerProcesses(workers, _start_mesh_process,
                                                       lost=lambda: _lost_mesh_workers(workers))
        except OSError as err:
            _MESH_PROCESSES[workers] = None
            warnings.warn(f"mesh processes could not start ({err}); making carvings' meshes in this process "
                          "(FSSWARP_MESH_WORKERS=0 does so without this warning)", CarveWarning, stacklevel=2)
    return _MESH_PROCESSES[workers]


def _stop_mesh_workers() -> None:
    """Stop the mesh processes at Python's exit, before its modules are torn down (the pool's
    own clean-up would then find them gone)."""
    for processes in _MESH_PROCESSES.values():
        if processes is not None:
            processes.close()
    _MESH_PROCESSES.clear()


def _start_mesh_process() -> None:
    """Set up a mesh process: the modules that :func:`voxel_mesh` needs are imported now."""
    import manifold3d  # noqa: F401
    import skimage.measure  # noqa: F401
    import trimesh  # noqa: F401


class MeshJob:
    """``voxel_mesh(voxels, smooth=smooth, faces=faces)`` being made: in a mesh process
    (:func:`start_mesh_workers`) from when the job is made, while the caller goes on, else in
    this process when :meth:`result` is first called; the same mesh either way, bit for bit.
    A caller that knows which carvings it will need has their meshes (~0.2 s each on a GPU
    host, mostly manifold3d's decimation, which holds the GIL) made side by side."""

    def __init__(self, voxels: VoxelCarving, *, smooth: int = 10, faces: int = 20_000):
        self.arguments = (voxels, smooth, faces)
        self.processes, self.mesh = start_mesh_workers(), None
        self.future = None if self.processes is None else self.processes.submit(_mesh_in_process, *self.arguments)

    def result(self):
        """The trimesh; raises what ``voxel_mesh`` raised, and issues the warnings it issued.
        Where a mesh process died (e.g. killed for memory), the mesh is made here instead."""
        if self.mesh is None:
            voxels, smooth, faces = self.arguments
            made = None if self.future is None else self.processes.outcome(self.future)
            if made is None:
                self.mesh = voxel_mesh(voxels, smooth=smooth, faces=faces)
            else:
                import trimesh

                vertices, triangles, issued = made
                for message, category in issued:
                    warnings.warn(message, category, stacklevel=2)
                self.mesh = trimesh.Trimesh(vertices, triangles, process=False)
        return self.mesh


def _lost_mesh_workers(workers: int) -> None:
    """The mesh processes of ``workers`` broke (a process died; ``WorkerProcesses``' ``lost``):
    a CarveWarning, and every mesh from now on is made in this process."""
    _MESH_PROCESSES[workers] = None
    warnings.warn("a mesh process ended unexpectedly (killed, or out of memory); making carvings' meshes in "
                  "this process from now on", CarveWarning, stacklevel=5)


def _mesh_in_process(voxels: VoxelCarving, smooth: int, faces: int):
    """(vertices (V, 3), triangles (F, 3), [(message, category)] of the warnings issued) of
    ``voxel_mesh``, in a mesh process."""
    with warnings.catch_warnings(record=True) as issued:
        warnings.simplefilter("always")
        mesh = voxel_mesh(voxels, smooth=smooth, faces=faces)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces), [(str(w.message), w.category) for w in issued]


def _crop(occupancy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the smallest box of ``occupancy`` that holds every kept voxel, its (3,) lower corner's
    index); the whole grid where none is kept."""
    lower, upper = np.zeros(3, np.int64), np.array(occupancy.shape)
    for axis in range(3):
        used = np.flatnonzero(occupancy.any(axis=tuple(a for a in range(3) if a != axis)))
        if len(used):
            lower[axis], upper[axis] = used[0], used[-1] + 1
    return occupancy[tuple(map(slice, lower, upper))], lower


def _fill_holes(occupancy: np.ndarray) -> np.ndarray:
    """``scipy.ndimage.binary_fill_holes`` of ``occupancy`` by one labelling (a third of its
    time): the empty voxels 6-connected to the grid's edge stay empty, every other is filled."""
    from scipy import ndimage

    labels, _ = ndimage.label(np.pad(~occupancy, 1, constant_values=True))
    return labels[1:-1, 1:-1, 1:-1] != labels[0, 0, 0]


def _closed(triangles: np.ndarray) -> bool:
    """Whether every edge of the (F, 3) triangles joins exactly two of them, which run along it
    in opposite directions (trimesh's is_watertight and is_winding_consistent together)."""
    if len(triangles) == 0 or len(triangles) % 2:
        return False
    start = triangles.astype(np.int64)
    end = start[:, [1, 2, 0]]
    count = int(start.max()) + 1
    keys = np.sort((2 * (np.minimum(start, end) * count + np.maximum(start, end)) + (start > end)).ravel())
    return bool(np.all(keys[0::2] % 2 == 0) and np.all(keys[1::2] == keys[0::2] + 1))


def _taubin(vertices: np.ndarray, triangles: np.ndarray, iterations: int) -> np.ndarray:
    """(V, 3) vertices after ``trimesh.smoothing.filter_taubin`` (λ = ν = 0.5, the mean of the
    edge neighbours) of a closed mesh, bit for bit: the same operator, each row's entries in
    column order, built once rather than from the mesh's cached graphs."""
    from scipy import sparse

    count = len(vertices)
    keys = np.sort((triangles * count + triangles[:, [1, 2, 0]]).ravel())  # the edges (row, column)
    rows, cols = np.divmod(keys, count)
    degree = np.bincount(rows, minlength=count)
    operator = sparse.csr_matrix((1.0 / degree[rows], cols, np.concatenate(([0], np.cumsum(degree)))),
                                 shape=(count, count))
    out = vertices.copy()
    for index in range(iterations):
        step = operator @ out - out
        if index % 2 == 0:
            out += 0.5 * step
        else:
            out -= 0.5 * step
    return out


#: First guess of _decimate's step k (of 256) from r, the faces to reach over the faces asked
#: for: k ≈ 9.5 (r - 1)^0.9, and the slope of log(faces) over log(k) it then assumes (0.9); both
#: fitted to coral-one, coral-two and table carvings at 96 to 160 voxels. They set how many
#: simplifications the search takes (2.9 on average there, against 9 by bisection), not its result.
_GUESS = (9.5, 0.9)
_SLOPE = 0.9
#: Guided steps of _decimate's search before it halves its bracket (at most 4 + 8 simplifications).
_GUIDED = 4


def _decimate(vertices: np.ndarray, triangles: np.ndarray, faces: int, max_tolerance: float):
    """(vertices (V, 3), triangles (F, 3)) of the mesh simplified by manifold3d (edge collapses
    within a tolerance; the result stays a closed 2-manifold) with tolerance k/256 of
    ``max_tolerance`` (``_step_tolerance``) at a step k in 1..256 where the face count reaches
    ``faces``: at most ``faces`` at k and more at k - 1 (k = 1: the mesh itself); else
    ``max_tolerance``'s mesh, where no step reaches it.

    The count mostly falls as k grows. The search keeps a bracket (more than ``faces`` at its
    bottom, at most at its top) and steps into it from a guess (``_GUESS``) by secants of
    log(count) over log(k), then by halving (``_GUIDED``): about three simplifications. Where
    the count crosses ``faces`` once, as in every carving measured (bench/mesh_profile.py),
    bisection over the same steps (8 halvings) finds the same k and this is the same mesh."""
    import manifold3d

    solid = manifold3d.Manifold(manifold3d.Mesh(vert_properties=np.asarray(vertices, np.float32),
                                                tri_verts=np.asarray(triangles, np.uint32)))
    counts = {0: len(triangles)}
    low, top, best = 0, 257, None  # above faces at low, at most faces at top (257: no such step yet)
    step = min(256, max(1, round(_GUESS[0] * max(len(triangles) / faces - 1.0, 0.01) ** _GUESS[1])))
    for guided in itertools.count(1):
        trial = solid.simplify(_step_tolerance(step, max_tolerance))
        counts[step] = trial.num_tri()
        if counts[step] <= faces:
            top, best = step, trial
        else:
            low = step
        if top - low == 1:
            break
        if guided >= _GUIDED:
            guess = 0.5 * (low + top)
        elif top < 257 and low > 0:  # a secant between the bracket's ends
            x0, x1 = math.log(low), math.log(top)
            y0, y1 = math.log(counts[low]), math.log(counts[top])
            guess = math.exp(x0 + (math.log(faces) - y0) * (x1 - x0) / (y1 - y0))
        else:
            guess = step * (counts[step] / faces) ** (1.0 / _SLOPE)
        step = min(max(math.ceil(guess), low + 1), top - 1)
    out = (trial if best is None else best).to_mesh()
    return np.asarray(out.vert_properties[:, :3], np.float64), np.asarray(out.tri_verts, np.int64)


def _step_tolerance(step: int, max_tolerance: float) -> float:
    """``step``/256 of ``max_tolerance`` as bisection over [0, max_tolerance] reaches it: the
    mean of the ends it has narrowed to, rounded at every halving as bisection rounds."""
    low, high, lo, hi = 0, 256, 0.0, float(max_tolerance)
    while step != high:
        middle, value = (low + high) // 2, 0.5 * (lo + hi)
        if step == middle:
            return value
        if step < middle:
            high, hi = middle, value
        else:
            low, lo = middle, value
    return hi


def _accept(vertices: np.ndarray, triangles: np.ndarray, what: str, *, closed: bool | None = None) -> bool:
    """Whether the mesh is still a watertight, consistently wound, outward volume (``closed``:
    known already); if not, a CarveWarning that ``what`` was skipped."""
    if (_closed(triangles) if closed is None else closed) and signed_volume(vertices[triangles]) > 0:
        return True
    warnings.warn(f"{what} broke the carved mesh's watertightness; kept the mesh without it",
                  CarveWarning, stacklevel=3)
    return False
