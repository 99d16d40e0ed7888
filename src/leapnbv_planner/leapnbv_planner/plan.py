"""One next-best-view plan from one frame, without ROS: the nbv node's whole computation.

:func:`plan_views` takes one :class:`leapnbv_planner.inputs.PlanInputs`: the frame's target
geometry and ground plane (any objects with the attributes of the Protocols ``TargetArrays`` /
``FloorPlane``: the node's conversion dataclasses, or ``PlanTarget`` / ``PlanFloor``), the node's
parameters, and optionally the robot's obstacle map with the frame's camera pose in it and the
person's body mesh. It builds the candidate ring, joins the map's obstacles to the frame's
background for the footprint test, checks feasibility (and the free paths), scores the candidates
with the configured terms, chooses the best feasible one and computes the base goal; views given as
``extra_foot_points`` (the committed goal, :mod:`leapnbv_planner.commitment`) are then checked and scored
the same way, beside the ring. The scoring gets the PlanInputs unchanged: each term reads what it
declared (:mod:`leapnbv_planner.requirements`: the map's lines of sight, the body mesh, the paths),
computed once and only for a term that reads it; no step here knows a term by name. The result,
:class:`Plan`, holds everything the node publishes (candidates, goal, base goal, markers).

Everything is in the frame's camera optical frame; the current camera is the origin.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Dict, List, Optional, Tuple, Union, cast, overload

import numpy as np

from leapnbv_planner.arrays import Array
from leapnbv_planner.candidates import (
    CandidateGenerationError,
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
from leapnbv_planner.inputs import BodyMesh, CameraInMap, CameraPose, FloorPlane, PlanInputs, TargetArrays
from leapnbv_planner.mesh_kernel import mesh_vertex_normals
from leapnbv_planner.obstacle_map import ObstacleMap, centres_in_observation
from leapnbv_planner.params import PlannerParams, default_nbv_params
from leapnbv_planner.reachability import Reachability, build_occupancy_grid, reachability
from leapnbv_planner.requirements import MESH_LINE_OF_SIGHT, TARGET_LINE_OF_SIGHT, PlanFrame
from leapnbv_planner.score_terms import ScoringContext, declared_requirements, get_term
from leapnbv_planner.scoring import CandidateScores, choose_best, score_context

if TYPE_CHECKING:  # the core needs no ROS; only the conversion to the message arrays imports it
    from leapnbv_common.conversions import ViewCandidatesArrays

__all__ = ["ExtraViews", "Frame", "Plan", "PlanInputError", "PlanInputs", "base_goal_frame", "level_frames",
           "mesh_vertex_normals", "plan_views"]

Frame = Tuple[Array, Array]  # (3, 3) rotation with axes as columns, (3,) position
# fit_to_free_space: the nearest probes of a candidate that are free on the floor grid and get the exact footprint test.
_EXACT_TESTS_PER_CANDIDATE = 16


class PlanInputError(ValueError):
    """The frame cannot be planned (invalid target or ground plane); the text says which."""


@dataclass
class ExtraViews:
    """The views of ``PlanInputs.extra_foot_points``, planned beside the ring: checked, path-searched and scored
    with the ring's rules and terms, on the ring's floor grid, so their scores compare with the ring's.

    Attributes:
        candidates: their poses: foot points on the frame's floor, cameras by the ring's mounting rule
            (``cameras_at_feet``: aimed at the frame's centroid), the ring's centre; ``is_current`` all False.
        feasibility: feasible (E,) and the reason codes (E,): travel range, footprint and (with reachability) a free
            path of at most max_path_length on the ring's grid (a foot point off the grid has none: UNREACHABLE).
        scores: the ring's terms and weights, (E, T) values and (E,) score (0 when infeasible unless
            score_infeasible).
        path_lengths: (E,) metres of the free path to each (inf: none), None when reachability is off.
        base_paths: per view, (P, 3) floor points of its path (as ``Plan.base_path``), None without one.
        up: (3,) the ground normal as the plane gives it (``Plan.up``).
        nudged_m: (E,) metres each view's foot point moved to free space (:func:`_nudge_to_free_space`; 0: it
            stayed), None from a caller that made the views otherwise.
    """

    candidates: CandidateSet
    feasibility: FeasibilityResult
    scores: CandidateScores
    path_lengths: Optional[Array]
    base_paths: List[Optional[Array]]
    up: Array
    nudged_m: Optional[Array] = None

    def __len__(self) -> int:
        return len(self.candidates)

    def pose(self, index: int) -> Frame:
        """(rotation, position) of view ``index``'s camera, the frame's optical frame."""
        return self.candidates.rotations[index], self.candidates.positions[index]

    def base_goal(self, index: int) -> Frame:
        """The robot base goal of view ``index``: its foot point, x toward the ring centre (as ``Plan.base_goal``)."""
        return base_goal_frame(self.candidates.foot_points[index], self.candidates.ring_center, self.up)


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
            candidate that was not scored), None without the map, when no score term read it (the body mesh
            scored in place of the paper's S_o) or when no candidate was scored.
        path_lengths: (C,) metres of the robot's shortest free path to each candidate (0 for the current
            view, inf: none), None when reachability is off.
        base_path: (P, 3) floor points of the path to the chosen candidate (the robot's foot point first,
            the goal's last), None when reachability is off or nothing is chosen.
        reach: the path search (grid, parents), None when reachability is off.
        mesh_line_of_sight_clear: (C,) the same share of the body mesh's vertices, None without map or mesh
            (or when no term read it).
        used_obstacle_map: the map (with the frame's camera pose) took part in the plan.
        computed: every requirement the scoring computed (:mod:`leapnbv_planner.requirements`), by name: its
            value for the scored candidates (rows in the order of ``flatnonzero(scored)``), None where the
            frame lacked it.
        extra: the views of ``PlanInputs.extra_foot_points``, None when none were given.
    """

    candidates: CandidateSet
    feasibility: FeasibilityResult
    scores: CandidateScores
    chosen_index: int
    includes_current_view: bool
    ring_radius: float
    up: Array
    base_goal: Optional[Frame]
    line_of_sight_clear: Optional[Array] = None
    path_lengths: Optional[Array] = None
    base_path: Optional[Array] = None
    reach: Optional[Reachability] = None
    mesh_line_of_sight_clear: Optional[Array] = None
    used_obstacle_map: bool = False
    computed: Dict[str, object] = field(default_factory=dict)
    extra: Optional[ExtraViews] = None

    def chosen_pose(self) -> Optional[Frame]:
        """(rotation, position) of the next-best view, None when none is feasible."""
        if self.chosen_index < 0:
            return None
        return self.candidates.rotations[self.chosen_index], self.candidates.positions[self.chosen_index]

    def base_path_frames(self) -> Optional[Tuple[Array, Array]]:
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


