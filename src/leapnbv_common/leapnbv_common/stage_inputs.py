"""Converters for the inputs stages take through :class:`leapnbv_common.stage.Stage`: each checks a
message's contract once, on arrival, and returns what the stage keeps.

The message <-> array conversions themselves live in :mod:`leapnbv_common.conversions`; these only
choose, per input, which of them runs on arrival and what is kept (a serialized image stays a view of
its bytes until a frame uses it).
"""
from __future__ import annotations

from typing import Any, Optional, Sequence

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
from leapnbv_common.mesh_faces import KnownMeshFaces, faces_id_count

__all__ = ["checked_serialized_image", "checked_depth_image", "checked_colour_image", "checked_camera_info",
           "checked_human_mesh", "human_mesh_face_count"]


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


def human_mesh_face_count(msg: Any) -> int:
    """The triangles a HumanMesh has: its own, or those its faces_id states (before they are looked up).

    Raises:
        ContractError: a faces_id that is not an id (``bad_mesh_faces``).
    """
    return len(msg.faces) // 3 if len(msg.faces) or not msg.faces_id else faces_id_count(msg.faces_id)


def checked_human_mesh(msg: Any, known_faces: Optional[KnownMeshFaces] = None) -> HumanMeshArrays:
    """A HumanMesh's arrays, once its size passed the limit (checked on the counts, before the arrays are read).

    known_faces: the triangle sets received on mesh_faces, for a mesh that names its triangles by id.

    Raises:
        ContractError: more than MAX_MESH_VERTICES vertices or MAX_MESH_FACES faces (``mesh_too_large``);
            triangles named by an id not received (``mesh_faces_unknown``).
        ConversionError: a mesh that breaks the HumanMesh contract (human_mesh_to_arrays).
    """
    check_mesh_size("HumanMesh", len(msg.vertices) // 3, human_mesh_face_count(msg))
    return human_mesh_to_arrays(msg, known_faces)
