"""One next-best-view plan from one frame, without ROS: the nbv node's whole computation.

:func:`plan_views` takes the frame's target geometry and ground plane (the conversion dataclasses
``TargetGeometryArrays`` / ``GroundPlaneArrays`` of :mod:`leapnbv_common.conversions`, or any
objects with the same attributes), the node's parameters, and optionally the robot's obstacle map
with the frame's camera pose in it. It builds the candidate ring, joins the map's obstacles to the
frame's background for the footprint test and multiplies S_o by each candidate's line-of-sight
clear share through the map, checks feasibility, scores the candidates with the configured terms,
chooses the best feasible one and computes the base goal. The result, :class:`Plan`, holds
everything the node publishes (candidates, goal, base goal, markers).

Everything is in the frame's camera optical frame; the current camera is the origin.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Optional, Tuple

import numpy as np

from leapnbv_planner.candidates import (
    CandidateSet,
    FeasibilityReason,
    FeasibilityResult,
    check_feasibility,
    generate_candidates,
    normalize_plane,
)
from leapnbv_planner.mesh_kernel import face_normal_sums, unit_normals
from leapnbv_planner.obstacle_map import VoxelObstacleMap, centres_in_observation, line_of_sight_clear_fraction
from leapnbv_planner.params import PlannerParams, default_nbv_params
from leapnbv_planner.reachability import Reachability, build_occupancy_grid, reachability
from leapnbv_planner.scoring import CandidateScores, choose_best, score_candidates

if TYPE_CHECKING:  # the core needs no ROS; only the conversion to the message arrays imports it
    from leapnbv_common.conversions import ViewCandidatesArrays

Frame = Tuple[np.ndarray, np.ndarray]  # (3, 3) rotation with axes as columns, (3,) position


class PlanInputError(ValueError):
    """The frame cannot be planned (invalid target or ground plane); the text says which."""


@dataclass
class Plan:
    """The plan of one frame.

    Attributes:
        candidates: the candidate poses (rotations, positions, foot points, ring centre).
        feasibility: feasible (C,) and the infeasible reason codes (C,).
        scores: term names, weights, (C, T) term values and the (C,) score.
        chosen_index: the chosen candidate, -1 when none is feasible.
        includes_current_view: candidate 0 is the current view.
        ring_radius: metres.
        up: (3,) the ground normal n as the plane gives it (pointing up, not necessarily unit length).
        base_goal: (rotation, position) of the robot base at the chosen view, None when none is chosen.
        line_of_sight_clear: (C,) the obstacle map's clear share per candidate, None without the map.
        path_lengths: (C,) metres of the robot's shortest free path to each candidate (0 for the current
            view, inf: none), None when reachability is off.
        base_path: (P, 3) floor points of the path to the chosen candidate (the robot's foot point first,
            the goal's last), None when reachability is off or nothing is chosen.
        reach: the path search (grid, parents), None when reachability is off.
    """

    candidates: CandidateSet
    feasibility: FeasibilityResult
    scores: CandidateScores
    chosen_index: int
    includes_current_view: bool
    ring_radius: float
    up: np.ndarray
    base_goal: Optional[Frame]
    line_of_sight_clear: Optional[np.ndarray] = None
    path_lengths: Optional[np.ndarray] = None
    base_path: Optional[np.ndarray] = None
    reach: Optional[Reachability] = None

    @property
    def used_obstacle_map(self) -> bool:
        return self.line_of_sight_clear is not None

    def chosen_pose(self) -> Optional[Frame]:
        """(rotation, position) of the next-best view, None when none is feasible."""
        if self.chosen_index < 0:
            return None
        return self.candidates.rotations[self.chosen_index], self.candidates.positions[self.chosen_index]

    def base_path_frames(self) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """((P, 3, 3), (P, 3)) poses along the path to the base goal: level, x along the path (the goal's own
        orientation last); None without a path."""
        if self.base_path is None or self.base_goal is None:
            return None
        points = np.asarray(self.base_path, dtype=np.float64)
        rotations = np.empty((len(points), 3, 3))
        for index in range(len(points) - 1):
            rotations[index] = base_goal_frame(points[index], points[index + 1], self.up)[0]
        rotations[-1] = self.base_goal[0]
        return rotations, points

    def ring_centre_frame(self) -> Frame:
        """A level frame on the ring centre (the ring marker's pose): z up, x toward the last candidate."""
        return base_goal_frame(self.candidates.ring_center, self.candidates.positions[-1], self.up)

    def to_arrays(self) -> ViewCandidatesArrays:
        """The ViewCandidates message values (pack them with conversions.arrays_to_view_candidates)."""
        from leapnbv_common.conversions import ViewCandidatesArrays

        return ViewCandidatesArrays(
            rotations=self.candidates.rotations, positions=self.candidates.positions,
            term_names=list(self.scores.term_names), term_weights=self.scores.term_weights,
            term_scores=self.scores.term_scores, score=self.scores.score, feasible=self.feasibility.feasible,
            infeasible_reason=np.asarray(self.feasibility.reasons, dtype=np.uint8), chosen_index=int(self.chosen_index),
            includes_current_view=bool(self.includes_current_view), ring_center=self.candidates.ring_center,
            ring_radius=float(self.ring_radius))


def base_goal_frame(foot_point: np.ndarray, ring_center: np.ndarray, up: np.ndarray) -> Frame:
    """The robot base goal: on the ground under the camera, x toward the target, z up (REP 103 base)."""
    up = up / np.linalg.norm(up)
    heading = ring_center - foot_point
    heading = heading - up * float(heading @ up)
    if np.linalg.norm(heading) < 1e-9:  # standing on the ring centre: keep any level heading
        heading = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 0.0, 1.0])
    x_axis = heading / np.linalg.norm(heading)
    y_axis = np.cross(up, x_axis)
    return np.column_stack([x_axis, y_axis, up]), np.asarray(foot_point, dtype=np.float64)


