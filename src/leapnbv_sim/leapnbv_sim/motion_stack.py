"""A simulated motion stack without ROS: a differential-drive base that follows a path and a pan-tilt head.

What a robot's navigation (e.g. Nav2 with a regulated pure-pursuit controller) and its head
controller do with the planner's goal, reduced to their kinematics:

* the **base** (x, y on the floor, heading ``yaw``, forward speed ``v``) follows a polyline of
  floor points toward its last point and ends facing the path's final heading. Each step it aims
  at a carrot ``lookahead_m`` further along the path than its own projection; it turns toward the
  carrot at most ``max_turn_rate_rad_s``, drives forward only while the carrot is within
  ``turn_in_place_rad`` of its heading (else it turns in place), never faster than
  ``max_speed_m_s`` nor than it can brake for before the path's end (``v^2 <= 2 a (s - v dt)``), and
  changes its speed by at most ``max_accel_m_s2`` per second, speeding up and braking alike. It
  never drives backwards.
* the **head** pans (about the base's z, within ``pan_limit_rad``) and tilts (the optical axis'
  downward pitch) toward a world heading and pitch at ``pan_rate_rad_s`` / ``tilt_rate_rad_s``.
  The camera sits ``camera_height`` above the base point with no roll
  (:func:`leapnbv_sim.poses.camera_pose_from_base_goal`).

A new path replaces the one followed (the base keeps its speed: it does not stop to take it); no
path (a withdrawn goal) brakes the base to a stop where it is, at the same deceleration. The base
has *arrived* when it is within ``goal_tolerance_m`` of the path's end, faces its final heading
within ``heading_tolerance_rad`` and stands still; the *view* is reached when the head also looks
where it was told within ``heading_tolerance_rad``.

Integration: :meth:`MotionStack.step` advances by ``dt`` seconds with the controls held over the
step (speed from the acceleration limit, then the heading change, then the position along the
mean heading of the step: exact for a straight drive, second order in ``dt`` for an arc).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional, Tuple

import numpy as np

from leapnbv_common.array_types import FloatArray
from leapnbv_sim.poses import CameraPose, camera_heading, camera_pitch, camera_pose_from_base_goal

__all__ = ["BaseLimits", "BaseState", "MotionStack", "wrap_angle", "path_length"]


def wrap_angle(angle: float) -> float:
    """An angle in [-pi, pi)."""
    return float((float(angle) + math.pi) % (2.0 * math.pi) - math.pi)


def path_length(points: FloatArray) -> float:
    """Length (m) of a polyline of (P, 2) or (P, 3) points (0 for fewer than two)."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 2:
        return 0.0
    return float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1)))


@dataclass(frozen=True)
class BaseLimits:
    """The base's and the head's limits and the controller's tolerances (all > 0 but the tolerances >= 0)."""

    max_speed_m_s: float = 0.5
    max_accel_m_s2: float = 0.5
    max_turn_rate_rad_s: float = 1.0
    pan_rate_rad_s: float = 1.5
    tilt_rate_rad_s: float = 1.0
    pan_limit_rad: float = math.radians(170.0)
    lookahead_m: float = 0.3
    turn_in_place_rad: float = math.radians(45.0)
    # Nav2's goal checker defaults are 0.25 m and 0.25 rad; tighter here, but wider than one camera period's
    # travel (0.05-0.1 m): a goal planned on a frame the base has since driven past is reached, not driven back to.
    goal_tolerance_m: float = 0.15
    heading_tolerance_rad: float = math.radians(5.0)

    def __post_init__(self) -> None:
        for name in ("max_speed_m_s", "max_accel_m_s2", "max_turn_rate_rad_s", "pan_rate_rad_s", "tilt_rate_rad_s",
                     "pan_limit_rad", "lookahead_m", "turn_in_place_rad"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"motion stack limit {name} must be a finite number > 0, got {value}")
        for name in ("goal_tolerance_m", "heading_tolerance_rad"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"motion stack tolerance {name} must be a finite number >= 0, got {value}")


@dataclass
class BaseState:
    """Where the robot is: the base on the floor, its speed, the head's pan and tilt (radians)."""

    x: float
    y: float
    yaw: float
    v: float = 0.0
    pan: float = 0.0
    tilt: float = 0.0


