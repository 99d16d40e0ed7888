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

import time
from collections import OrderedDict
from typing import Dict, List, NamedTuple, Optional, Set, Tuple

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from visualization_msgs.msg import Marker, MarkerArray

from leapnbv_common import topics
from leapnbv_common.camera_pose import StampedCameraPose, create_camera_pose_source
from leapnbv_common.contracts import DuplicateStampGuard, check_same_frame, refused
from leapnbv_common.conversions import (
    GroundPlaneArrays,
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
from leapnbv_common.process_tuning import tune_node_process
from leapnbv_common.pulled_input import HOUSEKEEPING_PERIOD_S, PulledInput
from leapnbv_common.qos import latched_goal_qos, latched_map_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stamp_cache import CompanionWait
from leapnbv_msgs.msg import GoalStatus, GroundPlane, HumanMesh, InputStamp, TargetGeometry, ViewCandidates
from leapnbv_planner.obstacle_map import voxel_map_from_centres, warm_up_obstacle_map
from leapnbv_planner.params import PlannerParams, nbv_params_class
from leapnbv_planner.plan import Plan, base_goal_frame, plan_views
from leapnbv_planner.scoring import warm_up_scoring

WAIT_CHECK_PERIOD_S = 0.02  # how often waiting targets are checked (the timer runs only while one waits)
GOAL_AGE_CHECK_PERIOD_S = 0.1  # how often the latched goal's age is checked (only while a goal is current)
PLANE_CACHE = 30  # ground planes remembered by stamp (to pair, and to carry an older one)
BODY_MESH_CACHE = 30  # body meshes (and frames waiting for theirs) remembered by stamp


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


class ReadyFrame(NamedTuple):
    """A target with the floor it will be planned on, and the inputs so far (waiting for its camera pose)."""

    target: TargetGeometry
    floor: GroundPlaneArrays
    inputs: List[tuple]
    since_ns: int


class NbvNode(Node):
    def __init__(self) -> None:
        super().__init__("nbv_node")
        self.diagnostics = StageDiagnostics(self)
        self.params: NodeParams = NodeParams(self, nbv_params_class(), self.on_params_change)
        p = self.params.value
        # Targets wait here for the plane of their stamp (planes are cached by stamp).
        self.ground = CompanionWait(int(p.ground_wait_s * 1e9), capacity=PLANE_CACHE, frame_name="target",
                                    companion_name="ground_plane", on_drop=self.diagnostics.drop_callback())
        self.pose_wait: Optional[ReadyFrame] = None  # a frame with its floor, waiting for its camera pose
        self.stamps = DuplicateStampGuard()  # one content per stamp and input (contracts)
        self.last_planned: Optional[int] = None
        self.candidates_pub = self.create_publisher(ViewCandidates, topics.VIEW_CANDIDATES, stage_output_qos())
        self.goal_pub = self.create_publisher(PoseStamped, topics.NEXT_BEST_VIEW, latched_goal_qos())
        self.base_goal_pub = self.create_publisher(PoseStamped, topics.BASE_GOAL, latched_goal_qos())
        self.status_pub = self.create_publisher(GoalStatus, topics.GOAL_STATUS, latched_goal_qos())
        self.base_path_pub = self.create_publisher(Path, topics.BASE_PATH, latched_goal_qos())
        self.markers_pub = self.create_publisher(MarkerArray, topics.MARKERS, stage_output_qos())
        self.goal_stamp: Optional[int] = None  # frame stamp of the last goal published
        self.goal_frame = ""
        self.goal_state = GoalStatus.STATE_NONE
        warm_up_scoring()  # compile the kernels before subscribing: the graph is ready only after it
        warm_up_obstacle_map()
        # Optional: the robot's map of static obstacles (voxel centres, latched) and the camera's
        # pose in that map per frame. Without them the planner sees only what the frame shows.
        self.obstacle_map = None
        self.obstacle_map_points: Optional[np.ndarray] = None
        self.obstacle_map_frame = ""
        self.obstacle_map_stamp = 0
        # The camera poses also carry an older ground plane into a frame whose own plane never came.
        self.camera_poses = create_camera_pose_source(p.camera_pose_source, self, p.camera_pose_cache,
                                                      self.on_camera_pose)
        # The poses come at camera rate; they are pulled when a frame needs one (leapnbv_common.pulled_input).
        self.pose_input = PulledInput.adopt(self, self.camera_poses)  # None for a source without a subscription
        if p.use_obstacle_map:
            self.create_subscription(PointCloud2, topics.OBSTACLE_MAP, self.on_obstacle_map, latched_map_qos())
        # The person's metric body mesh by stamp (the body_occlusion term), and frames waiting for theirs.
        self.body_meshes: Dict[int, tuple] = OrderedDict()  # oldest first
        self.waiting_for_mesh: Dict[int, ReadyFrame] = OrderedDict()  # oldest first
        self.create_subscription(HumanMesh, topics.HUMAN_MESH_METRIC, self.on_body_mesh, stage_input_qos(5))
        self.create_subscription(TargetGeometry, topics.TARGET_GEOMETRY, self.on_target, stage_input_qos(1))
        self.create_subscription(GroundPlane, topics.GROUND_PLANE, self.on_ground, stage_input_qos(PLANE_CACHE))
        # Ready once the stages before are connected.
        self.diagnostics.await_publishers(topics.TARGET_GEOMETRY, topics.GROUND_PLANE)
        self.wait_timer = self.create_timer(WAIT_CHECK_PERIOD_S, self.expire_waits)
        self.wait_timer.cancel()  # runs only while a target waits: an idle node does not wake up
        # A bad camera pose is counted within HOUSEKEEPING_PERIOD_S even while no frame is planned.
        self.create_timer(HOUSEKEEPING_PERIOD_S, self.pull_poses)
        self.age_timer = self.create_timer(GOAL_AGE_CHECK_PERIOD_S, self.check_goal_age)
        self.age_timer.cancel()  # runs only while a goal is current
        self.publish_status(GoalStatus.STATE_NONE, "no goal planned yet")

    def on_params_change(self, new: PlannerParams, changed: Set[str]) -> None:
        """Rebuild what depends on changed parameters (everything else is read at each plan)."""
        if "obstacle_map_resolution" in changed and self.obstacle_map_points is not None:
            # Raises ObstacleMapError (a ValueError: the change is refused) for a grid too large.
            self.obstacle_map = voxel_map_from_centres(self.obstacle_map_points, new.obstacle_map_resolution)
            self.get_logger().info(f"obstacle map rebuilt: {self.obstacle_map.voxel_count} voxels of"
                                   f" {new.obstacle_map_resolution} m")
        if "ground_wait_s" in changed:
            self.ground.wait_ns = int(new.ground_wait_s * 1e9)  # frames already waiting keep their place
        if "max_goal_age_s" in changed and self.goal_state == GoalStatus.STATE_CURRENT and new.max_goal_age_s > 0:
            self.age_timer.reset()  # the next check applies the new limit to the latched goal

    def now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def start_wait_timer(self) -> None:
        if self.wait_timer.is_canceled():
            self.wait_timer.reset()

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

    def pull_poses(self) -> None:
        if self.pose_input is not None:
            self.pose_input.drain()

    def camera_pose_for_frame(self, stamp_ns: int, camera_frame: str) -> Optional[StampedCameraPose]:
        """The frame's camera pose in the obstacle map's frame, or None when the frame cannot use the map."""
        if not self.map_in_use():
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

    # ------------------------------------------------------------------ pairing a target with its plane

    @rejects_bad_input("bad_ground_plane")
    def on_ground(self, msg: GroundPlane) -> None:
        # The contract: unit normal pointing up toward the camera, camera above it
        if refused(self.diagnostics, "bad_ground_plane", ground_plane_to_arrays, msg) or \
                refused(self.diagnostics, "bad_ground_plane", self.stamps.check, "ground_plane", msg):
            return
        ready = self.ground.add_companion(stamp_to_ns(msg.header.stamp), msg)
        if ready is not None:
            self.with_floor(*ready)

    @rejects_bad_input("bad_target")
    def on_target(self, msg: TargetGeometry, info) -> None:
        self.diagnostics.frame_in()
        self.diagnostics.input_seen("target_geometry", info)
        # The contract: finite points and box, its camera_info in its frame
        if refused(self.diagnostics, "bad_target", target_geometry_to_arrays, msg) or \
                refused(self.diagnostics, "bad_target", self.stamps.check, "target_geometry", msg):
            return
        stamp = stamp_to_ns(msg.header.stamp)
        if self.last_planned is not None and stamp <= self.last_planned:
            if self.last_planned - stamp < self.ground.restart_ns:
                self.diagnostics.drop("duplicate_stamp" if stamp == self.last_planned else "older_than_published")
                return
            self.last_planned = None  # the stamps started over (a replay from its start)
        if self.too_old(stamp):
            self.diagnostics.drop("too_old_to_plan")  # no goal could come of it: skip the work
            return
        ready = self.ground.add_frame(stamp, msg, self.now_ns())
        if ready is not None:
            self.with_floor(*ready)
        elif self.ground.waiting():
            self.start_wait_timer()

    def on_camera_pose(self, pose: StampedCameraPose) -> None:
        """A frame waiting for its camera pose is planned as soon as the pose is here."""
        if self.pose_wait is not None and pose.stamp_ns == stamp_to_ns(self.pose_wait.target.header.stamp):
            frame, self.pose_wait = self.pose_wait, None
            self.plan(frame)

    def expire_waits(self) -> None:
        if self.pose_wait is not None:
            self.pull_poses()  # its pose may be in the reader now (on_camera_pose plans it)
        for _, target in self.ground.expire(self.now_ns()):
            self.with_floor(target, None)
        if self.pose_wait is not None and \
                self.now_ns() - self.pose_wait.since_ns >= self.params.value.camera_pose_wait_s * 1e9:
            frame, self.pose_wait = self.pose_wait, None
            self.plan(frame)  # without the map (counted as no_camera_pose)
        wait_ns = self.params.value.body_mesh_wait_s * 1e9
        for stamp in [s for s, f in self.waiting_for_mesh.items() if self.now_ns() - f.since_ns >= wait_ns]:
            self.plan(self.waiting_for_mesh.pop(stamp), mesh_waited=True)
        if not self.ground.waiting() and self.pose_wait is None and not self.waiting_for_mesh:
            self.wait_timer.cancel()

    @rejects_bad_input("bad_body_mesh")
    def on_body_mesh(self, msg: HumanMesh) -> None:
        mesh = human_mesh_to_arrays(msg)
        stamp = stamp_to_ns(msg.header.stamp)
        self.body_meshes[stamp] = (mesh.vertices.astype(np.float64), mesh.faces.reshape(-1, 3))
        while len(self.body_meshes) > BODY_MESH_CACHE:
            self.body_meshes.popitem(last=False)
        waiting = self.waiting_for_mesh.pop(stamp, None)
        if waiting is not None:
            self.plan(waiting)

    def body_mesh_for(self, frame: ReadyFrame, mesh_waited: bool):
        """(found, mesh): the frame's body mesh when body_occlusion is scored; (False, None) puts the frame on
        hold until its mesh comes or body_mesh_wait_s runs out (then it is planned without: the paper's S_o)."""
        p = self.params.value
        if "body_occlusion" not in p.score_terms:
            return True, None
        stamp = stamp_to_ns(frame.target.header.stamp)
        mesh = self.body_meshes.get(stamp)
        if mesh is not None:
            return True, mesh
        # Wait only when some node publishes metric meshes (the graph's raster_node): without one, none comes.
        if not mesh_waited and p.body_mesh_wait_s > 0 and self.count_publishers(topics.HUMAN_MESH_METRIC) > 0:
            self.waiting_for_mesh[stamp] = frame._replace(since_ns=self.now_ns())
            while len(self.waiting_for_mesh) > BODY_MESH_CACHE:
                self.waiting_for_mesh.popitem(last=False)
            self.start_wait_timer()
            return False, None
        self.diagnostics.reject("no_body_mesh", "no metric body mesh of this frame: body_occlusion scored the "
                                "observed points")
        return True, None

    def carried_plane(self, target: TargetGeometry) -> Optional[Tuple[GroundPlaneArrays, List[tuple]]]:
        """The newest valid plane of an older frame (at most ground_max_age_s older), moved into this
        frame by the camera-pose delta, and the inputs it stands for; None when there is none."""
        p = self.params.value
        frame_stamp = stamp_to_ns(target.header.stamp)
        plane_stamp = frame_stamp
        self.pull_poses()
        pose_to = self.camera_poses.pose_at(frame_stamp, target.header.frame_id)
        if pose_to is None or p.ground_max_age_s <= 0:
            return None
        for stamp, plane in sorted(self.ground.companions.items(), key=lambda item: -item[0]):
            if stamp >= plane_stamp or not plane.valid:
                continue
            if plane_stamp - stamp > p.ground_max_age_s * 1e9:
                break
            pose_from = self.camera_poses.pose_at(stamp, plane.header.frame_id)
            if pose_from is None or pose_from.frame_id != pose_to.frame_id:
                continue
            arrays = ground_plane_to_arrays(plane)
            arrays.normal, arrays.offset = carry_plane(arrays.normal, arrays.offset, pose_from, pose_to)
            return arrays, [("ground_plane", stamp, InputStamp.CARRIED), ("camera_pose", stamp, InputStamp.CARRIED),
                            ("camera_pose", frame_stamp, InputStamp.SAME_FRAME)]
        return None

    # ------------------------------------------------------------------ planning and the goal

    def too_old(self, stamp_ns: int) -> bool:
        """Whether a frame of this stamp is older than max_goal_age_s now (never with a limit of 0)."""
        limit = self.params.value.max_goal_age_s
        return limit > 0 and self.now_ns() - stamp_ns > limit * 1e9

    @rejects_bad_input("bad_target")
    def with_floor(self, target: TargetGeometry, ground: Optional[GroundPlane]) -> None:
        """The target and its own plane (None: it never came): the floor to plan on, or the frame is dropped."""
        stamp = stamp_to_ns(target.header.stamp)
        if self.last_planned is not None and stamp <= self.last_planned:
            self.diagnostics.drop("older_than_published")
            return
        if not target.valid:
            self.diagnostics.reject("empty_target", "no person points in this frame: no goal")
            return
        inputs: List[tuple] = [("target_geometry", stamp)]
        if ground is not None and refused(self.diagnostics, "bad_target", check_same_frame, "target_geometry",
                                          target.header.frame_id, "ground_plane", ground.header.frame_id):
            return
        if ground is not None and ground.valid:
            floor = ground_plane_to_arrays(ground)
            inputs.append(("ground_plane", stamp_to_ns(ground.header.stamp)))
        else:
            carried = self.carried_plane(target)
            if carried is None:
                if ground is None:
                    self.diagnostics.reject("ground_plane_late", "no ground plane of this frame in time and none to"
                                            " carry by the camera pose: frame dropped, no goal")
                else:
                    self.diagnostics.reject("no_ground_plane", "no valid ground plane for this frame: no goal"
                                            " published")
                return
            floor, carried_inputs = carried
            inputs += carried_inputs
        self.last_planned = stamp
        frame = ReadyFrame(target, floor, inputs, self.now_ns())
        if self.pose_wait is not None:
            self.pose_wait = None
            self.diagnostics.drop("target_superseded")  # still waiting for its pose: this newer frame wins
        if self.map_in_use():
            self.pull_poses()
        if self.map_in_use() and self.camera_poses.pose_at(stamp, target.header.frame_id) is None \
                and self.params.value.camera_pose_wait_s > 0:
            self.pose_wait = frame  # DDS does not order topics: its pose may still be on the way
            self.camera_poses.expect(stamp, target.header.frame_id)
            self.start_wait_timer()
            return
        self.plan(frame)

    @rejects_bad_input("bad_target")
    def plan(self, frame: ReadyFrame, mesh_waited: bool = False) -> None:
        started = time.perf_counter()
        target, inputs = frame.target, list(frame.inputs)
        stamp = stamp_to_ns(target.header.stamp)
        if self.too_old(stamp):
            self.diagnostics.drop("too_old_to_plan")
            return
        found, body_mesh = self.body_mesh_for(frame, mesh_waited)
        if not found:
            return  # planned when the frame's body mesh comes (or the wait runs out)
        if body_mesh is not None:
            inputs.append((topics.HUMAN_MESH_METRIC, stamp))
        target_arrays = target_geometry_to_arrays(target)
        camera_pose = self.camera_pose_for_frame(stamp, target.header.frame_id)
        if camera_pose is not None:
            if ("camera_pose", stamp, InputStamp.SAME_FRAME) not in inputs:
                inputs.append(("camera_pose", stamp))
            inputs.append(("obstacle_map", self.obstacle_map_stamp, InputStamp.STATIC))
        plan = plan_views(target_arrays, frame.floor, self.params.value,
                          self.obstacle_map if camera_pose is not None else None, camera_pose, body_mesh)
        compute_time_ms = (time.perf_counter() - started) * 1e3
        # The goal first (what the motion stack waits for), then the candidates, the path and the markers.
        goal_published = False
        if plan.chosen_index < 0:
            self.diagnostics.reject("no_feasible_view", "every candidate is infeasible: no goal published")
        elif self.too_old(stamp):
            self.diagnostics.drop("goal_too_old")  # planning took it past the limit: no goal of it
        else:
            self.goal_pub.publish(PoseStamped(header=target.header, pose=pose_msg(*plan.chosen_pose())))
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
        # Replace the latched goals: a motion stack connecting later must not receive the old one.
        cleared = Header(frame_id="", stamp=self.get_clock().now().to_msg())
        self.goal_pub.publish(PoseStamped(header=cleared))
        self.base_goal_pub.publish(PoseStamped(header=cleared))
        self.base_path_pub.publish(Path(header=cleared))  # an empty path: no way to a current goal
        self.diagnostics.drop("goal_withdrawn_stale")
        self.publish_status(GoalStatus.STATE_STALE, f"no goal from a frame younger than {limit:g} s: the last one"
                            f" is {age_s:.2f} s old and was withdrawn")

    def publish_status(self, state: int, reason: str) -> None:
        now = self.now_ns()
        msg = GoalStatus(state=state, reason=reason, max_goal_age_s=float(self.params.value.max_goal_age_s))
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.goal_frame if state == GoalStatus.STATE_CURRENT else ""
        if self.goal_stamp is not None:
            msg.goal_stamp.sec, msg.goal_stamp.nanosec = divmod(self.goal_stamp, 1_000_000_000)
            msg.goal_age_s = float((now - self.goal_stamp) * 1e-9)
        self.goal_state = state
        self.status_pub.publish(msg)


def _score_colour(value: float, lo: float, hi: float):
    t = 0.0 if hi <= lo else (value - lo) / (hi - lo)
    return float(1.0 - t), float(t), 0.2  # red (low) -> green (high)


def candidate_markers(header, out: ViewCandidates, plan: Plan) -> MarkerArray:
    """Ring coloured by score, infeasible candidates as grey cubes, the chosen view as an arrow."""
    markers = MarkerArray()
    clear = Marker(header=header, ns="leapnbv_candidates", action=Marker.DELETEALL)
    markers.markers.append(clear)
    scores = np.asarray(out.score, dtype=np.float64)
    shown = scores[np.asarray(out.feasible, dtype=bool)]  # the colour scale of the candidates that were scored
    lo, hi = (float(shown.min()), float(shown.max())) if shown.size else (0.0, 1.0)
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
    tune_node_process()  # one BLAS thread, image buffers reused (leapnbv_common.process_tuning)
    run_node(NbvNode, args)


if __name__ == "__main__":
    main()
