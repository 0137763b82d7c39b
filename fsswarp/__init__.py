"""fsswarp: forward-scan sonar near the sea surface, on GPUs (NVIDIA Warp) and OpenCL.

The public API, one function per step of the pipeline (docs/method.md maps each to the paper):

    load_dataset(folder)                  a dataset folder -> Dataset
    simulate(scene, out, seed=0)          a scene (file, Manifest or built-in name) -> dataset folder
    carve(dataset, depth, tilt)           space carving -> CarveResult (mesh S0)
    estimate_pose(model, dataset)         depth D and tilt β by the whole-grid search -> PoseResult
    refine_shape(model, dataset, D, β)    shape refinement -> RefineResult
    reconstruct(dataset)                  carve, then alternate pose and shape steps -> ReconstructResult
    enhance(dataset, model, D, β)         ghost removal by LUT -> {view: EnhancedView}
    render(model, sonar, rig, D, β)       synthetic object/ghost/mirror layers -> {view: (5, bins, beams)}
    get_backend(name, device)             the kernel backend ("auto", "warp", "opencl")

Units: metres and radians in Python; degrees only in files and on the command line.
"""

from .backends import get_backend
from .carving import carve
from .dataset import load_dataset, load_scene
from .enhancement import enhance
from .pose import estimate_pose
from .reconstruction import reconstruct
from .refine import refine_shape
from .rendering import render
from .scenes import builtin_scene
from .simulation import simulate
from .system import keep_freed_memory

keep_freed_memory()  # NumPy's large temporaries reuse freed memory (fsswarp/system.py)

__version__ = "0.1.0"
__all__ = ["load_dataset", "load_scene", "builtin_scene", "simulate", "carve", "estimate_pose", "refine_shape",
           "reconstruct", "enhance", "render", "get_backend"]
