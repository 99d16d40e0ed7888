"""Points, point clouds, poses and paths: geometry_msgs / sensor_msgs / nav_msgs <-> arrays.

A pose's rotation is a matrix whose columns are the body's axes; the quaternion math is
:mod:`leapnbv_common.rotations`.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Dict, List, Optional, Sequence, Tuple

import numpy as np
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion
from nav_msgs.msg import Path
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from leapnbv_common.conversions.base import ConversionError, check_finite_fields
from leapnbv_common.rotations import quaternion_to_rotation, rotations_to_quaternions

if TYPE_CHECKING:
    import numpy.typing as npt

_XYZ_FIELDS = [
    PointField(name="x", offset=0, datatype=PointField.FLOAT32, count=1),
    PointField(name="y", offset=4, datatype=PointField.FLOAT32, count=1),
    PointField(name="z", offset=8, datatype=PointField.FLOAT32, count=1),
]


def xyz_to_pointcloud2(points: npt.ArrayLike, header: Optional[Header] = None) -> PointCloud2:
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


def pointcloud2_to_xyz(msg: PointCloud2) -> npt.NDArray[np.float32]:
    """(N, 3) float32 x, y, z from a PointCloud2 whose x, y, z fields are float32.

    Other fields and padding are skipped; organized clouds are flattened row by row.

    Raises:
        ConversionError: missing or non-float32 x/y/z fields, or a payload of the wrong length.
    """
    offsets: Dict[str, int] = {}
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


def point_msg(xyz: npt.ArrayLike) -> Point:
    """geometry_msgs/Point from a 3-vector."""
    x, y, z = (float(v) for v in np.asarray(xyz, dtype=np.float64).reshape(3))
    return Point(x=x, y=y, z=z)


def point_to_numpy(point: Point) -> npt.NDArray[np.float64]:
    """(3,) float64 from a geometry_msgs/Point."""
    return np.array([point.x, point.y, point.z], dtype=np.float64)


def obstacle_map_to_points(msg: PointCloud2) -> npt.NDArray[np.float32]:
    """(N, 3) float32 occupied-voxel centres of an obstacle map, checked: every point finite.

    Raises:
        ConversionError: a malformed cloud or a NaN / inf point (a map with one is corrupt: refused whole).
    """
    points = pointcloud2_to_xyz(msg)
    check_finite_fields("obstacle map", {"points": points})
    return points


def pose_msg(rotation: npt.ArrayLike, position: npt.ArrayLike) -> Pose:
    """geometry_msgs/Pose from a rotation matrix (columns = the body's axes) and a position."""
    return pose_msgs(np.asarray(rotation).reshape(1, 3, 3), np.asarray(position).reshape(1, 3))[0]


def pose_msgs(rotations: npt.ArrayLike, positions: npt.ArrayLike) -> List[Pose]:
    """geometry_msgs/Pose messages of (N, 3, 3) rotations and (N, 3) positions (the quaternions in one pass)."""
    quaternions = rotations_to_quaternions(rotations).tolist()
    points = np.asarray(positions, dtype=np.float64).reshape(-1, 3).tolist()
    return [Pose(position=Point(x=x, y=y, z=z), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw))
            for (x, y, z), (qx, qy, qz, qw) in zip(points, quaternions)]


def pose_to_numpy(pose: Pose) -> Tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """(rotation (3, 3), position (3,)) from a geometry_msgs/Pose."""
    q = pose.orientation
    return quaternion_to_rotation([q.x, q.y, q.z, q.w]), point_to_numpy(pose.position)


def poses_to_numpy(poses: Sequence[Pose]) -> Tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """((N, 3, 3) rotations, (N, 3) positions) from geometry_msgs/Pose messages."""
    pairs = [pose_to_numpy(pose) for pose in poses]
    return (np.array([r for r, _ in pairs], dtype=np.float64).reshape(-1, 3, 3),
            np.array([p for _, p in pairs], dtype=np.float64).reshape(-1, 3))


def path_msg(rotations: npt.ArrayLike, positions: npt.ArrayLike, header: Optional[Header] = None) -> Path:
    """A nav_msgs/Path of (P, 3, 3) rotations and (P, 3) positions, every pose with the path's header.

    Raises:
        ConversionError: as many rotations as positions are needed.
    """
    rotations = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if rotations.shape[0] != positions.shape[0]:
        raise ConversionError(f"path: {rotations.shape[0]} rotations for {positions.shape[0]} positions")
    msg = Path()
    if header is not None:
        msg.header = header
    msg.poses = [PoseStamped(header=msg.header, pose=pose) for pose in pose_msgs(rotations, positions)]
    return msg


def path_to_numpy(msg: Path) -> Tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """((P, 3, 3) rotations, (P, 3) positions) of a nav_msgs/Path (the inverse of path_msg)."""
    return poses_to_numpy([pose.pose for pose in msg.poses])
