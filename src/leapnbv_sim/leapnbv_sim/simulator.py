"""The simulated robot without ROS: its parameters, the scene they describe, and how its camera moves.

:class:`SimulatorParams` is the one source of the simulator node's parameters (names, defaults,
ranges, read-only flags: ``leapnbv_common.params``). A goal is reached at once (speed 0) or along a
straight line in sim time (:class:`CameraMotion`), the orientation slerped with the same progress
(:func:`interpolate_camera_pose`); or (``motion_stack``) a simulated motion stack follows the
latest current goal's base path (:class:`DrivenRobot` over :class:`leapnbv_sim.motion_stack.MotionStack`):
the continuous mode, in which the camera renders at camera rate while the robot drives.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional

import numpy as np

from leapnbv_common.array_types import FloatArray
from leapnbv_common.params import param
from leapnbv_perception.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_sim.generation import SceneConfig, generate_scene
from leapnbv_sim.motion_stack import BaseLimits, MotionStack
from leapnbv_sim.poses import HEAD_MODES, ROBOT_MOTIONS, CameraPose, RobotModel, camera_pitch
from leapnbv_sim.robot_frames import RobotFrameIds
from leapnbv_sim.scene import Scene
from leapnbv_stand_ins.files import ensure_stand_in_body_model


@dataclass
class SimulatorParams:
    """Parameters of the simulator node (the scene ones are read at start-up only)."""

    scene_seed: int = param(0, "seed of the synthetic scene (leapnbv_sim.generation.SceneConfig.seed)", min=0,
                            read_only=True)
    body_resolution: str = param("small", "stand-in body model resolution: small or full", choices=("small", "full"),
                                 read_only=True)
    body_model_path: str = param("", "SMPL-X layout .npz of the scene's body (empty: the stand-in of body_resolution)",
                                 read_only=True)
    walls: bool = param(True, "add a wall behind the person (and sometimes one beside)", read_only=True)
    depth_noise: bool = param(True, "corrupt the depth like a structured-light sensor", read_only=True)
    rate_hz: float = param(10.0, "frames per second from a timer; 0 = only when an in-process caller asks", min=0.0,
                           max=1000.0, read_only=True)
    move_speed_m_s: float = param(0.0, "0 = jump to each goal; > 0 = drive there on a straight line at this speed",
                                  min=0.0, max=100.0)
    frame_id: str = param("camera_color_optical_frame", "frame_id of every published frame", read_only=True)
    world_frame_id: str = param("sim_world", "frame_id of the published camera pose and obstacle map (the "
                                "simulator's world)", read_only=True)
    pose_memory: int = param(300, "how many published stamps keep their camera pose for goal lookups", min=1,
                             max=1_000_000)
    obstacle_map_resolution: float = param(0.1, "metres: voxel edge of the published obstacle map", min=0.01, max=2.0)
    publish_obstacle_map: bool = param(True, "publish the scene's static obstacles as a voxel map, as a robot's "
                                       "mapping stack would")
    robot_motion: str = param("base", "base: a goal drives the robot's base there and the camera stays at its "
                              "mounting height; free: the camera jumps to the goal's 6-DoF pose",
                              choices=ROBOT_MOTIONS)
    robot_head: str = param("pan_tilt", "pan_tilt: the camera tilts to the goal's pitch; fixed: it keeps its "
                            "mounting pitch (the start camera's)", choices=HEAD_MODES)
    robot_camera_height: float = param(0.0, "metres: the camera's mounting height; 0 = the height of the camera "
                                       "that observed the goal's frame", min=0.0, max=10.0)
    publish_tf: bool = param(True, "publish the robot's frames as a robot does: world_frame_id -> odom -> base -> "
                             "camera link on /tf at each frame's stamp, camera link -> frame_id on /tf_static")
    odom_frame_id: str = param("odom", "the odometry frame of the published TF tree", read_only=True)
    base_frame_id: str = param("base_link", "the robot's base frame of the published TF tree", read_only=True)
    camera_link_frame_id: str = param("camera_link", "the camera head's frame of the published TF tree (its "
                                      "optical frame is frame_id)", read_only=True)
    motion_stack: bool = param(False, "continuous mode: a simulated motion stack follows the latest CURRENT goal's "
                               "base_path at the base's and head's limits below while frames render (stops on a "
                               "withdrawn goal); off: each goal moves the camera as move_speed_m_s says",
                               read_only=True)
    replan_kept_goals: bool = param(True, "motion stack: a kept goal's new path (planned from where the robot is "
                                    "now) replaces the one followed; off: only a changed goal's path does "
                                    "(goal_status.goal_changed)")
    base_max_speed_m_s: float = param(0.5, "motion stack: the base's top speed", min=0.01, max=10.0)
    base_max_accel_m_s2: float = param(0.5, "motion stack: the base's acceleration and braking limit", min=0.01,
                                       max=20.0)
    base_max_turn_rate_rad_s: float = param(1.0, "motion stack: the base's turn rate", min=0.01, max=20.0)
    head_pan_rate_rad_s: float = param(1.5, "motion stack: the pan-tilt head's pan rate", min=0.01, max=20.0)
    head_tilt_rate_rad_s: float = param(1.0, "motion stack: the pan-tilt head's tilt rate", min=0.01, max=20.0)
    search_look_s: float = param(1.5, "motion stack: a goal withdrawn because the target is not seen: seconds it "
                                 "stands looking toward the target's last known place before it drives back",
                                 min=0.0, max=60.0)
    search_return_m: float = param(3.0, "motion stack: then the longest drive back along its own track to where it "
                                   "last saw the target from (0: it only looks)", min=0.0, max=50.0)
    search_back_off_m: float = param(0.5, "motion stack: how much farther back along its track than that place the "
                                     "search drives (within search_return_m): the last frame that saw the target "
                                     "mostly saw it at the edge of what hid it", min=0.0, max=50.0)
    publish_clock: bool = param(False, "publish /clock (the simulator owns sim time): at each frame's stamp before "
                                "the frame, and with rate_hz > 0 from the wall clock at clock_rate_hz (the "
                                "real-time mode)", read_only=True)
    clock_rate_hz: float = param(100.0, "real-time mode: how often /clock is published", min=1.0, max=1000.0,
                                 read_only=True)


def robot_model(params: SimulatorParams) -> RobotModel:
    """The robot the parameters describe (how a goal is reached)."""
    return RobotModel(motion=params.robot_motion, head=params.robot_head, camera_height=params.robot_camera_height)


def robot_frame_ids(params: SimulatorParams) -> RobotFrameIds:
    """The frames of the TF tree the simulator publishes (world_frame_id down to frame_id)."""
    return RobotFrameIds(world=params.world_frame_id, odom=params.odom_frame_id, base=params.base_frame_id,
                         head=params.camera_link_frame_id, camera=params.frame_id)


def base_limits(params: SimulatorParams) -> BaseLimits:
    """The motion stack's limits the parameters give."""
    return BaseLimits(max_speed_m_s=params.base_max_speed_m_s, max_accel_m_s2=params.base_max_accel_m_s2,
                      max_turn_rate_rad_s=params.base_max_turn_rate_rad_s, pan_rate_rad_s=params.head_pan_rate_rad_s,
                      tilt_rate_rad_s=params.head_tilt_rate_rad_s)


