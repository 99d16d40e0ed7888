"""The one place where ROS messages become numpy arrays and back.

Every node converts through these functions. They use the fast idioms: a message's byte payload
is filled from ``ndarray.tobytes()`` (or an ``array.array`` for typed sequences) and read with
``np.frombuffer`` (no copy), never through Python lists.
"""
from __future__ import annotations

import array
import struct
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

import numpy as np
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion
from nav_msgs.msg import Path
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
from std_msgs.msg import Header

from leapnbv_common.contracts import (
    FRAME_ID_MISMATCH,
    ContractError,
    check_boxes,
    check_finite,
    check_ground_plane,
    check_intrinsics,
)
from leapnbv_msgs.msg import (
    GroundPlane,
    HumanMesh,
    InputStamp,
    PersonDetection,
    PersonDetections,
    SceneGroundTruth,
    TargetGeometry,
    ViewCandidates,
)


class ConversionError(ContractError):
    """A message cannot be turned into the array it should hold, or breaks its contract
    (:mod:`leapnbv_common.contracts`); the text says what is wrong."""


# encoding -> (numpy dtype, channels)
IMAGE_ENCODINGS = {
    "rgb8": (np.uint8, 3),
    "bgr8": (np.uint8, 3),
    "mono8": (np.uint8, 1),
    "8UC1": (np.uint8, 1),
    "16UC1": (np.uint16, 1),
    "mono16": (np.uint16, 1),
    "32FC1": (np.float32, 1),
}


def image_to_numpy(msg: Image) -> np.ndarray:
    """View an Image's payload as an array, checking encoding, step and size.

    Args:
        msg: sensor_msgs/Image in one of IMAGE_ENCODINGS.

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


def image_to_rgb(msg: Image) -> np.ndarray:
    """(H, W, 3) uint8 RGB from an rgb8, bgr8 or mono8 Image (a copy only when reordering)."""
    image = image_to_numpy(msg)
    if msg.encoding == "rgb8":
        return image
    if msg.encoding == "bgr8":
        return np.ascontiguousarray(image[:, :, ::-1])
    if msg.encoding in ("mono8", "8UC1"):
        return np.repeat(image[:, :, None], 3, axis=2)
    raise ConversionError(f"colour image expected (rgb8, bgr8, mono8), got {msg.encoding!r}")


def depth_to_metres(msg: Image) -> np.ndarray:
    """(H, W) float32 depth in metres from a 16UC1 (millimetres) or 32FC1 (metres) Image.

    Invalid readings (0, NaN, inf, and negative 32FC1 values) become 0.0, the project's "no return"
    value: a depth camera never measures a surface behind itself.
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


def image_size(msg) -> Tuple[int, int]:
    """(width, height) of an Image or CameraInfo."""
    return int(msg.width), int(msg.height)


def numpy_to_image(image: np.ndarray, encoding: str, header: Optional[Header] = None) -> Image:
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


def camera_info_to_k(msg: CameraInfo) -> np.ndarray:
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


def make_camera_info(k: np.ndarray, width: int, height: int, header: Optional[Header] = None) -> CameraInfo:
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


_XYZ_FIELDS = [
    PointField(name="x", offset=0, datatype=PointField.FLOAT32, count=1),
    PointField(name="y", offset=4, datatype=PointField.FLOAT32, count=1),
    PointField(name="z", offset=8, datatype=PointField.FLOAT32, count=1),
]


def xyz_to_pointcloud2(points: np.ndarray, header: Optional[Header] = None) -> PointCloud2:
    """An unorganized PointCloud2 with float32 x, y, z fields from (N, 3) points."""
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    msg = PointCloud2()
    if header is not None:
        msg.header = header
    msg.height, msg.width = 1, int(points.shape[0])
    msg.fields = list(_XYZ_FIELDS)
    msg.is_bigendian = False
    msg.point_step, msg.row_step = 12, 12 * int(points.shape[0])
    msg.is_dense = bool(np.all(np.isfinite(points)))
    msg.data = np.ascontiguousarray(points).tobytes()
    return msg


