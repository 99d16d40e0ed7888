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
    cameras_at_feet,
    check_feasibility,
    cross,
    generate_candidates,
    normalize_plane,
    plane_basis,
    ring_radii,
)
from leapnbv_planner.footprint_kernel import elevated_plane_points, footprints_blocked_in_plane
from leapnbv_planner.mesh_kernel import face_normal_sums, unit_normals
from leapnbv_planner.obstacle_map import VoxelObstacleMap, centres_in_observation, line_of_sight_clear_fraction
from leapnbv_planner.params import PlannerParams, default_nbv_params
from leapnbv_planner.reachability import Reachability, build_occupancy_grid, reachability
from leapnbv_planner.scoring import CandidateScores, choose_best, score_candidates

if TYPE_CHECKING:  # the core needs no ROS; only the conversion to the message arrays imports it
    from leapnbv_common.conversions import ViewCandidatesArrays

Frame = Tuple[np.ndarray, np.ndarray]  # (3, 3) rotation with axes as columns, (3,) position
# Terms that never read the target points' line of sight through the map (body_occlusion reads the mesh's when the
# frame has a mesh); with only these, that walk is skipped.
_NO_TARGET_LINE_OF_SIGHT = ("visibility", "area", "body_occlusion", "travel")
# fit_to_free_space: the nearest probes of a candidate that are free on the floor grid and get the exact footprint test.
_EXACT_TESTS_PER_CANDIDATE = 16


class PlanInputError(ValueError):
    """The frame cannot be planned (invalid target or ground plane); the text says which."""


