"""nbv_node: TargetGeometry + the frame's GroundPlane -> ViewCandidates, next-best-view goal, markers.

Optional inputs: ``obstacle_map`` (PointCloud2 of occupied voxel centres in a fixed frame, latched,
as a mapping stack publishes it) and ``camera_pose`` (PoseStamped: the camera's optical frame in
that fixed frame, stamped with each camera frame). With both, the map's obstacles join the
footprint test and S_o counts only target points whose line of sight crosses free map space:
furniture the current view cannot see still keeps the robot from choosing a view behind it.
Without them (or for a frame whose pose is missing) the node plans from the frame alone.
"""
from __future__ import annotations

import time
from typing import Optional

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import Marker, MarkerArray

from leapnbv_common.conversions import (
    ViewCandidatesArrays,
    arrays_to_view_candidates,
    camera_info_to_k,
    point_msg,
    point_to_numpy,
    pointcloud2_to_xyz,
    pose_msg,
    pose_to_numpy,
    stamp_to_ns,
)
from leapnbv_common.diagnostics import StageDiagnostics, rejects_bad_input
from leapnbv_common.node_params import declare_parameters, run_node
from leapnbv_common.qos import latched_goal_qos, latched_map_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stamp_cache import CompanionWait, StampCache
from leapnbv_msgs.msg import GroundPlane, TargetGeometry, ViewCandidates
from leapnbv_planner.candidates import CandidateRingParams, check_feasibility, generate_candidates
from leapnbv_planner.obstacle_map import (
    centres_in_observation,
    line_of_sight_clear_fraction,
    voxel_map_from_centres,
    warm_up_obstacle_map,
)
from leapnbv_planner.scoring import ScoreWeights, choose_best, score_candidates, warm_up_scoring

PARAMETERS = {
    "num_candidates": (16, "viewpoints on the ring (the current view is added as candidate 0)"),
    "radius": (1.5, "metres: ring radius around the target, on the ground"),
    "include_current": (True, "score the current view as candidate 0, so staying is possible"),
    "max_travel": (3.0, "metres: farthest foot point from the robot's current one"),
    "robot_radius": (0.3, "metres: footprint radius checked for obstacles"),
    "floor_clearance": (0.05, "metres: background points higher than this above the floor are obstacles"),
    "weight_visibility": (0.03, "w_v, weight of S_v (share of target points in view)"),
    "weight_area": (0.14, "w_a, weight of S_a (projected target box area)"),
    "weight_occlusion": (0.83, "w_o, weight of S_o (share of target points not hidden)"),
    "delta_px": (4.0, "pixels: neighbourhood of the background depth test in S_o"),
    "ground_wait_s": (1.0, "how long a frame waits for the ground plane of the same stamp, then uses the latest"),
    "ground_max_age_s": (2.0, "a fallback ground plane older than this is not used"),
    "use_obstacle_map": (True, "use the robot's obstacle map (obstacle_map + camera_pose topics) when they arrive"),
    "obstacle_map_resolution": (0.1, "metres: voxel edge of the obstacle map (its points are voxel centres)"),
    "map_max_target_points": (1500, "target points whose line of sight is walked through the map, per candidate"),
    "map_target_margin": (0.1, "metres: the end of each line of sight, at the target, not checked in the map"),
    "camera_pose_cache": (30, "camera poses remembered by stamp, to find the pose of each planned frame"),
}


