"""Atomic outputs: write into a temporary sibling, then rename into place."""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

from .errors import InputError


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (a reader sees the old file or the new one).
    InputError (naming ``path``) where its folder cannot be made or written."""
    path = Path(path)
    try:
        if path.is_dir():
            raise InputError("is a folder; name a file", file=path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as err:
        raise InputError(f"cannot be written: {_blocked(path) or err.strerror}", file=path) from None
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp's 0600 would hide the file from the user's group
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    return path


def json_number(value: float) -> float | None:
    """``value`` as a float for a JSON record, or None where it is not finite (JSON has no
    NaN or infinity: ``json.dumps`` would write a file that readers refuse)."""
    return float(value) if math.isfinite(value) else None


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    return write_bytes(path, text.encode("utf-8"))


def check_output_folder(path: str | os.PathLike, *, marker: str) -> Path:
    """``path`` as a Path if ``output_folder`` can write it: absent under a folder that exists
    or can be made, empty, or an earlier output holding ``marker``; else InputError (field
    --out). Commands call it before their long work, so a wrong --out fails at once. The
    current folder and the folders above it are refused (replacing them would pull the
    folder out from under the shell), as is an existing folder that cannot be moved aside.
    Returns the path with links resolved: ``--out`` a link to a folder writes where it points,
    and the link stays."""
    value = str(path)
    path = Path(os.path.realpath(path))  # a link to a folder: the output goes where it points
    try:
        if Path.cwd().is_relative_to(path):
            raise InputError("is the current folder or holds it; name a new folder for the output",
                             field="--out", value=value)
        if path.exists():
            if not path.is_dir():
                raise InputError("exists and is not a folder", field="--out", value=value)
            if any(path.iterdir()) and not (path / marker).exists():
                raise InputError(f"folder exists and is not an fsswarp output of this command (no {marker}); "
                                 "choose another --out", field="--out", value=value)
            if not os.access(path, os.W_OK | os.X_OK):
                raise InputError("folder exists and is not writable, so it cannot be replaced",
                                 field="--out", value=value)
        blocked = _blocked(path)
    except OSError as err:  # a name too long, a folder on the way that cannot be searched
        raise InputError(f"cannot be used: {err.strerror}", field="--out", value=value) from None
    if blocked:
        raise InputError(f"cannot be created: {blocked}", field="--out", value=value)
    return path


def _umask() -> int:
    """The process's file-mode creation mask (read by setting it and back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _blocked(path: Path) -> str | None:
    """Why ``path`` cannot be created, judged by its nearest existing ancestor (not a folder,
    or not writable, or not searchable), or None."""
    above = path.parent
    try:
        while not above.exists() and above != above.parent:
            above = above.parent
        if not above.is_dir():
            return f"{above} is not a folder"
    except OSError as err:
        return err.strerror
    if not os.access(above, os.W_OK | os.X_OK):
        return f"{above} is not writable"
    return None


@contextlib.contextmanager
def output_folder(path: str | os.PathLike, *, marker: str) -> Iterator[Path]:
    """Yield a temporary folder that becomes ``path`` when the block ends without error.

    An existing ``path`` is replaced only if it holds ``marker`` (a file an earlier run of the
    same command wrote) or is empty; anything else is refused, so user files are never lost
    (:func:`check_output_folder`). On error the temporary folder is removed and ``path`` is
    left as it was.
    """
    value = str(path)
    path = check_output_folder(path, marker=marker)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp's 0700 would hide the output from the user's group
    except OSError as err:
        raise InputError(f"cannot be created: {err.strerror}", field="--out", value=value) from None
    try:
        yield tmp
        if path.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
            try:
                os.replace(path, old / "x")
            except OSError as err:
                old.rmdir()
                raise InputError(f"cannot be replaced: {err.strerror}", field="--out", value=value) from None
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def on_success(stack: contextlib.ExitStack, action) -> None:
    """Call ``action()`` when ``stack`` closes without an error, after the contexts entered on
    it later have closed (e.g. a figure batch waited for its figures): an output finished once
    its parts are done, and never while the stack unwinds from an error."""
    def finish(exc_type, exc, traceback) -> bool:
        if exc_type is None:
            action()
        return False
    stack.push(finish)