def search_limits(params: SimulatorParams) -> SearchLimits:
    """The lost-target search's limits the parameters give."""
    return SearchLimits(look_s=params.search_look_s, return_m=params.search_return_m,
                        back_off_m=params.search_back_off_m)


def load_scene(params: SimulatorParams) -> Scene:
    """Generate the scene the parameters describe (default SceneConfig otherwise).

    Raises:
        SceneError: The seed gives no usable scene.
    """
    path = params.body_model_path or ensure_stand_in_body_model(params.body_resolution)
    config = SceneConfig(seed=int(params.scene_seed), walls=bool(params.walls), depth_noise=bool(params.depth_noise),
                         body_resolution=str(params.body_resolution))
    return generate_scene(config, SMPLXModel.load(path))


def interpolate_camera_pose(start: CameraPose, goal: CameraPose, fraction: float) -> CameraPose:
    """A pose between two camera poses: position on the straight line, orientation slerped.

    R(f) = R_0 exp(f log(R_0^T R_1)), p(f) = p_0 + f (p_1 - p_0), with f clipped to [0, 1].

    Args:
        start: Pose at fraction 0.
        goal: Pose at fraction 1.
        fraction: Progress along the motion.

    Returns:
        The interpolated T_world_camera (exactly ``goal`` at fraction >= 1).
    """
    f = min(1.0, max(0.0, float(fraction)))
    if f >= 1.0:
        return goal.copy()
    relative = matrix_to_axis_angle(start.rotation.T @ goal.rotation)
    rotation = start.rotation @ axis_angle_to_matrix(f * np.asarray(relative, dtype=np.float64))
    position = start.position + f * (goal.position - start.position)
    return CameraPose(rotation, position)