@dataclass
class _Path:
    points: FloatArray  # (P, 2) floor points, the first where the robot stood when it was planned
    final_yaw: float
    cumulative: FloatArray = field(init=False)  # (P,) arc length at each point

    def __post_init__(self) -> None:
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1) if len(self.points) > 1 else np.zeros(0)
        self.cumulative = np.concatenate([[0.0], np.cumsum(seg)])

    @property
    def length(self) -> float:
        return float(self.cumulative[-1])

    def project(self, xy: FloatArray, from_s: float, window_m: float) -> float:
        """Arc length of the path's nearest point to ``xy`` within [from_s, from_s + window_m].

        Progress never goes back, and a path that passes near itself is not cut short.
        """
        best_s, best_d = from_s, math.inf
        for i in range(len(self.points) - 1):
            start, end = float(self.cumulative[i]), float(self.cumulative[i + 1])
            if end < from_s or start > from_s + window_m or end <= start:
                continue
            a, ab = self.points[i], self.points[i + 1] - self.points[i]
            seg = end - start
            t_min = max(0.0, (from_s - start) / seg)
            t_max = min(1.0, (from_s + window_m - start) / seg)
            t = float(np.clip((xy - a) @ ab / (seg * seg), t_min, t_max))
            d = float(np.linalg.norm(a + t * ab - xy))
            if d < best_d - 1e-12:
                best_s, best_d = start + t * seg, d
        return best_s

    def point_at(self, s: float) -> FloatArray:
        """The path's point at arc length ``s`` (clipped to the path)."""
        if len(self.points) == 1 or s >= self.length:
            return np.asarray(self.points[-1], dtype=np.float64).copy()
        s = max(0.0, s)
        i = int(np.searchsorted(self.cumulative, s, side="right") - 1)
        i = min(i, len(self.points) - 2)
        seg = float(self.cumulative[i + 1] - self.cumulative[i])
        t = 0.0 if seg <= 0.0 else (s - float(self.cumulative[i])) / seg
        point: FloatArray = self.points[i] + t * (self.points[i + 1] - self.points[i])
        return point


def _toward(current: float, target: float, max_step: float) -> float:
    """``current`` moved toward ``target`` by at most ``max_step``."""
    return current + float(np.clip(target - current, -max_step, max_step))


