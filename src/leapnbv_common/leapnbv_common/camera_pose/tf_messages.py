"""TF messages (tf2_msgs/TFMessage of geometry_msgs/TransformStamped) <-> the ROS-free transforms of tf_buffer.

The one place where a published link becomes a :class:`~leapnbv_common.tf_buffer.StampedTransform` and
back: the TF camera-pose source reads /tf and /tf_static through it, the simulator publishes its
robot's frames through it.
"""
from __future__ import annotations

from typing import List, Sequence

import numpy as np
from geometry_msgs.msg import Quaternion, TransformStamped, Vector3
from tf2_msgs.msg import TFMessage

from leapnbv_common.conversions import ConversionError, header_with_stamp, stamp_to_ns
from leapnbv_common.tf_buffer import StampedTransform, Transform

__all__ = ["transform_from_msg", "transform_msg", "tf_message"]


def transform_from_msg(msg: TransformStamped) -> StampedTransform:
    """A checked StampedTransform from a TransformStamped (parent = header.frame_id, child = child_frame_id).

    Raises:
        ConversionError: a quaternion that is not unit length (or NaN: refused, never normalized
            from garbage), a non-finite translation, or a missing frame name.
    """
    q, t = msg.transform.rotation, msg.transform.translation
    try:
        transform = Transform.checked([q.x, q.y, q.z, q.w], [t.x, t.y, t.z])
    except ValueError as error:
        raise ConversionError(f"transform {msg.header.frame_id!r} -> {msg.child_frame_id!r}: {error}") from None
    if not msg.header.frame_id or not msg.child_frame_id:
        raise ConversionError(f"transform needs both frames, got {msg.header.frame_id!r} -> {msg.child_frame_id!r}")
    return StampedTransform(str(msg.header.frame_id), str(msg.child_frame_id), stamp_to_ns(msg.header.stamp),
                            transform)


def transform_msg(link: StampedTransform) -> TransformStamped:
    """The TransformStamped of a link (what /tf and /tf_static carry)."""
    x, y, z, w = (float(v) for v in np.asarray(link.transform.rotation, dtype=np.float64).reshape(4))
    tx, ty, tz = (float(v) for v in np.asarray(link.transform.translation, dtype=np.float64).reshape(3))
    msg = TransformStamped(header=header_with_stamp(link.stamp_ns, link.parent), child_frame_id=link.child)
    msg.transform.translation = Vector3(x=tx, y=ty, z=tz)
    msg.transform.rotation = Quaternion(x=x, y=y, z=z, w=w)
    return msg


def tf_message(links: Sequence[StampedTransform]) -> TFMessage:
    """One TFMessage carrying every link (the way a broadcaster sends the links it has at once)."""
    transforms: List[TransformStamped] = [transform_msg(link) for link in links]
    return TFMessage(transforms=transforms)
