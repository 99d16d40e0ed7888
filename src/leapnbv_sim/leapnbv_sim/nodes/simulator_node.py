"""simulator_node: a simulated RGB-D camera on a robot that drives to the next-best-view goals it gets.

The node holds one synthetic scene (:mod:`leapnbv_sim.scene`, made by :mod:`leapnbv_sim.generation`)
and renders it from the robot's current camera pose, publishing what a RealSense driver would
(colour, aligned depth in mm, both camera infos) plus the simulator's ground truth, all five with
one header (stamp = the sim time of the frame, frame_id = the camera's optical frame). Before the
images it publishes the world pose of the camera it rendered from on ``/leapnbv/camera_pose``
(geometry_msgs/PoseStamped, T_world_camera_optical, frame ``world_frame_id``, stamp = the frame's
stamp): what the robot's localization would give the graph, so a node that needs the pose of a
frame has it when the frame arrives. With ``publish_tf`` (the default) it also publishes that pose as
a robot's TF tree (:mod:`leapnbv_sim.robot_frames`): ``world_frame_id -> odom -> base_link ->
camera_link`` on ``/tf`` at the frame's stamp, just before the PoseStamped, and ``camera_link ->
frame_id`` once on ``/tf_static`` (transient-local), so that the graph can take its camera pose from
TF (``camera_pose_source: tf`` with ``camera_pose_fixed_frame`` = ``world_frame_id``).

Every scene it switches to (:meth:`SimulatorNode.set_scene`, also the first one) it publishes once
as a map of its static obstacles (occluders, walls, furniture: not the floor, not the person) on
``/leapnbv/obstacle_map``: a sensor_msgs/PointCloud2 of the occupied voxel centres
(:meth:`~leapnbv_sim.scene.Scene.obstacle_voxel_centres` at ``obstacle_map_resolution``, like
OctoMap's ``octomap_point_cloud_centers``) in frame ``world_frame_id``, reliable and
transient-local (a node that starts late still gets the current map).

It remembers the world camera pose of every stamp it published (a bounded memory) and
subscribes to the next-best-view goal (``goal``, remapped to ``/leapnbv/next_best_view`` by
default): a camera pose in the optical frame of the observation whose stamp the goal carries.
That pose goes to the world with ``pose_in_world(T_world_observation, R, p)``; the robot
(``robot_motion`` = base, the default) drives its base to the goal's point on the floor and its
camera stays at the mounting height, tilted to the goal's pitch or at its mounting pitch
(``robot_head``; :class:`leapnbv_sim.poses.RobotModel`), or (``robot_motion`` = free) the camera
takes the goal's 6-DoF pose. The camera moves there:

* ``move_speed_m_s`` = 0: at once (the next frame is rendered from the goal);
* ``move_speed_m_s`` > 0: along the straight line from where the camera is at the goal's
  arrival, at that speed in sim time; the orientation is slerped with the same progress (the
  camera turns while it drives and arrives with the goal's orientation). Motion starts at the
  sim time of the latest published frame, so frame stamps alone decide where each frame is
  rendered from (deterministic for in-process callers that choose the stamps).

A goal whose stamp the node never published (or forgot), or in another frame, is rejected and
counted on /diagnostics; the camera then stays where it is.

Continuous mode (``motion_stack``, :class:`leapnbv_sim.simulator.DrivenRobot`): the goal does not move
the camera itself; a simulated motion stack follows the base path of the latest CURRENT goal
(``/leapnbv/base_path``, nav_msgs/Path in the observation's optical frame, taken to the world with
that stamp's remembered pose) at the base's limits (``base_max_*``), and stops on a withdrawn goal
(``/leapnbv/goal_status`` not CURRENT, or an empty path) or when sim time passes the goal's
``valid_until`` (on its own clock: the STALE status of a goal that aged out comes whenever the
planner's age check ran, and is only confirmed by it); a changed goal's path
(``goal_status.goal_changed``) replaces the one followed, a kept goal's too with
``replan_kept_goals``. The pan-tilt head turns toward the latest plan's ring centre
(``/leapnbv/view_candidates``) and tilts to the goal's pitch (``next_best_view``) at its rates.
Each frame is rendered from where the robot is at the frame's stamp: the motion stack advances by
the time since the previous frame. With ``publish_clock`` the node owns sim time: it publishes
``/clock`` at each frame's stamp just before the frame (the lockstep an in-process caller drives:
:meth:`SimulatorNode.publish_frame` with the stamps it chooses), and with ``rate_hz`` > 0 also from
the wall clock at ``clock_rate_hz`` (the real-time mode, in which the graph plans from whatever
frames it keeps up with).

Frames are rendered at ``rate_hz`` from a timer (stamp = the node clock, which follows /clock
under use_sim_time), or, with ``rate_hz`` = 0, only when an in-process caller asks
(:meth:`SimulatorNode.publish_frame`, which takes the stamp to use). An in-process caller may
also hand the node a ready :class:`~leapnbv_sim.scene.Scene` (:meth:`SimulatorNode.set_scene`)
instead of the ``scene_seed`` parameters. The parameters are
:class:`~leapnbv_sim.simulator.SimulatorParams` (the scene ones, the rate and the frame ids are read at
start-up; the others may change at runtime, and a change of the obstacle map's parameters publishes
the map again).

    python -m leapnbv_sim.nodes.simulator_node --ros-args -p scene_seed:=3 -p rate_hz:=5.0
"""
from __future__ import annotations

