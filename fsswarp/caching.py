"""Bounded caches that threads may share: :class:`Remembered`.

fsswarp keeps values it finds once by the digest of their inputs (a mesh topology's solver, a
face list's watertightness, summed-area tables of masks, segmentations, Warp's constant
uploads). Shape steps and reconstructions may run in threads of one process (docs/decisions.md,
"Threads"), so each of those caches is one of these: a value is made outside the lock, and two
threads that make one key at once both get the value kept first.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Any


class Remembered:
    """At most ``size`` values by key; the least recently used goes first beyond that."""

    def __init__(self, size: int):
        self.size = size
        self._values: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: Hashable, make: Callable[[], Any]) -> Any:
        """The value kept for ``key``, else ``make()``'s, now kept."""
        with self._lock:
            if key in self._values:
                self._values.move_to_end(key)
                return self._values[key]
        value = make()
        with self._lock:
            value = self._values.setdefault(key, value)  # another thread's, where it was first
            self._values.move_to_end(key)
            while len(self._values) > self.size:
                self._values.popitem(last=False)
        return value

    def clear(self) -> None:
        with self._lock:
            self._values.clear()

    def __len__(self) -> int:
        return len(self._values)
