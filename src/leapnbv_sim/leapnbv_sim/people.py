"""The people of a scene: the target, bystanders and passers-by, where they stand and how they move in sim time.

Every scene has its target (object id 1, the person the robot is to see, standing at the world
origin at time 0). A scene config may add other people (``SceneConfig.bystanders``,
``SceneConfig.passers_by``) and make the target move (``SceneConfig.target_motion``); they are
drawn here from their own random streams, so the rest of the scene is the one-person scene of the
same seed:

* a **bystander** stands still 0.6-1.5 m (``bystander_distance_range``) from the target, at 35-160 deg
  from the direction to the start camera on either side, turned any way, in the start view (its
  pelvis projects into the middle 90 % of the image's width) and off the start view's line of sight
  to the target (the convex hull of the robot's 0.3 m disc and the target's footprint): the start
  view's occlusion of the target is that of the one-person scene;
* a **passer-by** walks a straight line across the line of sight between the start camera and the
  target: it crosses that line at 15-85 % of the way from the target to the camera (where the floor
  is free: the occluders stand on that line too), 1-3 s after the scene starts
  (``passer_by_crossing_s_range``), at 0.5-1.0 m/s (``passer_by_speed_range``), at up to 25 deg off
  the perpendicular, walks on up to 1.0-2.5 m past it and then stands where it stopped; it faces
  where it walks and starts and ends off the line of sight. Its walk is shortened to the free floor
  on either side; one whose approach is then shorter than its speed and crossing time ask waits
  at its start before walking;
* a **walking target** (``target_motion = "walk"``) stands 0.5-2 s, turns in place to face a clear
  direction (0.5-1.0 rad/s), walks 0.8-2.0 m (``target_walk_length_range``) at 0.2-0.5 m/s
  (``target_speed_range``) and stands; one scene in three (or when no direction is clear) it only
  turns in place by 60-150 deg at 0.3-0.8 rad/s instead.

Every person keeps clear (``PEOPLE_CLEARANCE_M``) of the occluders, the furniture, the walls (and
stays on the target's side of each), the robot's start disc and the other people, over its whole
path for a moving one. A person's motion is :class:`PersonMotion` (its pelvis on the floor and its
heading, piecewise linear between keyframes); placing it at a time is a rigid motion of its posed
vertices about its pelvis's vertical axis (:func:`move_body`), no re-posing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

import numpy as np

from leapnbv_common.array_types import FloatArray
from leapnbv_perception.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_sim.body import PlacedBody, place_body, sample_body_pose
from leapnbv_sim.meshes import convex_hull_2d, convex_polygons_apart
from leapnbv_sim.poses import CameraPose, yaw_matrix

ROLE_TARGET = "target"
ROLE_BYSTANDER = "bystander"
ROLE_PASSER_BY = "passer_by"
#: The target's motions (SceneConfig.target_motion).
TARGET_MOTIONS = ("stand", "walk")
#: Gap a person keeps to obstacles, walls, the robot's start disc and the other people (m).
PEOPLE_CLEARANCE_M = 0.1
#: The robot's radius around the start camera's foot point (the clutter's keep-out uses the same).
ROBOT_RADIUS_M = 0.3
#: Placements drawn per person before it is given up (then the scene fails: SceneError).
PLACEMENT_TRIES = 200
#: Where a passer-by crosses the start view's line of sight: this share of the way from the target to the camera.
PASSER_BY_CROSSING_FRACTION = (0.15, 0.85)
#: The resolution of a walk shortened to the free floor (m).
FREE_LENGTH_STEP_M = 0.02
# Base colours of the other people (RGB 0..1): clothes tones apart from the target's red.
OTHER_PERSON_COLOURS = np.array([[0.30, 0.35, 0.70], [0.78, 0.62, 0.22], [0.35, 0.62, 0.58]])
# Mixed with the seed into the people's and the target motion's own random streams.
PEOPLE_STREAM = 13
TARGET_MOTION_STREAM = 17


def people_rng(seed: int) -> np.random.Generator:
    """The other people's random stream: independent of every other stream of the scene."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, PEOPLE_STREAM])