class NbvNode(Node):
    def __init__(self) -> None:
        super().__init__("nbv_node")
        p = self.params = declare_parameters(self, PARAMETERS)
        self.diagnostics = StageDiagnostics(self)
        self.ring = CandidateRingParams(
            num_candidates=p["num_candidates"], radius=p["radius"], include_current=p["include_current"],
            max_travel=p["max_travel"], robot_radius=p["robot_radius"], floor_clearance=p["floor_clearance"])
        self.weights = ScoreWeights(p["weight_visibility"], p["weight_area"], p["weight_occlusion"])
        self.ground = CompanionWait(int(p["ground_wait_s"] * 1e9))
        self.candidates_pub = self.create_publisher(ViewCandidates, "view_candidates", stage_output_qos())
        self.goal_pub = self.create_publisher(PoseStamped, "next_best_view", latched_goal_qos())
        self.base_goal_pub = self.create_publisher(PoseStamped, "base_goal", latched_goal_qos())
        self.markers_pub = self.create_publisher(MarkerArray, "markers", stage_output_qos())
        warm_up_scoring()  # compile the kernels before subscribing: the graph is ready only after it
        warm_up_obstacle_map()
        # Optional: the robot's map of static obstacles (voxel centres, latched) and the camera's
        # pose in that map per frame. Without them the planner sees only what the frame shows.
        self.obstacle_map = None
        self.obstacle_map_frame = ""
        self.camera_poses: StampCache = StampCache(max(1, int(p["camera_pose_cache"])))
        if p["use_obstacle_map"]:
            self.create_subscription(PointCloud2, "obstacle_map", self.on_obstacle_map, latched_map_qos())
            self.create_subscription(PoseStamped, "camera_pose", self.on_camera_pose, stage_input_qos(20))
        self.create_subscription(TargetGeometry, "target_geometry", self.on_target, stage_input_qos(5))
        self.create_subscription(GroundPlane, "ground_plane", self.on_ground, stage_input_qos(5))
        self.create_timer(0.02, self.expire_waits)

    def now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    @rejects_bad_input("bad_obstacle_map")
    def on_obstacle_map(self, msg: PointCloud2) -> None:
        self.obstacle_map = voxel_map_from_centres(pointcloud2_to_xyz(msg), self.params["obstacle_map_resolution"])
        self.obstacle_map_frame = msg.header.frame_id
        self.get_logger().info(f"obstacle map: {self.obstacle_map.voxel_count} voxels in frame {msg.header.frame_id!r}")

    @rejects_bad_input("bad_camera_pose")
    def on_camera_pose(self, msg: PoseStamped) -> None:
        rotation, position = pose_to_numpy(msg.pose)
        self.camera_poses.put(stamp_to_ns(msg.header.stamp), (msg.header.frame_id, rotation, position))

    def map_for_frame(self, target: TargetGeometry):
        """(obstacle map, R, t of the frame's camera in the map), or None when the frame cannot use it."""
        if self.obstacle_map is None:
            return None
        pose = self.camera_poses.get_exact(stamp_to_ns(target.header.stamp))
        if pose is None:
            self.diagnostics.reject("no_camera_pose", "no camera pose with this frame's stamp: planned without the map")
            return None
        frame_id, rotation, position = pose
        if frame_id != self.obstacle_map_frame:
            self.diagnostics.reject("camera_pose_frame", f"camera pose in frame {frame_id!r}, the obstacle map in"
                                    f" {self.obstacle_map_frame!r}: planned without the map")
            return None
        return self.obstacle_map, rotation, position

    @rejects_bad_input("bad_ground_plane")
    def on_ground(self, msg: GroundPlane) -> None:
        ready = self.ground.add_companion(stamp_to_ns(msg.header.stamp), msg)
        if ready is not None:
            self.plan(*ready)

    def on_target(self, msg: TargetGeometry) -> None:
        self.diagnostics.frame_in()
        ready = self.ground.add_frame(stamp_to_ns(msg.header.stamp), msg, self.now_ns())
        if ready is not None:
            self.plan(*ready)

    def expire_waits(self) -> None:
        for target, ground in self.ground.expire(self.now_ns()):
            self.diagnostics.reject("ground_plane_late", "used the latest ground plane instead of the frame's")
            self.plan(target, ground)

    def usable_ground(self, target: TargetGeometry, ground: Optional[GroundPlane]) -> Optional[GroundPlane]:
        if ground is None or not ground.valid:
            return None
        age_s = (stamp_to_ns(target.header.stamp) - stamp_to_ns(ground.header.stamp)) * 1e-9
        return ground if abs(age_s) <= self.params["ground_max_age_s"] else None

    @rejects_bad_input("bad_target")
    def plan(self, target: TargetGeometry, ground: Optional[GroundPlane]) -> None:
        started = time.perf_counter()
        if not target.valid:
            self.diagnostics.reject("empty_target", "no person points in this frame: no goal")
            return
        ground = self.usable_ground(target, ground)
        if ground is None:
            self.diagnostics.reject("no_ground_plane", "no valid ground plane for this frame: no goal published")
            return
        normal = np.array([ground.normal.x, ground.normal.y, ground.normal.z])
        centroid = point_to_numpy(target.centroid)
        target_points = pointcloud2_to_xyz(target.target_points)
        background = pointcloud2_to_xyz(target.background_points)
        k = camera_info_to_k(target.camera_info)
        candidates = generate_candidates(centroid, normal, ground.offset, self.ring)
        obstacles, line_of_sight_clear = background, None
        mapped = self.map_for_frame(target)
        if mapped is not None:
            obstacle_map, rotation, position = mapped
            obstacles = np.concatenate([background, centres_in_observation(obstacle_map, rotation, position)])
            line_of_sight_clear = line_of_sight_clear_fraction(
                obstacle_map, rotation, position, candidates.positions, target_points,
                self.params["map_max_target_points"], self.params["map_target_margin"])
        feasibility = check_feasibility(candidates, obstacles, normal, ground.offset, self.ring)
        scores = score_candidates(target_points, background, candidates.rotations, candidates.positions, k,
                                  target.camera_info.width, target.camera_info.height, self.weights,
                                  delta_px=self.params["delta_px"], line_of_sight_clear=line_of_sight_clear)
        chosen = choose_best(scores.score, feasibility.feasible, candidates.positions, np.zeros(3))

        views = ViewCandidatesArrays(
            rotations=candidates.rotations, positions=candidates.positions,
            term_names=["visibility", "area", "occlusion"],
            term_weights=np.array([self.weights.visibility, self.weights.area, self.weights.occlusion]),
            term_scores=np.column_stack([scores.s_visibility, scores.s_area, scores.s_occlusion]),
            score=scores.score, feasible=feasibility.feasible,
            infeasible_reason=np.asarray(feasibility.reasons, dtype=np.uint8), chosen_index=int(chosen),
            includes_current_view=bool(self.ring.include_current), ring_center=candidates.ring_center,
            ring_radius=float(self.ring.radius))
        out = arrays_to_view_candidates(views, target.header, (time.perf_counter() - started) * 1e3)
        self.candidates_pub.publish(out)
        if chosen >= 0:
            self.goal_pub.publish(PoseStamped(header=target.header, pose=out.poses[chosen]))
            self.base_goal_pub.publish(PoseStamped(header=target.header, pose=base_goal_pose(
                candidates.foot_points[chosen], candidates.ring_center, normal)))
        else:
            self.diagnostics.reject("no_feasible_view", "every candidate is infeasible: no goal published")
        self.markers_pub.publish(candidate_markers(target.header, out, candidates, normal))
        self.diagnostics.frame_out(target.header.stamp, out.compute_time_ms)


