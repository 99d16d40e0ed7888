"""nbv_node: TargetGeometry + the frame's GroundPlane -> ViewCandidates, next-best-view goal, markers.

The computation is :func:`leapnbv_planner.plan.plan_views`; this node unpacks the messages, waits
for the frame's ground plane, calls it, and publishes. Its parameters are the fields of
:func:`leapnbv_planner.params.nbv_params_class` (defaults, ranges, read-only flags there); a runtime
``ros2 param set`` is validated and applies to the next plan.

Optional inputs: ``obstacle_map`` (PointCloud2 of occupied voxel centres in a fixed frame, latched,
as a mapping stack publishes it) and the camera pose (from the ``camera_pose_source``, by default
the ``camera_pose`` PoseStamped topic: the camera's optical frame in that fixed frame, stamped with
each camera frame). With both, the map's obstacles join the footprint test and S_o counts only
target points whose line of sight crosses free map space: furniture the current view cannot see
still keeps the robot from choosing a view behind it. Without them (or for a frame whose pose is
missing) the node plans from the frame alone.
"""
from __future__ import annotations

import time
from collections import OrderedDict
from typing import Optional, Set

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import Marker, MarkerArray

from leapnbv_common import topics
from leapnbv_common.camera_pose import StampedCameraPose, create_camera_pose_source
from leapnbv_common.contracts import DuplicateStampGuard, check_same_frame, refused
from leapnbv_common.conversions import (
    arrays_to_view_candidates,
    ground_plane_to_arrays,
    human_mesh_to_arrays,
    obstacle_map_to_points,
    path_msg,
    point_msg,
    pose_msg,
    stamp_to_ns,
    target_geometry_to_arrays,
)
from leapnbv_common.diagnostics import StageDiagnostics, rejects_bad_input
from leapnbv_common.node_params import NodeParams, run_node
from leapnbv_common.qos import latched_goal_qos, latched_map_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stamp_cache import CompanionWait
from leapnbv_msgs.msg import GroundPlane, HumanMesh, TargetGeometry, ViewCandidates
from leapnbv_planner.obstacle_map import voxel_map_from_centres, warm_up_obstacle_map
from leapnbv_planner.params import PlannerParams, nbv_params_class
from leapnbv_planner.plan import Plan, base_goal_frame, plan_views
from leapnbv_planner.scoring import warm_up_scoring

BODY_MESH_CACHE = 30  # body meshes (and frames waiting for theirs) remembered by stamp