class MotionStack:
    """The simulated base and head (see the module docstring).

    Args:
        state: Where the robot starts.
        camera_height: The camera's optical centre above the floor (m), > 0.
        limits: The base's and head's limits.
    """

    def __init__(self, state: BaseState, camera_height: float, limits: Optional[BaseLimits] = None) -> None:
        if not (math.isfinite(float(camera_height)) and float(camera_height) > 0.0):
            raise ValueError(f"the camera's mounting height must be > 0, got {camera_height}")
        self.state = state
        self.camera_height = float(camera_height)
        self.limits = limits or BaseLimits()
        self._path: Optional[_Path] = None
        self._progress_s = 0.0
        self._at_end = False
        self._head_target: Optional[Tuple[float, float]] = None  # (world heading, pitch)
        #: Metres the base travelled since it was made (the odometry's distance).
        self.travelled_m = 0.0

    @classmethod
    def from_camera(cls, camera: CameraPose, limits: Optional[BaseLimits] = None) -> MotionStack:
        """A standing robot whose camera is at ``camera``.

        The base stands under it facing its heading, the head centred and tilted to its pitch.
        """
        position = np.asarray(camera.position, dtype=np.float64)
        state = BaseState(x=float(position[0]), y=float(position[1]), yaw=camera_heading(camera),
                          tilt=camera_pitch(camera))
        return cls(state, float(position[2]), limits)

    # ------------------------------------------------------------------ commands

    def set_path(self, points_xy: FloatArray, final_yaw: float) -> None:
        """Follow a new path of (P, 2) floor points (P >= 1) ending at ``final_yaw``, replacing the one followed.

        Raises:
            ValueError: No point, or a point or the heading not finite.
        """
        pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
        if len(pts) == 0 or not np.all(np.isfinite(pts)) or not math.isfinite(float(final_yaw)):
            raise ValueError("a path needs at least one finite floor point and a finite final heading")
        self._path = _Path(pts, float(final_yaw))
        self._progress_s = self._path.project(self.position_xy, 0.0, self._window_m())
        self._at_end = False

    def clear_path(self) -> None:
        """No goal any more: brake to a stop where the base is (the head keeps its angles)."""
        self._path = None
        self._head_target = None

    def look(self, heading_rad: float, pitch_rad: float) -> None:
        """Turn the head toward a world heading and a downward pitch (kept until changed or the path is cleared)."""
        if not (math.isfinite(float(heading_rad)) and math.isfinite(float(pitch_rad))):
            raise ValueError("the head's target must be finite")
        self._head_target = (float(heading_rad), float(pitch_rad))

    # ------------------------------------------------------------------ state

    @property
    def has_path(self) -> bool:
        return self._path is not None

    @property
    def position_xy(self) -> FloatArray:
        return np.array([self.state.x, self.state.y], dtype=np.float64)

    @property
    def remaining_m(self) -> float:
        """Path length still ahead of the base (0 without a path)."""
        if self._path is None:
            return 0.0
        return max(0.0, self._path.length - self._progress_s)

    def base_arrived(self) -> bool:
        """The base stands at the path's end facing its final heading (False without a path)."""
        if self._path is None:
            return False
        lim = self.limits
        end = self._path.points[-1]
        near = float(np.linalg.norm(self.position_xy - end)) <= lim.goal_tolerance_m
        facing = abs(wrap_angle(self._path.final_yaw - self.state.yaw)) <= lim.heading_tolerance_rad
        return near and facing and abs(self.state.v) < 1e-9

    def head_aligned(self) -> bool:
        """The head looks where it was told (True when it was told nothing)."""
        if self._head_target is None:
            return True
        heading, pitch = self._head_target
        camera_yaw = self.state.yaw + self.state.pan
        tol = self.limits.heading_tolerance_rad
        return abs(wrap_angle(heading - camera_yaw)) <= tol and abs(pitch - self.state.tilt) <= tol

    def arrived(self) -> bool:
        """The base arrived and the head looks where it was told: the goal's view is reached."""
        return self.base_arrived() and self.head_aligned()

    def camera_pose(self) -> CameraPose:
        """T_world_camera now."""
        s = self.state
        return camera_pose_from_base_goal(self.position_xy, s.yaw + s.pan, self.camera_height, s.tilt)

    # ------------------------------------------------------------------ integration

    def step(self, dt: float) -> None:
        """Advance the base and the head by ``dt`` seconds (>= 0)."""
        dt = float(dt)
        if not (math.isfinite(dt) and dt >= 0.0):
            raise ValueError(f"a motion step must be a finite number of seconds >= 0, got {dt}")
        if dt == 0.0:
            return
        lim, s = self.limits, self.state
        target_v, yaw_error = 0.0, 0.0
        path = self._path
        if path is not None:
            self._progress_s = path.project(self.position_xy, self._progress_s, self._window_m())
            end = path.points[-1]
            to_end = float(np.linalg.norm(end - self.position_xy))
            # Once at the end the base brakes and turns; if braking carried it out of the tolerance, it comes back
            # once it stands.
            if self._at_end and s.v == 0.0 and to_end > lim.goal_tolerance_m:
                self._at_end = False
            self._at_end = self._at_end or to_end <= lim.goal_tolerance_m
            if self._at_end:
                yaw_error = wrap_angle(path.final_yaw - s.yaw)
            else:
                carrot = path.point_at(self._progress_s + lim.lookahead_m)
                if float(np.linalg.norm(carrot - self.position_xy)) < 1e-9:
                    carrot = end
                yaw_error = wrap_angle(math.atan2(carrot[1] - s.y, carrot[0] - s.x) - s.yaw)
                if abs(yaw_error) <= lim.turn_in_place_rad:
                    remaining = max(to_end, path.length - self._progress_s)
                    # The fastest v that can still brake at max_accel before the end after this step's travel
                    # (v^2 <= 2 a (remaining - v dt)): it stops at the end, not a step's travel beyond it.
                    a_dt = lim.max_accel_m_s2 * dt
                    braking_v = -a_dt + math.sqrt(a_dt * a_dt + 2.0 * lim.max_accel_m_s2 * remaining)
                    target_v = min(lim.max_speed_m_s, braking_v)
        v0 = s.v
        v1 = _toward(v0, target_v, lim.max_accel_m_s2 * dt)
        yaw0 = s.yaw
        yaw1 = yaw0 + float(np.clip(yaw_error, -lim.max_turn_rate_rad_s * dt, lim.max_turn_rate_rad_s * dt))
        distance = 0.5 * (v0 + v1) * dt
        mean_yaw = 0.5 * (yaw0 + yaw1)
        s.x += distance * math.cos(mean_yaw)
        s.y += distance * math.sin(mean_yaw)
        s.yaw, s.v = wrap_angle(yaw1), v1
        self.travelled_m += abs(distance)
        self._step_head(dt)

    def _window_m(self) -> float:
        """How far along the path the base's projection may move in one step (it moves at most max speed)."""
        return max(1.0, 4.0 * self.limits.lookahead_m)

    def _step_head(self, dt: float) -> None:
        if self._head_target is None:
            return
        lim, s = self.limits, self.state
        heading, pitch = self._head_target
        pan_target = float(np.clip(wrap_angle(heading - s.yaw), -lim.pan_limit_rad, lim.pan_limit_rad))
        s.pan = _toward(s.pan, pan_target, lim.pan_rate_rad_s * dt)
        s.tilt = _toward(s.tilt, pitch, lim.tilt_rate_rad_s * dt)