@dataclass
class Plan:
    """The plan of one frame.

    Attributes:
        candidates: the candidate poses (rotations, positions, foot points, ring centre).
        feasibility: feasible (C,) and the infeasible reason codes (C,).
        scores: term names, weights, (C, T) term values and the (C,) score (0 for an infeasible candidate unless
            score_infeasible is set: those are not scored).
        chosen_index: the chosen candidate, -1 when none is feasible.
        includes_current_view: candidate 0 is the current view.
        ring_radius: metres.
        up: (3,) the ground normal n as the plane gives it (pointing up, not necessarily unit length).
        base_goal: (rotation, position) of the robot base at the chosen view, None when none is chosen.
        line_of_sight_clear: (C,) the obstacle map's clear share of the target points per candidate (NaN for a
            candidate that was not scored), None without the map or when no score term reads it (the body mesh
            scored in place of the paper's S_o).
        path_lengths: (C,) metres of the robot's shortest free path to each candidate (0 for the current
            view, inf: none), None when reachability is off.
        base_path: (P, 3) floor points of the path to the chosen candidate (the robot's foot point first,
            the goal's last), None when reachability is off or nothing is chosen.
        reach: the path search (grid, parents), None when reachability is off.
        mesh_line_of_sight_clear: (C,) the same share of the body mesh's vertices, None without map or mesh.
        used_obstacle_map: the map (with the frame's camera pose) took part in the plan.
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
    mesh_line_of_sight_clear: Optional[np.ndarray] = None
    used_obstacle_map: bool = False

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
        rotations[:-1] = level_frames(points[:-1], points[1:], self.up)
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
    foot_point = np.asarray(foot_point, dtype=np.float64)
    return level_frames(foot_point.reshape(1, 3), np.asarray(ring_center, dtype=np.float64).reshape(1, 3), up)[0], \
        foot_point


def level_frames(points: np.ndarray, towards: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(P, 3, 3) level frames (axes as columns): z along ``up``, x toward ``towards`` seen from ``points`` in the
    plane, y = z x x; where the two are on one vertical, any level x."""
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    heading = np.asarray(towards, dtype=np.float64) - np.asarray(points, dtype=np.float64)
    heading = heading - (heading @ up)[:, None] * up[None, :]
    length = np.sqrt(np.sum(heading * heading, axis=1))
    vertical = length < 1e-9
    if vertical.any():  # standing on the point: keep any level heading
        any_level = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 0.0, 1.0])
        heading[vertical] = any_level
        length[vertical] = np.linalg.norm(any_level)
    x_axis = heading / length[:, None]
    up_rows = np.broadcast_to(up, x_axis.shape)
    return np.stack([x_axis, cross(up_rows, x_axis), up_rows], axis=2)


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
    with_map = obstacle_map is not None and camera_pose is not None
    if with_map:
        rotation, position = _pose_arrays(camera_pose)
        obstacles = np.concatenate([background, centres_in_observation(obstacle_map, rotation, position)])
    # The obstacles above the floor clearance in plane coordinates, once for the footprint tests and the grid.
    unit_normal, unit_offset = normalize_plane(normal, offset)
    obstacles_in_plane = elevated_plane_points(obstacles, unit_normal, unit_offset, float(params.floor_clearance),
                                               *plane_basis(unit_normal))
    feasibility = check_feasibility(candidates, obstacles, normal, offset, params, obstacles_in_plane)
    reach, path_lengths = None, None
    if getattr(params, "reachability", False):
        feasibility, reach = _check_paths(candidates, feasibility, obstacles_in_plane, target, target_points, normal,
                                          offset, params)
        if getattr(params, "fit_to_free_space", False):
            candidates, feasibility = _fit_to_free_space(candidates, feasibility, reach, obstacles_in_plane,
                                                         centroid, normal, offset, params)
        path_lengths = np.where(candidates.is_current, 0.0, reach.path_lengths)
    # Only the candidates the robot can take are scored (the scoring kernels are most of a plan's time); the
    # others keep score 0 unless score_infeasible asks for every candidate's terms (to look at them).
    scored = np.ones(len(candidates), dtype=bool) if getattr(params, "score_infeasible", True) \
        else np.asarray(feasibility.feasible, dtype=bool)
    picked = np.flatnonzero(scored)
    # The target points' line of sight serves the paper's S_o (and body_occlusion without a mesh); with the
    # mesh scored in its place only the mesh vertices' is needed.
    target_clear_used = mesh_vertices is None or any(name not in _NO_TARGET_LINE_OF_SIGHT
                                                     for name in params.score_terms)

    def clear_share(points: np.ndarray) -> np.ndarray:
        """The map's clear line-of-sight share of ``points`` from each scored candidate (NaN for the others)."""
        return _on_scored(line_of_sight_clear_fraction(
            obstacle_map, rotation, position, candidates.positions[picked], points, params.map_max_target_points,
            params.map_target_margin), picked, len(candidates), np.nan)

    if with_map and target_clear_used:
        line_of_sight_clear = clear_share(target_points)
    if with_map and mesh_vertices is not None:
        mesh_clear = clear_share(mesh_vertices)
    scores = _score_picked(candidates, picked, target, target_points, background, params, line_of_sight_clear,
                           path_lengths, mesh_vertices, mesh_normals, mesh_clear)
    chosen = choose_best(scores.score, feasibility.feasible, candidates.positions, np.zeros(3))
    base_goal, base_path = None, None
    if chosen >= 0:
        base_goal = base_goal_frame(candidates.foot_points[chosen], candidates.ring_center, normal)
        if reach is not None:
            base_path = reach.path_to(candidates.foot_points[chosen])
    return Plan(candidates=candidates, feasibility=feasibility, scores=scores, chosen_index=int(chosen),
                includes_current_view=bool(params.include_current), ring_radius=float(params.radius),
                up=normal, base_goal=base_goal, line_of_sight_clear=line_of_sight_clear,
                path_lengths=path_lengths, base_path=base_path, reach=reach, mesh_line_of_sight_clear=mesh_clear,
                used_obstacle_map=with_map)


def _on_scored(values: np.ndarray, picked: np.ndarray, count: int, fill: float) -> np.ndarray:
    """(count,) array with ``values`` at the picked candidates and ``fill`` elsewhere."""
    full = np.full(count, fill, dtype=np.float64)
    full[picked] = values
    return full