def base_goal_frame(foot_point: Array, ring_center: Array, up: Array) -> Frame:
    """The robot base goal: on the ground under the camera, x toward the target, z up (REP 103 base)."""
    foot_point = np.asarray(foot_point, dtype=np.float64)
    return level_frames(foot_point.reshape(1, 3), np.asarray(ring_center, dtype=np.float64).reshape(1, 3), up)[0], \
        foot_point


def level_frames(points: Array, towards: Array, up: Array) -> Array:
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


@overload
def plan_views(inputs: PlanInputs) -> Plan:
    ...


@overload
def plan_views(inputs: TargetArrays, ground: FloorPlane, params: Optional[PlannerParams] = None,
               obstacle_map: Optional[ObstacleMap] = None, camera_pose: Union[CameraPose, Frame, None] = None,
               body_mesh: Optional[BodyMesh] = None) -> Plan:
    ...


def plan_views(inputs: Union[PlanInputs, TargetArrays], ground: Optional[FloorPlane] = None,
               params: Optional[PlannerParams] = None, obstacle_map: Optional[ObstacleMap] = None,
               camera_pose: Union[CameraPose, Frame, None] = None, body_mesh: Optional[BodyMesh] = None) -> Plan:
    """Plan the next-best view of one frame.

    Called as ``plan_views(PlanInputs(target, floor, params, obstacle_map, camera_pose, body_mesh))``. The
    older form ``plan_views(target, ground, params=None, obstacle_map=None, camera_pose=None, body_mesh=None)``
    makes that PlanInputs (its camera_pose may also be a (rotation, position) pair) and is the same plan.

    Args:
        inputs: the frame's inputs (see :class:`leapnbv_planner.inputs.PlanInputs`).

    Returns:
        The Plan.

    Raises:
        PlanInputError: the target or the ground plane is marked invalid.
        TypeError: a PlanInputs together with the older form's arguments, or the older form without ground.
        ValueError: (CandidateGenerationError, ScoringInputError, ObstacleMapError) an input of
            the wrong shape or value.
    """
    if isinstance(inputs, PlanInputs):
        if any(value is not None for value in (ground, params, obstacle_map, camera_pose, body_mesh)):
            raise TypeError("plan_views(PlanInputs) takes no further arguments: they are fields of PlanInputs")
        return _plan(inputs)
    if ground is None:
        raise TypeError("plan_views(target, ground, ...) needs the ground plane")
    return _plan(PlanInputs(target=inputs, floor=ground, params=default_nbv_params() if params is None else params,
                            obstacle_map=obstacle_map, camera_pose=_camera_pose(camera_pose), body_mesh=body_mesh))


