"""nbv_node: TargetGeometry + the frame's GroundPlane -> ViewCandidates, next-best-view goal, markers.

The computation is :func:`leapnbv_planner.plan.plan_views`; this node unpacks the messages, waits
for the frame's ground plane, calls it, and publishes. Its parameters are the fields of
:func:`leapnbv_planner.params.nbv_params_class` (defaults, ranges, read-only flags there); a runtime
``ros2 param set`` is validated and applies to the next plan.

One frame, one set of inputs: a target is planned with the ground plane of its own frame (same
stamp: ground_node stamps a plane with its frame's, the colour image's, stamp), waited for at most
``ground_wait_s``. When that plane never comes (or is not valid), the newest
valid plane of an older frame (at most ``ground_max_age_s`` older) is carried into the frame by the
camera-pose delta between the two stamps, when the camera pose of both is known; otherwise the
frame is dropped (``rejected.ground_plane_late`` / ``rejected.no_ground_plane``). Never "the latest
plane of any stamp". ViewCandidates list what they used (``inputs``).

Latest-frame scheduling: the target subscription keeps the newest message only, a target waiting
for its plane is superseded once a newer one is planned, a frame older than one already planned
is dropped, and a frame already older than ``max_goal_age_s`` is dropped before planning; every drop
is counted on /diagnostics (``dropped.<reason>``).

No stale goal: next_best_view / base_goal are published only when the frame is younger than
``max_goal_age_s`` by the node clock at publish time. ``goal_status`` (GoalStatus, latched) says
whether the latched goal may be acted on (CURRENT), and a timer replaces a goal that ages out by
an explicit "no goal": state STALE, and next_best_view / base_goal re-published with an empty
frame_id (docs/ARCHITECTURE.md, "Timing").

Optional inputs: ``obstacle_map`` (PointCloud2 of occupied voxel centres in a fixed frame, latched,
as a mapping stack publishes it) and the camera pose (from the ``camera_pose_source``, by default
the ``camera_pose`` PoseStamped topic: the camera's optical frame in that fixed frame, stamped with
each camera frame). With both, the map's obstacles join the footprint test and S_o counts only
target points whose line of sight crosses free map space: furniture the current view cannot see
still keeps the robot from choosing a view behind it. A frame waits at most ``camera_pose_wait_s``
for its pose; without one (or without a map) the node plans from the frame alone.
"""
from __future__ import annotations

import dataclasses
import time
from typing import List, Optional, Set, Tuple

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from visualization_msgs.msg import MarkerArray

from leapnbv_common import topics
from leapnbv_common.camera_pose import StampedCameraPose, create_camera_pose_source
from leapnbv_common.contracts import check_same_frame, refused
from leapnbv_common.conversions import (
    GroundPlaneArrays,
    arrays_to_view_candidates,
    ground_plane_to_arrays,
    human_mesh_to_arrays,
    obstacle_map_to_points,
    path_msg,
    pose_msg,
    set_stamp,
    stamp_to_ns,
    target_geometry_to_arrays,
)
from leapnbv_common.diagnostics import rejects_bad_input
from leapnbv_common.managed_node import ManagedNode
from leapnbv_common.node_params import run_node
from leapnbv_common.process_tuning import tune_node_process
from leapnbv_common.pulled_input import PulledInput
from leapnbv_common.qos import latched_goal_qos, latched_map_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stage import Companion, Frame, KeyInput, Received, Stage
from leapnbv_msgs.msg import GoalStatus, GroundPlane, HumanMesh, InputStamp, TargetGeometry, ViewCandidates
from leapnbv_planner.inputs import PlanInputs
from leapnbv_planner.nodes.markers import candidate_markers
from leapnbv_planner.obstacle_map import VoxelObstacleMap, voxel_map_from_centres, warm_up_obstacle_map
from leapnbv_planner.params import PlannerParams, nbv_params_class
from leapnbv_planner.plan import plan_views
from leapnbv_planner.requirements import BODY_MESH, Requirement
from leapnbv_planner.score_terms.base import declared_requirements, get_term
from leapnbv_planner.scoring import warm_up_scoring