def target_motion_rng(seed: int) -> np.random.Generator:
    """The target motion's random stream."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, TARGET_MOTION_STREAM])


@dataclass
class PersonMotion:
    """A person's pelvis on the floor (world xy) and heading over sim time, linear between keyframes.

    Before the first keyframe (time 0) and after the last the person stands as there. A segment
    either walks (heading fixed) or turns in place (position fixed). Headings are unwrapped: a
    segment turns by exactly the difference of its keyframes' headings.

    Attributes:
        times_s: (K,) increasing keyframe times, the first 0.
        xy: (K, 2) pelvis positions.
        heading_rad: (K,) headings (about world z, :func:`leapnbv_sim.body.place_body`'s convention).
    """

    times_s: FloatArray
    xy: FloatArray
    heading_rad: FloatArray

    def at(self, elapsed_s: float) -> Tuple[FloatArray, float]:
        """(pelvis xy (2,), heading) at a time (clamped to the keyframes' span)."""
        t = float(elapsed_s)
        x = float(np.interp(t, self.times_s, self.xy[:, 0]))
        y = float(np.interp(t, self.times_s, self.xy[:, 1]))
        return np.array([x, y]), float(np.interp(t, self.times_s, self.heading_rad))

    @property
    def duration_s(self) -> float:
        """When the last keyframe is reached (the person stands from then on)."""
        return float(self.times_s[-1])

    @property
    def max_speed_m_s(self) -> float:
        """The fastest segment's walking speed."""
        steps = np.linalg.norm(np.diff(self.xy, axis=0), axis=1)
        spans = np.diff(self.times_s)
        return float(np.max(steps / np.maximum(spans, 1e-12))) if len(spans) else 0.0

    @property
    def max_turn_rate_rad_s(self) -> float:
        """The fastest segment's turn rate."""
        spans = np.diff(self.times_s)
        turns = np.abs(np.diff(self.heading_rad))
        return float(np.max(turns / np.maximum(spans, 1e-12))) if len(spans) else 0.0

    @classmethod
    def from_keyframes(cls, keyframes: Sequence[Tuple[float, float, float, float]]) -> PersonMotion:
        """From (time, x, y, heading) rows; repeated times are dropped (a zero-length segment)."""
        rows = np.asarray(keyframes, dtype=np.float64).reshape(-1, 4)
        keep = np.concatenate([[True], np.diff(rows[:, 0]) > 0.0])
        rows = rows[keep]
        return cls(times_s=rows[:, 0].copy(), xy=rows[:, 1:3].copy(), heading_rad=rows[:, 3].copy())


@dataclass
class Person:
    """One person of a scene.

    Attributes:
        name: Its object name ("person" for the target, "person_bystander", "person_passer_by", ...).
        object_id: Its object id in the scene (the target's is 1).
        role: ROLE_TARGET, ROLE_BYSTANDER or ROLE_PASSER_BY.
        body: The body where it is now (in the scene at its time).
        start_body: The body at time 0 (what its motion moves).
        base_rgb: (3,) base colour of its faces.
        motion: How it moves; None: it stands still.
        vertex_slice: Where its vertices sit in the scene's vertices.
        face_slice: Where its faces sit in the scene's faces.
    """

    name: str
    object_id: int
    role: str
    body: PlacedBody
    start_body: PlacedBody
    base_rgb: FloatArray
    motion: Optional[PersonMotion]
    vertex_slice: slice
    face_slice: slice

    @property
    def moves(self) -> bool:
        return self.motion is not None

    def body_at(self, elapsed_s: float) -> Tuple[PlacedBody, bool]:
        """(the body at a time, whether it is turned from its start heading)."""
        if self.motion is None:
            return self.start_body, False
        xy0, heading0 = self.motion.at(0.0)
        xy, heading = self.motion.at(elapsed_s)
        turn = heading - heading0
        return move_body(self.start_body, xy - xy0, turn), turn != 0.0


@dataclass
class OtherPerson:
    """A person other than the target as generation places it (assemble_scene gives it its id and slices)."""

    role: str
    body: PlacedBody
    base_rgb: FloatArray
    motion: Optional[PersonMotion] = None


def pelvis_xy(body: PlacedBody) -> FloatArray:
    """(2,) the pelvis (root joint) of a placed body on the floor."""
    return np.asarray((body.root_joint + body.translation_world)[:2], dtype=np.float64)


def move_body(body: PlacedBody, offset_xy: FloatArray, turn_rad: float) -> PlacedBody:
    """The body turned by ``turn_rad`` about its pelvis's vertical axis, then shifted by ``offset_xy``.

    A rigid motion: with R the turn and J the root joint, the forward pass with root orientation
    R R_root gives R (v_f - J) + J, so the turned body's forward vertices are that and its
    translation only takes the shift (its parameters stay consistent with its vertices).
    """
    offset = np.array([float(offset_xy[0]), float(offset_xy[1]), 0.0])
    if turn_rad == 0.0:
        return PlacedBody(body.params_world, body.forward_vertices, body.root_joint,
                          body.translation_world + offset, body.faces)
    rotation = yaw_matrix(turn_rad)
    forward = (body.forward_vertices - body.root_joint) @ rotation.T + body.root_joint
    root = matrix_to_axis_angle(rotation @ axis_angle_to_matrix(body.params_world.root_pose))
    return PlacedBody(body.params_world.with_root(root), forward, body.root_joint,
                      body.translation_world + offset, body.faces)


def _disc(centre: FloatArray, radius: float, sides: int = 16) -> FloatArray:
    """A polygon around a disc (it contains the disc)."""
    angles = np.linspace(0.0, 2.0 * np.pi, sides, endpoint=False)
    scale = radius / math.cos(math.pi / sides)
    polygon: FloatArray = np.asarray(centre, dtype=np.float64)[:2] + scale * np.stack([np.cos(angles), np.sin(angles)],
                                                                                        axis=1)
    return polygon


def _capsule(a: FloatArray, b: FloatArray, radius: float) -> FloatArray:
    """The floor a disc of ``radius`` sweeps from a to b (a convex polygon around it)."""
    return convex_hull_2d(np.concatenate([_disc(a, radius), _disc(b, radius)]))


def body_radius(body: PlacedBody) -> float:
    """Largest horizontal distance of the body's vertices from its pelvis's vertical axis (any heading)."""
    return float(np.max(np.linalg.norm(body.vertices_world[:, :2] - pelvis_xy(body), axis=1)))


def _facing_heading(direction: FloatArray) -> float:
    """The heading (place_body's convention: 0 faces -x) that faces a floor direction."""
    return math.atan2(-float(direction[1]), -float(direction[0]))


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


@dataclass
class FloorPlan:
    """What people keep clear of on the floor (world xy), and the start view's line of sight.

    Attributes:
        obstacles: Convex footprints (K, 2) of the occluders and the furniture.
        walls: (a point of the wall, its unit normal toward the target's side) per wall.
        line_of_sight: Convex hull of the robot's start disc and the target's footprint (holds every
            ray from the start camera to the target).
        robot: The robot's start disc (a polygon).
        people: Footprints of the people placed so far (a moving one: its whole path).
    """

    obstacles: List[FloatArray]
    walls: List[Tuple[FloatArray, FloatArray]]
    line_of_sight: FloatArray
    robot: FloatArray
    people: List[FloatArray]

    @classmethod
    def of(cls, obstacle_vertices: Sequence[FloatArray], wall_vertices: Sequence[FloatArray], target: PlacedBody,
           camera: CameraPose) -> FloorPlan:
        """From the obstacles' and walls' world vertices, the target and the start camera."""
        obstacles = [convex_hull_2d(np.asarray(v)[:, :2]) for v in obstacle_vertices]
        walls = []
        origin = pelvis_xy(target)
        for vertices in wall_vertices:
            points = np.unique(np.round(np.asarray(vertices)[:, :2], 9), axis=0)
            a, b = points[0], points[-1]
            normal = np.array([-(b - a)[1], (b - a)[0]])
            normal /= max(float(np.linalg.norm(normal)), 1e-12)
            if float(normal @ (origin - a)) < 0.0:
                normal = -normal
            walls.append((a, normal))
        robot = _disc(camera.position, ROBOT_RADIUS_M)
        target_xy = target.vertices_world[:, :2]
        corners = np.array([target_xy.min(axis=0), [target_xy.max(axis=0)[0], target_xy.min(axis=0)[1]],
                            target_xy.max(axis=0), [target_xy.min(axis=0)[0], target_xy.max(axis=0)[1]]])
        line_of_sight = convex_hull_2d(np.concatenate([corners, robot]))
        return cls(obstacles, walls, line_of_sight, robot, [convex_hull_2d(target_xy)])

    def clear(self, polygon: FloatArray, gap: float = PEOPLE_CLEARANCE_M) -> bool:
        """Whether a footprint keeps ``gap`` from the obstacles, the walls, the robot and the people so far.

        The walls: on the target's side of each, ``gap`` away.
        """
        for a, normal in self.walls:
            if float(np.min((polygon - a) @ normal)) < gap:
                return False
        others = self.obstacles + [self.robot] + self.people
        return all(convex_polygons_apart(polygon, other, gap) for other in others)


def place_bystander(rng: np.random.Generator, body_model: SMPLXModel, plan: FloorPlan, target: PlacedBody,
                    camera: CameraPose, K: FloatArray, width: int,
                    distance_range: Tuple[float, float]) -> Optional[PlacedBody]:
    """A bystander standing near the target (the module's rule), or None when no draw fits.

    Draws, in order: pose and shape, heading, then per try a side, an angle from the direction to the
    camera and a distance. The plan gets its footprint.
    """
    pose, betas = sample_body_pose(rng)
    heading = rng.uniform(-math.pi, math.pi)
    body = place_body(body_model, heading, pose, betas)
    root_z = float((body.root_joint + body.translation_world)[2])
    origin = pelvis_xy(target)
    to_camera = math.atan2(camera.position[1] - origin[1], camera.position[0] - origin[0])
    for _ in range(PLACEMENT_TRIES):
        side = rng.choice([-1.0, 1.0])
        azimuth = to_camera + side * math.radians(rng.uniform(35.0, 160.0))
        distance = rng.uniform(*distance_range)
        position = origin + distance * np.array([math.cos(azimuth), math.sin(azimuth)])
        placed = move_body(body, position, 0.0)
        footprint = convex_hull_2d(placed.vertices_world[:, :2])
        pelvis_camera = camera.world_to_camera(np.array([[position[0], position[1], root_z]]))[0]
        if pelvis_camera[2] <= 0.0:
            continue
        u = K[0, 0] * pelvis_camera[0] / pelvis_camera[2] + K[0, 2]
        if abs(u - 0.5 * width) > 0.45 * width:
            continue
        if not (plan.clear(footprint) and convex_polygons_apart(footprint, plan.line_of_sight, PEOPLE_CLEARANCE_M)):
            continue
        plan.people.append(footprint)
        return placed
    return None


def place_passer_by(rng: np.random.Generator, body_model: SMPLXModel, plan: FloorPlan, target: PlacedBody,
                    camera: CameraPose, speed_range: Tuple[float, float],
                    crossing_range_s: Tuple[float, float]) -> Optional[Tuple[PlacedBody, PersonMotion]]:
    """A passer-by crossing the start view's line of sight (the module's rule): (body at time 0, motion), or None.

    Draws, in order: pose and shape, then per try the speed, the crossing time, the crossing point, the
    angle off the perpendicular, the direction and the distance walked past the line. The plan gets its path.
    """
    pose, betas = sample_body_pose(rng)
    origin = pelvis_xy(target)
    camera_xy = np.asarray(camera.position[:2], dtype=np.float64)
    line = camera_xy - origin
    across = np.array([-line[1], line[0]]) / max(float(np.linalg.norm(line)), 1e-12)
    standing = place_body(body_model, 0.0, pose, betas)
    # It walks without turning: the floor it sweeps is the hull of its footprint at both ends (exact for a
    # convex footprint), not a disc around its outstretched arms.
    footprint_at_origin = convex_hull_2d(standing.vertices_world[:, :2] - pelvis_xy(standing))

    def off_line_of_sight(footprint: FloatArray) -> bool:
        return convex_polygons_apart(footprint, plan.line_of_sight, PEOPLE_CLEARANCE_M)

    for _ in range(PLACEMENT_TRIES):
        speed = rng.uniform(*speed_range)
        crossing_s = rng.uniform(*crossing_range_s)
        fraction = rng.uniform(*PASSER_BY_CROSSING_FRACTION)
        off = math.radians(rng.uniform(-25.0, 25.0))
        sign = rng.choice([-1.0, 1.0])
        beyond = rng.uniform(1.0, 2.5)
        direction = sign * (yaw_matrix(off)[:2, :2] @ across)
        heading = _facing_heading(direction)
        crossing = origin + fraction * line
        footprint: FloatArray = np.asarray(footprint_at_origin @ yaw_matrix(heading)[:2, :2].T + crossing, np.float64)
        if not plan.clear(footprint):
            continue
        # As far as the floor is free on either side of the crossing, up to the drawn lengths: a passer-by
        # whose approach is shorter than its speed and crossing time ask waits there before it walks.
        approach = _free_length(plan, footprint, -direction, speed * crossing_s)
        beyond = _free_length(plan, footprint, direction, beyond)
        if not (off_line_of_sight(footprint - approach * direction)
                and off_line_of_sight(footprint + beyond * direction)):
            continue
        start, end = crossing - approach * direction, crossing + beyond * direction
        body = move_body(place_body(body_model, heading, pose, betas), start, 0.0)
        wait_s = crossing_s - approach / speed
        keyframes = [(0.0, start[0], start[1], heading)]
        if wait_s > 0:
            keyframes.append((wait_s, start[0], start[1], heading))
        motion = PersonMotion.from_keyframes(keyframes + [(crossing_s + beyond / speed, end[0], end[1], heading)])
        plan.people.append(_swept(footprint, -approach * direction, beyond * direction))
        return body, motion
    return None


def _swept(footprint: FloatArray, first: FloatArray, last: FloatArray) -> FloatArray:
    """The floor a convex footprint sweeps, translated from ``first`` to ``last`` (its hull at both ends)."""
    return convex_hull_2d(np.concatenate([footprint + first, footprint + last]))


def _free_length(plan: FloorPlan, footprint: FloatArray, direction: FloatArray, length: float) -> float:
    """The longest walk of a clear ``footprint`` along ``direction``, at most ``length``, over clear floor.

    To :data:`FREE_LENGTH_STEP_M`, by bisection: the swept floor only grows with the length.
    """
    zero = np.zeros(2)
    if plan.clear(_swept(footprint, zero, length * direction)):
        return length
    low, high = 0.0, length  # clear at low, not at high
    while high - low > FREE_LENGTH_STEP_M:
        middle = 0.5 * (low + high)
        if plan.clear(_swept(footprint, zero, middle * direction)):
            low = middle
        else:
            high = middle
    return low


def plan_target_motion(rng: np.random.Generator, plan: FloorPlan, target: PlacedBody, heading: float,
                       speed_range: Tuple[float, float], length_range: Tuple[float, float]) -> PersonMotion:
    """The walking target's motion (the module's rule); the plan gets its path.

    Draws, in order: walk or turn, the wait, the turn rate, speed and length of a walk (or the turn's
    angle and rate), then per try a walking direction.
    """
    origin = pelvis_xy(target)
    wait_s = rng.uniform(0.5, 2.0)
    walks = rng.random() >= 1.0 / 3.0
    turn_rate = rng.uniform(0.5, 1.0)
    speed = rng.uniform(*speed_range)
    length = rng.uniform(*length_range)
    if walks:
        radius = body_radius(target)
        plan.people.pop(0)  # the target's own standing footprint: its path replaces it
        for _ in range(PLACEMENT_TRIES):
            angle = rng.uniform(-math.pi, math.pi)
            direction = np.array([math.cos(angle), math.sin(angle)])
            end = origin + length * direction
            path = _capsule(origin, end, radius)
            if not plan.clear(path):
                continue
            turn = _wrap(_facing_heading(direction) - heading)
            turned_s = wait_s + abs(turn) / turn_rate
            plan.people.insert(0, path)
            return PersonMotion.from_keyframes([
                (0.0, origin[0], origin[1], heading), (wait_s, origin[0], origin[1], heading),
                (turned_s, origin[0], origin[1], heading + turn),
                (turned_s + length / speed, end[0], end[1], heading + turn)])
        plan.people.insert(0, convex_hull_2d(target.vertices_world[:, :2]))
    turn = rng.choice([-1.0, 1.0]) * math.radians(rng.uniform(60.0, 150.0))
    rate = rng.uniform(0.3, 0.8)
    return PersonMotion.from_keyframes([(0.0, origin[0], origin[1], heading), (wait_s, origin[0], origin[1], heading),
                                        (wait_s + abs(turn) / rate, origin[0], origin[1], heading + turn)])