def _camera_pose(camera_pose: Union[CameraPose, Frame, None]) -> Optional[CameraPose]:
    """A CameraPose of the older call form's camera_pose: an object with rotation and position, or a pair."""
    if camera_pose is None or (hasattr(camera_pose, "rotation") and hasattr(camera_pose, "position")):
        return cast(Optional[CameraPose], camera_pose)
    rotation, position = camera_pose
    return CameraInMap(np.asarray(rotation, dtype=np.float64), np.asarray(position, dtype=np.float64))


def _plan(inputs: PlanInputs) -> Plan:
    """plan_views of one PlanInputs."""
    target, ground, params = inputs.target, inputs.floor, inputs.params
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
    obstacles = background
    if inputs.obstacle_map is not None and inputs.camera_pose is not None:
        obstacles = np.concatenate([background, centres_in_observation(
            inputs.obstacle_map, np.asarray(inputs.camera_pose.rotation, dtype=np.float64),
            np.asarray(inputs.camera_pose.position, dtype=np.float64))])
    # The obstacles above the floor clearance in plane coordinates, once for the footprint tests and the grid.
    unit_normal, unit_offset = normalize_plane(normal, offset)
    obstacles_in_plane = elevated_plane_points(obstacles, unit_normal, unit_offset, float(params.floor_clearance),
                                               *plane_basis(unit_normal))
    feasibility = check_feasibility(candidates, obstacles, normal, offset, params, obstacles_in_plane)
    reach, path_lengths = None, None
    if params.reachability:
        feasibility, reach = _check_paths(candidates, feasibility, obstacles_in_plane, target, target_points, normal,
                                          offset, params)
        if params.fit_to_free_space:
            candidates, feasibility = _fit_to_free_space(candidates, feasibility, reach, obstacles_in_plane,
                                                         centroid, normal, offset, params)
        path_lengths = np.where(candidates.is_current, 0.0, reach.path_lengths)
    # Only the candidates the robot can take are scored (the scoring kernels are most of a plan's time); the
    # others keep score 0 unless score_infeasible asks for every candidate's terms (to look at them).
    scored = np.ones(len(candidates), dtype=bool) if params.score_infeasible \
        else np.asarray(feasibility.feasible, dtype=bool)
    picked = np.flatnonzero(scored)
    frame = PlanFrame(inputs=inputs, candidates=candidates, picked=picked, target_points=target_points,
                      path_lengths=path_lengths)
    scores, computed = _score_picked(frame, background)
    chosen = choose_best(scores.score, feasibility.feasible, candidates.positions, np.zeros(3))
    extra = None if inputs.extra_foot_points is None else \
        _plan_extra(inputs, candidates, obstacles, obstacles_in_plane, reach, target_points, background)
    base_goal, base_path = None, None
    if chosen >= 0:
        base_goal = base_goal_frame(candidates.foot_points[chosen], candidates.ring_center, normal)
        if reach is not None:
            base_path = reach.path_to(candidates.foot_points[chosen])
    return Plan(candidates=candidates, feasibility=feasibility, scores=scores, chosen_index=int(chosen),
                includes_current_view=bool(params.include_current), ring_radius=float(params.radius),
                up=normal, base_goal=base_goal,
                line_of_sight_clear=_on_scored_or_none(computed.get(TARGET_LINE_OF_SIGHT.name), picked,
                                                       len(candidates)),
                path_lengths=path_lengths, base_path=base_path, reach=reach,
                mesh_line_of_sight_clear=_on_scored_or_none(computed.get(MESH_LINE_OF_SIGHT.name), picked,
                                                            len(candidates)),
                used_obstacle_map=inputs.uses_obstacle_map, computed=computed, extra=extra)


