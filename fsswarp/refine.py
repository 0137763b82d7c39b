"""Shape refinement: move the model's vertices so that its synthetic views agree with the data
(paper §2.2–2.3, Figure 3b; DESIGN §8). Lengths in m, meshes (Nv, 3) vertices, (F, 3) faces.

One update at a given (D, β), over the views marked ``optimize``, with a
``fsswarp.compare.ViewComparison`` (the caller's, or one of ``settings.pose``):

1. Contours: the comparison locates the model at (D, β) (data and synthetic frontal contours
   of the object and of the distinct mirror blob, detection shift).
2. Contour motions: per contour point the ICP's matched-pair vector, else the rigid motion of
   the alignment; each beam's frontal patch (ray casting) collects them.
3. Patch motions: per patch one truncated-SVD least-squares solve (``rcond``) over every view
   and both components (``fsswarp.motion``); a mirror row is ``J_mirror(Q) H``, H = I − 2nnᵀ.
4. Overshoot (the intensity term of eq. 4): a ray hit whose pixel the synthetic view calls
   bright, the data dark (farther than ``tolerance`` from every highlight pixel) and no ghost
   or mirror reaches votes to move its triangle inward by that distance; a hit past the last
   highlight row of its beam does not vote. With ``top_level`` > 0 the double-bounce mirror's
   rays (sonar → surface → triangle: the top, seen from above) vote alike where the synthetic
   mirror2 layer is at least ``top_level`` × the threshold and no other component reaches, by
   that distance times the cosine between ray and normal. Triangles with a contour motion keep
   that one.
5. Vertex displacements: area-weighted motions with confidences, spread by the membrane solve
   ``(C + λ L) U = C Û`` (λ = ``smoothing``), capped at ``max_motion``, scaled by ``step``.
6. Safety: the topology never changes. A triangle whose normal would turn more than
   ``max_turn`` holds its vertices (neighbours tapered by ``HOLD_TAPER``) up to ``holds``
   times; then the whole step is halved up to ``halvings`` times, else refused.
"""

from __future__ import annotations

import functools
import math
import threading
import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import xxhash

from .caching import Remembered
from .compare import PoseSettings, PoseWarning, ViewComparison
from .errors import InputError, check_integer, is_finite_number, is_integer
from .motion import image_jacobian, truncated_lstsq
from .rendering import check_mesh, is_watertight, signed_volume
from .surface import surface_in_reference

#: Share of the step that the first rings of neighbours of a held vertex take (module
#: docstring, step 6); ring k of ``len(HOLD_TAPER)``, beyond them the full step.
HOLD_TAPER = (0.5, 0.75, 0.875)


@dataclass(frozen=True)
class RefineSettings:
    """Options of :func:`refine_shape` (the module docstring explains each).

    iterations : shape updates per call; step : fraction of the estimated motion applied
    max_motion : cap (m) of a patch motion per update; smoothing : membrane weight λ
    shrink : weight of the overshoot term (0: contours only); tolerance : (m) overshoot dead band
    mirror : use the mirror contours; rays : (K_θ, K_φ) rays per beam of the overshoot term
    top_level : the double-bounce votes' synthetic mirror2 level, × the detection threshold;
        0 (the default): none. 2 takes a carving's excess faster and erodes the true top over
        many updates; the reconstruction uses it at its answer (docs/decisions.md)
    corrupt : a pixel counts as ghost/mirror corrupted where the smoothed synthetic ghost +
        mirror layers exceed ``corrupt`` × the detection threshold
    rcond : truncated-SVD cut-off of the patch solves; max_turn : (rad) largest normal turn
    holds : rounds of holding offending vertices; halvings : then rounds of halving the
        whole step before it is refused; pose : contour settings (PoseSettings)
    """

    iterations: int = 1
    step: float = 0.7
    max_motion: float = 0.01
    smoothing: float = 4.0
    shrink: float = 1.5
    tolerance: float = 0.002
    mirror: bool = True
    rays: tuple[int, int] = (2, 32)
    top_level: float = 0.0
    corrupt: float = 0.5
    rcond: float = 1e-2
    max_turn: float = math.radians(60.0)
    holds: int = 16
    halvings: int = 4
    pose: PoseSettings = field(default_factory=PoseSettings)

    def __post_init__(self) -> None:
        for name, lowest in (("iterations", 1), ("holds", 0), ("halvings", 0)):
            check_integer(f"refine.{name}", getattr(self, name), lowest)
        for name, zero, high in (("step", False, 2.0), ("max_motion", False, 1.0), ("smoothing", False, 1e6),
                                 ("shrink", True, 10.0), ("tolerance", True, 1.0), ("corrupt", False, 1e6),
                                 ("top_level", True, 1e6),
                                 ("rcond", False, 1.0), ("max_turn", False, math.pi)):
            value = getattr(self, name)
            ok = is_finite_number(value) and value <= high
            if not (ok and (value >= 0 if zero else value > 0)):
                raise InputError(f"must be a number in {'[' if zero else '('}0, {high}]", field=f"refine.{name}",
                                 value=value)
        if len(self.rays) != 2 or not all(is_integer(k) and k >= 1 for k in self.rays):
            raise InputError("must be two integers >= 1", field="refine.rays", value=self.rays)


