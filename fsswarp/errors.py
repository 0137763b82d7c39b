"""Errors raised for user mistakes: one line naming the file, field and value."""

from __future__ import annotations

import numbers
from typing import Any

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


def _short(value: Any, limit: int = 60) -> str:
    """repr(value), its middle elided past ``limit`` characters: the end of a long path (the
    file's name) stays readable."""
    text = repr(value)
    head = 20
    return text if len(text) <= limit else text[:head] + "..." + text[head + 3 - limit:]
