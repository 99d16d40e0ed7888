"""Bounded caches of messages keyed by their header stamp, for pairing the inputs of one camera frame.

Nothing here ever pairs a message with a companion of another stamp (beyond an explicit slop), and
nothing here drops a message silently: every item that leaves a cache unused is handed to the
cache's ``on_drop(reason, stamp_ns)`` callback (a node counts it on /diagnostics as
``dropped.<reason>``) and counted in ``evicted`` / ``unpaired_dropped`` / ``superseded``.
"""
from __future__ import annotations

from collections import OrderedDict
from typing import Any, Callable, Generic, List, Optional, Tuple, TypeVar
from typing import OrderedDict as OrderedDictType

T = TypeVar("T")
#: A frame stamped this much before the newest one a stage served means the stamps started over.
STAMP_RESTART_NS = 10_000_000_000
DropCallback = Callable[[str, int], None]


def _ignore_drop(reason: str, stamp_ns: int) -> None:
    """The default on_drop: the counters on the cache object still count."""


class StampCache(Generic[T]):
    """Keeps the last `capacity` items by stamp (nanoseconds); the oldest falls out first.

    Used to pair messages of different topics computed from the same camera frame without
    message_filters: a node caches one stream and looks up the other's stamp.

    Args:
        capacity: Items kept.
        evict_reason: The reason an item evicted beyond capacity is reported under.
        on_drop: Called as ``on_drop(reason, stamp_ns)`` for every item evicted unused (and by
            drop_older_than / clear with their reason).
    """

    def __init__(self, capacity: int = 10, evict_reason: str = "evicted",
                 on_drop: Optional[DropCallback] = None) -> None:
        if capacity < 1:
            raise ValueError(f"StampCache capacity must be >= 1, got {capacity}")
        self.capacity = capacity
        self.evict_reason = evict_reason
        self.on_drop: DropCallback = on_drop or _ignore_drop
        self._items: OrderedDictType[int, T] = OrderedDict()
        self.evicted = 0

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, stamp_ns: int) -> bool:
        return stamp_ns in self._items

    def items(self) -> List[Tuple[int, T]]:
        """(stamp, item) pairs in insertion order, oldest first (a copy: safe to pop while iterating)."""
        return list(self._items.items())

    def put(self, stamp_ns: int, item: T) -> None:
        """Insert (or replace) the item for a stamp, evicting the oldest beyond capacity (reported)."""
        self._items[stamp_ns] = item
        self._items.move_to_end(stamp_ns)
        while len(self._items) > self.capacity:
            stamp, _ = self._items.popitem(last=False)
            self.evicted += 1
            self.on_drop(self.evict_reason, stamp)

    def get_exact(self, stamp_ns: int) -> Optional[T]:
        """The item with exactly this stamp, or None."""
        return self._items.get(stamp_ns)

    def newest(self) -> Optional[Tuple[int, T]]:
        """The (stamp, item) with the largest stamp, or None when empty."""
        if not self._items:
            return None
        stamp = max(self._items)
        return stamp, self._items[stamp]

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
        """Remove and return the item for a stamp, or None (taken for use: not reported as dropped)."""
        return self._items.pop(stamp_ns, None)

    def drop_older_than(self, stamp_ns: int, reason: Optional[str] = None) -> int:
        """Drop every item stamped before stamp_ns; each is reported as ``reason`` when given.

        Returns:
            How many were dropped.
        """
        old = [s for s in self._items if s < stamp_ns]
        for s in old:
            del self._items[s]
            if reason is not None:
                self.on_drop(reason, s)
        return len(old)

    def clear(self, reason: Optional[str] = None) -> int:
        """Drop everything (reported as ``reason`` when given); returns how many."""
        stamps = list(self._items)
        self._items.clear()
        if reason is not None:
            for s in stamps:
                self.on_drop(reason, s)
        return len(stamps)


class ExactStampPairer(Generic[T]):
    """Pairs two streams whose messages carry the same stamp, whichever arrives first.

    `add_first` / `add_second` return the completed (first, second) pair, or None while the
    companion has not arrived. Unpaired messages fall out of a bounded cache (counted in
    `unpaired_dropped` and reported to ``on_drop`` as ``<first_name>_unpaired`` /
    ``<second_name>_unpaired``), so a stream that stops never grows memory.
    """

    def __init__(self, capacity: int = 10, first_name: str = "first", second_name: str = "second",
                 on_drop: Optional[DropCallback] = None) -> None:
        self.names = (first_name, second_name)
        self._first: StampCache[Any] = StampCache(capacity, first_name + "_unpaired", on_drop)
        self._second: StampCache[Any] = StampCache(capacity, second_name + "_unpaired", on_drop)

    @property
    def unpaired_dropped(self) -> int:
        return self._first.evicted + self._second.evicted

    def add_first(self, stamp_ns: int, item: Any) -> Optional[Tuple[Any, Any]]:
        other = self._add(self._first, self._second, stamp_ns, item)
        return None if other is None else (item, other)

    def add_second(self, stamp_ns: int, item: Any) -> Optional[Tuple[Any, Any]]:
        other = self._add(self._second, self._first, stamp_ns, item)
        return None if other is None else (other, item)

    def drop_older_than(self, stamp_ns: int) -> int:
        """Drop the unpaired messages of both streams stamped before stamp_ns (a newer frame was paired:
        they can only be older frames now); each reported as ``<name>_superseded``. Returns how many."""
        return (self._first.drop_older_than(stamp_ns, self.names[0] + "_superseded")
                + self._second.drop_older_than(stamp_ns, self.names[1] + "_superseded"))

    @staticmethod
    def _add(own: StampCache[Any], others: StampCache[Any], stamp_ns: int, item: Any) -> Optional[Any]:
        """The waiting partner of this stamp (taken out of ``others``), else keep ``item`` in ``own``."""
        other = others.pop(stamp_ns)
        if other is None:
            own.put(stamp_ns, item)
        return other