def pointcloud2_to_xyz(msg: PointCloud2) -> np.ndarray:
    """(N, 3) float32 x, y, z from a PointCloud2 whose x, y, z fields are float32.

    Other fields and padding are skipped; organized clouds are flattened row by row.

    Raises:
        ConversionError: missing or non-float32 x/y/z fields, or a payload of the wrong length.
    """
    offsets = {}
    for field in msg.fields:
        if field.name in ("x", "y", "z"):
            if field.datatype != PointField.FLOAT32:
                raise ConversionError(f"PointCloud2 field {field.name!r} is not FLOAT32")
            offsets[field.name] = int(field.offset)
    if set(offsets) != {"x", "y", "z"}:
        raise ConversionError(f"PointCloud2 needs x, y, z fields, found {[f.name for f in msg.fields]}")
    count = int(msg.width) * int(msg.height)
    step = int(msg.point_step)
    if step < 12 or len(msg.data) < count * step or int(msg.row_step) * int(msg.height) != len(msg.data):
        raise ConversionError(
            f"PointCloud2 of {count} points with point_step {step}, row_step {msg.row_step} "
            f"does not match its {len(msg.data)} bytes"
        )
    if count == 0:
        return np.zeros((0, 3), dtype=np.float32)
    endian = ">" if msg.is_bigendian else "<"
    if step == 12 and (offsets["x"], offsets["y"], offsets["z"]) == (0, 4, 8) and int(msg.height) == 1:
        return np.frombuffer(msg.data, dtype=endian + "f4").reshape(count, 3).astype(np.float32, copy=False)
    rows = np.frombuffer(msg.data, dtype=np.uint8).reshape(int(msg.height), int(msg.row_step))
    records = rows[:, : int(msg.width) * step].reshape(count, step)
    out = np.empty((count, 3), dtype=np.float32)
    for axis, name in enumerate("xyz"):
        o = offsets[name]
        out[:, axis] = np.ascontiguousarray(records[:, o : o + 4]).view(endian + "f4")[:, 0]
    return out


def float32_sequence(values: np.ndarray) -> array.array:
    """An array.array('f') for a float32[] message field (fast, and accepted with field checks on)."""
    return array.array("f", np.ascontiguousarray(values, dtype=np.float32).tobytes())


def uint32_sequence(values: np.ndarray) -> array.array:
    """An array.array('I') for a uint32[] message field."""
    return array.array("I", np.ascontiguousarray(values, dtype=np.uint32).tobytes())


def point_msg(xyz: np.ndarray) -> Point:
    """geometry_msgs/Point from a 3-vector."""
    x, y, z = (float(v) for v in np.asarray(xyz, dtype=np.float64).reshape(3))
    return Point(x=x, y=y, z=z)


def point_to_numpy(point: Point) -> np.ndarray:
    """(3,) float64 from a geometry_msgs/Point."""
    return np.array([point.x, point.y, point.z], dtype=np.float64)


def box_to_detection(box_xyxy_score: np.ndarray) -> PersonDetection:
    """PersonDetection from [x_min, y_min, x_max, y_max, score]."""
    x0, y0, x1, y1, score = (float(v) for v in np.asarray(box_xyxy_score).reshape(5))
    return PersonDetection(x_min=x0, y_min=y0, x_max=x1, y_max=y1, score=score)


def detection_to_box(det: PersonDetection) -> np.ndarray:
    """(5,) float32 [x_min, y_min, x_max, y_max, score] from a PersonDetection."""
    return np.array([det.x_min, det.y_min, det.x_max, det.y_max, det.score], dtype=np.float32)


def detections_to_boxes(msg: PersonDetections) -> np.ndarray:
    """(N, 5) float32 [x_min, y_min, x_max, y_max, score] of a PersonDetections, checked.

    Raises:
        ConversionError: an empty image size, or a detection that is not finite, has a score outside
            [0, 1], an empty or inverted box, or a box outside the image (contracts.check_boxes).
    """
    size = (int(msg.image_width), int(msg.image_height))
    if size[0] <= 0 or size[1] <= 0:
        raise ConversionError(f"PersonDetections image size {size[0]}x{size[1]} is empty")
    boxes = np.array([detection_to_box(d) for d in msg.detections], np.float32).reshape(-1, 5)
    try:
        return check_boxes(boxes, size)
    except ContractError as error:
        raise ConversionError(str(error)) from None


@dataclass
class HumanMeshArrays:
    """The arrays of a HumanMesh message.

    vertices (V, 3) float32 in the virtual crop camera, faces (F, 3) uint32, virtual intrinsics
    (fx, fy, cx, cy), the body parameters as axis-angle, and the camera translation.
    """

    vertices: np.ndarray
    faces: np.ndarray
    virtual_intrinsics: Tuple[float, float, float, float]
    image_size: Tuple[int, int]
    detection: np.ndarray
    processed_box: np.ndarray
    root_pose: np.ndarray
    body_pose: np.ndarray
    left_hand_pose: np.ndarray
    right_hand_pose: np.ndarray
    jaw_pose: np.ndarray
    betas: np.ndarray
    expression: np.ndarray
    cam_translation: np.ndarray
    model_id: str = ""


# SMPL-X body parameters (axis-angle poses, shape, expression) carried by HumanMesh and SceneGroundTruth.
_BODY_PARAM_SIZES = {
    "root_pose": 3,
    "body_pose": 63,
    "left_hand_pose": 45,
    "right_hand_pose": 45,
    "jaw_pose": 3,
    "betas": 10,
    "expression": 10,
}
_MESH_PARAM_SIZES = {"processed_box": 4, **_BODY_PARAM_SIZES, "cam_translation": 3}