import sys
import time
from collections import OrderedDict
from typing import Any, Callable, Dict, List, Optional, Set, Tuple
from typing import OrderedDict as OrderedDictType

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import Header
from tf2_msgs.msg import TFMessage

from leapnbv_common.conversions import (
    ConversionError,
    path_to_numpy,
    pose_msg,
    pose_to_numpy,
    stamp_to_ns,
    xyz_to_pointcloud2,
)
from leapnbv_common.diagnostics import StageDiagnostics, rejects_bad_input
from leapnbv_common.node_params import NodeParams, run_node
from leapnbv_common.qos import (
    camera_input_qos,
    latched_goal_qos,
    latched_map_qos,
    stage_output_qos,
    tf_qos,
    tf_static_qos,
)
from leapnbv_common.topics import (
    BASE_PATH,
    CAMERA_POSE_TOPIC,
    COLOR_IMAGE_TOPIC,
    COLOR_INFO_TOPIC,
    DEPTH_IMAGE_TOPIC,
    DEPTH_INFO_TOPIC,
    GOAL_STATUS,
    GROUND_TRUTH_TOPIC,
    NEXT_BEST_VIEW_TOPIC,
    OBSTACLE_MAP_TOPIC,
    SCENE_PEOPLE_TOPIC,
    TF_STATIC_TOPIC,
    TF_TOPIC,
    VIEW_CANDIDATES,
    output_topic,
)
from leapnbv_msgs.msg import GoalStatus, SceneGroundTruth, ScenePeople, TargetTrack, ViewCandidates
from leapnbv_sim.frame_messages import camera_frame_messages, robot_static_tf_message, robot_tf_message
from leapnbv_sim.poses import CameraPose, pose_in_world
from leapnbv_sim.render import RenderedFrame
from leapnbv_sim.scene import Scene
from leapnbv_sim.simulator import (
    CameraMotion,
    DrivenRobot,
    SimulatorParams,
    base_limits,
    load_scene,
    robot_frame_ids,
    robot_model,
    search_limits,
)

DEFAULT_GOAL_TOPIC = NEXT_BEST_VIEW_TOPIC
# Local remap of the relative goal topic applied unless the caller remaps it itself.
DEFAULT_GOAL_REMAP = ["--ros-args", "-r", "goal:=" + DEFAULT_GOAL_TOPIC]
# Camera drivers offer sensor-data QoS: best effort, keep the last 5 frames.
CAMERA_QOS_DEPTH = 5
CLOCK_TOPIC = "/clock"
# The motion stack reads the latched goal topics with a deeper queue than the publisher's 1: a withdrawal and the
# next goal can both arrive between two spins of an in-process caller, and neither may be lost.
GOAL_READER_DEPTH = 10


def clock_publisher(node: Node) -> Callable[[int], None]:
    """A /clock publisher on ``node``: call it with a sim time (ns) to publish it."""
    publisher = node.create_publisher(Clock, CLOCK_TOPIC, 10)

    def publish(stamp_ns: int) -> None:
        msg = Clock()
        msg.clock.sec, msg.clock.nanosec = divmod(int(stamp_ns), 1_000_000_000)
        publisher.publish(msg)

    return publish