class NbvNode(Node):
    def __init__(self) -> None:
        super().__init__("nbv_node")
        self.diagnostics = StageDiagnostics(self)
        self.params: NodeParams = NodeParams(self, nbv_params_class(), self.on_params_change)
        p = self.params.value
        self.ground = CompanionWait(int(p.ground_wait_s * 1e9))
        self.stamps = DuplicateStampGuard()  # one content per stamp and input (contracts)
        self.candidates_pub = self.create_publisher(ViewCandidates, topics.VIEW_CANDIDATES, stage_output_qos())
        self.goal_pub = self.create_publisher(PoseStamped, topics.NEXT_BEST_VIEW, latched_goal_qos())
        self.base_goal_pub = self.create_publisher(PoseStamped, topics.BASE_GOAL, latched_goal_qos())
        self.base_path_pub = self.create_publisher(Path, topics.BASE_PATH, latched_goal_qos())
        self.markers_pub = self.create_publisher(MarkerArray, topics.MARKERS, stage_output_qos())
        warm_up_scoring()  # compile the kernels before subscribing: the graph is ready only after it
        warm_up_obstacle_map()
        # Optional: the robot's map of static obstacles (voxel centres, latched) and the camera's
        # pose in that map per frame. Without them the planner sees only what the frame shows.
        self.obstacle_map = None
        self.obstacle_map_points: Optional[np.ndarray] = None
        self.obstacle_map_frame = ""
        self.camera_poses = None
        if p.use_obstacle_map:
            self.create_subscription(PointCloud2, topics.OBSTACLE_MAP, self.on_obstacle_map, latched_map_qos())
            self.camera_poses = create_camera_pose_source(p.camera_pose_source, self, p.camera_pose_cache)
        # The person's metric body mesh by stamp (the body_occlusion term), and frames waiting for theirs.
        self.body_meshes: OrderedDict[int, tuple] = OrderedDict()
        self.waiting_for_mesh: OrderedDict[int, tuple] = OrderedDict()
        self.create_subscription(HumanMesh, topics.HUMAN_MESH_METRIC, self.on_body_mesh, stage_input_qos(5))
        self.create_subscription(TargetGeometry, topics.TARGET_GEOMETRY, self.on_target, stage_input_qos(5))
        self.create_subscription(GroundPlane, topics.GROUND_PLANE, self.on_ground, stage_input_qos(5))
        self.create_timer(0.02, self.expire_waits)

    def on_params_change(self, new: PlannerParams, changed: Set[str]) -> None:
        """Rebuild what depends on changed parameters (everything else is read at each plan)."""
        if "obstacle_map_resolution" in changed and self.obstacle_map_points is not None:
            # Raises ObstacleMapError (a ValueError: the change is refused) for a grid too large.
            self.obstacle_map = voxel_map_from_centres(self.obstacle_map_points, new.obstacle_map_resolution)
            self.get_logger().info(f"obstacle map rebuilt: {self.obstacle_map.voxel_count} voxels of"
                                   f" {new.obstacle_map_resolution} m")
        if "ground_wait_s" in changed:
            self.ground.wait_ns = int(new.ground_wait_s * 1e9)  # frames already waiting keep their place

    def now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    @rejects_bad_input("bad_obstacle_map")
    def on_obstacle_map(self, msg: PointCloud2) -> None:
        points = obstacle_map_to_points(msg)  # a map with a NaN point is refused whole (the previous one stays)
        self.obstacle_map = voxel_map_from_centres(points, self.params.value.obstacle_map_resolution)
        self.obstacle_map_points = points
        self.obstacle_map_frame = msg.header.frame_id
        self.get_logger().info(f"obstacle map: {self.obstacle_map.voxel_count} voxels in frame {msg.header.frame_id!r}")

    def camera_pose_for_frame(self, stamp_ns: int, camera_frame: str) -> Optional[StampedCameraPose]:
        """The frame's camera pose in the obstacle map's frame, or None when the frame cannot use the map."""
        if self.obstacle_map is None or self.camera_poses is None:
            return None
        pose = self.camera_poses.pose_at(stamp_ns, camera_frame)
        if pose is None:
            self.diagnostics.reject("no_camera_pose", "no camera pose with this frame's stamp: planned without the map")
            return None
        if pose.frame_id != self.obstacle_map_frame:
            self.diagnostics.reject("camera_pose_frame", f"camera pose in frame {pose.frame_id!r}, the obstacle map in"
                                    f" {self.obstacle_map_frame!r}: planned without the map")
            return None
        return pose

    @rejects_bad_input("bad_ground_plane")
    def on_ground(self, msg: GroundPlane) -> None:
        # The contract: unit normal pointing up toward the camera, camera above it
        if refused(self.diagnostics, "bad_ground_plane", ground_plane_to_arrays, msg) or \
                refused(self.diagnostics, "bad_ground_plane", self.stamps.check, "ground_plane", msg):
            return
        ready = self.ground.add_companion(stamp_to_ns(msg.header.stamp), msg)
        if ready is not None:
            self.plan(*ready)

    @rejects_bad_input("bad_target")
    def on_target(self, msg: TargetGeometry) -> None:
        self.diagnostics.frame_in()
        # The contract: finite points and box, its camera_info in its frame
        if refused(self.diagnostics, "bad_target", target_geometry_to_arrays, msg) or \
                refused(self.diagnostics, "bad_target", self.stamps.check, "target_geometry", msg):
            return
        ready = self.ground.add_frame(stamp_to_ns(msg.header.stamp), msg, self.now_ns())
        if ready is not None:
            self.plan(*ready)

    def expire_waits(self) -> None:
        for target, ground in self.ground.expire(self.now_ns()):
            self.diagnostics.reject("ground_plane_late", "used the latest ground plane instead of the frame's")
            self.plan(target, ground)
        wait_ns = self.params.value.body_mesh_wait_s * 1e9
        for stamp in [s for s, (_, _, since) in self.waiting_for_mesh.items() if self.now_ns() - since >= wait_ns]:
            target, ground, _ = self.waiting_for_mesh.pop(stamp)
            self.plan(target, ground, mesh_waited=True)

    @rejects_bad_input("bad_body_mesh")
    def on_body_mesh(self, msg: HumanMesh) -> None:
        mesh = human_mesh_to_arrays(msg)
        stamp = stamp_to_ns(msg.header.stamp)
        self.body_meshes[stamp] = (mesh.vertices.astype(np.float64), mesh.faces.reshape(-1, 3))
        while len(self.body_meshes) > BODY_MESH_CACHE:
            self.body_meshes.popitem(last=False)
        waiting = self.waiting_for_mesh.pop(stamp, None)
        if waiting is not None:
            self.plan(waiting[0], waiting[1])

    def body_mesh_for(self, target: TargetGeometry, ground: GroundPlane, mesh_waited: bool):
        """(found, mesh): the frame's body mesh when body_occlusion is scored; (False, None) puts the frame on
        hold until its mesh comes or body_mesh_wait_s runs out (then it is planned without: the paper's S_o)."""
        p = self.params.value
        if "body_occlusion" not in p.score_terms:
            return True, None
        stamp = stamp_to_ns(target.header.stamp)
        mesh = self.body_meshes.get(stamp)
        if mesh is not None:
            return True, mesh
        if not mesh_waited and p.body_mesh_wait_s > 0:
            self.waiting_for_mesh[stamp] = (target, ground, self.now_ns())
            while len(self.waiting_for_mesh) > BODY_MESH_CACHE:
                self.waiting_for_mesh.popitem(last=False)
            return False, None
        self.diagnostics.reject("no_body_mesh", "no metric body mesh of this frame: body_occlusion scored the "
                                "observed points")
        return True, None

    def usable_ground(self, target: TargetGeometry, ground: Optional[GroundPlane]) -> Optional[GroundPlane]:
        if ground is None or not ground.valid:
            return None
        age_s = (stamp_to_ns(target.header.stamp) - stamp_to_ns(ground.header.stamp)) * 1e-9
        return ground if abs(age_s) <= self.params.value.ground_max_age_s else None

    @rejects_bad_input("bad_target")
    def plan(self, target: TargetGeometry, ground: Optional[GroundPlane], mesh_waited: bool = False) -> None:
        started = time.perf_counter()
        if not target.valid:
            self.diagnostics.reject("empty_target", "no person points in this frame: no goal")
            return
        ground = self.usable_ground(target, ground)
        if ground is not None and refused(self.diagnostics, "bad_target", check_same_frame, "target_geometry",
                                          target.header.frame_id, "ground_plane", ground.header.frame_id):
            return
        if ground is None:
            self.diagnostics.reject("no_ground_plane", "no valid ground plane for this frame: no goal published")
            return
        found, body_mesh = self.body_mesh_for(target, ground, mesh_waited)
        if not found:
            return  # planned when the frame's body mesh comes (or the wait runs out)
        target_arrays = target_geometry_to_arrays(target)
        camera_pose = self.camera_pose_for_frame(stamp_to_ns(target.header.stamp), target.header.frame_id)
        plan = plan_views(target_arrays, ground_plane_to_arrays(ground), self.params.value,
                          self.obstacle_map if camera_pose is not None else None, camera_pose, body_mesh)
        out = arrays_to_view_candidates(plan.to_arrays(), target.header, (time.perf_counter() - started) * 1e3)
        self.candidates_pub.publish(out)
        if plan.chosen_index >= 0:
            self.goal_pub.publish(PoseStamped(header=target.header, pose=out.poses[plan.chosen_index]))
            self.base_goal_pub.publish(PoseStamped(header=target.header, pose=pose_msg(*plan.base_goal)))
            path = plan.base_path_frames()
            if path is not None:
                self.base_path_pub.publish(path_msg(*path, target.header))
        else:
            self.diagnostics.reject("no_feasible_view", "every candidate is infeasible: no goal published")
        self.markers_pub.publish(candidate_markers(target.header, out, plan))
        self.diagnostics.frame_out(target.header.stamp, out.compute_time_ms)


