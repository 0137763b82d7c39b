"""The project's value checks, in one place.

``InputError`` is a user's mistake (a file's field, a command-line option): one line naming
the file, field and value; the command line prints it and exits 2. ``check_*`` raise it
(integers, numbers with a condition, depth (m) and tilt (rad)). ``finite_vectors`` and
``real_array`` check arguments of the Python API and the kernel backends (ValueError /
TypeError naming the argument); ``is_*`` are the predicates they share.
"""

from __future__ import annotations

import math
import numbers
from typing import Any, Callable

import numpy as np

_UNSET = object()


class InputError(ValueError):
    """Bad user input. The command line prints ``str(err)`` as one line and exits 2.

    ``InputError("must be > 0", file="dataset.toml", field="sonar.beams", value=-3)`` reads
    ``dataset.toml: sonar.beams = -3: must be > 0``.
    """

    def __init__(self, message: str, *, file: Any = None, field: str | None = None,
                 value: Any = _UNSET):
        self.message = message
        self.file = None if file is None else str(file)
        self.field = field
        self.value = value
        super().__init__(str(self))

    def with_file(self, file: Any) -> "InputError":
        """The same error, naming ``file`` if it named none."""
        if self.file is not None:
            return self
        return InputError(self.message, file=file, field=self.field, value=self.value)

    def __str__(self) -> str:
        where = []
        if self.file is not None:
            where.append(self.file)
        if self.field is not None:
            where.append(self.field if self.value is _UNSET else f"{self.field} = {_short(self.value)}")
        text = ": ".join(where + [self.message])
        return " ".join(text.split())  # always one line


def is_integer(value: Any) -> bool:
    """An int or NumPy integer, not a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def check_integer(name: str, value: Any, minimum: int) -> None:
    """InputError naming field ``name`` unless ``value`` is an integer >= ``minimum``."""
    if not is_integer(value) or value < minimum:
        raise InputError(f"must be an integer >= {minimum}", field=name, value=value)


def is_number(value: Any) -> bool:
    """An int, float or NumPy real scalar, not a bool."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)


def is_finite_number(value: Any) -> bool:
    """A finite :func:`is_number`."""
    return is_number(value) and math.isfinite(value)


def degrees_shown(angle: float) -> float:
    """``angle`` (rad) in degrees to 12 significant digits: the value as the user typed it,
    without the radian round trip's last digits (95° shows as 95.0)."""
    return float(f"{math.degrees(angle):.12g}")


def check_number(field: str, value: Any, ok: Callable[[float], bool], message: str, *,
                 degrees: bool = False) -> None:
    """InputError naming ``field`` unless ``value`` is a finite number (m, or rad shown in
    degrees with ``degrees``) for which ``ok(value)`` holds (else ``message``)."""
    def shown(v: Any) -> Any:
        return degrees_shown(v) if degrees and is_finite_number(v) else v

    if not is_number(value):
        raise InputError(f"must be a number ({'degrees' if degrees else 'm'})", field=field, value=value)
    if not math.isfinite(value):
        raise InputError("must be finite", field=field, value=shown(value))
    if not ok(value):
        raise InputError(message, field=field, value=shown(value))


def check_depth_tilt(depth: Any, tilt: Any) -> None:
    """InputError (field ``--depth`` or ``--tilt``, the tilt shown in degrees) unless depth (m)
    is a finite number > 0 and tilt (rad) a finite number in (-π/2, π/2)."""
    if not (is_finite_number(depth) and depth > 0):
        raise InputError("must be a finite depth > 0 (m)", field="--depth",
                         value=float(depth) if is_number(depth) else depth)
    if not (is_finite_number(tilt) and abs(tilt) < math.pi / 2):
        raise InputError("must be a finite tilt in (-90, 90) degrees", field="--tilt",
                         value=degrees_shown(tilt) if is_number(tilt) else tilt)


def finite_array(name: str, value: Any, ndim: int) -> np.ndarray:
    """``value`` as a float64 array of ``ndim`` dimensions with finite entries, or InputError
    naming ``name``."""
    array = np.asarray(value, np.float64)
    if array.ndim != ndim:
        raise InputError(f"must have {ndim} dimensions", field=name, value=array.shape)
    if not np.all(np.isfinite(array)):
        raise InputError("must be finite", field=name, value="NaN/inf")
    return array


def finite_vectors(name: str, value: Any, last: int) -> np.ndarray:
    """``value`` as a float64 array of shape (..., last) with finite entries, or ValueError
    naming ``name`` (an argument of the Python API, not a file's field)."""
    array = np.asarray(value, dtype=np.float64)
    if array.ndim < 1 or array.shape[-1] != last:
        raise ValueError(f"{name} must have shape (..., {last}), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} holds non-finite values")
    return array


def real_array(name: str, value: Any, shape: tuple, dtype=np.float32) -> np.ndarray:
    """``value`` as a C-contiguous finite array of ``dtype`` (float32 or float64) and ``shape``
    (a letter = any length), or ValueError / TypeError naming ``name`` (an API argument)."""
    try:
        array = np.asarray(value)
    except (ValueError, TypeError) as err:  # ragged nested lists
        raise ValueError(f"{name} must be an array of shape {_shape_text(shape)}: {err}") from None
    if array.dtype.kind not in "fiu":
        raise TypeError(f"{name} must hold real numbers, got dtype {array.dtype}")
    if array.ndim != len(shape) or any(isinstance(s, int) and s != n for s, n in zip(shape, array.shape)):
        raise ValueError(f"{name} must have shape {_shape_text(shape)}, got {array.shape}")
    with np.errstate(over="ignore"):  # too large for float32: reported as inf below
        array = np.ascontiguousarray(array, dtype=dtype)
    finite = np.isfinite(array)
    if not finite.all():
        bad = np.argwhere(~finite)[0]
        raise ValueError(f"{name} must be finite in {array.dtype.name}, got {array[tuple(bad)]} at index "
                         f"{tuple(int(i) for i in bad)}")
    return array


def _shape_text(shape: tuple) -> str:
    return "(" + ", ".join(str(s) for s in shape) + ")"


def _short(value: Any, limit: int = 60) -> str:
    """repr(value), its middle elided past ``limit`` characters: the end of a long path (the
    file's name) stays readable."""
    text = repr(value)
    head = 20
    return text if len(text) <= limit else text[:head] + "..." + text[head + 3 - limit:]
