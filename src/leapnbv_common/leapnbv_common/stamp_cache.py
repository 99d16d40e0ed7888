"""A small bounded cache of messages keyed by their header stamp, for exact or near matching."""
from __future__ import annotations

from collections import OrderedDict
from typing import Any, Generic, Optional, Tuple, TypeVar
from typing import OrderedDict as OrderedDictType

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
        self._items: OrderedDictType[int, T] = OrderedDict()
        self.evicted = 0

    def __len__(self) -> int:
        return len(self._items)

    def items(self) -> list:
        """(stamp, item) pairs, oldest first (a copy: safe to pop while iterating)."""
        return list(self._items.items())

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


class ExactStampPairer(Generic[T]):
    """Pairs two streams whose messages carry the same stamp, whichever arrives first.

    `add_first` / `add_second` return the completed (first, second) pair, or None while the
    companion has not arrived. Unpaired messages fall out of a bounded cache (counted in
    `unpaired_dropped`), so a stream that stops never grows memory.
    """

    def __init__(self, capacity: int = 10) -> None:
        self._first: StampCache = StampCache(capacity)
        self._second: StampCache = StampCache(capacity)

    @property
    def unpaired_dropped(self) -> int:
        return self._first.evicted + self._second.evicted

    def add_first(self, stamp_ns: int, item: Any) -> Optional[Tuple[Any, Any]]:
        other = self._add(self._first, self._second, stamp_ns, item)
        return None if other is None else (item, other)

    def add_second(self, stamp_ns: int, item: Any) -> Optional[Tuple[Any, Any]]:
        other = self._add(self._second, self._first, stamp_ns, item)
        return None if other is None else (other, item)

    @staticmethod
    def _add(own: StampCache, others: StampCache, stamp_ns: int, item: Any) -> Optional[Any]:
        """The waiting partner of this stamp (taken out of ``others``), else keep ``item`` in ``own``."""
        other = others.pop(stamp_ns)
        if other is None:
            own.put(stamp_ns, item)
        return other


class CompanionWait:
    """Holds frames until a companion message with the same stamp arrives, or a wait expires.

    Used where a stage prefers the companion computed from the same camera frame (the ground
    plane of that frame) so that replays are deterministic, but must not stall when it is late
    or missing: `expire(now_ns)` hands back the frames whose wait ran out, to be served with
    the latest companion instead.
    """

    def __init__(self, wait_ns: int, capacity: int = 10) -> None:
        self.wait_ns = wait_ns
        self._frames: StampCache = StampCache(capacity)
        self._companions: StampCache = StampCache(capacity)
        self.latest_companion: Optional[Any] = None

    def add_frame(self, stamp_ns: int, frame: Any, now_ns: int) -> Optional[Tuple[Any, Any]]:
        """Returns (frame, companion) at once when the companion is already here."""
        companion = self._companions.get_exact(stamp_ns)
        if companion is not None:
            return frame, companion
        if self.wait_ns <= 0:
            return frame, self.latest_companion
        self._frames.put(stamp_ns, (frame, now_ns))
        return None

    def add_companion(self, stamp_ns: int, companion: Any) -> Optional[Tuple[Any, Any]]:
        """Store a companion; returns (frame, companion) when a frame was waiting for it."""
        self._companions.put(stamp_ns, companion)
        self.latest_companion = companion
        waiting = self._frames.pop(stamp_ns)
        return (waiting[0], companion) if waiting is not None else None

    def expire(self, now_ns: int) -> list:
        """(frame, latest companion or None) for every frame that waited longer than wait_ns."""
        expired = []
        for stamp in list(self._frames._items):
            frame, since = self._frames._items[stamp]
            if now_ns - since >= self.wait_ns:
                del self._frames._items[stamp]
                expired.append((frame, self.latest_companion))
        return expired
