"""Sonar image synthesis: object, ghost, mirror and double-bounce mirror layers (DESIGN §3–4).

:func:`render` renders a mesh (trimesh, reference frame) at a rig's poses for (depth m, tilt
rad) and returns ``{view name: (5, bins, beams) float32}``, the layers in the order of
``LAYERS``: object, ghost, mirror, mirror2 and total (= the sum of the four). The kernels run
on a backend (``Backend.render``: kernels/render.cl and its Warp twin);
``tests/oracle_render.py`` is their float64 oracle. :func:`render_views` renders given view
poses, (N, 3, 3) rotations and (N, 3) translations, with the surface planes in the view frames,
(N, 3) unit normals and (N,) offsets in m.

Image formation, per beam b: K_θ × K_φ sub-rays (``RenderSettings.samples``, default
(2, 64)) across the beam's width and the elevation aperture, each of weight 1/(K_θ K_φ). A
sub-ray's first hit at range r with incidence cosine c deposits c^γ (object) at (b, bin(r));
its path via the sea surface deposits r_s · (c · c_in)^(γ/2) as ghost at (b, bin((r + q)/2))
and as mirror at (beam(θ(P')), bin((r + q)/2)), P' the mirror image of the hit and q = |P'|;
a sub-ray that meets the surface first deposits r_s² · c2^γ as mirror2 after its reflected leg.
Defaults γ = 1, r_s = 0.9. Deposits are summed in fixed point (2^24 per unit) with integer
atomics: layers depend neither on the threads' order nor on the sub-rays left out, which reach
neither the mesh's box nor its mirror (``ray_spans``; a GPU finds them itself); views that share a pose
cast their direct legs once (``shared_poses``). docs/method.md gives every step.
:func:`stream_views` renders views in batches, handing each to a consumer on a worker thread.

:func:`add_noise` draws the simulator's noise (Gamma speckle of ``looks``, an exponential
floor at ``background`` of the 99th-percentile echo); :func:`log_compress` maps an image to dB
for figures.
"""

from __future__ import annotations

import queue
import threading
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import xxhash

from .caching import Remembered
from .errors import InputError, check_depth_tilt, finite_array, is_integer
from .rig import Rig
from .sonar import SonarSpec, to_polar
from .surface import COMPONENTS, apparent_returns, view_planes

#: Layers of a rendered view, in array order: the four components, then their sum.
LAYERS = COMPONENTS + ("total",)

#: Watertightness by the digest of the faces it depends on alone (``is_watertight``, for
#: ``check_mesh`` and refinement's ``_apply``): shape refinement makes a new mesh of the same
#: faces at every step (6 ms each for trimesh to
#: judge on coral-one's carved model, a few µs to hash). The last 64 face lists.
_WATERTIGHT = Remembered(64)


class RenderWarning(UserWarning):
    """Something the user should change, though the render went ahead."""


@dataclass(frozen=True)
class RenderSettings:
    """Image-formation settings (DESIGN §4).

    samples : (K_θ, K_φ) sub-rays per beam across its width and the elevation aperture
    gamma : exponent γ of the Lambertian-type echo ``cos^γ``
    surface_reflection : r_s, the sea surface's reflection coefficient per bounce
    """

    samples: tuple[int, int] = (2, 64)
    gamma: float = 1.0
    surface_reflection: float = 0.9

    def __post_init__(self) -> None:
        k = self.samples
        if (len(k) != 2 or any(not is_integer(v) for v in k)
                or not (1 <= k[0] <= 64 and 1 <= k[1] <= 1024)):
            raise InputError("must be two integers K_theta in 1..64 and K_phi in 1..1024",
                             field="samples", value=tuple(k))
        if not (np.isfinite(self.gamma) and 0 < self.gamma <= 10):
            raise InputError("must be in (0, 10]", field="gamma", value=self.gamma)
        if not (np.isfinite(self.surface_reflection) and 0 <= self.surface_reflection <= 1):
            raise InputError("must be in [0, 1]", field="surface_reflection", value=self.surface_reflection)


def check_mesh(mesh, *, name: str = "mesh", judge_watertight: bool = True):
    """``(vertices (Nv, 3) float64, faces (Nf, 3) int64)`` of a trimesh, or InputError if it holds
    no triangles or non-finite vertices; warns (RenderWarning) when it is not watertight (unless
    ``judge_watertight`` is False: a caller that judged these faces already)."""
    vertices = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), np.float64)
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), np.int64)
    if faces.ndim != 2 or faces.shape[0] == 0 or faces.shape[1] != 3:
        raise InputError("holds no triangles", field=name, value=f"{len(faces)} faces")
    if not np.all(np.isfinite(vertices)):
        raise InputError("has non-finite vertices", field=name, value=int((~np.isfinite(vertices)).sum()))
    if judge_watertight and hasattr(type(mesh), "is_watertight") and not is_watertight(mesh):
        warnings.warn(f"{name} is not watertight: ghost and mirror legs may leak through holes; "
                      "close it (e.g. trimesh's fill_holes) or use a closed mesh", RenderWarning, stacklevel=2)
    return vertices, faces


