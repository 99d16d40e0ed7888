"""nbv_node's inputs beside the target: the frame's floor, the obstacle map, the metric body mesh.

:class:`FrameFloor` gives a frame the ground plane of its own stamp, else the newest valid plane of an
older frame (at most ``ground_max_age_s`` older) carried into it by the camera-pose delta
(:func:`leapnbv_planner.floor_carry.carry_plane`), else nothing (counted: no goal). Never "the
latest plane of any stamp". :class:`ObstacleMapInput` keeps the robot's latched map of static
obstacles (voxel centres in a fixed frame) and says whether a frame can use it: only with a camera
pose of its stamp in the map's frame.
"""
from __future__ import annotations

import dataclasses
from typing import Any, List, Optional, Set, Tuple

import numpy as np
from sensor_msgs.msg import PointCloud2

from leapnbv_common import topics
from leapnbv_common.array_types import Float32Array, FloatArray, IntArray
from leapnbv_common.camera_pose import CameraPoseSource, StampedCameraPose
from leapnbv_common.contracts import ContractError, check_same_frame, refused
from leapnbv_common.conversions import GroundPlaneArrays, TargetGeometryArrays, obstacle_map_to_points, stamp_to_ns
from leapnbv_common.diagnostics import rejects_bad_input
from leapnbv_common.mesh_faces import KnownMeshFaces
from leapnbv_common.qos import latched_map_qos
from leapnbv_common.stage import Frame
from leapnbv_common.stage_inputs import checked_human_mesh
from leapnbv_msgs.msg import HumanMesh, InputStamp
from leapnbv_planner.floor_carry import carry_plane
from leapnbv_planner.obstacle_map import VoxelObstacleMap, voxel_map_from_centres
from leapnbv_planner.obstacle_memory import ObstacleMemory, ObstacleMemoryParams, frame_obstacle_points

__all__ = ["body_mesh_arrays", "FrameFloor", "ObstacleMapInput"]

#: A floor to plan on and the inputs (name, stamp ns[, relation]) it stands for.
Floor = Tuple[GroundPlaneArrays, List[tuple]]


def body_mesh_arrays(msg: HumanMesh, known_faces: Optional[KnownMeshFaces] = None) -> Tuple[FloatArray, IntArray]:
    """(vertices (V, 3) float64, faces (F, 3)) of a metric body mesh, checked (what BODY_MESH terms read).

    known_faces: the triangle sets received on mesh_faces, for a mesh that names its triangles by id.

    Raises:
        ContractError: a mesh above MAX_MESH_VERTICES / MAX_MESH_FACES (``mesh_too_large``), triangles named by an
            id not received (``mesh_faces_unknown``), or one that breaks the HumanMesh contract.
    """
    mesh = checked_human_mesh(msg, known_faces)
    faces: IntArray = mesh.faces.reshape(-1, 3)
    return mesh.vertices.astype(np.float64), faces