def _plan_extra(inputs: PlanInputs, ring: CandidateSet, obstacles: Array, obstacles_in_plane: Array,
                reach: Optional[Reachability], target_points: Array, background: Array) -> ExtraViews:
    """The extra views planned beside the ring, after it: its grid and clouds, its rules, a scoring of their own (the
    ring's values and choice never see them).

    Raises:
        CandidateGenerationError: the foot points are not (E, 3) finite values.
    """
    params, ground = inputs.params, inputs.floor
    feet = np.asarray(inputs.extra_foot_points, dtype=np.float64)
    if feet.ndim != 2 or feet.shape[1] != 3 or not np.all(np.isfinite(feet)):
        raise CandidateGenerationError(f"extra_foot_points must be finite (E, 3) values, got shape {feet.shape}")
    normal = np.asarray(ground.normal, dtype=np.float64).reshape(3)
    unit_normal, unit_offset = normalize_plane(normal, float(ground.offset))
    # Onto this frame's floor: a point planned on an earlier frame's plane is off this one by the planes' difference.
    feet = feet - (feet @ unit_normal + unit_offset)[:, None] * unit_normal[None, :]
    rotations, positions = cameras_at_feet(feet, np.asarray(inputs.target.centroid, dtype=np.float64).reshape(3),
                                           unit_normal, ring.camera_height, params)
    views = CandidateSet(rotations=rotations, positions=positions, foot_points=feet, ring_center=ring.ring_center,
                         camera_height=ring.camera_height, is_current=np.zeros(len(feet), dtype=bool))
    feasibility = check_feasibility(views, obstacles, normal, float(ground.offset), params, obstacles_in_plane)
    path_lengths = None
    nudged = np.zeros(len(feet))
    if reach is not None:
        path_lengths = reach.path_lengths_at(feet)
        reasons = np.asarray(feasibility.reasons).copy()
        # The ring's rule (_check_paths): a free path of at most max_path_length.
        reachable = np.isfinite(path_lengths) & (path_lengths <= float(params.max_path_length))
        reasons[(reasons == int(FeasibilityReason.OK)) & ~reachable] = int(FeasibilityReason.UNREACHABLE)
        feasibility = FeasibilityResult(feasible=reasons == int(FeasibilityReason.OK), reasons=reasons)
        if params.fit_to_free_space and float(params.commit_same_goal_m) > 0.0:
            views, feasibility, path_lengths, nudged = _nudge_to_free_space(
                views, feasibility, path_lengths, reach, obstacles_in_plane,
                np.asarray(inputs.target.centroid, dtype=np.float64).reshape(3), normal,
                float(ground.offset), params)
    scored = np.ones(len(views), dtype=bool) if params.score_infeasible \
        else np.asarray(feasibility.feasible, dtype=bool)
    frame = PlanFrame(inputs=inputs, candidates=views, picked=np.flatnonzero(scored), target_points=target_points,
                      path_lengths=path_lengths)
    scores, _ = _score_picked(frame, background)
    base_paths = [reach.path_to(foot) if reach is not None and ok else None
                  for foot, ok in zip(views.foot_points, np.asarray(feasibility.feasible, dtype=bool))]
    return ExtraViews(candidates=views, feasibility=feasibility, scores=scores, path_lengths=path_lengths,
                      base_paths=base_paths, up=normal, nudged_m=nudged)


