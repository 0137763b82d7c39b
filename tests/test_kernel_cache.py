"""``fsswarp info``'s kernel-cache lines (fsswarp/backends/cache.py) on the CPU backends: cold
on fresh cache folders, without compiling anything itself; warm where a synthesis compiled or
built the kernels; cold again when the driver's cache is gone, even where its folder is made
anew with the same inode; ``info --warm-up`` compiles the Warp modules that the cache lacks
(and says that OpenCL built its programs with the backend). Every step runs in a child process
whose caches all lie in one temporary folder (``families.cache_environment``)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys

import pytest

from fsswarp.benchmark.families import cache_environment

from conftest import backend_for

SYNTHESIS = """
import sys
from fsswarp.backends import get_backend
from fsswarp.benchmark.families import coral_batch
sonar, mesh, rot, t, n, d = coral_batch(1)
backend = get_backend(sys.argv[1], sys.argv[2])
backend.render(backend.load_mesh(mesh.vertices, mesh.faces), sonar, rot, t, n, d, (1, 4), gamma=1.0,
               surface_reflection=0.9)
"""


def child(env: dict, *args: str) -> str:
    done = subprocess.run([sys.executable, *args], env=env, capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr
    return done.stdout


def cache_line(text: str, backend: str, device: str) -> str:
    """The state ("warm", "partly warm", "cold", "unknown") and reason on info's kernel-cache
    line for a backend and device."""
    lines = text.split("\nkernel cache", 1)[1].splitlines()
    line = next(line for line in lines if line.startswith(f"  - {backend} ") and f" {device}: " in line)
    return line.split(f" {device}: ", 1)[1]


@pytest.fixture()
def caches(tmp_path) -> dict:
    return dict(os.environ, **cache_environment(tmp_path))


def test_warp_cache_cold_then_render_compiled_then_warmed_up(caches, tmp_path, wp_device):
    """On the CPU and on CUDA, where the render module's launches ask 128 threads per block
    (``RAY_BLOCK``, not Warp's default): the check looks for the variant that was built; ``info
    --warm-up`` then compiles the modules still missing, in the variants the check (and so each
    launch) looks for, and a second warm-up compiles none."""
    line = cache_line(child(caches, "-m", "fsswarp", "info"), "warp", wp_device)
    assert line.startswith(f"cold (no module compiled for {wp_device} in "), line
    assert not any((tmp_path / "warp").rglob("*.meta")), "info compiled a Warp module"
    child(caches, "-c", SYNTHESIS, "warp", wp_device)
    line = cache_line(child(caches, "-m", "fsswarp", "info"), "warp", wp_device)
    assert line.startswith("partly warm (render compiled, project, carve, raycast, closest, pose, icp not"), line
    built = [p.parent for p in (tmp_path / "warp").rglob("*.meta")]
    assert [p.name.rsplit("_", 1)[0] for p in built] == ["wp_fsswarp.backends.warp.render"]
    warm = ["--backend", "warp", "--device", wp_device, "info", "--warm-up"]
    first = child(caches, "-m", "fsswarp", *warm)
    assert f"warm-up of warp on {wp_device}: compiled project, carve, raycast, closest, pose, icp in " in first
    assert cache_line(first, "warp", wp_device).startswith("warm (all 7 modules compiled for "), first
    assert len(list((tmp_path / "warp").rglob("*.meta"))) == 7
    second = child(caches, "-m", "fsswarp", *warm)
    assert f"warm-up of warp on {wp_device}: every module loaded from the cache in " in second
    # the check names the module folder Warp wrote: remove it and the module reads missing again
    shutil.rmtree(built[0])
    line = cache_line(child(caches, "-m", "fsswarp", "info"), "warp", wp_device)
    assert line.startswith("partly warm (project, carve, raycast, closest, pose, icp compiled, render not"), line


def test_opencl_warm_up_says_its_programs_were_built_with_the_backend(caches):
    device = backend_for("opencl-cpu").device
    text = child(caches, "-m", "fsswarp", "--backend", "opencl", "--device", "pocl", "info", "--warm-up")
    assert f"warm-up of opencl on {device}: its programs built (or loaded from the driver's cache) as the backend " \
           "was made, in " in text
    assert cache_line(text, "opencl", device).startswith("warm ("), text


def test_pocl_cache_cold_then_warm_then_cold_without_the_driver_cache(caches, tmp_path):
    device = backend_for("opencl-cpu").device
    line = cache_line(child(caches, "-m", "fsswarp", "info"), "opencl", device)
    assert line.startswith("cold (project.cl, carve.cl, raycast.cl, render.cl, pose.cl"), line
    assert not any((tmp_path / "xdg" / "fsswarp").rglob("*")), "info built fsswarp's programs"
    child(caches, "-c", SYNTHESIS, "opencl", device)
    line = cache_line(child(caches, "-m", "fsswarp", "info"), "opencl", device)
    assert re.match(r"warm \(\d programs built for this device and driver in the driver's cache ", line), line
    assert str(tmp_path / "pocl") in line
    assert [p.name for p in (tmp_path / "pocl").glob("*fsswarp-cache-id*")] == ["fsswarp-cache-id"]
    # PoCL's binaries gone, the folder made anew (PoCL does so at its start; the file system
    # may give it the same inode): the records alone do not make it warm
    shutil.rmtree(tmp_path / "pocl")
    (tmp_path / "pocl").mkdir()
    assert cache_line(child(caches, "-m", "fsswarp", "info"), "opencl", device).startswith("cold"), line
