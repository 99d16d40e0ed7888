"""What planning reads and writes: GroundPlane, TargetGeometry and ViewCandidates <-> arrays."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, List, Optional, Sequence, Tuple

import numpy as np
from std_msgs.msg import Header

from leapnbv_common.contracts import FRAME_ID_MISMATCH, ContractError, check_ground_plane
from leapnbv_common.conversions.base import ConversionError, check_finite_fields, float32_sequence
from leapnbv_common.conversions.geometry import (
    point_msg,
    point_to_numpy,
    pointcloud2_to_xyz,
    pose_msgs,
    poses_to_numpy,
    xyz_to_pointcloud2,
)
from leapnbv_common.conversions.images import camera_info_to_k, make_camera_info
from leapnbv_common.conversions.stamps import input_stamp_msgs
from leapnbv_msgs.msg import GroundPlane, TargetGeometry, ViewCandidates

if TYPE_CHECKING:
    import numpy.typing as npt


# --------------------------------------------------------------------------- GroundPlane


@dataclass
class GroundPlaneArrays:
    """The values of a GroundPlane message: the floor n.x + d = 0 in the camera optical frame.

    ``normal`` (3,) float64 points up (toward the camera side); ``offset`` d is then the camera's
    height above the floor. ``source`` is GroundPlane.SOURCE_RANSAC or SOURCE_CAMERA_POSE;
    ``quality`` is the 0..1 trust figure (leapnbv_geometry.ground.floor_quality).
    """

    normal: npt.NDArray[Any]
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
        check_ground_plane(plane.normal, plane.offset, plane.valid, plane.source,  # type: ignore[arg-type]
                           GROUND_PLANE_SOURCES)  # (contracts types the normal Sequence[float]; any 3-vector works)
    except ContractError as error:
        raise ConversionError(str(error)) from None
    return plane


def arrays_to_ground_plane(plane: GroundPlaneArrays, header: Optional[Header] = None,
                           compute_time_ms: float = 0.0, inputs: Sequence[Tuple[Any, ...]] = ()) -> GroundPlane:
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

    target_points: npt.NDArray[Any]
    background_points: npt.NDArray[Any]
    centroid: npt.NDArray[Any]
    bbox_min: npt.NDArray[Any]
    bbox_max: npt.NDArray[Any]
    mask_pixel_count: int
    visible_fraction: float
    depth_offset: float
    valid: bool
    k: npt.NDArray[Any]
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
    check_finite_fields("TargetGeometry", {
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
                              compute_time_ms: float = 0.0, inputs: Sequence[Tuple[Any, ...]] = ()) -> TargetGeometry:
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

    rotations: npt.NDArray[Any]
    positions: npt.NDArray[Any]
    term_names: List[str]
    term_weights: npt.NDArray[Any]
    term_scores: npt.NDArray[Any]
    score: npt.NDArray[Any]
    feasible: npt.NDArray[Any]
    infeasible_reason: npt.NDArray[Any]
    chosen_index: int
    includes_current_view: bool
    ring_center: npt.NDArray[Any]
    ring_radius: float

    def __len__(self) -> int:
        return int(self.score.shape[0])

    def term(self, name: str) -> npt.NDArray[Any]:
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
                              compute_time_ms: float = 0.0, inputs: Sequence[Tuple[Any, ...]] = ()) -> ViewCandidates:
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