@dataclass(frozen=True)
class RefineStep:
    """One shape update: patches with a contour motion and with an overshoot vote, the mean
    vertex displacement (m) applied, the step factor used (0: refused), and the ACE (m) of
    the model it started from."""

    contour_patches: int
    shrink_patches: int
    mean_displacement: float
    step: float
    ace: float


@dataclass(frozen=True)
class RefineResult:
    """What :func:`refine_shape` did.

    mesh : the refined trimesh (same topology); views : names of the views used
    ce_before, ce_after : (V,) per-view CE (eq. 5, m; NaN: no contour) of the object contours
    ace_before, ace_after : their means (ACE, eq. 9); steps : one RefineStep per update
    mean_displacement : mean vertex displacement (m) over all updates; seconds : wall time
    """

    mesh: object
    views: tuple[str, ...]
    ce_before: np.ndarray
    ce_after: np.ndarray
    ace_before: float
    ace_after: float
    steps: tuple[RefineStep, ...]
    mean_displacement: float
    seconds: float

    @property
    def patches_moved(self) -> int:
        """Triangles with a motion (contour or overshoot), summed over the updates."""
        return sum(s.contour_patches + s.shrink_patches for s in self.steps)


def refine_shape(model, dataset, depth: float, tilt: float, *, settings: RefineSettings = RefineSettings(),
                 backend=None, comparison: ViewComparison | None = None) -> RefineResult:
    """Refine ``model`` (closed trimesh, reference frame of (depth m, tilt rad)) against the
    optimized views of ``dataset``: ``settings.iterations`` updates of the module docstring.

    comparison : the ViewComparison of ``dataset`` to measure with (its settings stand for
        ``settings.pose``, and it carries the backend, so give no backend with it); default
        one of ``settings.pose`` on ``backend``. It is left with the refined mesh located at
        (depth, tilt), as ce_after found it.
    Raises InputError when the model is seen in none of the optimized views."""
    import trimesh

    start = time.perf_counter()
    vertices, faces = check_mesh(model, name="model")
    if comparison is None:
        comparison = ViewComparison(dataset, settings=settings.pose, backend=backend)
    elif backend is not None:
        raise ValueError("the backend comes with the comparison: give either a backend or a comparison")
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    steps, moved = [], []
    ce_before, views = None, ()
    topology = _topology(mesh)  # the topology never changes (step 6): one for every update
    membrane = _Membrane(topology, settings.smoothing)
    for _ in range(settings.iterations):
        update = _Update(mesh, dataset, depth, tilt, settings, comparison)
        if ce_before is None:
            ce_before, views = update.errors, update.comparison.data.names
        displacement = update.displacement(membrane)
        mesh, factor = _apply(mesh, displacement, settings, topology)
        norm = float(np.linalg.norm(displacement, axis=1).mean()) * factor
        moved.append(norm)
        steps.append(RefineStep(update.contour_patches, update.shrink_patches, norm, factor,
                                _nanmean(update.errors)))
        if factor == 0.0:
            break
    after = _Update(mesh, dataset, depth, tilt, settings, comparison, motions=False)
    ce_after = np.array([after.errors[after.comparison.data.names.index(n)]
                         if n in after.comparison.data.names else math.nan for n in views])
    return RefineResult(mesh=mesh, views=views, ce_before=ce_before, ce_after=ce_after,
                        ace_before=_nanmean(ce_before), ace_after=_nanmean(ce_after), steps=tuple(steps),
                        mean_displacement=float(np.mean(moved)), seconds=time.perf_counter() - start)