def _score_colour(value: float, lo: float, hi: float):
    t = 0.0 if hi <= lo else (value - lo) / (hi - lo)
    return float(1.0 - t), float(t), 0.2  # red (low) -> green (high)


def candidate_markers(header, out: ViewCandidates, plan: Plan) -> MarkerArray:
    """Ring coloured by score, infeasible candidates as grey cubes, the chosen view as an arrow."""
    markers = MarkerArray()
    clear = Marker(header=header, ns="leapnbv_candidates", action=Marker.DELETEALL)
    markers.markers.append(clear)
    scores = np.asarray(out.score, dtype=np.float64)
    lo, hi = (float(scores.min()), float(scores.max())) if scores.size else (0.0, 1.0)
    for i, pose in enumerate(out.poses):
        m = Marker(header=header, ns="leapnbv_candidates", id=i, pose=pose)
        m.frame_locked = False
        if out.feasible[i]:
            m.type = Marker.SPHERE
            m.scale.x = m.scale.y = m.scale.z = 0.12
            m.color.r, m.color.g, m.color.b = _score_colour(float(scores[i]), lo, hi)
        else:
            m.type = Marker.CUBE
            m.scale.x = m.scale.y = m.scale.z = 0.1
            m.color.r = m.color.g = m.color.b = 0.5
        m.color.a = 1.0
        markers.markers.append(m)
    if out.chosen_index >= 0:
        # Arrow markers point along their x axis; the camera looks along its z axis.
        arrow = Marker(header=header, ns="leapnbv_chosen", id=0, type=Marker.ARROW)
        start = plan.candidates.positions[out.chosen_index]
        end = start + 0.5 * plan.candidates.rotations[out.chosen_index][:, 2]
        arrow.points = [point_msg(start), point_msg(end)]
        arrow.scale.x, arrow.scale.y, arrow.scale.z = 0.04, 0.08, 0.1
        arrow.color.g, arrow.color.b, arrow.color.a = 0.8, 1.0, 1.0
        markers.markers.append(arrow)
    centre = Marker(header=header, ns="leapnbv_ring_center", id=0, type=Marker.CYLINDER)
    # A flat disc on the ground: the cylinder's axis (its z) along the plane normal.
    centre.pose = pose_msg(*base_goal_frame(plan.candidates.ring_center, plan.candidates.positions[-1], plan.up))
    centre.scale.x = centre.scale.y = 2 * out.ring_radius
    centre.scale.z = 0.005
    centre.color.b, centre.color.a = 1.0, 0.15
    markers.markers.append(centre)
    return markers


def main(args=None) -> None:
    run_node(NbvNode, args)


if __name__ == "__main__":
    main()