def _nudge_to_free_space(views: CandidateSet, feasibility: FeasibilityResult, path_lengths: Array,
                         reach: Reachability, obstacles_in_plane: Array, centroid: Array, normal: Array,
                         offset: float, params: PlannerParams) -> Tuple[CandidateSet, FeasibilityResult, Array, Array]:
    """Extra views that stand in an obstacle or have no path move to the nearest free, reachable foot point within
    ``commit_same_goal_m`` of their own (the same goal, by the commitment's rule).

    A committed goal is often a ring candidate that fit_to_free_space moved to the edge of free space. The next
    frame's grid is anchored at the robot's new foot point and its obstacle points come from a new view, so that
    edge moves by a fraction of a cell and the goal's own cell or footprint flips between free and blocked from
    one frame to the next (corridor seed 10: 18 goal switches, UNREACHABLE and back); the ring's own candidates
    are refitted every frame and never see it. Probes are grid cells around the foot point (an exact square
    lattice, so that their order by distance is an integer order, the same on every CPU), no nearer the target
    than min_free_radius, within max_travel, reached by a path of at most max_path_length, and then pass the exact
    footprint test; the nearest wins, then the shorter path (to the micrometre), then the first in lattice order.

    Returns:
        (views, feasibility, path lengths, metres each view moved: 0 for those that stayed).
    """
    reasons = np.asarray(feasibility.reasons)
    movable = np.flatnonzero((reasons == int(FeasibilityReason.OBSTACLE))
                             | (reasons == int(FeasibilityReason.UNREACHABLE)))
    nudged = np.zeros(len(reasons))
    if movable.size == 0:
        return views, feasibility, path_lengths, nudged
    step = float(reach.grid.cell)
    reach_cells = int(np.floor(float(params.commit_same_goal_m) / step + 1e-9))
    i, j = np.meshgrid(np.arange(-reach_cells, reach_cells + 1), np.arange(-reach_cells, reach_cells + 1),
                       indexing="ij")
    squared = (i * i + j * j).reshape(-1)
    keep = (squared > 0) & (squared * step * step <= float(params.commit_same_goal_m) ** 2 + 1e-12)
    i, j, squared = i.reshape(-1)[keep], j.reshape(-1)[keep], squared[keep]
    unit_normal, unit_offset = normalize_plane(normal, offset)
    e1, e2 = plane_basis(unit_normal)
    offsets = (i * step)[:, None] * e1[None, :] + (j * step)[:, None] * e2[None, :]
    feet = (views.foot_points[movable][:, None, :] + offsets[None, :, :]).reshape(-1, 3)  # (movable x probes, 3)
    owners = np.repeat(movable, len(offsets))
    squared_all = np.tile(squared, len(movable))
    lengths = reach.path_lengths_at(feet)
    ok = _probe_passes_grid(feet, lengths, -unit_offset * unit_normal, params) \
        & (np.linalg.norm(feet - views.ring_center[None, :], axis=1) >= float(params.min_free_radius) - 1e-9)
    order = np.lexsort((np.arange(len(feet)), np.round(np.where(ok, lengths, np.inf), 6), squared_all, owners))
    moved = _nearest_free_probes(feet, owners, order[ok[order]], obstacles_in_plane, unit_normal, params)
    if not moved:
        return views, feasibility, path_lengths, nudged
    indices = np.fromiter(moved.keys(), dtype=np.int64)
    chosen = np.fromiter(moved.values(), dtype=np.int64)
    fitted = _moved_to(views, indices, feet[chosen], centroid, unit_normal, params)
    reasons = reasons.copy()
    reasons[indices] = int(FeasibilityReason.OK)
    path_lengths = np.asarray(path_lengths, dtype=np.float64).copy()
    path_lengths[indices] = lengths[chosen]
    nudged[indices] = step * np.sqrt(squared_all[chosen].astype(np.float64))
    return fitted, FeasibilityResult(feasible=reasons == int(FeasibilityReason.OK), reasons=reasons), path_lengths, \
        nudged


def _probe_passes_grid(feet: Array, lengths: Array, current_foot: Array, params: PlannerParams) -> Array:
    """Probe foot points reached by a path of at most max_path_length and within max_travel of the robot."""
    passes: Array = np.isfinite(lengths) & (lengths <= float(params.max_path_length)) \
        & (np.linalg.norm(feet - current_foot[None, :], axis=1) <= float(params.max_travel))
    return passes