class _Update:
    """Contours, CE per view and (unless ``motions`` is False) the patch motions of one model."""

    def __init__(self, mesh, dataset, depth, tilt, settings: RefineSettings, comparison: ViewComparison, *,
                 motions: bool = True):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PoseWarning)  # unseen views are simply not used
            self.comparison = comparison.use(mesh, depth, tilt)
        self.mesh, self.settings, self.depth, self.tilt = mesh, settings, depth, tilt
        if not motions:  # CE alone
            self.errors = comparison.contour_errors(depth, tilt)
            return
        data = comparison.data
        contours, shift = comparison.synthetic_contours(depth, tilt)
        self.rot, self.t, self.n_view, self.d_view = (a[0] for a in comparison.view_poses(data.views, np.array([depth]),
                                                                                   np.array([tilt])))
        self.errors = np.full(len(data.views), math.nan)
        self.contour = {}  # (component, view) -> (beams, 2-D motions (beams, 2))
        for c, k, beams, source, goal, result in comparison.align(contours, shift, (0, 1) if settings.mirror else (0,)):
            if c == 0:
                self.errors[k] = result.error
            vectors = result.motions.copy()
            i, j = result.pairs[:, 0], result.pairs[:, 1]
            vectors[i] = goal[j] - source[i]
            self.contour[(c, k)] = (beams, vectors)
        self.motion = np.zeros((len(mesh.faces), 3))
        contour_faces = self._contour_motions()
        shrink_faces = self._overshoot(dataset, contour_faces) if settings.shrink > 0 else np.zeros(0, int)
        self.contour_patches, self.shrink_patches = len(contour_faces), len(shrink_faces)

    # --- contour term ---------------------------------------------------------------------
    def _contour_motions(self) -> np.ndarray:
        """Least-squares 3-D motions of the frontal patches (object and mirror rows jointly);
        fills ``self.motion`` and returns the faces that got one."""
        comparison = self.comparison
        contours = [(c, k, beams, vectors) for (c, k), (beams, vectors) in self.contour.items()]
        component, view, face, vectors = comparison.frontal_motions(self.rot, self.t, self.n_view, self.d_view,
                                                                 contours)
        if not face.size:
            return np.zeros(0, int)
        chosen = np.unique(face)
        row = np.searchsorted(chosen, face)
        n_views = len(comparison.data.views)
        moves = np.zeros((len(chosen), 2, n_views, 2))
        counts = np.zeros((len(chosen), 2, n_views))
        np.add.at(moves, (row, component, view), vectors)
        np.add.at(counts, (row, component, view), 1.0)
        seen = counts > 0
        moves = np.divide(moves, counts[..., None], out=np.zeros_like(moves), where=counts[..., None] > 0)
        centres = self.mesh.vertices[self.mesh.faces[chosen]].mean(axis=1)  # trimesh's triangles_center, of these
        normal, offset = surface_in_reference(comparison.rig, self.depth, self.tilt)
        h = np.eye(3) - 2.0 * np.outer(normal, normal)
        virtual = centres @ h + 2.0 * float(offset) * normal
        jac = []
        for c, points in ((0, centres), (1, virtual)):
            p_view = np.einsum("kvi,vij->kvj", points[:, None, :] - self.t[None], self.rot)
            p_view = np.where(seen[:, c, :, None], p_view, (0.0, 1.0, 0.0))
            surface = None if c == 0 else (self.n_view[None], self.d_view[None])
            j = np.einsum("kvaj,vij->kvai", image_jacobian(p_view, surface=surface), self.rot)
            jac.append(j if c == 0 else j @ h)
        a = np.where(seen[..., None, None], np.stack(jac, axis=1), 0.0).reshape(len(chosen), -1, 3)
        b = np.where(seen[..., None], moves, 0.0).reshape(len(chosen), -1)
        self.motion[chosen] = truncated_lstsq(a, b, self.settings.rcond)[0]
        return chosen

    # --- overshoot term -------------------------------------------------------------------
    def _overshoot(self, dataset, skip: np.ndarray) -> np.ndarray:
        """Inward motions of triangles whose echo lands where the data is dark (module
        docstring, step 4); fills ``self.motion`` except on ``skip``; returns the faces moved.
        The views' direct rays go to the backend in one launch, their double-bounce legs in a
        second; the synthetic views are the layers that the comparison rendered at its (D, β)
        (``ViewComparison.predicted``); each is smoothed only in the rows that its votes read
        (:func:`smoothed_rows`)."""
        comparison, sonar, st = self.comparison, self.comparison.sonar, self.settings
        data = comparison.data
        segmentation = comparison.settings.segment
        sigma = (segmentation.sigma_bins, segmentation.sigma_beams)
        k_theta, k_phi = st.rays
        width = float(np.mean(np.diff(sonar.beam_centres)))
        theta = (sonar.beam_centres[:, None] + ((np.arange(k_theta) + 0.5) / k_theta - 0.5) * width).ravel()
        phi = -sonar.half_elevation + (np.arange(k_phi) + 0.5) / k_phi * sonar.elevation_fov
        th, ph = np.meshgrid(theta, phi, indexing="ij")
        u = np.stack([np.cos(ph) * np.sin(th), np.cos(ph) * np.cos(th), np.sin(ph)], axis=-1).reshape(-1, 3)
        beam_of_ray = np.repeat(np.arange(sonar.beams), k_theta * k_phi)
        n_views = len(data.views)
        directions = np.stack([u @ rot.T for rot in self.rot])  # (V, R, 3), reference frame
        dist, faces = comparison.backend.cast_rays(comparison.mesh, np.repeat(self.t, len(u), axis=0),
                                                directions.reshape(-1, 3))
        dist, faces = dist.astype(np.float64).reshape(n_views, -1), faces.reshape(n_views, -1)
        up = u @ self.n_view.T  # (R, V)
        surface = np.where(up > 0, self.d_view / np.where(up > 0, up, 1.0), np.inf).T  # (V, R): range to the surface
        if st.top_level > 0:
            normal = surface_in_reference(comparison.rig, self.depth, self.tilt)[0]
            top = _double_bounce(comparison.backend, comparison.mesh, directions, self.t, surface, dist, normal,
                                self.mesh.face_normals)
        voting = np.array([comparison.highlight[comparison.views.index(name)].any() for name in data.views])
        if not voting.any():
            return np.zeros(0, int)
        names = tuple(name for name, votes in zip(data.views, voting) if votes)
        dark, last_rows = dataset.derived(("overshoot", names, segmentation), lambda: _stacked(
            [dataset.derived(("overshoot", name, segmentation),
                             lambda: _dark_distance(comparison.highlight[comparison.views.index(name)], sonar))
             for name in names]))
        view, ray = np.nonzero(np.isfinite(dist) & (dist < surface) & voting[:, None])
        families = [(view, dist[view, ray], beam_of_ray[ray], faces[view, ray], None, slice(0, 2), 1.0,
                     slice(1, None))]
        if st.top_level > 0:
            leg_view = np.repeat(np.arange(n_views), [len(rays) for rays, *_ in top])
            rays, ranges, face, cosine = (np.concatenate([legs[i] for legs in top]) for i in range(4))
            keep = voting[leg_view]
            families.append((leg_view[keep], ranges[keep], beam_of_ray[rays[keep]], face[keep], cosine[keep],
                             slice(3, 4), st.top_level, slice(0, 3)))
        local = np.cumsum(voting) - 1  # a voting view's place among the dark maps
        total, votes = _overshoot_votes(comparison.predicted_rows, data.threshold, dark, last_rows, local, families,
                                        sonar, sigma, st, len(self.mesh.faces))
        votes[skip] = 0.0
        chosen = np.flatnonzero(votes > 0)
        self.motion[chosen] = -st.shrink * (total[chosen] / votes[chosen])[:, None] * self.mesh.face_normals[chosen]
        return chosen

    # --- vertex displacements -------------------------------------------------------------
    def displacement(self, membrane: "_Membrane") -> np.ndarray:
        """(Nv, 3) vertex displacements: capped patch motions, area-weighted to the vertices,
        spread and smoothed by the membrane solve (module docstring, step 5)."""
        mesh, st = self.mesh, self.settings
        motion = self.motion
        norm = np.linalg.norm(motion, axis=1)
        motion = motion * np.minimum(1.0, st.max_motion / np.maximum(norm, 1e-300))[:, None]
        moving = norm > 0
        n = len(mesh.vertices)
        area = np.repeat(mesh.area_faces, 3)
        corners = mesh.faces.ravel()
        adjacent = np.bincount(corners, weights=area, minlength=n)
        covered = np.bincount(corners, weights=area * np.repeat(moving, 3), minlength=n)
        target = np.stack([np.bincount(corners, weights=area * np.repeat(motion[:, i], 3), minlength=n)
                           for i in range(3)], axis=1)
        target = np.divide(target, covered[:, None], out=np.zeros_like(target), where=covered[:, None] > 0)
        confidence = np.divide(covered, adjacent, out=np.zeros(n), where=adjacent > 0)
        return membrane.solve(confidence + 1e-9, confidence[:, None] * target)


