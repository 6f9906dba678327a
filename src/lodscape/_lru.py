"""One least-recently-used map with a byte count: the streamer's cache and memory stages, the
GPU stage and a tileset's decoded tiles all keep their budgets with it. Not thread-safe: each
owner holds its own lock where it is shared between threads."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterator
from typing import Generic, TypeVar

__all__ = ["ByteLRU"]

K = TypeVar("K")
V = TypeVar("V")


class ByteLRU(Generic[K, V]):
    """Values with their sizes in bytes, least recently used first."""

    def __init__(self) -> None:
        self._items: OrderedDict[K, tuple[V, int]] = OrderedDict()
        self.nbytes = 0

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, key: object) -> bool:
        return key in self._items

    def __iter__(self) -> Iterator[K]:
        """Keys, least recently used first."""
        return iter(self._items)

    def values(self) -> Iterator[V]:
        """Values, least recently used first."""
        return (v for v, _ in self._items.values())

    def get(self, key: K) -> V | None:
        """The value (now the most recently used), or None."""
        item = self._items.get(key)
        if item is None:
            return None
        self._items.move_to_end(key)
        return item[0]

    def peek(self, key: K) -> V | None:
        """The value, leaving the order as it is."""
        item = self._items.get(key)
        return None if item is None else item[0]

    def size(self, key: K) -> int:
        item = self._items.get(key)
        return 0 if item is None else item[1]

    def touch(self, key: K) -> None:
        if key in self._items:
            self._items.move_to_end(key)

    def put(self, key: K, value: V, nbytes: int) -> None:
        """Store (or replace) ``key`` as the most recently used."""
        old = self._items.pop(key, None)
        if old is not None:
            self.nbytes -= old[1]
        self._items[key] = (value, int(nbytes))
        self.nbytes += int(nbytes)

    def pop(self, key: K) -> V | None:
        item = self._items.pop(key, None)
        if item is None:
            return None
        self.nbytes -= item[1]
        return item[0]

    def shrink(self, limit: float, keep: frozenset[K] | set[K] = frozenset()) -> list[tuple[K, V]]:
        """Drop the least recently used entries, except ``keep``, until at most ``limit`` bytes
        are held (or only kept ones are left); returns what was dropped, oldest first."""
        gone: list[tuple[K, V]] = []
        if self.nbytes <= limit:
            return gone
        for key in list(self._items):
            if self.nbytes <= limit:
                break
            if key in keep:
                continue
            value, nbytes = self._items.pop(key)
            self.nbytes -= nbytes
            gone.append((key, value))
        return gone

    def clear(self) -> None:
        self._items.clear()
        self.nbytes = 0
