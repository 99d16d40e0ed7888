"""Converters for the inputs stages take through :class:`leapnbv_common.stage.Stage`: each checks a
message's contract once, on arrival, and returns what the stage keeps.

The message <-> array conversions themselves live in :mod:`leapnbv_common.conversions`; these only
choose, per input, which of them runs on arrival and what is kept (a serialized image stays a view of
its bytes until a frame uses it).
"""
from __future__ import annotations

from typing import Sequence

from sensor_msgs.msg import CameraInfo

from leapnbv_common.conversions import COLOUR_ENCODINGS, DEPTH_ENCODINGS, SerializedImage, camera_info_to_k, check_image

__all__ = ["checked_serialized_image", "checked_depth_image", "checked_colour_image", "checked_camera_info"]


def checked_serialized_image(cdr: bytes, encodings: Sequence[str], what: str) -> SerializedImage:
    """A serialized Image read in place, its encoding, step and payload checked (a view, no conversion).

    Raises:
        ConversionError: malformed bytes, an encoding not in ``encodings``, or a payload of the wrong size.
    """
    image = SerializedImage(cdr)
    check_image(image, encodings, what)
    return image


def checked_depth_image(cdr: bytes) -> SerializedImage:
    """A serialized depth Image (one of DEPTH_ENCODINGS) read in place and checked.

    Raises:
        ConversionError: as checked_serialized_image.
    """
    return checked_serialized_image(cdr, DEPTH_ENCODINGS, "depth")


def checked_colour_image(cdr: bytes) -> SerializedImage:
    """A serialized colour Image (one of COLOUR_ENCODINGS) read in place and checked.

    Raises:
        ConversionError: as checked_serialized_image.
    """
    return checked_serialized_image(cdr, COLOUR_ENCODINGS, "colour")


def checked_camera_info(msg: CameraInfo) -> CameraInfo:
    """The camera_info itself, once its intrinsics passed the contract (finite, positive focal lengths).

    Raises:
        ConversionError: intrinsics that break the contract.
    """
    camera_info_to_k(msg)
    return msg
