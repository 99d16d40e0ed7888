"""What the planner plans from: its inputs as Protocols, and PlanInputs, the one value that carries them.

The planner reads its inputs by attribute, so any object with the attributes will do: the node passes
the conversion dataclasses of :mod:`leapnbv_common.conversions` (``TargetGeometryArrays``,
``GroundPlaneArrays``) and :class:`leapnbv_common.camera_pose.StampedCameraPose`, which need ROS
messages to import; a caller without ROS (tests, benchmarks, offline tools) uses :class:`PlanTarget`,
:class:`PlanFloor` and :class:`CameraInMap` here. The Protocols say what is read; a type checker holds
both kinds to them.

:class:`PlanInputs` bundles one frame's inputs with the parameters. ``plan_views`` passes it
unchanged to the scoring (``ScoringContext.frame.inputs``), so a score term that needs a new input
(the person's velocity, say) reads a new field of PlanInputs through a requirement provider
(:mod:`leapnbv_planner.requirements`); nothing between the caller and the term changes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Protocol, Tuple

from leapnbv_planner.arrays import Array
from leapnbv_planner.obstacle_map import ObstacleMap
from leapnbv_planner.params import PlannerParams, default_nbv_params

# (vertices (V, 3), faces (F, 3) int indices): the person's metric body mesh in the frame's optical frame.
BodyMesh = Tuple[Array, Array]

__all__ = ["BodyMesh", "CameraInMap", "CameraPose", "FloorPlane", "ObstacleMap", "PlanFloor", "PlanInputs",
           "PlanTarget", "TargetArrays"]


class TargetArrays(Protocol):
    """The frame's target geometry, camera optical frame (``TargetGeometryArrays`` has these and more)."""

    @property
    def target_points(self) -> Array:
        """(N, 3) float32 or float64 points on the person."""

    @property
    def background_points(self) -> Array:
        """(M, 3) the other points of the frame."""

    @property
    def centroid(self) -> Array:
        """(3,) the person's centre (the ring's)."""

    @property
    def k(self) -> Array:
        """(3, 3) intrinsics of the depth image the points come from."""

    @property
    def width(self) -> int:
        """Image width in pixels."""

    @property
    def height(self) -> int:
        """Image height in pixels."""

    @property
    def valid(self) -> bool:
        """False: no person in the frame (it cannot be planned)."""


class FloorPlane(Protocol):
    """The floor n.x + d = 0 in the camera optical frame (``GroundPlaneArrays`` has these and more)."""

    @property
    def normal(self) -> Array:
        """(3,) n, pointing up (toward the camera side)."""

    @property
    def offset(self) -> float:
        """d: the camera's height above the floor for a unit n."""

    @property
    def valid(self) -> bool:
        """False: no floor found in the frame (it cannot be planned)."""


class CameraPose(Protocol):
    """The frame's camera in the obstacle map's frame: p_map = rotation @ p_camera + position
    (``StampedCameraPose`` has these and more)."""

    @property
    def rotation(self) -> Array:
        """(3, 3) rotation, columns the camera's optical axes in the map."""

    @property
    def position(self) -> Array:
        """(3,) the camera's optical centre in the map."""


@dataclass(frozen=True)
class PlanTarget:
    """A :class:`TargetArrays` without messages; see there for each field."""

    target_points: Array
    background_points: Array
    centroid: Array
    k: Array
    width: int
    height: int
    valid: bool = True


@dataclass(frozen=True)
class PlanFloor:
    """A :class:`FloorPlane` without messages; see there for each field."""

    normal: Array
    offset: float
    valid: bool = True


@dataclass(frozen=True)
class CameraInMap:
    """A :class:`CameraPose` without messages; see there for each field."""

    rotation: Array
    position: Array


@dataclass(frozen=True)
class PlanInputs:
    """One frame's inputs to :func:`leapnbv_planner.plan.plan_views`, in the frame's camera optical frame.

    Attributes:
        target: the frame's target and background points and its camera.
        floor: the frame's ground plane.
        params: the nbv node's parameters (an instance of
            :func:`leapnbv_planner.params.nbv_params_class`: the ring, the terms and their weights); the
            robot's defaults when not given.
        obstacle_map: the robot's obstacle map; used only together with camera_pose.
        camera_pose: the frame's camera in the map's frame (the caller checks that its frame is the map's).
        body_mesh: the person's metric body mesh (the raster node's human_mesh_metric), or None.
        extra_foot_points: (E, 3) foot points of further views to score beside the ring (the committed goal of
            :mod:`leapnbv_planner.commitment`, brought into this frame), or None (nothing more is computed). Each
            is projected onto the frame's floor and gets its camera by the ring's mounting rule; it is checked,
            path-searched and scored like a ring candidate, reported in ``Plan.extra`` and never chosen by the
            plan (the ring's candidates, indices and choice are the same with or without them).
    """

    target: TargetArrays
    floor: FloorPlane
    params: PlannerParams = field(default_factory=default_nbv_params)
    obstacle_map: Optional[ObstacleMap] = None
    camera_pose: Optional[CameraPose] = None
    body_mesh: Optional[BodyMesh] = None
    extra_foot_points: Optional[Array] = None

    @property
    def uses_obstacle_map(self) -> bool:
        """The map takes part in the plan: it and the frame's camera pose in it are both given."""
        return self.obstacle_map is not None and self.camera_pose is not None