GOAL_AGE_CHECK_PERIOD_S = 0.1  # how often the latched goal's age is checked (only while a goal is current)
PLANE_CACHE = 30  # ground planes remembered by stamp (to pair, and to carry an older one)
BODY_MESH_CACHE = 30  # body meshes (and frames waiting for theirs) remembered by stamp


def body_mesh_arrays(msg: HumanMesh) -> Tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, faces (F, 3)) of a metric body mesh, checked (what BODY_MESH terms read)."""
    mesh = human_mesh_to_arrays(msg)
    return mesh.vertices.astype(np.float64), mesh.faces.reshape(-1, 3)


def carry_plane(normal: np.ndarray, offset: float, pose_from: StampedCameraPose,
                pose_to: StampedCameraPose) -> Tuple[np.ndarray, float]:
    """The plane n.x + d = 0 of camera frame ``pose_from`` expressed in camera frame ``pose_to``.

    Both poses are camera -> fixed frame (p_fixed = R p_camera + t). A point x_to of the new frame is
    R_from^T (R_to x_to + t_to - t_from) in the old one, so n_to = R_to^T R_from n and
    d_to = d + n . R_from^T (t_to - t_from).
    """
    n = np.asarray(normal, dtype=np.float64)
    r_from, r_to = pose_from.rotation, pose_to.rotation
    n_to = r_to.T @ (r_from @ n)
    d_to = float(offset) + float(n @ (r_from.T @ (pose_to.position - pose_from.position)))
    return n_to, d_to


class NbvNode(ManagedNode):
    def __init__(self) -> None:
        super().__init__("nbv_node", nbv_params_class())

    def configure_stage(self) -> None:
        p = self.params.value
        self.candidates_pub = self.create_lifecycle_publisher(ViewCandidates, topics.VIEW_CANDIDATES,
                                                              stage_output_qos())
        # The latched goal topics are plain publishers: activate says "no goal yet" on them and deactivate
        # withdraws the goal, at the edges of the active state, where a lifecycle publisher drops what it gets.
        self.goal_pub = self.create_publisher(PoseStamped, topics.NEXT_BEST_VIEW, latched_goal_qos())
        self.base_goal_pub = self.create_publisher(PoseStamped, topics.BASE_GOAL, latched_goal_qos())
        self.status_pub = self.create_publisher(GoalStatus, topics.GOAL_STATUS, latched_goal_qos())
        self.base_path_pub = self.create_publisher(Path, topics.BASE_PATH, latched_goal_qos())
        self.markers_pub = self.create_lifecycle_publisher(MarkerArray, topics.MARKERS, stage_output_qos())
        self.goal_stamp: Optional[int] = None  # frame stamp of the last goal published
        self.goal_frame = ""
        self.goal_state = GoalStatus.STATE_NONE
        warm_up_scoring()  # compile the kernels before subscribing: the graph is ready only after it
        warm_up_obstacle_map()
        # Optional: the robot's map of static obstacles (voxel centres, latched) and the camera's
        # pose in that map per frame. Without them the planner sees only what the frame shows.
        self.obstacle_map: Optional[VoxelObstacleMap] = None
        self.obstacle_map_points: Optional[np.ndarray] = None
        self.obstacle_map_frame = ""
        self.obstacle_map_stamp = 0
        # The target starts the work (the newest only); it takes the plane of its own frame (waited for),
        # its camera pose while a map is in use (DDS does not order topics: waited for briefly) and its
        # metric body mesh while a chosen term reads it (BODY_MESH) and some node publishes them.
        self.stage = Stage(self, KeyInput("target_geometry", TargetGeometry, topics.TARGET_GEOMETRY,
                                          target_geometry_to_arrays, stage_input_qos(1), bad_reason="bad_target",
                                          frame_name="target", accept=self.accept_target), [
            Companion("ground_plane", GroundPlane, topics.GROUND_PLANE, ground_plane_to_arrays,
                      stage_input_qos(PLANE_CACHE), wait_s=lambda f: self.params.value.ground_wait_s,
                      capacity=PLANE_CACHE),
            Companion("camera_pose", lookup=self.frame_camera_pose, needed=lambda f: self.map_in_use(),
                      wait_s=lambda f: self.params.value.camera_pose_wait_s,
                      expect=lambda f: self.camera_poses.expect(f.stamp_ns, f.header.frame_id)),
            Companion(topics.HUMAN_MESH_METRIC, HumanMesh, topics.HUMAN_MESH_METRIC, body_mesh_arrays,
                      stage_input_qos(5), needed=lambda f: self.terms_need(BODY_MESH),
                      wait_s=self.body_mesh_wait_s, missing_reason="no_body_mesh",
                      missing_detail=lambda f: "no metric body mesh of this frame: body_occlusion scored the observed"
                      " points", capacity=BODY_MESH_CACHE, bad_reason="bad_body_mesh"),
        ], self.plan, capacity=PLANE_CACHE)
        # The camera poses also carry an older ground plane into a frame whose own plane never came. They
        # come at camera rate and are pulled when a frame needs one (leapnbv_common.pulled_input).
        self.camera_poses = create_camera_pose_source(p.camera_pose_source, self, p.camera_pose_cache,
                                                      lambda pose: self.stage.companion_arrived("camera_pose"))
        self.stage.add_pulled(PulledInput.adopt(self, self.camera_poses))  # None for a source without one

    def activate_stage(self) -> None:
        if self.params.value.use_obstacle_map:
            self.create_subscription(PointCloud2, topics.OBSTACLE_MAP, self.on_obstacle_map, latched_map_qos())
        self.stage.start()
        self.diagnostics.await_publishers(topics.TARGET_GEOMETRY, topics.GROUND_PLANE)
        self.age_timer = self.create_timer(GOAL_AGE_CHECK_PERIOD_S, self.check_goal_age)
        self.age_timer.cancel()  # runs only while a goal is current
        self.publish_status(GoalStatus.STATE_NONE, "no goal planned yet")

    def deactivate_stage(self) -> None:
        """No goal from a planner that stopped: a motion stack must not keep acting on the last one."""
        self.stage.stop()
        if self.goal_state == GoalStatus.STATE_CURRENT:
            self.withdraw_goal()
            self.publish_status(GoalStatus.STATE_NONE, "the planner was deactivated: the last goal was withdrawn")

    def on_params_change(self, new: PlannerParams, changed: Set[str]) -> None:
        """Rebuild what depends on changed parameters (everything else is read at each plan)."""
        if "obstacle_map_resolution" in changed and self.obstacle_map_points is not None:
            # Raises ObstacleMapError (a ValueError: the change is refused) for a grid too large.
            self.obstacle_map = voxel_map_from_centres(self.obstacle_map_points, new.obstacle_map_resolution)
            self.get_logger().info(f"obstacle map rebuilt: {self.obstacle_map.voxel_count} voxels of"
                                   f" {new.obstacle_map_resolution} m")
        if "max_goal_age_s" in changed and self.goal_state == GoalStatus.STATE_CURRENT and new.max_goal_age_s > 0:
            self.age_timer.reset()  # the next check applies the new limit to the latched goal

    def now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    @rejects_bad_input("bad_obstacle_map")
    def on_obstacle_map(self, msg: PointCloud2) -> None:
        points = obstacle_map_to_points(msg)  # a map with a NaN point is refused whole (the previous one stays)
        self.obstacle_map = voxel_map_from_centres(points, self.params.value.obstacle_map_resolution)
        self.obstacle_map_points = points
        self.obstacle_map_frame = msg.header.frame_id
        self.obstacle_map_stamp = stamp_to_ns(msg.header.stamp)
        self.get_logger().info(f"obstacle map: {self.obstacle_map.voxel_count} voxels in frame {msg.header.frame_id!r}")

    def map_in_use(self) -> bool:
        return self.obstacle_map is not None and self.params.value.use_obstacle_map

    def terms_need(self, requirement: Requirement) -> bool:
        """Whether a chosen score term declares this requirement (the node waits only for inputs a term reads)."""
        terms = [get_term(name) for name in self.params.value.score_terms]
        return requirement.name in declared_requirements(terms)

    def body_mesh_wait_s(self, frame: Frame) -> float:
        """Wait for a body mesh only while some node publishes them (the graph's raster_node): else none comes."""
        if self.count_publishers(topics.HUMAN_MESH_METRIC) == 0:
            return 0.0
        return self.params.value.body_mesh_wait_s

    def frame_camera_pose(self, frame: Frame) -> Optional[Received]:
        pose = self.camera_poses.pose_at(frame.stamp_ns, frame.header.frame_id)
        return None if pose is None else Received(pose.stamp_ns, frame.header, pose)

    def accept_target(self, target: Received) -> Optional[str]:
        """Drop a frame that is already too old for a goal before any work (a drop reason, or None)."""
        return "too_old_to_plan" if self.too_old(target.stamp_ns) else None

    def camera_pose_for_frame(self, frame: Frame) -> Optional[StampedCameraPose]:
        """The frame's camera pose in the obstacle map's frame, or None when the frame cannot use the map."""
        if not self.map_in_use():
            return None
        pose = frame["camera_pose"]
        if pose is None:
            self.diagnostics.reject("no_camera_pose", "no camera pose with this frame's stamp: planned without the map")
            return None
        if pose.frame_id != self.obstacle_map_frame:
            self.diagnostics.reject("camera_pose_frame", f"camera pose in frame {pose.frame_id!r}, the obstacle map in"
                                    f" {self.obstacle_map_frame!r}: planned without the map")
            return None
        return pose

    def carried_plane(self, frame: Frame) -> Optional[Tuple[GroundPlaneArrays, List[tuple]]]:
        """The newest valid plane of an older frame (at most ground_max_age_s older), moved into this
        frame by the camera-pose delta, and the inputs it stands for; None when there is none."""
        p = self.params.value
        frame_stamp = frame.stamp_ns
        self.stage.pull()
        pose_to = self.camera_poses.pose_at(frame_stamp, frame.header.frame_id)
        if pose_to is None or p.ground_max_age_s <= 0:
            return None
        for stamp, plane in sorted(self.stage.caches["ground_plane"].items(), key=lambda item: -item[0]):
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

    # ------------------------------------------------------------------ planning and the goal

    def too_old(self, stamp_ns: int) -> bool:
        """Whether a frame of this stamp is older than max_goal_age_s now (never with a limit of 0)."""
        limit = self.params.value.max_goal_age_s
        return limit > 0 and self.now_ns() - stamp_ns > limit * 1e9

    def frame_floor(self, frame: Frame) -> Optional[Tuple[GroundPlaneArrays, List[tuple]]]:
        """The floor to plan the frame on and the inputs it stands for: the frame's own valid plane, else an
        older one carried into it by the camera poses; None (counted): the frame gets no goal."""
        ground = frame.received("ground_plane")
        if ground is not None and refused(self.diagnostics, "bad_target", check_same_frame, "target_geometry",
                                          frame.header.frame_id, "ground_plane", ground.frame_id):
            return None
        if ground is not None and ground.value.valid:
            return ground.value, [("ground_plane", ground.stamp_ns, InputStamp.SAME_FRAME)]
        carried = self.carried_plane(frame)
        if carried is None:
            if ground is None:
                self.diagnostics.reject("ground_plane_late", "no ground plane of this frame in time and none to"
                                        " carry by the camera pose: frame dropped, no goal")
            else:
                self.diagnostics.reject("no_ground_plane", "no valid ground plane for this frame: no goal published")
        return carried

    def plan(self, frame: Frame) -> None:
        started = time.perf_counter()
        target: TargetGeometry = frame.key.message
        stamp = frame.stamp_ns
        if self.too_old(stamp):
            self.diagnostics.drop("too_old_to_plan")
            return
        if not target.valid:
            self.diagnostics.reject("empty_target", "no person points in this frame: no goal")
            return
        floor = self.frame_floor(frame)
        if floor is None:
            return
        inputs: List[tuple] = [("target_geometry", stamp), *floor[1]]
        body_mesh = frame[topics.HUMAN_MESH_METRIC]
        if body_mesh is not None:
            inputs.append((topics.HUMAN_MESH_METRIC, stamp))
        camera_pose = self.camera_pose_for_frame(frame)
        if camera_pose is not None:
            if ("camera_pose", stamp, InputStamp.SAME_FRAME) not in inputs:
                inputs.append(("camera_pose", stamp))
            inputs.append(("obstacle_map", self.obstacle_map_stamp, InputStamp.STATIC))
        plan = plan_views(PlanInputs(frame["target_geometry"], floor[0], self.params.value,
                                     self.obstacle_map if camera_pose is not None else None, camera_pose, body_mesh))
        compute_time_ms = (time.perf_counter() - started) * 1e3
        # The goal first (what the motion stack waits for), then the candidates, the path and the markers.
        goal_published = False
        chosen = plan.chosen_pose()
        if chosen is None or plan.base_goal is None:
            self.diagnostics.reject("no_feasible_view", "every candidate is infeasible: no goal published")
        elif self.too_old(stamp):
            self.diagnostics.drop("goal_too_old")  # planning took it past the limit: no goal of it
        else:
            self.goal_pub.publish(PoseStamped(header=target.header, pose=pose_msg(*chosen)))
            self.base_goal_pub.publish(PoseStamped(header=target.header, pose=pose_msg(*plan.base_goal)))
            self.goal_stamp, self.goal_frame = stamp, target.header.frame_id
            goal_published = True
            self.publish_status(GoalStatus.STATE_CURRENT, "goal published")
            if self.params.value.max_goal_age_s > 0 and self.age_timer.is_canceled():
                self.age_timer.reset()
        out = arrays_to_view_candidates(plan.to_arrays(), target.header, compute_time_ms, inputs=inputs)
        self.candidates_pub.publish(out)
        if goal_published:
            path = plan.base_path_frames()
            if path is not None:
                self.base_path_pub.publish(path_msg(*path, target.header))
        if self.markers_pub.get_subscription_count() > 0:  # built and sent only while RViz / Foxglove listens
            self.markers_pub.publish(candidate_markers(target.header, out, plan))
        self.diagnostics.frame_out(target.header.stamp, out.compute_time_ms)

    def check_goal_age(self) -> None:
        """The timer: a current goal whose frame is now older than max_goal_age_s is withdrawn."""
        limit = self.params.value.max_goal_age_s
        if self.goal_state != GoalStatus.STATE_CURRENT or self.goal_stamp is None or limit <= 0:
            self.age_timer.cancel()
            return
        age_s = (self.now_ns() - self.goal_stamp) * 1e-9
        if age_s <= limit:
            return
        self.age_timer.cancel()
        self.withdraw_goal()
        self.diagnostics.drop("goal_withdrawn_stale")
        self.publish_status(GoalStatus.STATE_STALE, f"no goal from a frame younger than {limit:g} s: the last one"
                            f" is {age_s:.2f} s old and was withdrawn")

    def withdraw_goal(self) -> None:
        """Replace the latched goals by "no goal": a motion stack connecting later must not receive the old one."""
        cleared = Header(frame_id="", stamp=self.get_clock().now().to_msg())
        self.goal_pub.publish(PoseStamped(header=cleared))
        self.base_goal_pub.publish(PoseStamped(header=cleared))
        self.base_path_pub.publish(Path(header=cleared))  # an empty path: no way to a current goal

    def publish_status(self, state: int, reason: str) -> None:
        now = self.now_ns()
        msg = GoalStatus(state=state, reason=reason, max_goal_age_s=float(self.params.value.max_goal_age_s))
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.goal_frame if state == GoalStatus.STATE_CURRENT else ""
        if self.goal_stamp is not None:
            set_stamp(msg.goal_stamp, self.goal_stamp)
            msg.goal_age_s = float((now - self.goal_stamp) * 1e-9)
        self.goal_state = state
        self.status_pub.publish(msg)


def main(args=None) -> None:
    tune_node_process()  # one BLAS thread, image buffers reused (leapnbv_common.process_tuning)
    run_node(NbvNode, args)


if __name__ == "__main__":
    main()