class _Topology:
    """What refinement needs of one (F, 3) face list of ``n`` vertices, which no update changes
    (module docstring, step 6): its unique (E, 2) ``edges``, whether it is ``watertight``, and
    (on first use) the membrane system's sparsity (``system``), whose one solver a membrane
    holds ``lock`` for while it factors and solves (refinements may run in threads).
    :func:`_topology` remembers them by the faces."""

    def __init__(self, mesh):
        self.lock = threading.Lock()
        self.edges = np.array(mesh.edges_unique, np.int64)
        self.edges.setflags(write=False)
        self.watertight = is_watertight(mesh)
        self.n = len(mesh.vertices)

    @functools.cached_property
    def system(self) -> tuple[object, object, np.ndarray]:
        """(solver, upper, diagonal): the system (diag(w) + λ L) of :class:`_Membrane` has the
        pattern of the graph Laplacian L (:func:`_graph_laplacian`) whatever w and λ, so QDLDL's
        LDLᵀ ``solver`` (``qdldl.Solver``: its AMD fill-reducing order and symbolic
        factorization) is set up once, on L + I; ``upper`` is L's upper triangle (CSC, sorted
        indices), the pattern the solver takes, and ``diagonal`` the positions of its diagonal
        entries in its data, column by column."""
        import qdldl
        from scipy.sparse import triu

        upper = triu(_graph_laplacian(self.edges, self.n), format="csc")
        upper.sort_indices()
        columns = np.repeat(np.arange(self.n), np.diff(upper.indptr))
        diagonal = np.flatnonzero(upper.indices == columns)
        start = upper.copy()
        start.data[diagonal] += 1.0
        solver = qdldl.Solver(start, upper=True)
        for array in (upper.data, upper.indices, upper.indptr, diagonal):
            array.setflags(write=False)  # shared by every solve of this topology
        return solver, upper, diagonal