def _score_picked(candidates: CandidateSet, picked: np.ndarray, target: Any, target_points: np.ndarray,
                  background: np.ndarray, params: PlannerParams, line_of_sight_clear: Optional[np.ndarray],
                  path_lengths: Optional[np.ndarray], mesh_vertices: Optional[np.ndarray],
                  mesh_normals: Optional[np.ndarray], mesh_clear: Optional[np.ndarray]) -> CandidateScores:
    """The scores of the picked candidates; every other candidate's terms and score are 0."""
    terms = params.term_weights()
    count = len(candidates)
    if len(picked) == 0:
        return CandidateScores(term_names=[name for name, _ in terms],
                               term_weights=np.array([weight for _, weight in terms], dtype=np.float64),
                               term_scores=np.zeros((count, len(terms))), score=np.zeros(count))

    def on_picked(values: Optional[np.ndarray]) -> Optional[np.ndarray]:
        return None if values is None else values[picked]

    scores = score_candidates(target_points, background, candidates.rotations[picked], candidates.positions[picked],
                              target.k, target.width, target.height, terms, delta_px=params.delta_px,
                              line_of_sight_clear=on_picked(line_of_sight_clear), path_lengths=on_picked(path_lengths),
                              travel_scale=float(getattr(params, "max_path_length", 6.0)),
                              mesh_vertices=mesh_vertices, mesh_normals=mesh_normals,
                              mesh_line_of_sight_clear=on_picked(mesh_clear))
    if len(picked) == count:
        return scores
    term_scores = np.zeros((count, len(terms)))
    term_scores[picked] = scores.term_scores
    return CandidateScores(term_names=scores.term_names, term_weights=scores.term_weights, term_scores=term_scores,
                           score=_on_scored(scores.score, picked, count, 0.0))


def _fit_to_free_space(candidates: CandidateSet, feasibility: FeasibilityResult, reach: Reachability,
                       obstacles_in_plane: np.ndarray, centroid: np.ndarray, normal: np.ndarray, offset: float,
                       params: PlannerParams) -> Tuple[CandidateSet, FeasibilityResult]:
    """Ring candidates that stand in an obstacle or have no path move to the nearest foot point (to where they
    stood) that is free and reachable within their own patch of the rings: radius in their ring's band (down to,
    not onto, the next inner ring's radius; the innermost ring down to min_free_radius; never outward), bearing
    within half the angle between two candidates of their own. Probes one grid cell apart (radially, and along
    the arc); a foot point must be free on the floor grid, reached by a path of at most max_path_length, within
    max_travel, and pass the exact footprint test. ``reach.path_lengths`` and ``reach.reachable`` are updated
    for the moved candidates."""
    reasons = np.asarray(feasibility.reasons)
    movable = (reasons == int(FeasibilityReason.OBSTACLE)) | (reasons == int(FeasibilityReason.UNREACHABLE))
    first_ring = 1 if params.include_current else 0
    per_ring = int(params.num_candidates)
    radii = ring_radii(params)
    step = float(reach.grid.cell)
    half_gap = np.pi / max(per_ring, 1)
    unit_normal, unit_offset = normalize_plane(normal, offset)
    current_foot = -unit_offset * unit_normal
    owners, probes, shifts = [], [], []
    movable[:first_ring] = False
    ring_of = (np.arange(len(reasons)) - first_ring) // max(per_ring, 1)
    for ring, outer in enumerate(radii):
        members = np.flatnonzero(movable & (ring_of == ring))
        if members.size == 0:
            continue
        # The ring's patch as (radius, angle) offsets, the same for each of its candidates.
        radius = np.arange(float(outer), 0.0, -step)
        radius = radius[radius > float(radii[ring - 1]) + 1e-6] if ring > 0 else \
            radius[radius >= float(params.min_free_radius) - 1e-9]  # never onto the inner ring
        if radius.size == 0:
            continue
        radius = radius[:, None]
        reach_cells = np.floor(half_gap * float(outer) / step)
        arc = np.arange(-reach_cells, reach_cells + 1) * step
        inside = np.abs(arc[None, :]) < half_gap * radius  # the arc ends where the neighbours' patches begin
        angle = (arc[None, :] / radius)[inside]
        length = np.broadcast_to(radius, inside.shape)[inside]
        feet = candidates.foot_points[members]
        bearing = feet - candidates.ring_center
        bearing /= np.maximum(np.linalg.norm(bearing, axis=1), 1e-12)[:, None]
        side = cross(unit_normal[None, :], bearing)
        points = (candidates.ring_center[None, None, :]
                  + (length * np.cos(angle))[None, :, None] * bearing[:, None, :]
                  + (length * np.sin(angle))[None, :, None] * side[:, None, :])  # (members, probes, 3)
        owners.append(np.repeat(members, len(angle)))
        probes.append(points.reshape(-1, 3))
        shifts.append(np.linalg.norm(points - feet[:, None, :], axis=2).reshape(-1))
    if not probes:
        return candidates, feasibility
    owners_array, feet, shift = np.concatenate(owners), np.concatenate(probes), np.concatenate(shifts)
    lengths = reach.path_lengths_at(feet)
    ok = (shift > 1e-9) & np.isfinite(lengths) & (lengths <= float(params.max_path_length)) \
        & (np.linalg.norm(feet - current_foot[None, :], axis=1) <= float(params.max_travel))
    # Per candidate, its few nearest probes that pass on the grid go to the exact footprint test (one call).
    order = np.lexsort((shift, owners_array))
    order = order[ok[order]]
    tested = np.concatenate([group[:_EXACT_TESTS_PER_CANDIDATE] for group in
                             np.split(order, np.flatnonzero(np.diff(owners_array[order])) + 1)]) if order.size \
        else order
    moved = {}
    if tested.size:
        e1, e2 = plane_basis(unit_normal)
        blocked = footprints_blocked_in_plane(obstacles_in_plane, np.ascontiguousarray(feet[tested] @ e1),
                                              np.ascontiguousarray(feet[tested] @ e2), float(params.robot_radius))
        for probe in tested[~blocked]:  # nearest first within each candidate's group
            moved.setdefault(int(owners_array[probe]), int(probe))
    if not moved:
        return candidates, feasibility
    indices = np.fromiter(moved.keys(), dtype=np.int64)
    chosen = np.fromiter(moved.values(), dtype=np.int64)
    rotations, positions = cameras_at_feet(feet[chosen], centroid, unit_normal, candidates.camera_height, params)
    fitted = CandidateSet(rotations=candidates.rotations.copy(), positions=candidates.positions.copy(),
                          foot_points=candidates.foot_points.copy(), ring_center=candidates.ring_center,
                          camera_height=candidates.camera_height, is_current=candidates.is_current)
    fitted.rotations[indices], fitted.positions[indices], fitted.foot_points[indices] = rotations, positions, \
        feet[chosen]
    reach.path_lengths = reach.path_lengths.copy()
    reach.reachable = reach.reachable.copy()
    reach.path_lengths[indices], reach.reachable[indices] = lengths[chosen], True
    reasons = reasons.copy()
    reasons[indices] = int(FeasibilityReason.OK)
    return fitted, FeasibilityResult(feasible=reasons == int(FeasibilityReason.OK), reasons=reasons)


