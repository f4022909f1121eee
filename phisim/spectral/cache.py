"""A small thread-safe least-recently-used cache for FFT plans (bounded, size given per call)."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

V = TypeVar("V")

__all__ = ["LRUCache"]


class LRUCache(Generic[V]):
    """At most ``maxsize`` values, the least recently used evicted first.

    The bound is passed to :meth:`get` (it follows :attr:`phisim.spectral.settings.FFTSettings.plan_cache_size`),
    so a smaller setting shrinks the cache at its next use. An evicted plan stays valid for a caller that
    still holds it; it is freed with its last reference.
    """

    def __init__(self, maxsize: int = 32):
        self.maxsize = int(maxsize)
        self._data: OrderedDict[Hashable, V] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: Hashable, factory: Callable[[], V], maxsize: int | None = None) -> V:
        """The value of ``key``, made by ``factory()`` (under the cache's lock) when missing.

        Args:
            key: Hashable key.
            factory: Makes the value; called at most once per miss.
            maxsize: The bound to keep from now on (default: the current one).
        """
        with self._lock:
            if maxsize is not None:
                self.maxsize = int(maxsize)
            value = self._data.get(key)
            if value is not None:
                self._data.move_to_end(key)
            else:
                value = self._data[key] = factory()
            while len(self._data) > max(self.maxsize, 1):
                self._data.popitem(last=False)
            return value

    def clear(self) -> None:
        """Drop every cached value."""
        with self._lock:
            self._data.clear()

    def keys(self) -> list:
        """The cached keys, least recently used first."""
        with self._lock:
            return list(self._data)

    def __len__(self) -> int:
        return len(self._data)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._data