class FrameFloor:
    """The floor a frame is planned on (see the module docstring).

    Args:
        node: The nbv node (its ``stage``, ``params.value``, ``diagnostics``).
        camera_poses: The node's camera-pose source.
    """

    def __init__(self, node: Any, camera_poses: CameraPoseSource) -> None:
        self.node = node
        self.camera_poses = camera_poses

    def __call__(self, frame: Frame) -> Optional[Floor]:
        """The frame's own valid plane, else an older one carried into it; None (counted): the frame gets no goal."""
        diagnostics = self.node.diagnostics
        ground = frame.received("ground_plane")
        if ground is not None and refused(diagnostics, "bad_target", check_same_frame, "target_geometry",
                                          frame.header.frame_id, "ground_plane", ground.frame_id):
            return None
        if ground is not None and ground.value.valid:
            return ground.value, [("ground_plane", ground.stamp_ns, InputStamp.SAME_FRAME)]
        carried = self.carried(frame)
        if carried is None:
            if ground is None:
                diagnostics.reject("ground_plane_late", "no ground plane of this frame in time and none to"
                                   " carry by the camera pose: frame dropped, no goal")
            else:
                diagnostics.reject("no_ground_plane", "no valid ground plane for this frame: no goal published")
        return carried

    def carried(self, frame: Frame) -> Optional[Floor]:
        """An older frame's plane moved into this frame, and the inputs it stands for; None when there is none.

        The newest valid plane at most ground_max_age_s older whose camera pose is known, carried by the
        camera-pose delta between the two stamps.
        """
        p = self.node.params.value
        frame_stamp = frame.stamp_ns
        self.node.stage.pull()
        pose_to = self.camera_poses.pose_at(frame_stamp, frame.header.frame_id)
        if pose_to is None or p.ground_max_age_s <= 0:
            return None
        for stamp, plane in sorted(self.node.stage.caches["ground_plane"].items(), key=lambda item: -item[0]):
            if stamp >= frame_stamp or not plane.value.valid:
                continue
            if frame_stamp - stamp > p.ground_max_age_s * 1e9:
                break
            pose_from = self.camera_poses.pose_at(stamp, plane.frame_id)
            if pose_from is None or pose_from.frame_id != pose_to.frame_id:
                continue
            arrays = dataclasses.replace(plane.value)
            arrays.normal, arrays.offset = carry_plane(arrays.normal, arrays.offset, pose_from, pose_to)
            return arrays, [("ground_plane", stamp, InputStamp.CARRIED), ("camera_pose", stamp, InputStamp.CARRIED),
                            ("camera_pose", frame_stamp, InputStamp.SAME_FRAME)]
        return None


class ObstacleMapInput:
    """The robot's map of static obstacles (PointCloud2 of occupied voxel centres, latched), optional.

    Args:
        node: The nbv node (its ``params.value``, ``diagnostics``, logger).
    """

    def __init__(self, node: Any) -> None:
        self.node = node
        self.diagnostics = node.diagnostics
        self.get_logger = node.get_logger  # rejects_bad_input logs through it
        self.map: Optional[VoxelObstacleMap] = None
        self.points: Optional[Float32Array] = None
        self.frame_id = ""
        self.stamp_ns = 0

    def subscribe(self) -> None:
        """Subscribe to the map (activate; the base class destroys the subscription on deactivate)."""
        self.node.create_subscription(PointCloud2, topics.OBSTACLE_MAP, self.on_message, latched_map_qos())

    @rejects_bad_input("bad_obstacle_map")
    def on_message(self, msg: PointCloud2) -> None:
        # Counted before any work: a map too large is refused whole and the previous one stays in use.
        if refused(self.diagnostics, "obstacle_map_too_large", check_map_size, int(msg.width) * int(msg.height),
                   int(self.node.params.value.max_obstacle_voxels), self.map):
            return
        points = obstacle_map_to_points(msg)  # a map with a NaN point is refused whole (the previous one stays)
        self.map = voxel_map_from_centres(points, self.node.params.value.obstacle_map_resolution)
        self.points = points
        self.frame_id = msg.header.frame_id
        self.stamp_ns = stamp_to_ns(msg.header.stamp)
        self.node.get_logger().info(f"obstacle map: {self.map.voxel_count} voxels in frame {msg.header.frame_id!r}")

    def rebuild(self, resolution: float) -> None:
        """The map again on a new voxel size.

        Raises:
            ObstacleMapError: a grid too large (a ValueError: the parameter change is refused).
        """
        if self.points is not None:
            self.map = voxel_map_from_centres(self.points, resolution)
            self.node.get_logger().info(f"obstacle map rebuilt: {self.map.voxel_count} voxels of {resolution} m")

    def in_use(self) -> bool:
        return self.map is not None and bool(self.node.params.value.use_obstacle_map)

    def camera_pose_for(self, frame: Frame, source: Any = None) -> Tuple[Optional[StampedCameraPose], str]:
        """(the frame's camera pose in the map's frame, or None; why the frame is planned without the map, or "").

        Without a usable pose the frame is planned without the map, counted (``no_camera_pose``: missing, or
        refused by the camera-pose ``source``, which says why when it has ``refusal_at``; ``camera_pose_frame``)
        and said (``counted.planned_without.obstacle_map``, the rejection's detail, goal_status).
        """
        if not self.in_use():
            return None, ""
        pose: Optional[StampedCameraPose] = frame["camera_pose"]
        refusal_at = getattr(source, "refusal_at", None)
        refusal = refusal_at(frame.stamp_ns) if pose is None and refusal_at is not None else None
        if pose is None:
            reason, why = "no_camera_pose", (f"the camera pose of this frame was refused ({refusal})" if refusal
                                             else "no camera pose with this frame's stamp came")
        elif pose.frame_id != self.frame_id:
            reason, why = "camera_pose_frame", (f"the camera pose is in frame {pose.frame_id!r}, the obstacle map in"
                                                f" {self.frame_id!r}")
        else:
            return pose, ""
        self.diagnostics.reject(reason, why + ": planned without the obstacle map")
        self.diagnostics.count("planned_without.obstacle_map")
        return None, why