def _pose_arrays(camera_pose: Any) -> Frame:
    """(rotation, position) of a StampedCameraPose-like object or a (rotation, position) pair."""
    if hasattr(camera_pose, "rotation") and hasattr(camera_pose, "position"):
        return np.asarray(camera_pose.rotation, dtype=np.float64), np.asarray(camera_pose.position, dtype=np.float64)
    rotation, position = camera_pose
    return np.asarray(rotation, dtype=np.float64), np.asarray(position, dtype=np.float64)


def mesh_vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) unit outward vertex normals of a triangle mesh (area-weighted face normals summed per vertex).

    The faces' winding decides the sign; a closed body's normals are turned outward when they point, on
    the whole, toward its centre. A vertex in no face gets a zero normal (it never faces a camera).

    Raises:
        ValueError: vertices not (V, 3) or faces not (F, 3) indices into them.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"mesh: vertices must be (V, 3) and faces (F, 3), got {vertices.shape} and {faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError(f"mesh: face indices must lie in [0, {len(vertices)})")
    vertices = np.ascontiguousarray(vertices)
    centre = vertices.mean(axis=0)
    normals, total, magnitude = unit_normals(face_normal_sums(vertices, np.ascontiguousarray(faces)), vertices,
                                             centre)
    # The sign of the sum decides; when it is too near 0 for the summation order not to matter (never for a body),
    # it is taken as numpy sums it.
    if abs(total) <= 1e-9 * magnitude:
        total = float(np.sum(normals * (vertices - centre)))
    if total < 0.0:
        normals = -normals
    return normals