class CompanionWait:
    """Holds a frame until the companion message of the same stamp arrives, for a bounded time.

    Used where a stage needs a companion computed from the same camera frame (the ground plane of
    that frame). It never hands over a companion of another stamp: a frame whose companion did not
    come within ``wait_ns`` is handed back alone by :meth:`expire`, and the node decides (drop it
    and count it, or serve it from what it has and record that in the output's inputs).

    Frames come out in stamp order, never an older one after a newer one: when a frame is served,
    the older frames still waiting are dropped (reported as ``<frame_name>_superseded``); a frame
    not newer than the newest one served is refused (``<frame_name>_older_than_served`` /
    ``<frame_name>_duplicate``). At most ``capacity`` frames wait (the oldest is dropped:
    ``<frame_name>_evicted``). Companions are kept in a bounded cache by stamp (reported as
    ``<companion_name>_evicted`` when they fall out).

    Args:
        wait_ns: How long a frame waits for its companion.
        capacity: Companions kept, and frames waiting.
        frame_name, companion_name: Names of the two streams in the drop reasons.
        on_drop: ``on_drop(reason, stamp_ns)`` for each frame or companion dropped unused.
        restart_ns: A frame this much older than the newest served one means the stamps started over
            (a replay from its start, a simulator reset): the waiting frames are forgotten and it is
            served as new.
    """

    def __init__(self, wait_ns: int, capacity: int = 10, frame_name: str = "frame", companion_name: str = "companion",
                 on_drop: Optional[DropCallback] = None, restart_ns: int = STAMP_RESTART_NS) -> None:
        self.wait_ns = wait_ns
        self.restart_ns = restart_ns
        self.restarts = 0
        self.on_drop: DropCallback = on_drop or _ignore_drop
        self.frame_name = frame_name
        self._frames: StampCache[Any] = StampCache(capacity, frame_name + "_evicted", self._report)
        self._companions: StampCache[Any] = StampCache(capacity, companion_name + "_evicted", self._report)
        self.served_stamp: Optional[int] = None  # newest frame stamp handed out (paired or expired)

    def _report(self, reason: str, stamp_ns: int) -> None:
        self.on_drop(reason, stamp_ns)

    @property
    def companions(self) -> StampCache[Any]:
        """The companion cache (by stamp), e.g. to look for an older companion to carry into a frame."""
        return self._companions

    def waiting(self) -> List[int]:
        """Stamps of the frames waiting now, oldest first."""
        return sorted(stamp for stamp, _ in self._frames.items())

    def _serve(self, stamp_ns: int) -> None:
        """A frame of this stamp goes out: older waiting frames can no longer be the newest result."""
        self._frames.drop_older_than(stamp_ns, self.frame_name + "_superseded")
        if self.served_stamp is None or stamp_ns > self.served_stamp:
            self.served_stamp = stamp_ns

    def add_frame(self, stamp_ns: int, frame: Any, now_ns: int) -> Optional[Tuple[Any, Any]]:
        """Returns (frame, companion) at once when the companion is already here, else the frame waits
        (with wait_ns <= 0 it does not: (frame, None) comes back at once).

        A frame not newer than the newest one served is refused (reported) and None is returned.
        """
        if self.served_stamp is not None and self.served_stamp - stamp_ns >= self.restart_ns:
            self.reset()
            self.restarts += 1
        if self.served_stamp is not None and stamp_ns <= self.served_stamp:
            self.on_drop(self.frame_name + ("_duplicate" if stamp_ns == self.served_stamp else "_older_than_served"),
                         stamp_ns)
            return None
        companion = self._companions.get_exact(stamp_ns)
        if companion is not None:
            self._frames.pop(stamp_ns)
            self._serve(stamp_ns)
            return frame, companion
        if self.wait_ns <= 0:  # no waiting: the frame comes back at once, alone
            self._frames.pop(stamp_ns)
            self._serve(stamp_ns)
            return frame, None
        self._frames.put(stamp_ns, (frame, now_ns))
        return None

    def add_companion(self, stamp_ns: int, companion: Any) -> Optional[Tuple[Any, Any]]:
        """Store a companion; returns (frame, companion) when a frame of its stamp was waiting."""
        self._companions.put(stamp_ns, companion)
        waiting = self._frames.pop(stamp_ns)
        if waiting is None:
            return None
        self._serve(stamp_ns)
        return waiting[0], companion

    def expire(self, now_ns: int) -> List[Tuple[int, Any]]:
        """(stamp, frame) of every frame that waited wait_ns or longer for its companion, oldest first.

        They leave the wait (the node counts what it does with them).
        """
        expired = []
        for stamp in self.waiting():
            item = self._frames.get_exact(stamp)
            if item is not None and now_ns - item[1] >= self.wait_ns:
                self._frames.pop(stamp)
                self._serve(stamp)
                expired.append((stamp, item[0]))
        return expired

    def reset(self) -> None:
        """Forget the served stamp and the frames waiting (the stamps jumped back: a replay restarted).

        The companions stay: the new run's first ones may have arrived before its first frame.
        """
        self._frames.clear(self.frame_name + "_reset")
        self.served_stamp = None