def is_watertight(mesh) -> bool:
    """A trimesh's ``is_watertight``, remembered by the digest of its (Nf, 3) faces (it depends
    on them alone; ``_WATERTIGHT``)."""
    key = xxhash.xxh3_128_digest(np.ascontiguousarray(mesh.faces, np.int64))
    return _WATERTIGHT.get(key, lambda: bool(mesh.is_watertight))


def signed_volume(triangles: np.ndarray) -> float:
    """Signed volume (m³) enclosed by (F, 3, 3) triangles, positive for outward normals (the
    divergence theorem; trimesh's ``volume`` integrates its mass properties, several times
    the work that this sign test needs)."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    return float(np.einsum("ij,ij->", a, np.cross(b, c))) / 6.0


def render_views(mesh, sonar: SonarSpec, rotations, translations, plane_normals, plane_offsets, *,
                 settings: RenderSettings = RenderSettings(), backend=None) -> np.ndarray:
    """Noise-free layers of N views of ``mesh`` (reference frame), in one launch.

    rotations (N, 3, 3), translations (N, 3): poses, ``P_ref = R @ P_view + t``;
    plane_normals (N, 3), plane_offsets (N,): the surface in each view frame (the grid search
    passes one (pose, plane) pair per cell and view). Returns (N, 5, bins, beams) float32 in
    the order of ``LAYERS``. ``backend`` defaults to ``get_backend("auto")``.
    """
    backend, handle, rotations, translations, normals, offsets = _prepared(
        mesh, rotations, translations, plane_normals, plane_offsets, backend)
    layers = backend.render(handle, sonar, rotations, translations, normals, offsets, settings.samples,
                            gamma=settings.gamma, surface_reflection=settings.surface_reflection)
    return with_total(layers)


def stream_views(mesh, sonar: SonarSpec, rotations, translations, plane_normals, plane_offsets,
                 consume: Callable[[int, np.ndarray], None], *, settings: RenderSettings = RenderSettings(),
                 backend=None, batch: int = 256, queued: int = 2) -> None:
    """``render_views`` streamed: the views rendered ``batch`` at a time (``Backend.render_batches``:
    page-locked copies overlapped with the next batch on a GPU) and ``consume(index, layers)``
    called for every view in order, layers its (5, bins, beams) float32 array (the order of
    ``LAYERS``, bit for bit ``render_views``'), on one worker thread fed by a queue of at most
    ``queued`` batches: consuming (noise, encoding, writing to disk) overlaps the rendering of
    the next batches, and rendering waits when the consumer falls ``queued`` batches behind.
    The consumer's first exception is raised here, after the worker stopped."""
    backend, handle, rotations, translations, normals, offsets = _prepared(
        mesh, rotations, translations, plane_normals, plane_offsets, backend)
    batches = backend.render_batches(handle, sonar, rotations, translations, normals, offsets, settings.samples,
                                     gamma=settings.gamma, surface_reflection=settings.surface_reflection,
                                     batch=batch)
    work: queue.Queue = queue.Queue(maxsize=queued)
    failed: list[BaseException] = []

    def worker() -> None:
        while (item := work.get()) is not None:
            start, layers = item
            if not failed:
                try:
                    for k, stack in enumerate(with_total(layers)):
                        consume(start + k, stack)
                except BaseException as err:  # noqa: BLE001 - raised in the caller's thread
                    failed.append(err)

    thread = threading.Thread(target=worker, name="fsswarp-consumer", daemon=True)
    thread.start()
    try:
        for start, layers in batches:
            if failed:
                break
            work.put((start, layers.copy()))  # the staging buffer is the next batch's
    finally:
        batches.close()
        work.put(None)
        thread.join()
    if failed:
        raise failed[0]


def _prepared(mesh, rotations, translations, plane_normals, plane_offsets, backend):
    """(backend, mesh handle, checked poses and planes) of ``render_views`` and ``stream_views``,
    or InputError; ``backend`` None: ``get_backend("auto")``."""
    from .backends import get_backend

    vertices, faces = check_mesh(mesh, name="mesh")
    rotations = finite_array("pose rotations", rotations, 3)
    translations = finite_array("pose translations", translations, 2)
    normals = finite_array("plane normals", plane_normals, 2)
    offsets = finite_array("plane offsets", plane_offsets, 1)
    if np.any(offsets <= 0):
        raise InputError("the sonar must lie below the surface (offset > 0)", field="plane offsets",
                         value=float(offsets.min()))
    backend = backend or get_backend()
    return backend, backend.load_mesh(vertices, faces), rotations, translations, normals, offsets


def rig_poses(rig: Rig, depth: float, tilt: float, names) -> tuple[np.ndarray, ...]:
    """(rotations (N, 3, 3), translations (N, 3), plane normals (N, 3), plane offsets (N,)) of
    the rig's views ``names`` at (depth m, tilt rad): the inputs of ``render_views``."""
    check_depth_tilt(depth, tilt)
    index = [rig.index(name) for name in names]
    return tuple(a[index] for a in view_planes(rig, depth, tilt))


def with_total(layers: np.ndarray) -> np.ndarray:
    """(N, 4, bins, beams) float32 component layers -> (N, 5, bins, beams), their float32 sum
    appended (the order of ``LAYERS``)."""
    return np.concatenate([layers, layers.sum(axis=1, keepdims=True, dtype=np.float32)], axis=1)


def render(mesh, sonar: SonarSpec, rig: Rig, depth: float, tilt: float, *, views=None,
           settings: RenderSettings = RenderSettings(), backend=None) -> dict[str, np.ndarray]:
    """Synthetic views of ``mesh`` (reference frame) at the rig's poses for (depth m, tilt rad).

    views : names to render (default: all). Returns ``{view name: (5, bins, beams) float32}``
    with layers in the order of ``LAYERS``. Warns when the mesh falls outside a view's window.
    """
    names = rig.names if views is None else list(views)
    rot, t, n, d = rig_poses(rig, depth, tilt, names)
    warn_outside_window(mesh, sonar, rot, t, n, d, names)
    images = render_views(mesh, sonar, rot, t, n, d, settings=settings, backend=backend)
    return dict(zip(names, images))


def warn_outside_window(mesh, sonar: SonarSpec, rotations, translations, normals, offsets, names) -> None:
    """Warn (RenderWarning) naming the views where the object or its ghost falls outside the
    range window or the fan, and what to change."""
    points = np.asarray(mesh.vertices, np.float64)
    for name, rot, t, n, d in zip(names, rotations, translations, normals, offsets):
        p = (points - t) @ rot
        rng, theta, phi = to_polar(p)
        seen = sonar.in_window(rng, theta, phi)
        if not seen.any():
            warnings.warn(f"view {name}: the object lies outside the range window, fan or elevation "
                          f"aperture (ranges {rng.min():.2f}-{rng.max():.2f} m, window "
                          f"{sonar.range_min:g}-{sonar.range_max:g} m): move the target or widen the window",
                          RenderWarning, stacklevel=3)
            continue
        ghost_range = apparent_returns(p[seen], n, d)["ghost"][1]
        if ghost_range.max() > sonar.range_max:
            warnings.warn(f"view {name}: ghost returns reach {ghost_range.max():.2f} m, beyond range_max_m = "
                          f"{sonar.range_max:g}: raise range_max_m to see them", RenderWarning, stacklevel=3)


def add_noise(image, rng: np.random.Generator, *, looks: float = 4.0, background: float = 0.05) -> np.ndarray:
    """Seeded speckle and background noise on a (bins, beams) linear image.

    Multiplicative speckle ~ Gamma(looks, 1/looks) (mean 1) and additive background ~
    Exponential with mean ``background`` × the image's 99th percentile of non-zero values.
    Returns float32 ≥ 0 of the same shape."""
    image = np.asarray(image, np.float32)
    nonzero = image[image > 0]
    scale = float(np.percentile(nonzero, 99)) if nonzero.size else 1.0
    speckle = rng.gamma(looks, 1.0 / looks, size=image.shape)
    floor = rng.exponential(background * scale, size=image.shape)
    return (image * speckle + floor).astype(np.float32)


def log_compress(image, *, dynamic_range_db: float = 60.0, peak: float | None = None) -> np.ndarray:
    """DIDSON-style 8-bit log compression of a linear image: ``255·(1 + 20 log10(I/peak)/DR)``,
    clipped to 0..255. ``peak`` defaults to the image maximum. Returns uint8, same shape."""
    image = np.asarray(image, np.float64)
    peak = float(image.max()) if peak is None else float(peak)
    if not peak > 0:
        return np.zeros(image.shape, np.uint8)
    with np.errstate(divide="ignore"):
        db = 20.0 * np.log10(np.maximum(image, 0.0) / peak)
    return np.clip(np.rint(255.0 * (1.0 + db / dynamic_range_db)), 0, 255).astype(np.uint8)
