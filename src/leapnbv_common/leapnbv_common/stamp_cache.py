"""A small bounded cache of messages keyed by their header stamp, for exact or near matching."""
from __future__ import annotations

from collections import OrderedDict
from typing import Any, Generic, Optional, Tuple, TypeVar

T = TypeVar("T")


class StampCache(Generic[T]):
    """Keeps the last `capacity` items by stamp (nanoseconds); the oldest falls out first.

    Used to pair messages of different topics computed from the same camera frame without
    message_filters: a node caches one stream and looks up the other's stamp.
    """

    def __init__(self, capacity: int = 10) -> None:
        if capacity < 1:
            raise ValueError(f"StampCache capacity must be >= 1, got {capacity}")
        self.capacity = capacity
        self._items: OrderedDict[int, T] = OrderedDict()
        self.evicted = 0

    def __len__(self) -> int:
        return len(self._items)

    def put(self, stamp_ns: int, item: T) -> None:
        """Insert (or replace) the item for a stamp, evicting the oldest beyond capacity."""
        self._items[stamp_ns] = item
        self._items.move_to_end(stamp_ns)
        while len(self._items) > self.capacity:
            self._items.popitem(last=False)
            self.evicted += 1

    def get_exact(self, stamp_ns: int) -> Optional[T]:
        """The item with exactly this stamp, or None."""
        return self._items.get(stamp_ns)

    def find_nearest(self, stamp_ns: int, slop_ns: int) -> Optional[Tuple[int, T]]:
        """The (stamp, item) closest to stamp_ns within +-slop_ns, or None. Ties go to the earlier."""
        best: Optional[Tuple[int, Any]] = None
        best_gap = slop_ns + 1
        for stamp, item in self._items.items():
            gap = abs(stamp - stamp_ns)
            if gap < best_gap or (gap == best_gap and best is not None and stamp < best[0]):
                best, best_gap = (stamp, item), gap
        return best

    def pop(self, stamp_ns: int) -> Optional[T]:
        """Remove and return the item for a stamp, or None."""
        return self._items.pop(stamp_ns, None)

    def drop_older_than(self, stamp_ns: int) -> int:
        """Drop every item stamped before stamp_ns; returns how many were dropped."""
        old = [s for s in self._items if s < stamp_ns]
        for s in old:
            del self._items[s]
        return len(old)