def base_goal_pose(foot_point: np.ndarray, ring_center: np.ndarray, up: np.ndarray):
    """The robot base goal: on the ground under the camera, x toward the target, z up (REP 103 base)."""
    up = up / np.linalg.norm(up)
    heading = ring_center - foot_point
    heading = heading - up * float(heading @ up)
    if np.linalg.norm(heading) < 1e-9:  # standing on the ring centre: keep any level heading
        heading = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 0.0, 1.0])
    x_axis = heading / np.linalg.norm(heading)
    y_axis = np.cross(up, x_axis)
    return pose_msg(np.column_stack([x_axis, y_axis, up]), foot_point)


def _score_colour(value: float, lo: float, hi: float):
    t = 0.0 if hi <= lo else (value - lo) / (hi - lo)
    return float(1.0 - t), float(t), 0.2  # red (low) -> green (high)


def candidate_markers(header, out: ViewCandidates, candidates, up: np.ndarray) -> MarkerArray:
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
        start = candidates.positions[out.chosen_index]
        end = start + 0.5 * candidates.rotations[out.chosen_index][:, 2]
        arrow.points = [point_msg(start), point_msg(end)]
        arrow.scale.x, arrow.scale.y, arrow.scale.z = 0.04, 0.08, 0.1
        arrow.color.g, arrow.color.b, arrow.color.a = 0.8, 1.0, 1.0
        markers.markers.append(arrow)
    centre = Marker(header=header, ns="leapnbv_ring_center", id=0, type=Marker.CYLINDER)
    # A flat disc on the ground: the cylinder's axis (its z) along the plane normal.
    centre.pose = base_goal_pose(candidates.ring_center, candidates.positions[-1], up)
    centre.scale.x = centre.scale.y = 2 * out.ring_radius
    centre.scale.z = 0.005
    centre.color.b, centre.color.a = 1.0, 0.15
    markers.markers.append(centre)
    return markers


def main(args=None) -> None:
    run_node(NbvNode, args)


if __name__ == "__main__":
    main()