class CameraMotion:
    """A straight-line camera motion in sim time (speed 0: the goal is reached at once)."""

    def __init__(self, start: CameraPose, goal: CameraPose, start_ns: int, speed_m_s: float) -> None:
        self.start = start
        self.goal = goal
        self.start_ns = int(start_ns)
        self.speed_m_s = float(speed_m_s)
        self.distance_m = float(np.linalg.norm(goal.position - start.position))

    def fraction_at(self, stamp_ns: int) -> float:
        """Progress in [0, 1] at a sim time (1 for an instant move or a pure turn)."""
        if self.speed_m_s <= 0.0 or self.distance_m < 1e-9:
            return 1.0
        travelled = max(0, int(stamp_ns) - self.start_ns) * 1e-9 * self.speed_m_s
        return min(1.0, travelled / self.distance_m)

    def pose_at(self, stamp_ns: int) -> CameraPose:
        return interpolate_camera_pose(self.start, self.goal, self.fraction_at(stamp_ns))


def level_heading(rotation: FloatArray) -> float:
    """Heading (rad about world z) of a level frame's x axis (a base pose of a nav_msgs/Path)."""
    x_axis = np.asarray(rotation, dtype=np.float64).reshape(3, 3)[:, 0]
    return float(math.atan2(x_axis[1], x_axis[0]))


#: What the robot's search for a lost target is doing (:attr:`DrivenRobot.search_phase`).
SEARCH_NONE = "none"  # no search: following a goal, or standing without one
SEARCH_LOOKING = "looking"  # braking / standing, the head toward the target's last known place
SEARCH_RETURNING = "returning"  # driving back along its own track to where it last saw the target from
SEARCH_WAITING = "waiting"  # back there (or nowhere to go back to): standing and looking; the search is over
SEARCH_PHASES = (SEARCH_NONE, SEARCH_LOOKING, SEARCH_RETURNING, SEARCH_WAITING)
#: The track a search may drive back along keeps this many positions (one per camera frame that moved the base).
MAX_TRACK_POINTS = 10_000


@dataclass(frozen=True)
class SearchLimits:
    """How far the search for a lost target goes (:class:`DrivenRobot`).

    Attributes:
        look_s: seconds the robot stands looking toward the target's last known place before it drives back.
        return_m: the longest drive back along its own track (0: it only looks).
        back_off_m: how much farther back along the track than the place nearest the last seen-from place it
            drives (within return_m): that frame mostly saw the person at the edge of what hid them (furnished
            seed 25 without the map went back to where 3 x 10 pixels of the person showed, and stood there).
    """

    look_s: float = 1.5
    return_m: float = 3.0
    back_off_m: float = 0.5

    def __post_init__(self) -> None:
        for name in ("look_s", "return_m", "back_off_m"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"search limit {name} must be a finite number >= 0, got {value}")