def _nearest_free_probes(feet: Array, owners: Array, order: Array, obstacles_in_plane: Array, unit_normal: Array,
                         params: PlannerParams) -> Dict[int, int]:
    """The first free probe of each owner: ``order`` lists the probes that passed the grid's tests, grouped by owner
    and best first; each owner's first _EXACT_TESTS_PER_CANDIDATE go to the exact footprint test (one call).

    Returns:
        {owner: index of its chosen probe in ``feet``}, for the owners with a free probe.
    """
    if order.size == 0:
        return {}
    tested = np.concatenate([group[:_EXACT_TESTS_PER_CANDIDATE] for group in
                             np.split(order, np.flatnonzero(np.diff(owners[order])) + 1)])
    e1, e2 = plane_basis(unit_normal)
    blocked = footprints_blocked_in_plane(obstacles_in_plane, np.ascontiguousarray(feet[tested] @ e1),
                                          np.ascontiguousarray(feet[tested] @ e2), float(params.robot_radius))
    moved: Dict[int, int] = {}
    for probe in tested[~blocked]:  # best first within each owner's group
        moved.setdefault(int(owners[probe]), int(probe))
    return moved


def _moved_to(candidates: CandidateSet, indices: Array, feet: Array, centroid: Array, unit_normal: Array,
              params: PlannerParams) -> CandidateSet:
    """A copy of ``candidates`` with those at ``indices`` standing on ``feet``, looking at the target."""
    rotations, positions = cameras_at_feet(feet, centroid, unit_normal, candidates.camera_height, params)
    fitted = CandidateSet(rotations=candidates.rotations.copy(), positions=candidates.positions.copy(),
                          foot_points=candidates.foot_points.copy(), ring_center=candidates.ring_center,
                          camera_height=candidates.camera_height, is_current=candidates.is_current)
    fitted.rotations[indices], fitted.positions[indices], fitted.foot_points[indices] = rotations, positions, feet
    return fitted


def _on_scored(values: Array, picked: Array, count: int, fill: float) -> Array:
    """(count,) array with ``values`` at the picked candidates and ``fill`` elsewhere."""
    full = np.full(count, fill, dtype=np.float64)
    full[picked] = values
    return full


def _on_scored_or_none(values: object, picked: Array, count: int) -> Optional[Array]:
    """_on_scored with NaN for the candidates not scored; None for a requirement not computed or absent."""
    return None if values is None else _on_scored(np.asarray(values, dtype=np.float64), picked, count, np.nan)


def _score_picked(frame: PlanFrame, background: Array) -> Tuple[CandidateScores, Dict[str, object]]:
    """The scores of the picked candidates (every other candidate's terms and score are 0), and the requirements
    the terms read."""
    params, target, candidates, picked = frame.inputs.params, frame.inputs.target, frame.candidates, frame.picked
    terms = params.term_weights()
    count = len(candidates)
    if len(picked) == 0:
        return CandidateScores(term_names=[name for name, _ in terms],
                               term_weights=np.array([weight for _, weight in terms], dtype=np.float64),
                               term_scores=np.zeros((count, len(terms))), score=np.zeros(count)), {}
    context = ScoringContext(frame.target_points, background, candidates.rotations[picked],
                             candidates.positions[picked], target.k, target.width, target.height,
                             delta_px=params.delta_px, params=params, frame=frame,
                             declared=declared_requirements([get_term(name) for name, _ in terms], params))
    scores = score_context(context, terms)
    computed = context.computed()
    if len(picked) == count:
        return scores, computed
    term_scores = np.zeros((count, len(terms)))
    term_scores[picked] = scores.term_scores
    return CandidateScores(term_names=scores.term_names, term_weights=scores.term_weights, term_scores=term_scores,
                           score=_on_scored(scores.score, picked, count, 0.0)), computed


