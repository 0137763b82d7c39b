"""Records of fsswarp's OpenCL builds, for ``fsswarp info`` (``cache.opencl_cache``): each
build writes a file named by pyopencl's cache key (device, driver, options, source) holding
the driver's cache folder and the token of the marker file fsswarp keeps in that folder
(``programs.program`` writes them)."""

from __future__ import annotations

import os
import secrets
from pathlib import Path

#: The marker file fsswarp keeps in a driver's cache folder: a random token that names this
#: folder's lifetime (a folder removed and made anew, by the driver itself at its start, has
#: none; its inode alone is no proof: file systems reuse inodes at once).
MARKER = "fsswarp-cache-id"


def cache_home() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")


def build_key(device, options: tuple[str, ...], source: str) -> str:
    """pyopencl's cache key of ``source`` built with ``options`` for ``device`` (its platform,
    device and driver versions, pyopencl's version)."""
    from pyopencl.cache import get_cache_key

    return get_cache_key(device, " ".join(options).encode(), source)


def records() -> Path:
    return cache_home() / "fsswarp" / "opencl"


def record_build(devices, options: tuple[str, ...], source: str) -> None:
    """Note that ``source`` was built with ``options`` for ``devices`` (``opencl_cache``): the
    record holds the driver's cache folder and its marker's token, so that a cache folder
    removed since (and made anew) reads cold. A folder that cannot be written, or a driver that
    keeps no cache folder, is passed over (no record: cold)."""
    try:
        folder = records()
        folder.mkdir(parents=True, exist_ok=True)
        for device in devices:
            _mark(device)
            identity = driver_identity(device)
            if identity != "-":
                (folder / build_key(device, options, source)).write_text(identity)
    except OSError:
        pass


def driver_identity(device) -> str:
    """"<folder> <token>" of the device's driver cache as it is now, the token its marker's
    ("-" where no cache is kept or no marker is found)."""
    where = _kept_cache(device)
    try:
        return "-" if where is None else f"{where} {(where / MARKER).read_text().strip()}"
    except OSError:
        return "-"


def _mark(device) -> None:
    """Write a fresh marker into the device's driver cache folder where it has none."""
    where = _kept_cache(device)
    if where is None or (where / MARKER).is_file():
        return
    draft = where / f".{MARKER}.{os.getpid()}"
    draft.write_text(secrets.token_hex(16))
    try:
        os.link(draft, where / MARKER)  # atomic, and never over a marker another process wrote
    except FileExistsError:
        pass
    finally:
        draft.unlink()


def _kept_cache(device) -> Path | None:
    """The device's driver cache folder where the driver keeps one and it exists, else None."""
    where, off = driver_cache(device)
    return None if where is None or off or not where.is_dir() else where


def driver_cache(device) -> tuple[Path | None, str]:
    """(the folder where the driver of ``device`` (a pyopencl Device) caches binaries, None
    for pyopencl's own cache; why it is off, else "")."""
    platform = device.platform.name.lower()
    if "portable computing language" in platform or "pocl" in platform:
        if os.environ.get("POCL_KERNEL_CACHE", "1") == "0":
            return None, "PoCL's kernel cache is off (POCL_KERNEL_CACHE=0)"
        return Path(os.environ.get("POCL_CACHE_DIR") or cache_home() / "pocl" / "kcache"), ""
    from pyopencl.characterize import nv_compute_capability

    if nv_compute_capability(device) is not None:
        if os.environ.get("CUDA_CACHE_DISABLE", "0") == "1":
            return None, "NVIDIA's JIT cache is off (CUDA_CACHE_DISABLE=1)"
        return Path(os.environ.get("CUDA_CACHE_PATH") or Path.home() / ".nv" / "ComputeCache"), ""
    return None, ""