class DrivenRobot:
    """The continuous mode's robot: what a motion stack does with the planner's goal topics, in sim time.

    It follows the base path of the latest CURRENT goal (:meth:`take_path`, world frame) and stops on a
    withdrawn one (:meth:`withdraw`). A changed goal's path always replaces the one followed; a kept goal's
    path (the same goal, planned from where the robot is now) only with ``replan_kept``. The head (pan-tilt)
    turns toward the target (the latest plan's ring centre or the target's last known place,
    :meth:`look_at_target`) from wherever the base is and tilts to the goal's pitch (:meth:`take_view`); a
    fixed head keeps its pan at 0 and its mounting pitch.

    The goal it follows may be acted on until its ``valid_until`` (GoalStatus; :meth:`hold_goal_until`): the
    robot brakes there on its own clock (:meth:`drive`), as a motion stack should, so a late or lost
    withdrawal (a slow link, a frozen planner) does not keep it driving, and the moment it stops does not
    depend on when the planner's own age check ran.

    A goal withdrawn because the target is no longer seen (:meth:`lose_target`) starts a bounded,
    deterministic search: the base brakes to a stop with the head toward the target's last known place
    (LOOKING); after ``search.look_s`` without a new goal it drives back along its own track to the place
    of the latest frame that saw the target (:meth:`saw_target_from`), at most ``search.return_m``, and turns
    toward the target there (RETURNING); then it stands and looks (WAITING). The next CURRENT goal's path
    ends the search.

    Args:
        camera: The camera's pose now (the robot stands under it).
        limits: The base's and head's limits.
        head: One of ``HEAD_MODES``.
        replan_kept: Whether a kept goal's path replaces the one followed.
        search: The lost-target search's limits (defaults: :class:`SearchLimits`).
    """

    def __init__(self, camera: CameraPose, limits: BaseLimits, head: str = "pan_tilt", replan_kept: bool = True,
                 search: Optional[SearchLimits] = None) -> None:
        if head not in HEAD_MODES:
            raise ValueError(f"head must be one of {HEAD_MODES}, got {head!r}")
        self.stack = MotionStack.from_camera(camera, limits)
        self.head = head
        self.replan_kept = bool(replan_kept)
        self.search = search or SearchLimits()
        self.mounting_pitch = camera_pitch(camera)
        self._pitch = self.mounting_pitch
        self._target_xy: Optional[FloatArray] = None
        #: Seconds driven since the robot was made (the sum of advance()'s steps).
        self.clock_s = 0.0
        # The base's positions, one per advance (the start first): the track a search drives back along.
        self._track: List[FloatArray] = [self.stack.position_xy]
        self._seen_from: Optional[FloatArray] = None  # camera (floor) position of the latest frame that saw the target
        self.search_phase = SEARCH_NONE
        self._search_since_s = 0.0
        # Until when (sim ns) the goal followed may be acted on, and where its target was last known when its
        # status said the target is not seen (None: seen; the expiry is then a withdrawal, else a loss).
        self.goal_valid_until_ns: Optional[int] = None
        self._goal_target_lost = False
        self._goal_target_place: Optional[FloatArray] = None
        #: Paths taken (replacing the one followed), withdrawals and searches started, for the episode's record.
        self.paths_taken = 0
        self.withdrawals = 0
        self.searches = 0

    def camera_pose(self) -> CameraPose:
        """T_world_camera now."""
        return self.stack.camera_pose()

    def advance(self, dt_s: float) -> CameraPose:
        """Drive ``dt_s`` seconds on (the head re-aimed at the target from where the camera is), the camera then."""
        self._aim()
        self.stack.step(dt_s)
        self.clock_s += float(dt_s)
        if float(np.linalg.norm(self.stack.position_xy - self._track[-1])) > 1e-6:
            self._track.append(self.stack.position_xy)
            if len(self._track) > MAX_TRACK_POINTS:
                del self._track[0]
        self._search_step()
        return self.stack.camera_pose()

    def drive(self, from_ns: int, to_ns: int) -> CameraPose:
        """Drive from sim time ``from_ns`` to ``to_ns`` (:meth:`advance`), braking at the goal's ``valid_until``.

        A goal still followed when sim time passes its ``valid_until`` ends there (integer nanoseconds, so the
        split does not depend on rounding): :meth:`withdraw`, or :meth:`lose_target` when its last status said
        the target is not seen; the rest of the step is driven after it.
        """
        until = self.goal_valid_until_ns
        if until is not None and self.stack.has_path and int(to_ns) > until:
            first_ns = max(0, until - int(from_ns))
            if first_ns > 0:
                self.advance(first_ns * 1e-9)
            self.goal_valid_until_ns = None
            if self._goal_target_lost:
                self.lose_target(self._goal_target_place)
            else:
                self.withdraw()
            return self.advance((int(to_ns) - int(from_ns) - first_ns) * 1e-9)
        return self.advance((int(to_ns) - int(from_ns)) * 1e-9)

    def hold_goal_until(self, valid_until_ns: Optional[int], target_lost: bool = False,
                        target_place: Optional[FloatArray] = None) -> None:
        """A CURRENT status of the goal: it may be acted on until ``valid_until_ns`` (None: no limit).

        ``target_lost``: the status said the target is not seen, so the goal's expiry starts the search toward
        ``target_place`` (world; None: the latest plan's ring centre).
        """
        self.goal_valid_until_ns = None if valid_until_ns is None else int(valid_until_ns)
        self._goal_target_lost = bool(target_lost)
        self._goal_target_place = None if target_place is None else np.asarray(target_place, dtype=np.float64).copy()

    def take_path(self, points_world: FloatArray, final_rotation_world: FloatArray, goal_changed: bool) -> bool:
        """A CURRENT goal's base path (world (P, 3) points, the last pose's world rotation); whether it was taken.

        A path taken ends a search.

        Raises:
            ValueError: No point, or a point not finite.
        """
        if self.stack.has_path and not goal_changed and not self.replan_kept:
            return False
        points = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        if not np.all(np.isfinite(points)) or len(points) == 0:
            raise ValueError("a path needs at least one finite point")
        self.stack.set_path(points[:, :2], level_heading(final_rotation_world))
        self.search_phase = SEARCH_NONE
        self.paths_taken += 1
        return True

    def take_view(self, goal_camera_world: CameraPose) -> None:
        """The goal's camera view: the head tilts to its pitch (a pan-tilt head)."""
        if self.head == "pan_tilt":
            self._pitch = camera_pitch(goal_camera_world)
        self._aim()

    def look_at_target(self, target_world: FloatArray) -> None:
        """The target's floor point (world): a pan-tilt head pans toward it from wherever the camera is."""
        self._target_xy = np.asarray(target_world, dtype=np.float64).reshape(-1)[:2].copy()
        self._aim()

    def saw_target_from(self, camera_world: FloatArray) -> None:
        """A frame rendered with the camera at ``camera_world`` (world) saw the target: where a search returns to."""
        self._seen_from = np.asarray(camera_world, dtype=np.float64).reshape(-1)[:2].copy()

    def withdraw(self) -> None:
        """The goal was withdrawn (STALE, NONE, an empty path) with the target in view: brake to a stop.

        The head stays where it is; a search stops too.
        """
        if self.stack.has_path:
            self.withdrawals += 1
        self.stack.clear_path()
        self.search_phase = SEARCH_NONE

    def no_path(self) -> None:
        """An empty base path (no way to the goal, or the goal withdrawn): :meth:`withdraw`, unless a search is on.

        The search's path is its own, not the planner's; and a loss's empty path and its status (which starts the
        search) come on two topics, in either order: whether the robot searched must not depend on that order.
        """
        if self.search_phase == SEARCH_NONE:
            self.withdraw()

    def lose_target(self, last_known_world: Optional[FloatArray] = None) -> None:
        """The goal was withdrawn because the target is not seen: brake and start the search (once per loss).

        Args:
            last_known_world: Where the target was last known (world; its floor point is used); None: the latest
                plan's ring centre (:meth:`look_at_target`).
        """
        if last_known_world is not None:
            self.look_at_target(last_known_world)
        if self.search_phase != SEARCH_NONE:
            return  # searching already: the search's own path is not a goal to withdraw
        if self.stack.has_path:
            self.withdrawals += 1
        self.stack.clear_path()
        self.searches += 1
        self.search_phase = SEARCH_LOOKING
        self._search_since_s = self.clock_s
        self._aim()

    def arrived(self) -> bool:
        """At the path's end, facing its heading, standing, the head aligned."""
        return self.stack.arrived()

    def return_path(self) -> Optional[FloatArray]:
        """(P, 2) the track back to the point nearest the latest seen-from place, then ``back_off_m`` on.

        At most ``return_m`` long; the base's position first; None when there is no such place or the base is
        already there.
        """
        if self._seen_from is None or self.search.return_m <= 0.0:
            return None
        track = self._track
        points = [track[-1]]
        along = [0.0]  # metres driven back to each of points
        best, best_distance = 0, float(np.linalg.norm(track[-1] - self._seen_from))
        for point in reversed(track[:-1]):
            travelled = along[-1] + float(np.linalg.norm(point - points[-1]))
            if travelled > self.search.return_m + 1e-9:
                break
            points.append(point)
            along.append(travelled)
            distance = float(np.linalg.norm(point - self._seen_from))
            if distance < best_distance - 1e-12:
                best, best_distance = len(points) - 1, distance
        reach = along[best] + self.search.back_off_m + 1e-9
        while best + 1 < len(points) and along[best + 1] <= reach:
            best += 1
        if best == 0 or along[best] <= self.stack.limits.goal_tolerance_m:
            return None
        return np.array(points[:best + 1])

    def _search_step(self) -> None:
        """The search's next phase, once the current one is done."""
        if self.search_phase == SEARCH_LOOKING and self.clock_s - self._search_since_s >= self.search.look_s - 1e-9:
            path = self.return_path()
            if path is None:
                self.search_phase = SEARCH_WAITING
                return
            end = path[-1]
            target = self._target_xy
            heading = math.atan2(target[1] - end[1], target[0] - end[0]) if target is not None \
                and float(np.linalg.norm(target - end)) > 1e-6 else self.stack.state.yaw
            self.stack.set_path(path, heading)
            self.search_phase = SEARCH_RETURNING
        elif self.search_phase == SEARCH_RETURNING and self.stack.base_arrived():
            self.search_phase = SEARCH_WAITING

    def _aim(self) -> None:
        if self.head != "pan_tilt":
            return
        s = self.stack.state
        if self._target_xy is not None and float(np.hypot(self._target_xy[0] - s.x, self._target_xy[1] - s.y)) > 0.2:
            heading = math.atan2(self._target_xy[1] - s.y, self._target_xy[0] - s.x)
        else:
            heading = s.yaw + s.pan
        self.stack.look(heading, self._pitch)
