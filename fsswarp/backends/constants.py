"""Numeric constants that the kernels of both backends share, each defined once here.

Lengths in metres. The Warp kernels take them as ``wp.constant``; the OpenCL kernels receive
them as kernel arguments (ray lengths) or as ``-D`` build options (``opencl_defines``).
"""

from __future__ import annotations

#: ε (m): a ray leaving a surface starts this far past it (render's mirror2 leg and
#: ``frontal_faces``' reflected ray), and render's leg tests stop this short of their end.
RAY_EPSILON = 1e-4
#: ``frontal_faces``: a mirror patch counts as seen directly from the sonar when the first hit
#: toward it lies within this distance (m) of it.
FRONTAL_VISIBLE = 2e-3
#: "No limit" (m): the longest ray of ``cast_rays`` (its default), of ``frontal_faces`` and of
#: the OpenCL render.
MAX_DISTANCE = 1e6
#: The Warp kernels' bound on a ray (m): Warp's ``cast_rays`` clamps ``max_distance`` to it, and
#: the Warp render uses it as "no limit" where the OpenCL render uses ``MAX_DISTANCE``.
WARP_FAR = 1e30
#: Margin (rad) of the sub-ray spans (``fsswarp.backends.base.ray_spans``, Warp's
#: ``view_spans_kernel``, OpenCL's ``view_spans``) around the azimuths and elevations a mesh
#: covers; the kernels' float32 sub-ray angles round by about 1e-7 rad.
SPAN_MARGIN = 1e-4
#: Indices are clamped to ±2^30 before conversion to int32, so far-away points cannot overflow.
INDEX_LIMIT = 1073741824.0
#: Fixed-point scale of render's integer accumulator: 2^24 = 1.
FIXED_SCALE = 16777216.0
#: Threads per ICP run on a GPU (``Backend.icp_runs``): the first works, the others return, so
#: each run has a warp of its own instead of 32 runs sharing one warp and its divergent loops
#: (the run's iterations, its points' searches and its median's partitioning differ from run
#: to run). One on a CPU device. A run's operations are the same either way.
GPU_ICP_LANES = 32
#: The render's queue of hits (``Backend.hit_queue``): the render kernel queues each sub-ray's
#: hit before the surface, and a second kernel deposits their returns (the object's, and the
#: ghost and mirror after the two legs via the surface), so that the legs fill whole warps
#: (about one sub-ray in four of a warp reaches them) and the first kernel keeps few registers.
#: The queue's slots per thread of a launch: a render whose queue overflows is made again with
#: room for every hit (the same deposits; ``fsswarp.backends.base.hit_queue_size``). On a CPU
#: OpenCL deposits each hit's returns at once (no queue); Warp, one thread there, keeps it.
GPU_HIT_QUEUE = 1 / 4
CPU_HIT_QUEUE = 1 / 2
#: Sub-rays per chunk of a render launch: each view's span of sub-rays (found on the device,
#: Warp's ``view_spans_kernel``, OpenCL's ``view_spans``) is cut into chunks, each chunk knows
#: its view, and a warp's 32 threads take 32 sub-rays of one chunk.
RAY_CHUNK = 64
#: Threads of a GPU's render launch per multiprocessor: each takes every such thread count's
#: sub-ray of the chunks in turn, so none is launched for a sub-ray no view casts (a CPU device
#: launches one per sub-ray, docs/decisions.md).
RENDER_THREADS_PER_UNIT = 2048


def opencl_defines() -> tuple[str, ...]:
    """``-D`` build options that define ``FSS_INDEX_LIMIT``, ``FSS_FIXED`` and ``FSS_SPAN_MARGIN``
    (float literals)."""
    return (f"-DFSS_INDEX_LIMIT={INDEX_LIMIT!r}f", f"-DFSS_FIXED={FIXED_SCALE!r}f",
            f"-DFSS_SPAN_MARGIN={SPAN_MARGIN!r}f")