def _check_paths(candidates: CandidateSet, feasibility: FeasibilityResult, obstacles_in_plane: np.ndarray,
                 target: Any, target_points: np.ndarray, normal: np.ndarray, offset: float,
                 params: PlannerParams) -> Tuple[FeasibilityResult, Reachability]:
    """Feasible candidates without a free path of at most max_path_length become UNREACHABLE."""
    unit_normal, unit_offset = normalize_plane(normal, offset)
    current_foot = -unit_offset * unit_normal
    grid = build_occupancy_grid(np.zeros((0, 3)), target_points, unit_normal, unit_offset,
                                np.vstack([candidates.foot_points, current_foot[None]]), params.grid_resolution,
                                params.robot_radius, params.floor_clearance, params.unknown_space,
                                camera=(np.asarray(target.k, dtype=np.float64).reshape(3, 3), int(target.width),
                                        int(target.height)), obstacle_plane_points=obstacles_in_plane)
    reach = reachability(grid, current_foot, candidates.foot_points, params.max_path_length, params.robot_radius)
    reasons = np.asarray(feasibility.reasons).copy()
    unreachable = (reasons == int(FeasibilityReason.OK)) & ~reach.reachable & ~np.asarray(candidates.is_current)
    reasons[unreachable] = int(FeasibilityReason.UNREACHABLE)
    return FeasibilityResult(feasible=reasons == int(FeasibilityReason.OK), reasons=reasons), reach