class ObstacleMemoryInput:
    """The obstacle memory (parameter ``obstacle_memory``): a map built from the frames, while no map is in use.

    Each planned frame's background points (the target geometry's, the person left out) go into a
    :class:`~leapnbv_planner.obstacle_memory.ObstacleMemory` in the camera pose's fixed frame, and its occupied
    voxels are the map that frame is planned with. A frame without its camera pose is planned without the memory
    (counted ``planned_without.obstacle_memory``, said on goal_status) and not taken in. The memory is forgotten
    when the parameter goes off, its voxel size or limits change, or a frame's stamp goes back (a replay started
    over); a new fixed frame starts it over.

    Args:
        node: The nbv node (``params.value``, ``diagnostics``, ``obstacle_map``).
    """

    def __init__(self, node: Any) -> None:
        self.node = node
        self.memory: Optional[ObstacleMemory] = None

    def in_use(self) -> bool:
        return bool(self.node.params.value.obstacle_memory) and not self.node.obstacle_map.in_use()

    def forget(self) -> None:
        self.memory = None

    def params_changed(self, changed: Set[str]) -> None:
        if changed & {"obstacle_memory", "obstacle_map_resolution", "obstacle_memory_half_life_s",
                      "obstacle_memory_max_voxels"}:
            self.forget()

    def voxel_count(self) -> int:
        return 0 if self.memory is None else len(self.memory)

    def take(self, frame: Frame, target: TargetGeometryArrays
             ) -> Tuple[Optional[StampedCameraPose], Optional[VoxelObstacleMap], str]:
        """(the frame's camera pose, the memory's map with this frame in it, ""), or (None, None, why not)."""
        p = self.node.params.value
        pose: Optional[StampedCameraPose] = frame["camera_pose"]
        if pose is None:
            why = "no camera pose with this frame's stamp came"
            self.node.diagnostics.count("planned_without.obstacle_memory")
            return None, None, why
        if self.memory is None or (self.memory.stamp_ns is not None and frame.stamp_ns < self.memory.stamp_ns):
            self.memory = ObstacleMemory(ObstacleMemoryParams(
                resolution=p.obstacle_map_resolution, half_life_s=p.obstacle_memory_half_life_s,
                max_voxels=p.obstacle_memory_max_voxels))
        points, distances = frame_obstacle_points(target.background_points, target.target_points, pose.rotation,
                                                  pose.position, p.obstacle_map_resolution)
        self.memory.add_points(points, distances, frame.stamp_ns, pose.frame_id)
        return pose, voxel_map_from_centres(self.memory.occupied_centres(), p.obstacle_map_resolution), ""


def check_map_size(count: int, limit: int, previous: Optional[VoxelObstacleMap]) -> None:
    """An obstacle map of at most ``limit`` voxel centres (ContractError ``obstacle_map_too_large``)."""
    if count > limit:
        kept = f"the previous map ({previous.voxel_count} voxels) stays in use" if previous is not None else \
            "planned without a map until a smaller one comes"
        raise ContractError(f"obstacle map of {count} voxels is larger than max_obstacle_voxels ({limit}): {kept}",
                            "obstacle_map_too_large")
