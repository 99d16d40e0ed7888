"""Converters for the inputs stages take through :class:`leapnbv_common.stage.Stage`: each checks a
message's contract once, on arrival, and returns what the stage keeps.

The message <-> array conversions themselves live in :mod:`leapnbv_common.conversions`; these only
choose, per input, which of them runs on arrival and what is kept (a serialized image stays a view of
its bytes until a frame uses it).
"""
from __future__ import annotations

from typing import Any, Sequence

from sensor_msgs.msg import CameraInfo

from leapnbv_common.contracts import check_mesh_size
from leapnbv_common.conversions import (
    COLOUR_ENCODINGS,
    DEPTH_ENCODINGS,
    HumanMeshArrays,
    SerializedImage,
    camera_info_to_k,
    check_image,
    human_mesh_to_arrays,
)

__all__ = ["checked_serialized_image", "checked_depth_image", "checked_colour_image", "checked_camera_info",
           "checked_human_mesh"]


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


def checked_human_mesh(msg: Any) -> HumanMeshArrays:
    """A HumanMesh's arrays, once its size passed the limit (checked on the counts, before the arrays are read).

    Raises:
        ContractError: more than MAX_MESH_VERTICES vertices or MAX_MESH_FACES faces (``mesh_too_large``).
        ConversionError: a mesh that breaks the HumanMesh contract (human_mesh_to_arrays).
    """
    check_mesh_size("HumanMesh", len(msg.vertices) // 3, len(msg.faces) // 3)
    return human_mesh_to_arrays(msg)