def _read_float32_fields(msg, sizes) -> dict:
    """name -> (size,) float32 array of the fixed-size float fields of a message."""
    return {name: np.asarray(getattr(msg, name), dtype=np.float32).reshape(size) for name, size in sizes.items()}


def _check_finite_fields(what: str, fields: dict) -> None:
    """ConversionError naming the first field of ``fields`` (name -> array) with a NaN or inf."""
    for name, values in fields.items():
        try:
            check_finite(f"{what} {name}", values)
        except ContractError as error:
            raise ConversionError(str(error)) from None


def _write_float32_fields(msg, values, sizes) -> None:
    """Set the fixed-size float fields of a message from an object with attributes of the same names."""
    for name, size in sizes.items():
        setattr(msg, name, np.asarray(getattr(values, name), dtype=np.float32).reshape(size))


def human_mesh_to_arrays(msg: HumanMesh) -> HumanMeshArrays:
    """Arrays from a HumanMesh, checking that vertices and faces are consistent.

    Raises:
        ConversionError: vertex or face counts not multiples of 3, a face index out of range,
            non-finite vertices, or non-positive virtual focal lengths.
    """
    vertices = np.frombuffer(msg.vertices, dtype=np.float32) if len(msg.vertices) else np.zeros(0, np.float32)
    faces = np.frombuffer(msg.faces, dtype=np.uint32) if len(msg.faces) else np.zeros(0, np.uint32)
    if vertices.size == 0 or vertices.size % 3:
        raise ConversionError(f"HumanMesh has {vertices.size} vertex floats (need a non-zero multiple of 3)")
    if faces.size == 0 or faces.size % 3:
        raise ConversionError(f"HumanMesh has {faces.size} face indices (need a non-zero multiple of 3)")
    vertices = vertices.reshape(-1, 3)
    faces = faces.reshape(-1, 3)
    if int(faces.max()) >= vertices.shape[0]:
        raise ConversionError(
            f"HumanMesh face index {int(faces.max())} out of range for {vertices.shape[0]} vertices"
        )
    if not np.all(np.isfinite(vertices)):
        raise ConversionError("HumanMesh vertices contain NaN or inf")
    if not (msg.fx > 0 and msg.fy > 0):
        raise ConversionError(f"HumanMesh virtual focal lengths must be positive, got {msg.fx}, {msg.fy}")
    if not np.all(np.isfinite([msg.cx, msg.cy])):
        raise ConversionError(f"HumanMesh virtual principal point is not finite: {msg.cx}, {msg.cy}")
    if msg.image_width <= 0 or msg.image_height <= 0:
        raise ConversionError(f"HumanMesh image size {msg.image_width}x{msg.image_height} is empty")
    params = _read_float32_fields(msg, _MESH_PARAM_SIZES)
    _check_finite_fields("HumanMesh", params)
    if not np.all(np.isfinite(detection_to_box(msg.detection))):
        raise ConversionError("HumanMesh detection box is not finite")
    return HumanMeshArrays(
        vertices=vertices,
        faces=faces,
        virtual_intrinsics=(float(msg.fx), float(msg.fy), float(msg.cx), float(msg.cy)),
        image_size=(int(msg.image_width), int(msg.image_height)),
        detection=detection_to_box(msg.detection),
        model_id=msg.model_id,
        **params,
    )


def arrays_to_human_mesh(mesh: HumanMeshArrays, header: Optional[Header] = None,
                         compute_time_ms: float = 0.0, inputs: Sequence[tuple] = ()) -> HumanMesh:
    """A HumanMesh message from arrays (the inverse of human_mesh_to_arrays); ``inputs``: see input_stamp_msgs."""
    msg = HumanMesh(inputs=input_stamp_msgs(inputs))
    if header is not None:
        msg.header = header
    msg.detection = box_to_detection(mesh.detection)
    msg.vertices = float32_sequence(mesh.vertices)
    msg.faces = uint32_sequence(mesh.faces)
    msg.fx, msg.fy, msg.cx, msg.cy = (float(v) for v in mesh.virtual_intrinsics)
    msg.image_width, msg.image_height = (int(v) for v in mesh.image_size)
    _write_float32_fields(msg, mesh, _MESH_PARAM_SIZES)
    msg.model_id = mesh.model_id
    msg.compute_time_ms = float(compute_time_ms)
    return msg