#: :class:`_Topology` by the digest of the (F, 3) faces (refinement calls on the models of one
#: carving share it; setting up its solver takes ~12 ms on coral-one's 9.5k vertices).
#: The last 8 face lists; one topology, and so one solver and one lock, per face list.
_TOPOLOGIES = Remembered(8)


def _topology(mesh) -> _Topology:
    """The :class:`_Topology` of a trimesh's faces, remembered (``_TOPOLOGIES``)."""
    faces = np.ascontiguousarray(mesh.faces, np.int64)
    key = xxhash.xxh3_128_digest(faces) + len(mesh.vertices).to_bytes(8, "little")
    return _TOPOLOGIES.get(key, lambda: _Topology(mesh))


class _Membrane:
    """The membrane solve of one mesh topology (module docstring, step 5): x (Nv, 3) of
    (diag(w) + λ L) x = b, L the (Nv, Nv) graph Laplacian of the ``topology``
    (:class:`_Topology`), λ = ``smoothing``. The system is symmetric positive definite and
    diagonally dominant, so an LDLᵀ factorization without pivoting is stable: the topology's
    QDLDL solver factors each system anew in the order it found once (4-5 ms on coral-one's
    carved model against SuperLU's 10 ms). The solution agrees with a dense solve to the
    rounding of a backward-stable factorization (tests/test_refine.py)."""

    def __init__(self, topology: _Topology, smoothing: float):
        with topology.lock:  # its set-up is made once
            self.solver, self.upper, self.diagonal = topology.system
        self.lock = topology.lock
        self.data = smoothing * self.upper.data  # λ L, upper triangle, CSC

    def solve(self, weights: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """x for the (Nv,) positive ``weights`` w and the (Nv, 3) ``rhs`` b."""
        from scipy.sparse import csc_matrix

        data = self.data.copy()
        data[self.diagonal] += weights
        system = csc_matrix((data, self.upper.indices, self.upper.indptr), shape=self.upper.shape)
        with self.lock:  # the topology's one solver, factored and solved by one thread at a time
            self.solver.update(system, upper=True)
            return np.stack([self.solver.solve(np.ascontiguousarray(rhs[:, k])) for k in range(rhs.shape[1])],
                            axis=1)


def _double_bounce(backend, mesh, directions: np.ndarray, origins: np.ndarray, surface: np.ndarray,
                  direct: np.ndarray, normal, face_normals: np.ndarray) -> list[tuple]:
    """The double-bounce legs of rays (sonar → surface → triangle): of the (V, R, 3) unit
    ``directions`` from the (V, 3) ``origins``, those that reach the surface (at the (V, R)
    distances ``surface``, inf where never) before any triangle (the (V, R) ``direct``
    distances), reflected there about the surface's unit ``normal`` (3,) and cast against the
    backend ``mesh`` handle in one launch. All in one frame. Returns per view (indices of the
    rays whose leg hits, their ranges: surface + leg (m), the faces hit, |cos| between the leg
    and the face's normal of the (F, 3) ``face_normals``)."""
    normal = np.asarray(normal, np.float64)
    reach = np.isfinite(surface) & (surface > 0) & ~(direct < surface)
    view, ray = np.nonzero(reach)
    incoming = directions[view, ray]
    start = origins[view] + surface[view, ray, None] * incoming
    leg = incoming - 2.0 * (incoming @ normal)[:, None] * normal
    dist, faces = backend.cast_rays(mesh, start, leg)
    hit = np.isfinite(dist)
    view, ray, leg, faces = view[hit], ray[hit], leg[hit], faces[hit]
    ranges = surface[view, ray] + dist[hit].astype(np.float64)
    cosine = np.abs(np.einsum("ij,ij->i", leg, face_normals[faces]))
    bounds = np.searchsorted(view, np.arange(len(directions) + 1))
    return [(ray[a:b], ranges[a:b], faces[a:b], cosine[a:b]) for a, b in zip(bounds[:-1], bounds[1:])]


def _overshoot_votes(read, threshold: np.ndarray, dark: np.ndarray, last_rows: np.ndarray, local: np.ndarray,
                     families: list, sonar, sigma: tuple[float, float], settings: RefineSettings,
                     n_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """(summed gaps (F,), vote counts (F,)) of the overshoot term (module docstring, step 4),
    every view at once. read(start, stop) : image rows [start, stop) of the (V, 4, bins, beams)
    synthetic layers (read once, the rows the votes' smoothing reaches); threshold : (V, bins);
    dark, last_rows : (K, bins, beams), (K, beams) of the voting views (:func:`_dark_distance`),
    view v's at ``local[v]``; families : (view (N,), range m (N,), beam (N,), face (N,), gap
    weight (N,) or None, bright layers, level × threshold, other layers), each in view order. A
    triangle's votes are summed view by view, each view's families in their order."""
    bins = threshold.shape[1]
    placed = []
    for view, ranges, beam, face, weight, *layers in families:
        row = np.rint(sonar.bin_coordinate(ranges)).astype(int)
        inside = (row >= 0) & (row < bins)
        if inside.any():
            placed.append((view[inside], row[inside], beam[inside], face[inside],
                           None if weight is None else weight[inside], *layers))
    if not placed:
        return np.zeros(n_faces), np.zeros(n_faces)
    radius = _smoothing_radius(sigma)
    first = max(min(int(p[1].min()) for p in placed) - radius, 0)
    synthetic = read(first, min(max(int(p[1].max()) for p in placed) + 1 + radius, bins))
    found = []
    for view, row, beam, face, weight, bright_layers, level, other_layers in placed:
        lo, hi = int(row.min()), int(row.max()) + 1  # the rows the votes read
        band = row - lo
        bright = smoothed_rows(synthetic[:, bright_layers], sigma, lo, hi, first=first, bins=bins)[view, band, beam] \
            > level * threshold[view, row]
        other = smoothed_rows(synthetic[:, other_layers], sigma, lo, hi, first=first, bins=bins)[view, band, beam] \
            > settings.corrupt * threshold[view, row]
        gap = dark[local[view], row, beam]
        within = row <= last_rows[local[view], beam]  # not beyond the data (step 4)
        vote = bright & ~other & (gap > settings.tolerance) & within
        if weight is not None:
            gap = gap * weight
        found.append((view[vote], face[vote], gap[vote]))
    view, face, gap = (np.concatenate(parts) for parts in zip(*found))
    order = np.argsort(view, kind="stable")  # view by view; within a view, family by family
    face, gap = face[order], gap[order]
    return np.bincount(face, gap, n_faces), np.bincount(face, minlength=n_faces).astype(np.float64)


def _smoothing_radius(sigma: tuple[float, float]) -> int:
    """Rows that :func:`smoothed_rows`' range pass reaches each side: int(4 σ_range + 0.5)."""
    return int(4.0 * float(sigma[0]) + 0.5)


def smoothed_rows(layers: np.ndarray, sigma: tuple[float, float], lo: int, hi: int, *, first: int = 0,
                  bins: int | None = None) -> np.ndarray:
    """Rows [lo, hi) of ``scipy.ndimage.gaussian_filter(layers.sum(axis=0), sigma)`` (default
    truncate and reflecting border) of each image, bit for bit, from the rows the range
    smoothing reaches, which alone are summed: the filter runs along range, then across beams,
    and a row of the first pass reads only the rows within its radius
    (:func:`_smoothing_radius`; the border is the image's, never the band's). layers : (..., L,
    R, beams), image rows [first, first + R) of images of ``bins`` rows (default first + R),
    holding the rows the smoothing reaches; returns (..., hi − lo, beams)."""
    from scipy import ndimage

    radius = _smoothing_radius(sigma)
    bins = first + layers.shape[-2] if bins is None else bins
    start, stop = max(lo - radius, 0), min(hi + radius, bins)
    summed = layers[..., start - first:stop - first, :].sum(axis=-3)
    sigmas = (0.0,) * (summed.ndim - 2) + tuple(sigma)  # an axis of σ 0 is not filtered
    return ndimage.gaussian_filter(summed, sigmas)[..., lo - start:hi - start, :]


def _graph_laplacian(edges: np.ndarray, n: int):
    """(n, n) sparse graph Laplacian (degree − adjacency, CSR) of the unique (E, 2) edges of a
    mesh of n vertices."""
    from scipy.sparse import coo_matrix, diags

    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    graph = (graph + graph.T).tocsr()
    return diags(np.asarray(graph.sum(axis=1)).ravel()) - graph


def _apply(mesh, displacement: np.ndarray, settings: RefineSettings, topology: _Topology | None = None):
    """The mesh moved by ``step`` × displacement. Where a triangle's normal would turn by more
    than ``max_turn`` (or it degenerates), its vertices are held still, their neighbours
    tapered (:func:`_hold_weights`), and the step is tried again, up to ``holds`` times; then,
    while any still turns too far or the volume reverses, the step is halved (up to
    ``halvings`` times). A triangle that is degenerate before the step is not judged (its
    normal is undefined). A mesh that is not watertight refuses every step (moving vertices keeps the faces,
    so watertightness is judged once). Returns (mesh, factor used), the factor scaled by the
    mean vertex weight, 0 when refused. ``topology`` : the mesh's (:func:`_topology`), if known."""
    import trimesh

    topology = _topology(mesh) if topology is None else topology
    before = mesh.face_normals
    judged = np.linalg.norm(before, axis=1) > 0.5  # a degenerate triangle has no normal to turn
    watertight = topology.watertight
    factor = settings.step
    held = np.zeros(len(mesh.vertices), bool)
    weight = np.ones(len(mesh.vertices))
    for attempt in range(settings.holds + settings.halvings + 1):
        moved = trimesh.Trimesh(mesh.vertices + factor * displacement * weight[:, None], mesh.faces, process=False)
        bad = judged & (np.einsum("ij,ij->i", moved.face_normals, before) <= math.cos(settings.max_turn))
        if not bad.any() and watertight and signed_volume(moved.triangles) > 0:
            return moved, factor * float(weight.mean())
        if attempt < settings.holds:
            held[mesh.faces[bad].ravel()] = True
            weight = _hold_weights(held, topology.edges)
        else:
            factor *= 0.5
    return mesh, 0.0


def _hold_weights(held: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(Nv,) share of the step per vertex: 0 where ``held`` (Nv,) bool, ``HOLD_TAPER[k-1]``
    on the k-th ring of edge (E, 2) neighbours around the held vertices, 1 beyond."""
    weight = np.where(held, 0.0, 1.0)
    ring = held
    for share in HOLD_TAPER:
        touched = np.zeros_like(ring)
        touched[edges[:, 0][ring[edges[:, 1]]]] = True
        touched[edges[:, 1][ring[edges[:, 0]]]] = True
        ring = touched & (weight == 1.0)
        weight[ring] = share
    return weight


def _dark_distance(highlight: np.ndarray, sonar) -> tuple[np.ndarray, np.ndarray]:
    """Of a data view's (bins, beams) highlight mask: every pixel's distance (m) to the nearest
    highlight pixel (range axis in δR, beam axis in arc length at the highlight's median
    range), and :func:`_last_echo_rows`; both read-only."""
    from scipy import ndimage

    width = float(np.mean(np.diff(sonar.beam_centres)))
    rng = float(np.median(sonar.bin_ranges[np.flatnonzero(highlight.any(axis=1))]))
    dark = ndimage.distance_transform_edt(~highlight, sampling=(sonar.range_step, rng * width))
    last_rows = _last_echo_rows(highlight)
    dark.setflags(write=False)
    last_rows.setflags(write=False)
    return dark, last_rows


def _stacked(maps: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """The (K, bins, beams) dark distances and (K, beams) last rows of K views'
    :func:`_dark_distance`, read-only."""
    dark, last_rows = (np.stack(parts) for parts in zip(*maps))
    dark.setflags(write=False)
    last_rows.setflags(write=False)
    return dark, last_rows


def _last_echo_rows(highlight: np.ndarray) -> np.ndarray:
    """(beams,) per beam of a (bins, beams) highlight mask its last highlight row, or the
    image's last row where the beam has none (then every echo in it is unexplained)."""
    bins = highlight.shape[0]
    last = bins - 1 - np.argmax(highlight[::-1], axis=0)
    return np.where(highlight.any(axis=0), last, bins - 1)


def _nanmean(values) -> float:
    values = np.asarray(values, np.float64)
    finite = values[np.isfinite(values)]
    return float(finite.mean()) if finite.size else math.nan