def plan_views(target: Any, ground: Any, params: Optional[PlannerParams] = None,
               obstacle_map: Optional[VoxelObstacleMap] = None, camera_pose: Any = None,
               body_mesh: Optional[Tuple[np.ndarray, np.ndarray]] = None) -> Plan:
    """Plan the next-best view of one frame.

    Args:
        target: TargetGeometryArrays (target_points, background_points, centroid, k, width, height,
            valid) of the frame.
        ground: GroundPlaneArrays (normal pointing up, offset, valid) of the frame.
        params: an instance of :func:`leapnbv_planner.params.nbv_params_class` (ring, terms and
            their weights, delta_px, map_max_target_points, map_target_margin); the robot's
            defaults when None.
        obstacle_map: the robot's obstacle map, used only together with camera_pose.
        camera_pose: the frame's camera in the map's frame: a StampedCameraPose (rotation,
            position attributes) or a (rotation, position) pair; the caller checks that its frame
            is the map's.
        body_mesh: optional (vertices (V, 3), faces (F, 3)) of the person's metric body mesh in the
            frame's optical frame (the raster node's human_mesh_metric): the body_occlusion term scores it.

    Returns:
        The Plan.

    Raises:
        PlanInputError: the target or the ground plane is marked invalid.
        ValueError: (CandidateGenerationError, ScoringInputError, ObstacleMapError) an input of
            the wrong shape or value.
    """
    params = default_nbv_params() if params is None else params
    if not target.valid:
        raise PlanInputError("the target geometry is not valid (no person points)")
    if not ground.valid:
        raise PlanInputError("the ground plane is not valid")
    normal = np.asarray(ground.normal, dtype=np.float64).reshape(3)
    offset = float(ground.offset)
    centroid = np.asarray(target.centroid, dtype=np.float64).reshape(3)
    # float64 once here (the messages carry float32), not again in every step that reads the clouds.
    target_points = np.ascontiguousarray(target.target_points, dtype=np.float64)
    background = np.ascontiguousarray(target.background_points, dtype=np.float64)
    candidates = generate_candidates(centroid, normal, offset, params)
    obstacles, line_of_sight_clear, mesh_clear = background, None, None
    mesh_vertices = mesh_normals = None
    if body_mesh is not None and "body_occlusion" in params.score_terms:
        mesh_vertices = np.asarray(body_mesh[0], dtype=np.float64)
        mesh_normals = mesh_vertex_normals(mesh_vertices, body_mesh[1])
    if obstacle_map is not None and camera_pose is not None:
        rotation, position = _pose_arrays(camera_pose)
        obstacles = np.concatenate([background, centres_in_observation(obstacle_map, rotation, position)])
        line_of_sight_clear = line_of_sight_clear_fraction(
            obstacle_map, rotation, position, candidates.positions, target_points,
            params.map_max_target_points, params.map_target_margin)
        if mesh_vertices is not None:
            mesh_clear = line_of_sight_clear_fraction(
                obstacle_map, rotation, position, candidates.positions, mesh_vertices,
                params.map_max_target_points, params.map_target_margin)
    feasibility = check_feasibility(candidates, obstacles, normal, offset, params)
    reach, path_lengths = None, None
    if getattr(params, "reachability", False):
        feasibility, reach = _check_paths(candidates, feasibility, obstacles, target, target_points, normal, offset,
                                          params)
        path_lengths = np.where(candidates.is_current, 0.0, reach.path_lengths)
    scores = score_candidates(target_points, background, candidates.rotations, candidates.positions, target.k,
                              target.width, target.height, params.term_weights(), delta_px=params.delta_px,
                              line_of_sight_clear=line_of_sight_clear, path_lengths=path_lengths,
                              travel_scale=float(getattr(params, "max_path_length", 6.0)),
                              mesh_vertices=mesh_vertices, mesh_normals=mesh_normals,
                              mesh_line_of_sight_clear=mesh_clear)
    chosen = choose_best(scores.score, feasibility.feasible, candidates.positions, np.zeros(3))
    base_goal, base_path = None, None
    if chosen >= 0:
        base_goal = base_goal_frame(candidates.foot_points[chosen], candidates.ring_center, normal)
        if reach is not None:
            base_path = reach.path_to(candidates.foot_points[chosen])
    return Plan(candidates=candidates, feasibility=feasibility, scores=scores, chosen_index=int(chosen),
                includes_current_view=bool(params.include_current), ring_radius=float(params.radius),
                up=normal, base_goal=base_goal, line_of_sight_clear=line_of_sight_clear,
                path_lengths=path_lengths, base_path=base_path, reach=reach)


def _check_paths(candidates: CandidateSet, feasibility: FeasibilityResult, obstacles: np.ndarray, target: Any,
                 target_points: np.ndarray, normal: np.ndarray, offset: float,
                 params: PlannerParams) -> Tuple[FeasibilityResult, Reachability]:
    """Feasible candidates without a free path of at most max_path_length become UNREACHABLE."""
    unit_normal, unit_offset = normalize_plane(normal, offset)
    current_foot = -unit_offset * unit_normal
    grid = build_occupancy_grid(obstacles, target_points, unit_normal, unit_offset,
                                np.vstack([candidates.foot_points, current_foot[None]]), params.grid_resolution,
                                params.robot_radius, params.floor_clearance, params.unknown_space,
                                camera=(np.asarray(target.k, dtype=np.float64).reshape(3, 3), int(target.width),
                                        int(target.height)))
    reach = reachability(grid, current_foot, candidates.foot_points, params.max_path_length, params.robot_radius)
    reasons = np.asarray(feasibility.reasons).copy()
    unreachable = (reasons == int(FeasibilityReason.OK)) & ~reach.reachable & ~np.asarray(candidates.is_current)
    reasons[unreachable] = int(FeasibilityReason.UNREACHABLE)
    return FeasibilityResult(feasible=reasons == int(FeasibilityReason.OK), reasons=reasons), reach