def stamp_to_ns(stamp) -> int:
    """Nanoseconds since the epoch from a builtin_interfaces/Time."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def rotations_to_quaternions(rotations: np.ndarray) -> np.ndarray:
    """(N, 4) (x, y, z, w) unit quaternions of (N, 3, 3) rotation matrices (Shepperd's method, w >= 0).

    Per matrix the largest of trace, m00, m11, m22 picks the formula whose divisor is far from 0;
    every formula is evaluated on every row (a few vector operations instead of a Python loop per
    pose) and each row keeps its own."""
    m = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    m00, m01, m02 = m[:, 0, 0], m[:, 0, 1], m[:, 0, 2]
    m10, m11, m12 = m[:, 1, 0], m[:, 1, 1], m[:, 1, 2]
    m20, m21, m22 = m[:, 2, 0], m[:, 2, 1], m[:, 2, 2]
    trace = m00 + m11 + m22
    case = np.where(trace > 0, 0, np.where((m00 > m11) & (m00 > m22), 1, np.where(m11 > m22, 2, 3)))
    with np.errstate(invalid="ignore", divide="ignore"):  # the rows a formula is not picked for
        s = 2.0 * np.sqrt(np.stack([trace + 1.0, 1.0 + m00 - m11 - m22, 1.0 + m11 - m00 - m22,
                                    1.0 + m22 - m00 - m11]))
        formulas = np.stack([
            [(m21 - m12) / s[0], (m02 - m20) / s[0], (m10 - m01) / s[0], 0.25 * s[0]],
            [0.25 * s[1], (m01 + m10) / s[1], (m02 + m20) / s[1], (m21 - m12) / s[1]],
            [(m01 + m10) / s[2], 0.25 * s[2], (m12 + m21) / s[2], (m02 - m20) / s[2]],
            [(m02 + m20) / s[3], (m12 + m21) / s[3], 0.25 * s[3], (m10 - m01) / s[3]],
        ])  # (4 formulas, 4 components, N)
    q = formulas[case, :, np.arange(len(m))]
    q /= np.sqrt(np.sum(q * q, axis=1))[:, None]
    return np.where(q[:, 3:4] < 0, -q, q)


def quaternion_to_rotation(xyzw: np.ndarray) -> np.ndarray:
    """3x3 rotation matrix of a (x, y, z, w) quaternion (normalized first)."""
    x, y, z, w = np.asarray(xyzw, dtype=np.float64).reshape(4) / np.linalg.norm(xyzw)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def pose_msg(rotation: np.ndarray, position: np.ndarray) -> Pose:
    """geometry_msgs/Pose from a rotation matrix (columns = the body's axes) and a position."""
    return pose_msgs(np.asarray(rotation).reshape(1, 3, 3), np.asarray(position).reshape(1, 3))[0]


def pose_msgs(rotations: np.ndarray, positions: np.ndarray) -> List[Pose]:
    """geometry_msgs/Pose messages of (N, 3, 3) rotations and (N, 3) positions (the quaternions in one pass)."""
    quaternions = rotations_to_quaternions(rotations).tolist()
    points = np.asarray(positions, dtype=np.float64).reshape(-1, 3).tolist()
    return [Pose(position=Point(x=x, y=y, z=z), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw))
            for (x, y, z), (qx, qy, qz, qw) in zip(points, quaternions)]


def pose_to_numpy(pose: Pose) -> Tuple[np.ndarray, np.ndarray]:
    """(rotation (3, 3), position (3,)) from a geometry_msgs/Pose."""
    q = pose.orientation
    return quaternion_to_rotation([q.x, q.y, q.z, q.w]), point_to_numpy(pose.position)


# --------------------------------------------------------------------------- InputStamp


def input_stamp_msgs(inputs: Sequence[tuple]) -> List[InputStamp]:
    """The ``inputs`` field of a stage output: InputStamp messages from (name, stamp_ns[, relation]) tuples.

    ``relation`` is an InputStamp constant (SAME_FRAME when left out).
    """
    out = []
    for item in inputs:
        name, stamp_ns = str(item[0]), int(item[1])
        relation = int(item[2]) if len(item) > 2 else InputStamp.SAME_FRAME
        msg = InputStamp(name=name, relation=relation)
        msg.stamp.sec, msg.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
        out.append(msg)
    return out


def serialized_header_stamp_ns(cdr: bytes) -> int:
    """The header stamp of a CDR-serialized message that starts with a std_msgs/Header, without
    deserializing it (a node that subscribes ``raw=True`` keeps frames it may never use as bytes).

    Raises:
        ConversionError: fewer than 12 bytes.
    """
    if len(cdr) < 12:
        raise ConversionError(f"serialized message of {len(cdr)} bytes has no header")
    sec, nanosec = struct.unpack_from("<iI" if cdr[1] == 1 else ">iI", cdr, 4)
    return sec * 1_000_000_000 + nanosec


def serialized_image_header(cdr: bytes) -> Tuple[Header, int, int]:
    """(header, height, width) of a CDR-serialized sensor_msgs/Image, without copying its pixels.

    Raises:
        ConversionError: the bytes are too short for an Image header.
    """
    try:
        order = "<" if cdr[1] == 1 else ">"
        sec, nanosec, length = struct.unpack_from(order + "iII", cdr, 4)
        end = 16 + length  # the frame_id string, NUL included
        frame_id = bytes(cdr[16:end - 1]).decode("utf-8") if length else ""
        offset = 4 + ((end - 4 + 3) // 4) * 4  # CDR aligns the uint32s to 4 from the payload start
        height, width = struct.unpack_from(order + "II", cdr, offset)
    except (struct.error, IndexError, UnicodeDecodeError) as exc:
        raise ConversionError(f"serialized Image header unreadable: {exc}") from None
    header = Header(frame_id=frame_id)
    header.stamp.sec, header.stamp.nanosec = sec, nanosec
    return header, int(height), int(width)


class SerializedImage:
    """A CDR-serialized sensor_msgs/Image read in place: its header and fields, ``data`` a view into the
    serialized bytes (no copy). It stands in for the Image wherever only those are read: check_image,
    image_size, image_to_numpy, depth_to_metres, and the duplicate-stamp guard (whose fingerprint covers
    the header and the whole serialized message).

    Raises:
        ConversionError: bytes that do not hold a whole Image.
    """

    def __init__(self, cdr: bytes) -> None:
        self.cdr = cdr
        try:
            order = "<" if cdr[1] == 1 else ">"

            def aligned(pos: int, size: int) -> int:  # CDR aligns from the start of the payload (byte 4)
                return 4 + ((pos - 4 + size - 1) // size) * size

            def string(pos: int) -> Tuple[str, int]:
                (length,) = struct.unpack_from(order + "I", cdr, pos)
                text = bytes(cdr[pos + 4:pos + 4 + max(0, length - 1)]).decode("utf-8")
                return text, pos + 4 + length

            sec, nanosec = struct.unpack_from(order + "iI", cdr, 4)
            frame_id, pos = string(12)
            pos = aligned(pos, 4)
            self.height, self.width = struct.unpack_from(order + "II", cdr, pos)
            self.encoding, pos = string(pos + 8)
            self.is_bigendian = cdr[pos]
            pos = aligned(pos + 1, 4)
            self.step, length = struct.unpack_from(order + "II", cdr, pos)
            pos += 8
        except (struct.error, IndexError, UnicodeDecodeError) as exc:
            raise ConversionError(f"serialized Image unreadable: {exc}") from None
        if pos + length > len(cdr):
            raise ConversionError(f"serialized Image holds {len(cdr) - pos} of its {length} data bytes")
        self.data = memoryview(cdr)[pos:pos + length]
        self.header = Header(frame_id=frame_id)
        self.header.stamp.sec, self.header.stamp.nanosec = sec, nanosec

    @staticmethod
    def get_fields_and_field_types() -> dict:
        return {"header": "std_msgs/Header", "cdr": "sequence<uint8>"}


def input_stamps(msg) -> List[Tuple[str, int, int]]:
    """(name, stamp ns, relation) of every input a stage output lists (its ``inputs`` field), in order."""
    return [(str(i.name), stamp_to_ns(i.stamp), int(i.relation)) for i in msg.inputs]


# --------------------------------------------------------------------------- GroundPlane


@dataclass
class GroundPlaneArrays:
    """The values of a GroundPlane message: the floor n.x + d = 0 in the camera optical frame.

    ``normal`` (3,) float64 points up (toward the camera side); ``offset`` d is then the camera's
    height above the floor. ``source`` is GroundPlane.SOURCE_RANSAC or SOURCE_CAMERA_POSE;
    ``quality`` is the 0..1 trust figure (leapnbv_geometry.ground.floor_quality).
    """

    normal: np.ndarray
    offset: float
    valid: bool
    source: int = GroundPlane.SOURCE_RANSAC
    inlier_count: int = 0
    inlier_ratio: float = 0.0
    quality: float = 0.0


GROUND_PLANE_SOURCES = (GroundPlane.SOURCE_RANSAC, GroundPlane.SOURCE_CAMERA_POSE)


def ground_plane_to_arrays(msg: GroundPlane) -> GroundPlaneArrays:
    """GroundPlaneArrays from a GroundPlane message, checked.

    Raises:
        ConversionError: an unknown source or, for a valid plane, a non-finite or non-unit normal, a
            normal pointing down, or the camera on or below the floor (contracts.check_ground_plane).
    """
    plane = GroundPlaneArrays(
        normal=np.array([msg.normal.x, msg.normal.y, msg.normal.z], dtype=np.float64),
        offset=float(msg.offset), valid=bool(msg.valid), source=int(msg.source),
        inlier_count=int(msg.inlier_count), inlier_ratio=float(msg.inlier_ratio), quality=float(msg.quality))
    try:
        check_ground_plane(plane.normal, plane.offset, plane.valid, plane.source, GROUND_PLANE_SOURCES)
    except ContractError as error:
        raise ConversionError(str(error)) from None
    return plane


def arrays_to_ground_plane(plane: GroundPlaneArrays, header: Optional[Header] = None,
                           compute_time_ms: float = 0.0, inputs: Sequence[tuple] = ()) -> GroundPlane:
    """A GroundPlane message (the inverse of ground_plane_to_arrays); ``inputs``: see input_stamp_msgs."""
    msg = GroundPlane(offset=float(plane.offset), inlier_count=int(plane.inlier_count),
                      inlier_ratio=float(plane.inlier_ratio), valid=bool(plane.valid), source=int(plane.source),
                      quality=float(plane.quality), inputs=input_stamp_msgs(inputs))
    if header is not None:
        msg.header = header
    msg.normal.x, msg.normal.y, msg.normal.z = (float(v) for v in np.asarray(plane.normal).reshape(3))
    msg.compute_time_ms = float(compute_time_ms)
    return msg


# --------------------------------------------------------------------------- TargetGeometry


@dataclass
class TargetGeometryArrays:
    """The values of a TargetGeometry message, all in the camera optical frame of its frame.

    target_points (N, 3) and background_points (M, 3) float32; centroid, bbox_min, bbox_max (3,)
    float64; ``k`` (3, 3) with ``width`` x ``height`` the depth image the points come from.
    """

    target_points: np.ndarray
    background_points: np.ndarray
    centroid: np.ndarray
    bbox_min: np.ndarray
    bbox_max: np.ndarray
    mask_pixel_count: int
    visible_fraction: float
    depth_offset: float
    valid: bool
    k: np.ndarray
    width: int
    height: int


def target_geometry_to_arrays(msg: TargetGeometry) -> TargetGeometryArrays:
    """TargetGeometryArrays from a TargetGeometry message, checked.

    Raises:
        ConversionError: a point cloud or the camera info is malformed, a value is not finite, a valid
            target has no points or an inverted box, or the camera info names another frame
            (reason frame_id_mismatch).
    """
    if msg.camera_info.header.frame_id != msg.header.frame_id:
        raise ConversionError(f"TargetGeometry is in frame {msg.header.frame_id!r} but its camera_info in "
                              f"{msg.camera_info.header.frame_id!r}", FRAME_ID_MISMATCH)
    target = _target_geometry_arrays(msg)
    _check_finite_fields("TargetGeometry", {
        "target_points": target.target_points, "background_points": target.background_points,
        "centroid": target.centroid, "bbox_min": target.bbox_min, "bbox_max": target.bbox_max,
        "depth_offset": target.depth_offset})
    if not 0.0 <= target.visible_fraction <= 1.0:
        raise ConversionError(f"TargetGeometry visible_fraction {target.visible_fraction} is outside [0, 1]")
    if target.valid and target.target_points.shape[0] == 0:
        raise ConversionError("TargetGeometry is marked valid but has no target points")
    if target.valid and not np.all(target.bbox_min <= target.bbox_max):
        raise ConversionError(f"TargetGeometry box is inverted: min {target.bbox_min.tolist()}, "
                              f"max {target.bbox_max.tolist()}")
    return target


def _target_geometry_arrays(msg: TargetGeometry) -> TargetGeometryArrays:
    return TargetGeometryArrays(
        target_points=pointcloud2_to_xyz(msg.target_points),
        background_points=pointcloud2_to_xyz(msg.background_points),
        centroid=point_to_numpy(msg.centroid), bbox_min=point_to_numpy(msg.bbox_min),
        bbox_max=point_to_numpy(msg.bbox_max), mask_pixel_count=int(msg.mask_pixel_count),
        visible_fraction=float(msg.visible_fraction), depth_offset=float(msg.depth_offset), valid=bool(msg.valid),
        k=camera_info_to_k(msg.camera_info), width=int(msg.camera_info.width), height=int(msg.camera_info.height))


def arrays_to_target_geometry(target: TargetGeometryArrays, header: Optional[Header] = None,
                              compute_time_ms: float = 0.0, inputs: Sequence[tuple] = ()) -> TargetGeometry:
    """A TargetGeometry message (the inverse of target_geometry_to_arrays); the camera info gets ``header``;
    ``inputs``: see input_stamp_msgs."""
    msg = TargetGeometry(inputs=input_stamp_msgs(inputs))
    if header is not None:
        msg.header = header
    msg.target_points = xyz_to_pointcloud2(target.target_points, header)
    msg.background_points = xyz_to_pointcloud2(target.background_points, header)
    msg.centroid = point_msg(target.centroid)
    msg.bbox_min = point_msg(target.bbox_min)
    msg.bbox_max = point_msg(target.bbox_max)
    msg.mask_pixel_count = int(target.mask_pixel_count)
    msg.visible_fraction = float(target.visible_fraction)
    msg.depth_offset = float(target.depth_offset)
    msg.valid = bool(target.valid)
    msg.camera_info = make_camera_info(target.k, target.width, target.height, header)
    msg.compute_time_ms = float(compute_time_ms)
    return msg


# --------------------------------------------------------------------------- ViewCandidates


@dataclass
class ViewCandidatesArrays:
    """The values of a ViewCandidates message for C candidates and T score terms.

    rotations (C, 3, 3) and positions (C, 3): candidate camera poses in the observation's optical
    frame; term_scores (C, T) in the order of term_names, term_weights (T,); score (C,);
    feasible (C,) bool; infeasible_reason (C,) uint8; chosen_index (-1: none feasible).
    """

    rotations: np.ndarray
    positions: np.ndarray
    term_names: List[str]
    term_weights: np.ndarray
    term_scores: np.ndarray
    score: np.ndarray
    feasible: np.ndarray
    infeasible_reason: np.ndarray
    chosen_index: int
    includes_current_view: bool
    ring_center: np.ndarray
    ring_radius: float

    def __len__(self) -> int:
        return int(self.score.shape[0])

    def term(self, name: str) -> np.ndarray:
        """(C,) values of one score term.

        Raises:
            KeyError: no term of that name.
        """
        if name not in self.term_names:
            raise KeyError(f"no score term {name!r}; terms are {self.term_names}")
        return self.term_scores[:, self.term_names.index(name)]


def view_candidates_to_arrays(msg: ViewCandidates) -> ViewCandidatesArrays:
    """ViewCandidatesArrays from a ViewCandidates message.

    Raises:
        ConversionError: the per-candidate fields disagree in length with the poses.
    """
    count = len(msg.poses)
    names = [str(name) for name in msg.term_names]
    term_scores = np.asarray(msg.term_scores, dtype=np.float64)
    lengths = {"score": len(msg.score), "feasible": len(msg.feasible), "infeasible_reason": len(msg.infeasible_reason)}
    if any(length != count for length in lengths.values()) or term_scores.size != count * len(names) \
            or len(msg.term_weights) != len(names):
        raise ConversionError(f"ViewCandidates with {count} poses and {len(names)} terms has {lengths}, "
                              f"{term_scores.size} term scores and {len(msg.term_weights)} weights")
    rotations, positions = poses_to_numpy(msg.poses)
    return ViewCandidatesArrays(
        rotations=rotations, positions=positions,
        term_names=names, term_weights=np.asarray(msg.term_weights, dtype=np.float64),
        term_scores=term_scores.reshape(count, len(names)), score=np.asarray(msg.score, dtype=np.float64),
        feasible=np.asarray(msg.feasible, dtype=bool), infeasible_reason=np.asarray(msg.infeasible_reason, np.uint8),
        chosen_index=int(msg.chosen_index), includes_current_view=bool(msg.includes_current_view),
        ring_center=point_to_numpy(msg.ring_center), ring_radius=float(msg.ring_radius))


def arrays_to_view_candidates(views: ViewCandidatesArrays, header: Optional[Header] = None,
                              compute_time_ms: float = 0.0, inputs: Sequence[tuple] = ()) -> ViewCandidates:
    """A ViewCandidates message (the inverse of view_candidates_to_arrays); ``inputs``: see input_stamp_msgs."""
    msg = ViewCandidates(chosen_index=int(views.chosen_index), includes_current_view=bool(views.includes_current_view),
                         ring_center=point_msg(views.ring_center), ring_radius=float(views.ring_radius),
                         inputs=input_stamp_msgs(inputs))
    if header is not None:
        msg.header = header
    msg.poses = pose_msgs(views.rotations, views.positions)
    msg.term_names = [str(name) for name in views.term_names]
    msg.term_weights = float32_sequence(views.term_weights)
    msg.term_scores = float32_sequence(np.asarray(views.term_scores).reshape(-1))
    msg.score = float32_sequence(views.score)
    msg.feasible = [bool(f) for f in views.feasible]
    msg.infeasible_reason = np.asarray(views.infeasible_reason, dtype=np.uint8).tobytes()
    msg.compute_time_ms = float(compute_time_ms)
    return msg


# --------------------------------------------------------------------------- SceneGroundTruth

# The float fields of SceneGroundTruth: the body parameters and the translation in the camera frame.
_GROUND_TRUTH_PARAM_SIZES = {**_BODY_PARAM_SIZES, "translation": 3}


@dataclass
class SceneGroundTruthArrays:
    """The simulator's truth for one frame: the visible person's box (x0, y0, x1, y1, score; all zero
    when no person is visible), the body parameters in the camera frame, and the occlusion share."""

    person_box: np.ndarray
    root_pose: np.ndarray
    body_pose: np.ndarray
    left_hand_pose: np.ndarray
    right_hand_pose: np.ndarray
    jaw_pose: np.ndarray
    betas: np.ndarray
    expression: np.ndarray
    translation: np.ndarray
    occlusion_share: float
    body_model_id: str


def scene_ground_truth_to_arrays(msg: SceneGroundTruth) -> SceneGroundTruthArrays:
    """SceneGroundTruthArrays from a SceneGroundTruth message, checked.

    Raises:
        ConversionError: a value is not finite, the occlusion share is outside [0, 1], or the person box
            is inverted (x_max < x_min or y_max < y_min; an empty box means nobody is visible) or its
            score is outside [0, 1].
    """
    params = _read_float32_fields(msg, _GROUND_TRUTH_PARAM_SIZES)
    truth = SceneGroundTruthArrays(person_box=detection_to_box(msg.person_box),
                                   occlusion_share=float(msg.occlusion_share), body_model_id=str(msg.body_model_id),
                                   **params)
    _check_finite_fields("SceneGroundTruth", {"person_box": truth.person_box,
                                              "occlusion_share": truth.occlusion_share, **params})
    if not 0.0 <= truth.occlusion_share <= 1.0:
        raise ConversionError(f"SceneGroundTruth occlusion_share {truth.occlusion_share} is outside [0, 1]")
    x0, y0, x1, y1, score = (float(v) for v in truth.person_box)
    if x1 < x0 or y1 < y0 or not 0.0 <= score <= 1.0:
        raise ConversionError(f"SceneGroundTruth person_box [{x0}, {y0}, {x1}, {y1}] with score {score} is inverted "
                              "or its score is outside [0, 1] (an empty box means nobody is visible)")
    return truth


def arrays_to_scene_ground_truth(truth: SceneGroundTruthArrays, header: Optional[Header] = None) -> SceneGroundTruth:
    """A SceneGroundTruth message (the inverse of scene_ground_truth_to_arrays)."""
    msg = SceneGroundTruth(person_box=box_to_detection(truth.person_box), body_model_id=str(truth.body_model_id),
                           occlusion_share=float(truth.occlusion_share))
    if header is not None:
        msg.header = header
    _write_float32_fields(msg, truth, _GROUND_TRUTH_PARAM_SIZES)
    return msg


def obstacle_map_to_points(msg: PointCloud2) -> np.ndarray:
    """(N, 3) float32 occupied-voxel centres of an obstacle map, checked: every point finite.

    Raises:
        ConversionError: a malformed cloud or a NaN / inf point (a map with one is corrupt: refused whole).
    """
    points = pointcloud2_to_xyz(msg)
    _check_finite_fields("obstacle map", {"points": points})
    return points


def header_with_stamp(stamp_ns: int, frame_id: str) -> Header:
    """A std_msgs/Header for a stamp in nanoseconds."""
    header = Header(frame_id=str(frame_id))
    header.stamp.sec, header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return header


def poses_to_numpy(poses: Sequence[Pose]) -> Tuple[np.ndarray, np.ndarray]:
    """((N, 3, 3) rotations, (N, 3) positions) from geometry_msgs/Pose messages."""
    pairs = [pose_to_numpy(pose) for pose in poses]
    return (np.array([r for r, _ in pairs], dtype=np.float64).reshape(-1, 3, 3),
            np.array([p for _, p in pairs], dtype=np.float64).reshape(-1, 3))


def path_msg(rotations: np.ndarray, positions: np.ndarray, header: Optional[Header] = None) -> Path:
    """A nav_msgs/Path of (P, 3, 3) rotations and (P, 3) positions, every pose with the path's header."""
    rotations = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if rotations.shape[0] != positions.shape[0]:
        raise ConversionError(f"path: {rotations.shape[0]} rotations for {positions.shape[0]} positions")
    msg = Path()
    if header is not None:
        msg.header = header
    msg.poses = [PoseStamped(header=msg.header, pose=pose) for pose in pose_msgs(rotations, positions)]
    return msg


def path_to_numpy(msg: Path) -> Tuple[np.ndarray, np.ndarray]:
    """((P, 3, 3) rotations, (P, 3) positions) of a nav_msgs/Path (the inverse of path_msg)."""
    return poses_to_numpy([pose.pose for pose in msg.poses])