def goal_reader_qos() -> QoSProfile:
    """The motion stack's subscriptions to the latched goal topics (reliable, transient-local, depth 10)."""
    return QoSProfile(depth=GOAL_READER_DEPTH, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


class SimulatorError(ValueError):
    """The simulator cannot do what was asked (no scene, bad stamp); the text says why."""


class SimulatorNode(Node):
    """The simulated robot camera (see the module docstring).

    Args:
        scene: A ready scene (in-process callers); generated from the parameters when None.
        **node_kwargs: Passed to rclpy's Node (e.g. ``parameter_overrides``, ``cli_args``);
            without ``cli_args`` the goal topic is remapped to /leapnbv/next_best_view.
    """

    def __init__(self, scene: Optional[Scene] = None, **node_kwargs: Any) -> None:
        node_kwargs.setdefault("cli_args", list(DEFAULT_GOAL_REMAP))
        super().__init__("simulator_node", **node_kwargs)
        self.node_params = NodeParams(self, SimulatorParams, on_change=self._on_params_change)
        p = self.node_params.value
        self.diagnostics = StageDiagnostics(self, hardware_id="simulator")
        self.frame_id = p.frame_id
        camera_qos = camera_input_qos(CAMERA_QOS_DEPTH)
        self.frame_pubs = {
            COLOR_IMAGE_TOPIC: self.create_publisher(Image, COLOR_IMAGE_TOPIC, camera_qos),
            COLOR_INFO_TOPIC: self.create_publisher(CameraInfo, COLOR_INFO_TOPIC, camera_qos),
            DEPTH_IMAGE_TOPIC: self.create_publisher(Image, DEPTH_IMAGE_TOPIC, camera_qos),
            DEPTH_INFO_TOPIC: self.create_publisher(CameraInfo, DEPTH_INFO_TOPIC, camera_qos),
            # The detector and HMR nodes pair every image with its ground truth: deliver it reliably.
            GROUND_TRUTH_TOPIC: self.create_publisher(SceneGroundTruth, GROUND_TRUTH_TOPIC, stage_output_qos(10)),
            # The other people, with the same stamp (empty in a one-person scene), as reliably.
            SCENE_PEOPLE_TOPIC: self.create_publisher(ScenePeople, SCENE_PEOPLE_TOPIC, stage_output_qos(10)),
        }
        self.pose_pub = self.create_publisher(PoseStamped, CAMERA_POSE_TOPIC, stage_output_qos(10))
        self.frame_ids = robot_frame_ids(p)
        self.tf_pub = self.create_publisher(TFMessage, TF_TOPIC, tf_qos())
        # A static broadcaster's QoS (depth 1, transient-local): its one message reaches late listeners.
        self.tf_static_pub = self.create_publisher(TFMessage, TF_STATIC_TOPIC, tf_static_qos(1))
        if p.publish_tf:
            self.tf_static_pub.publish(robot_static_tf_message(self.frame_ids))
        # Created before the first set_scene below, which publishes the first scene's map.
        self.map_pub = self.create_publisher(PointCloud2, OBSTACLE_MAP_TOPIC, latched_map_qos())
        self.create_subscription(PoseStamped, "goal", self.on_goal, latched_goal_qos())
        self.clock_pub = clock_publisher(self) if p.publish_clock else None
        #: The sim time last published on /clock (publish_clock), None before.
        self.clock_ns: Optional[int] = None
        if p.motion_stack:
            self.create_subscription(GoalStatus, output_topic(GOAL_STATUS), self.on_goal_status, goal_reader_qos())
            self.create_subscription(Path, output_topic(BASE_PATH), self.on_base_path, goal_reader_qos())
            self.create_subscription(ViewCandidates, output_topic(VIEW_CANDIDATES), self.on_view_candidates,
                                     stage_output_qos(10))

        self.scene: Optional[Scene] = None
        self.camera: Optional[CameraPose] = None
        self.motion: Optional[CameraMotion] = None
        #: Continuous mode: the robot the motion stack drives (made with each scene).
        self.robot: Optional[DrivenRobot] = None
        #: Continuous mode: the latest goal status received, and every status of the current scene, in order.
        self.goal_status: Optional[GoalStatus] = None
        self.goal_statuses: List[GoalStatus] = []
        #: Continuous mode: the latest CURRENT status's valid_until (ns; None: no limit, or none yet).
        self.held_valid_until_ns: Optional[int] = None
        #: Continuous mode: stamp of the frame the latest path taken was planned on, and its world points.
        self.last_path_stamp_ns: Optional[int] = None
        self.last_path_world: Optional[np.ndarray] = None
        #: Continuous mode: stamps of the latest base path and view candidates received (taken or not).
        self.last_path_msg_stamp_ns: Optional[int] = None
        self.last_view_candidates_stamp_ns: Optional[int] = None
        self.frame_count = 0
        #: Sim time of the current scene's first frame: the scene's time 0 (Scene.at_time), None before it.
        self.scene_start_ns: Optional[int] = None
        self.last_stamp_ns: Optional[int] = None
        self.last_goal_stamp_ns: Optional[int] = None
        self.goals_accepted = 0
        self._poses: OrderedDictType[int, CameraPose] = OrderedDict()  # oldest stamp first
        if scene is None:
            scene = load_scene(p)
        self.set_scene(scene)
        if p.rate_hz > 0.0:
            self.create_timer(1.0 / p.rate_hz, self.on_timer)
            if self.clock_pub is not None:  # the real-time mode: sim time follows the wall clock
                self.create_timer(1.0 / p.clock_rate_hz, self.publish_wall_clock)

    @property
    def params(self) -> SimulatorParams:
        """The parameters in force."""
        return self.node_params.value

    def _on_params_change(self, params: SimulatorParams, changed: Set[str]) -> None:
        """A runtime change: a new obstacle map resolution or switch publishes the map again, TF switched on its
        static links."""
        if changed & {"obstacle_map_resolution", "publish_obstacle_map"} and params.publish_obstacle_map:
            self.publish_obstacle_map(params.obstacle_map_resolution)
        if "publish_tf" in changed and params.publish_tf:
            self.tf_static_pub.publish(robot_static_tf_message(self.frame_ids))

    # ------------------------------------------------------------------ scene and camera state

    def set_scene(self, scene: Scene, camera: Optional[CameraPose] = None) -> None:
        """Switch to a scene: camera at its start pose (or ``camera``), no motion, no remembered stamps.

        Forgetting the stamps makes any goal planned in the previous scene (e.g. the latched
        last goal) a rejected one instead of a jump to nonsense. The new scene's obstacle map is
        published once (unless ``publish_obstacle_map`` is off).
        """
        self.scene = scene
        start = camera if camera is not None else scene.start_camera
        self.camera = start.copy()
        self.motion = None
        self.frame_count = 0
        self.scene_start_ns = None
        self._poses.clear()
        self.last_goal_stamp_ns = None
        p = self.params
        self.robot = DrivenRobot(start, base_limits(p), p.robot_head, p.replan_kept_goals,
                                 search_limits(p)) if p.motion_stack else None
        self.goal_status = None
        self.held_valid_until_ns = None
        self.goal_statuses = []
        self.last_path_stamp_ns = None
        self.last_path_world = None
        self.last_path_msg_stamp_ns = None
        self.last_view_candidates_stamp_ns = None
        if self.params.publish_obstacle_map:
            self.publish_obstacle_map()

    def publish_obstacle_map(self, resolution: Optional[float] = None) -> PointCloud2:
        """Publish the current scene's obstacle voxel centres (world frame, stamp = now) and return the message.

        Args:
            resolution: Voxel edge (m); ``obstacle_map_resolution`` when None.

        Raises:
            SimulatorError: No scene.
        """
        if self.scene is None:
            raise SimulatorError("no scene loaded")
        if resolution is None:
            resolution = self.params.obstacle_map_resolution
        centres = self.scene.obstacle_voxel_centres(resolution)
        header = Header(frame_id=self.params.world_frame_id, stamp=self.get_clock().now().to_msg())
        if self.params.publish_clock:  # on sim time: the graph's clock is the frames' stamps, not the wall's
            header.stamp.sec, header.stamp.nanosec = divmod(self.last_stamp_ns or 0, 1_000_000_000)
        msg = xyz_to_pointcloud2(centres, header)
        self.map_pub.publish(msg)
        return msg

    def publish_map_points(self, centres: np.ndarray, stamp_ns: int) -> PointCloud2:
        """Publish other occupied voxel centres (world frame) as the obstacle map, at ``stamp_ns``: e.g. a map
        built from the frames' depth (leapnbv_planner.obstacle_memory) in place of the scene's."""
        header = Header(frame_id=self.params.world_frame_id)
        header.stamp.sec, header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
        msg = xyz_to_pointcloud2(centres, header)
        self.map_pub.publish(msg)
        return msg

    @property
    def body_model_id(self) -> str:
        return self.scene.body_model_id if self.scene is not None else ""

    def camera_pose_at(self, stamp_ns: int) -> Optional[CameraPose]:
        """The world camera pose a published stamp was rendered from, if still remembered."""
        return self._poses.get(int(stamp_ns))

    def move_to(self, goal: CameraPose, start_ns: Optional[int] = None) -> None:
        """Start moving the camera to a world pose (at once when move_speed_m_s is 0).

        Args:
            goal: Target T_world_camera.
            start_ns: Sim time the motion starts; the latest published stamp when None.
        """
        if self.camera is None:  # (a goal names a rendered frame's stamp: there is a camera once one was)
            raise ValueError("no camera pose yet: no frame has been rendered")
        if start_ns is None:
            start_ns = self.last_stamp_ns if self.last_stamp_ns is not None else 0
        speed = self.params.move_speed_m_s
        self.motion = CameraMotion(self.camera, goal, int(start_ns), speed)
        if speed <= 0.0:
            self.camera = self.motion.pose_at(int(start_ns))
            self.motion = None

    # ------------------------------------------------------------------ frames

    @rejects_bad_input("render_failed")
    def on_timer(self) -> None:
        self.publish_frame()

    def publish_frame(self, stamp_ns: Optional[int] = None) -> Tuple[int, RenderedFrame]:
        """Render the scene from the current camera and publish the camera pose, then the five topics.

        The scene is rendered as it is at the frame's time (:meth:`~leapnbv_sim.scene.Scene.at_time`: the sim time
        since the scene's first frame, the first frame after :meth:`set_scene`), so its moving people walk with
        sim time; a scene whose people stand renders the same at every time.

        Args:
            stamp_ns: Sim time of the frame (header stamp); the node clock's now when None.
                Stamps must increase (a motion in progress is evaluated at this time).

        Returns:
            (stamp_ns, the rendered frame).

        Raises:
            SimulatorError: No scene, or a stamp not later than the previous one (the timer's
                guard counts it on /diagnostics and keeps the node running).
        """
        self.diagnostics.frame_in()
        started = time.perf_counter()
        if self.scene is None or self.camera is None:
            raise SimulatorError("no scene loaded")
        if stamp_ns is None:
            stamp_ns = self.get_clock().now().nanoseconds
        stamp_ns = int(stamp_ns)
        if self.last_stamp_ns is not None and stamp_ns <= self.last_stamp_ns and self.frame_count > 0:
            raise SimulatorError(f"frame stamp {stamp_ns} ns is not after the previous {self.last_stamp_ns} ns")
        if self.robot is not None:
            driven_from = self.last_stamp_ns if self.last_stamp_ns is not None and self.frame_count else stamp_ns
            self.camera = self.robot.drive(driven_from, stamp_ns)
        elif self.motion is not None:
            self.camera = self.motion.pose_at(stamp_ns)
            if self.motion.fraction_at(stamp_ns) >= 1.0:
                self.motion = None
        camera = self.camera
        if self.clock_pub is not None:  # sim time reaches the frame's stamp before the frame
            self.publish_clock(stamp_ns)
        if self.frame_count == 0 or self.scene_start_ns is None:
            self.scene_start_ns = stamp_ns  # the scene's first frame is its time 0
        # The scene as it is at the frame's time (its people where they walked to; a standing scene is itself).
        frame = self.scene.at_time((stamp_ns - self.scene_start_ns) * 1e-9).render(camera,
                                                                                    frame_index=self.frame_count)
        header = Header(frame_id=self.frame_id)
        header.stamp.sec, header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
        messages = camera_frame_messages(frame, header, self.body_model_id)
        # Calibration and the camera pose first: a node that pairs images with their intrinsics
        # or their pose has them on arrival.
        for topic in (COLOR_INFO_TOPIC, DEPTH_INFO_TOPIC):
            self.frame_pubs[topic].publish(messages.pop(topic))
        if self.params.publish_tf:
            self.tf_pub.publish(robot_tf_message(camera, stamp_ns, self.frame_ids))
        pose_header = Header(frame_id=self.params.world_frame_id, stamp=header.stamp)
        self.pose_pub.publish(PoseStamped(header=pose_header, pose=pose_msg(camera.rotation, camera.position)))
        for topic, message in messages.items():  # ground truth, colour, depth
            self.frame_pubs[topic].publish(message)

        self._poses[stamp_ns] = camera.copy()
        while len(self._poses) > self.params.pose_memory:
            self._poses.popitem(last=False)
        self.last_stamp_ns = stamp_ns
        self.frame_count += 1
        self.diagnostics.frame_out(header.stamp, (time.perf_counter() - started) * 1e3)
        return stamp_ns, frame

    def publish_clock(self, stamp_ns: int) -> None:
        """Publish /clock at ``stamp_ns`` (nothing without ``publish_clock``)."""
        if self.clock_pub is None:
            return
        self.clock_pub(stamp_ns)
        self.clock_ns = int(stamp_ns)

    def publish_wall_clock(self) -> None:
        """The real-time mode's /clock: the node's (wall) clock now."""
        self.publish_clock(self.get_clock().now().nanoseconds)

    # ------------------------------------------------------------------ goals

    @rejects_bad_input("bad_goal")
    def on_goal(self, msg: PoseStamped) -> None:
        if not msg.header.frame_id:
            return  # "no current goal" (the planner withdrew a stale one): the robot stays where it is
        stamp = stamp_to_ns(msg.header.stamp)
        if msg.header.frame_id != self.frame_id:
            raise ConversionError(f"goal in frame {msg.header.frame_id!r}, expected {self.frame_id!r}")
        observation = self.camera_pose_at(stamp)
        if observation is None:
            self.diagnostics.reject("unknown_goal_stamp",
                                    f"goal stamped {stamp} ns: no frame with that stamp is remembered; staying")
            return
        rotation, position = pose_to_numpy(msg.pose)
        if not (np.all(np.isfinite(rotation)) and np.all(np.isfinite(position))):
            raise ConversionError("goal pose is not finite")
        goal = pose_in_world(observation, rotation, position)
        if self.robot is not None:
            self.robot.take_view(goal)  # the motion stack drives the base path; the goal aims the head
        else:
            self.move_to(robot_model(self.params).reach(observation, goal))
        self.last_goal_stamp_ns = stamp
        self.goals_accepted += 1

    @rejects_bad_input("bad_goal_status")
    def on_goal_status(self, msg: GoalStatus) -> None:
        """Continuous mode: a goal that is not CURRENT (withdrawn, aged out, none) stops the robot.

        With the target not seen (``target`` NOT_SEEN or LOST) the stop starts the robot's search
        (:meth:`DrivenRobot.lose_target`: look toward the target's last known place, then drive back to where it
        was last seen from). A status whose target is TRACKED tells where the target was seen from (the camera of
        its frame). A status about a goal planned on a frame this scene never rendered (a previous scene's,
        arriving late) is not about the robot's goal: ignored.
        """
        if self.camera_pose_at(stamp_to_ns(msg.goal_stamp)) is None:
            return
        self.goal_status = msg
        self.goal_statuses.append(msg)
        if self.robot is None:
            return
        target = msg.target
        if target.state == TargetTrack.STATE_TRACKED:
            seen_from = self.camera_pose_at(stamp_to_ns(target.header.stamp))
            if seen_from is not None:
                self.robot.saw_target_from(seen_from.position)
        lost, place = self._target_last_known(target)
        if msg.state == GoalStatus.STATE_CURRENT:
            valid_until = stamp_to_ns(msg.valid_until)
            self.held_valid_until_ns = valid_until if valid_until > 0 else None
            self.robot.hold_goal_until(self.held_valid_until_ns, lost, place)
            return
        if msg.state == GoalStatus.STATE_STALE and self._aged_out(msg.header):
            if lost and not self.robot.stack.has_path:
                self.robot.lose_target(place)  # braked already: the search starts now
            elif lost:
                self.robot.hold_goal_until(self.held_valid_until_ns, lost, place)
            return
        if lost:
            self.robot.lose_target(place)
        else:
            self.robot.withdraw()

    def _aged_out(self, header: Header) -> bool:
        """Whether a withdrawal (its header stamped when it was made) came after the held goal's valid_until.

        The robot then brakes at valid_until on its own clock (DrivenRobot.drive), not when the withdrawal
        arrives: on sim time the planner's age check may run while a frame is in flight or only after the next
        one, and the episode would depend on this machine's speed.
        """
        return self.held_valid_until_ns is not None and stamp_to_ns(header.stamp) > self.held_valid_until_ns

    def _target_last_known(self, target: TargetTrack) -> Tuple[bool, Optional[np.ndarray]]:
        """Whether a status's target is not seen (NOT_SEEN, LOST), and then its last known place (world) if any."""
        if target.state not in (TargetTrack.STATE_NOT_SEEN, TargetTrack.STATE_LOST):
            return False, None
        place = np.array([target.position.x, target.position.y, target.position.z], dtype=np.float64)
        known = target.fixed_frame == self.params.world_frame_id and bool(np.all(np.isfinite(place)))
        return True, place if known else None

    @rejects_bad_input("bad_base_path")
    def on_base_path(self, msg: Path) -> None:
        """Continuous mode: the CURRENT goal's base path, in the observation's optical frame, to follow."""
        if self.robot is None:
            return
        if not msg.header.frame_id or not msg.poses:
            if not self._aged_out(msg.header):
                self.robot.no_path()  # "no way to a current goal"
            return
        if msg.header.frame_id != self.frame_id:
            raise ConversionError(f"base path in frame {msg.header.frame_id!r}, expected {self.frame_id!r}")
        stamp = stamp_to_ns(msg.header.stamp)
        self.last_path_msg_stamp_ns = stamp
        observation = self.camera_pose_at(stamp)
        if observation is None:
            self.diagnostics.reject("unknown_path_stamp",
                                    f"base path stamped {stamp} ns: no frame with that stamp is remembered")
            return
        rotations, positions = path_to_numpy(msg)
        if not (np.all(np.isfinite(rotations)) and np.all(np.isfinite(positions))):
            raise ConversionError("base path is not finite")
        points = positions @ observation.rotation.T + observation.position
        final_rotation = observation.rotation @ rotations[-1]
        status = self.goal_status
        # The status of this path's goal comes first (nbv_node publishes it before the path); without it: a new goal.
        changed = status is None or stamp_to_ns(status.goal_stamp) != stamp or bool(status.goal_changed)
        if self.robot.take_path(points, final_rotation, changed):
            self.last_path_stamp_ns = stamp
            self.last_path_world = points

    @rejects_bad_input("bad_view_candidates")
    def on_view_candidates(self, msg: ViewCandidates) -> None:
        """Continuous mode: the plan's ring centre (the target's floor point) is where the head looks."""
        if self.robot is None or msg.header.frame_id != self.frame_id:
            return
        observation = self.camera_pose_at(stamp_to_ns(msg.header.stamp))
        if observation is None:
            return
        self.last_view_candidates_stamp_ns = stamp_to_ns(msg.header.stamp)
        centre = np.array([msg.ring_center.x, msg.ring_center.y, msg.ring_center.z], dtype=np.float64)
        if np.all(np.isfinite(centre)) and msg.ring_radius > 0.0:
            self.robot.look_at_target(observation.rotation @ centre + observation.position)


def _global_args_remap_goal(args: Optional[List[str]]) -> bool:
    return any(str(arg).startswith("goal:=") for arg in (args if args is not None else sys.argv))


def main(args: Optional[List[str]] = None) -> None:
    """Run the node from parameters (``--ros-args -p scene_seed:=N ...``) until Ctrl-C."""
    kwargs: Dict[str, Any] = {}
    if _global_args_remap_goal(args):
        kwargs["cli_args"] = []  # the command line remaps the goal itself (local rules would win)
    run_node(lambda: SimulatorNode(**kwargs), args)


if __name__ == "__main__":
    main()
