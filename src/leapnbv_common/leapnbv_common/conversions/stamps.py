"""Stamps: builtin_interfaces/Time <-> nanoseconds, headers, and the ``inputs`` list of a stage output."""
from __future__ import annotations

from typing import Any, List, Protocol, Sequence, Tuple

from std_msgs.msg import Header

from leapnbv_msgs.msg import InputStamp

NS_PER_S = 1_000_000_000


class Stamp(Protocol):
    """What a stamp is to these functions: builtin_interfaces/Time, rosgraph_msgs/Clock's clock, ..."""

    sec: int
    nanosec: int


def stamp_to_ns(stamp: Stamp) -> int:
    """Nanoseconds since the epoch from a builtin_interfaces/Time."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def set_stamp(stamp: Stamp, stamp_ns: int) -> None:
    """Fill a builtin_interfaces/Time in place (``msg.header.stamp``, ``InputStamp.stamp``, ...) from nanoseconds.

    Args:
        stamp: the Time to fill.
        stamp_ns: nanoseconds since the epoch; a negative value gives a negative ``sec`` and
            ``nanosec`` in [0, 1e9) (floor division), as rclpy's Time does.
    """
    stamp.sec, stamp.nanosec = divmod(int(stamp_ns), NS_PER_S)


def ns_to_stamp(stamp_ns: int) -> Any:
    """A new builtin_interfaces/Time of a stamp in nanoseconds (see set_stamp)."""
    stamp = Header().stamp  # std_msgs/Header's own Time: a builtin_interfaces/msg/Time
    set_stamp(stamp, stamp_ns)
    return stamp


def header_with_stamp(stamp_ns: int, frame_id: str) -> Header:
    """A std_msgs/Header for a stamp in nanoseconds."""
    header = Header(frame_id=str(frame_id))
    set_stamp(header.stamp, stamp_ns)
    return header


def input_stamp_msgs(inputs: Sequence[Tuple[Any, ...]]) -> List[InputStamp]:
    """The ``inputs`` field of a stage output: InputStamp messages from (name, stamp_ns[, relation]) tuples.

    ``relation`` is an InputStamp constant (SAME_FRAME when left out).
    """
    out = []
    for item in inputs:
        name, stamp_ns = str(item[0]), int(item[1])
        relation = int(item[2]) if len(item) > 2 else InputStamp.SAME_FRAME
        msg = InputStamp(name=name, relation=relation)
        set_stamp(msg.stamp, stamp_ns)
        out.append(msg)
    return out


def input_stamps(msg: Any) -> List[Tuple[str, int, int]]:
    """(name, stamp ns, relation) of every input a stage output lists (its ``inputs`` field), in order."""
    return [(str(i.name), stamp_to_ns(i.stamp), int(i.relation)) for i in msg.inputs]
