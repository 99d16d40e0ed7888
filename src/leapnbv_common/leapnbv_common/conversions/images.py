"""Images and camera infos: sensor_msgs/Image <-> arrays (every encoding the graph uses), CameraInfo <-> K."""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Dict, Optional, Sequence, Tuple

import numpy as np
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from leapnbv_common.contracts import ContractError, check_intrinsics
from leapnbv_common.conversions.base import ConversionError

if TYPE_CHECKING:
    import numpy.typing as npt

# encoding -> (numpy dtype, channels)
IMAGE_ENCODINGS: Dict[str, Tuple[Any, int]] = {
    "rgb8": (np.uint8, 3),
    "bgr8": (np.uint8, 3),
    "mono8": (np.uint8, 1),
    "8UC1": (np.uint8, 1),
    "16UC1": (np.uint16, 1),
    "mono16": (np.uint16, 1),
    "32FC1": (np.float32, 1),
}


def image_to_numpy(msg: Image) -> npt.NDArray[Any]:
    """View an Image's payload as an array, checking encoding, step and size.

    Args:
        msg: sensor_msgs/Image in one of IMAGE_ENCODINGS (or a SerializedImage).

    Returns:
        (H, W) or (H, W, C) array in the message's own channel order and native byte order.
        Read-only when no byte swap was needed (it views the message buffer).

    Raises:
        ConversionError: unknown encoding, zero size, a step that does not fit the width, or a
            payload of the wrong length.
    """
    if msg.encoding not in IMAGE_ENCODINGS:
        raise ConversionError(
            f"unsupported image encoding {msg.encoding!r}; expected one of {sorted(IMAGE_ENCODINGS)}"
        )
    dtype, channels = IMAGE_ENCODINGS[msg.encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height == 0 or width == 0:
        raise ConversionError(f"empty {msg.encoding} image: {width}x{height}")
    itemsize = np.dtype(dtype).itemsize
    row_bytes = width * channels * itemsize
    if step < row_bytes or step % itemsize:
        raise ConversionError(
            f"{msg.encoding} image step {step} does not fit width {width} "
            f"({row_bytes} bytes per row needed)"
        )
    if len(msg.data) != step * height:
        raise ConversionError(
            f"{msg.encoding} image {width}x{height} with step {step} needs {step * height} bytes, "
            f"got {len(msg.data)}"
        )
    wire = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    rows = np.frombuffer(msg.data, dtype=wire).reshape(height, step // itemsize)
    image = rows[:, : width * channels]
    if wire != np.dtype(dtype):
        image = image.astype(dtype)  # byte-swap big-endian data to native order
    return image.reshape(height, width, channels) if channels > 1 else image


def image_to_rgb(msg: Image) -> npt.NDArray[np.uint8]:
    """(H, W, 3) uint8 RGB from an rgb8, bgr8 or mono8 Image (a copy only when reordering).

    Raises:
        ConversionError: another encoding, or a malformed image (see image_to_numpy).
    """
    image = image_to_numpy(msg)
    if msg.encoding == "rgb8":
        return image
    if msg.encoding == "bgr8":
        return np.ascontiguousarray(image[:, :, ::-1])
    if msg.encoding in ("mono8", "8UC1"):
        return np.repeat(image[:, :, None], 3, axis=2)
    raise ConversionError(f"colour image expected (rgb8, bgr8, mono8), got {msg.encoding!r}")


def depth_to_metres(msg: Image) -> npt.NDArray[np.float32]:
    """(H, W) float32 depth in metres from a 16UC1 (millimetres) or 32FC1 (metres) Image.

    Invalid readings (0, NaN, inf, and negative 32FC1 values) become 0.0, the project's "no return"
    value: a depth camera never measures a surface behind itself.

    Raises:
        ConversionError: another encoding, or a malformed image (see image_to_numpy).
    """
    image = image_to_numpy(msg)
    if msg.encoding in ("16UC1", "mono16"):
        return image.astype(np.float32) * np.float32(0.001)
    if msg.encoding == "32FC1":
        depth = np.array(image, dtype=np.float32)
        depth[~(np.isfinite(depth) & (depth > 0.0))] = 0.0
        return depth
    raise ConversionError(f"depth image expected (16UC1 or 32FC1), got {msg.encoding!r}")


DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")
COLOUR_ENCODINGS = ("rgb8", "bgr8", "mono8", "8UC1")


def check_image(msg: Image, encodings: Sequence[str], what: str) -> Tuple[int, int]:
    """Check an Image's encoding, step and payload without converting it (a view); returns (width, height).

    Raises:
        ConversionError: an encoding not in ``encodings`` or a malformed image (see image_to_numpy).
    """
    if msg.encoding not in encodings:
        raise ConversionError(f"{what} image expected ({', '.join(encodings)}), got {msg.encoding!r}")
    image_to_numpy(msg)
    return int(msg.width), int(msg.height)


def image_size(msg: Any) -> Tuple[int, int]:
    """(width, height) of an Image, a SerializedImage or a CameraInfo."""
    return int(msg.width), int(msg.height)


def numpy_to_image(image: npt.ArrayLike, encoding: str, header: Optional[Header] = None) -> Image:
    """Build an Image from an array (native byte order, is_bigendian = 0).

    Raises:
        ConversionError: the array's dtype or channel count does not match the encoding.
    """
    if encoding not in IMAGE_ENCODINGS:
        raise ConversionError(f"unsupported image encoding {encoding!r}")
    dtype, channels = IMAGE_ENCODINGS[encoding]
    image = np.asarray(image)
    shape_ok = image.ndim == 2 if channels == 1 else (image.ndim == 3 and image.shape[2] == channels)
    if image.dtype != dtype or not shape_ok:
        raise ConversionError(
            f"{encoding} needs a {np.dtype(dtype).name} array with {channels} channel(s), "
            f"got {image.dtype.name} {image.shape}"
        )
    msg = Image()
    if header is not None:
        msg.header = header
    msg.height, msg.width = int(image.shape[0]), int(image.shape[1])
    msg.encoding = encoding
    msg.is_bigendian = 0 if np.little_endian else 1
    msg.step = int(image.shape[1] * channels * image.itemsize)
    msg.data = np.ascontiguousarray(image).tobytes()
    return msg


def camera_info_to_k(msg: CameraInfo) -> npt.NDArray[np.float64]:
    """The 3x3 intrinsic matrix of a CameraInfo.

    Raises:
        ConversionError: K is not a valid pinhole matrix (non-finite, non-positive focal lengths), the
            size is empty, or the principal point lies outside the image (contracts.check_intrinsics).
    """
    k = np.asarray(msg.k, dtype=np.float64).reshape(3, 3)
    try:
        check_intrinsics(k, msg.width, msg.height)
    except ContractError as error:
        raise ConversionError(str(error)) from None
    return k


def make_camera_info(k: npt.ArrayLike, width: int, height: int, header: Optional[Header] = None) -> CameraInfo:
    """A CameraInfo for an ideal pinhole camera (no distortion) with intrinsics K."""
    k = np.asarray(k, dtype=np.float64).reshape(3, 3)
    msg = CameraInfo()
    if header is not None:
        msg.header = header
    msg.width, msg.height = int(width), int(height)
    msg.distortion_model = "plumb_bob"
    msg.d = [0.0] * 5
    msg.k = k.ravel().tolist()
    msg.r = np.eye(3).ravel().tolist()
    p = np.zeros((3, 4))
    p[:, :3] = k
    msg.p = p.ravel().tolist()
    return msg