def _fit_to_free_space(candidates: CandidateSet, feasibility: FeasibilityResult, reach: Reachability,
                       obstacles_in_plane: Array, centroid: Array, normal: Array, offset: float,
                       params: PlannerParams) -> Tuple[CandidateSet, FeasibilityResult]:
    """Ring candidates that stand in an obstacle or have no path move to the nearest foot point (to where they
    stood) that is free and reachable within their own patch of the rings: radius in their ring's band (down to,
    not onto, the next inner ring's radius; the innermost ring down to min_free_radius; never outward), bearing
    within half the angle between two candidates of their own. Probes one grid cell apart (radially, and along
    the arc); a foot point must be free on the floor grid, reached by a path of at most max_path_length, within
    max_travel, and pass the exact footprint test. Of two probes equally near (one the other's mirror image
    across the candidate's bearing), the one with the shorter path is taken, then the clockwise one (seen
    from above). ``reach.path_lengths`` and ``reach.reachable`` are updated for the moved candidates."""
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
        # The distance from the foot point from (radius, |angle|): a probe and its mirror image across the
        # bearing are equally near to the last bit (from the points, the CPU's rounding ordered the pair).
        # |p - f|^2 = (length - r0)^2 + 4 length r0 sin^2(angle / 2), without the cancellation of the cosine form.
        own_radius = np.linalg.norm(feet - candidates.ring_center, axis=1)[:, None]
        half_chord = np.sin(np.abs(angle) / 2.0)[None, :]
        shifts.append(np.sqrt((length[None, :] - own_radius) ** 2
                              + 4.0 * length[None, :] * own_radius * half_chord * half_chord).reshape(-1))
    if not probes:
        return candidates, feasibility
    owners_array, feet, shift = np.concatenate(owners), np.concatenate(probes), np.concatenate(shifts)
    lengths = reach.path_lengths_at(feet)
    ok = (shift > 1e-9) & _probe_passes_grid(feet, lengths, current_foot, params)
    # Of two probes equally near (mirror images), the one with the shorter path first, then the clockwise one.
    order = np.lexsort((np.arange(len(shift)), np.where(ok, lengths, np.inf), shift, owners_array))
    moved = _nearest_free_probes(feet, owners_array, order[ok[order]], obstacles_in_plane, unit_normal, params)
    if not moved:
        return candidates, feasibility
    indices = np.fromiter(moved.keys(), dtype=np.int64)
    chosen = np.fromiter(moved.values(), dtype=np.int64)
    fitted = _moved_to(candidates, indices, feet[chosen], centroid, unit_normal, params)
    reach.path_lengths = reach.path_lengths.copy()
    reach.reachable = reach.reachable.copy()
    reach.path_lengths[indices], reach.reachable[indices] = lengths[chosen], True
    reasons = reasons.copy()
    reasons[indices] = int(FeasibilityReason.OK)
    return fitted, FeasibilityResult(feasible=reasons == int(FeasibilityReason.OK), reasons=reasons)


def _floor_reach(candidates: CandidateSet, obstacles_in_plane: Array, target: TargetArrays, target_points: Array,
                 normal: Array, offset: float, params: PlannerParams, robot_radius: float) -> Reachability:
    """The path search from the robot over the floor grid around the ring's foot points, obstacles grown by
    ``robot_radius``; the path lengths are the ring's."""
    unit_normal, unit_offset = normalize_plane(normal, offset)
    current_foot = -unit_offset * unit_normal
    grid = build_occupancy_grid(np.zeros((0, 3)), target_points, unit_normal, unit_offset,
                                np.vstack([candidates.foot_points, current_foot[None]]), params.grid_resolution,
                                robot_radius, params.floor_clearance, params.unknown_space,
                                camera=(np.asarray(target.k, dtype=np.float64).reshape(3, 3), int(target.width),
                                        int(target.height)), obstacle_plane_points=obstacles_in_plane)
    return reachability(grid, current_foot, candidates.foot_points, params.max_path_length, robot_radius)


def _check_paths(candidates: CandidateSet, feasibility: FeasibilityResult, obstacles_in_plane: Array,
                 target: TargetArrays, target_points: Array, normal: Array, offset: float,
                 params: PlannerParams) -> Tuple[FeasibilityResult, Reachability]:
    """Feasible candidates without a free path of at most max_path_length become UNREACHABLE."""
    reach = _floor_reach(candidates, obstacles_in_plane, target, target_points, normal, offset, params,
                         float(params.robot_radius))
    reasons = np.asarray(feasibility.reasons).copy()
    unreachable = (reasons == int(FeasibilityReason.OK)) & ~reach.reachable & ~np.asarray(candidates.is_current)
    reasons[unreachable] = int(FeasibilityReason.UNREACHABLE)
    return FeasibilityResult(feasible=reasons == int(FeasibilityReason.OK), reasons=reasons), reach
