"""One evaluation episode without ROS: which candidate each method picks, and what the view from it shows.

Every method picks one of the SAME scored candidates of the start frame (the graph's
``ViewCandidates``, as ``ViewCandidatesArrays``):

* ``leap_nbv``: the graph's own choice (chosen_index, the deployed weights);
* ``stay``: candidate 0, the current view;
* ``random``: a feasible ring candidate drawn with a per-scene seed (staying is not a random move);
* ``<term>_only`` for every score term the planner reports (today ``visibility_only``,
  ``area_only``, ``occlusion_only``): the arg-max of that term alone over the feasible
  candidates, the planner's ``choose_best`` with one-hot weights;
* ``oracle`` (when every candidate is rendered): the feasible candidate with the best
  ground-truth surface coverage, the ceiling of the candidate ring.

The robot is sent to each pick (``pose_in_world`` of the start camera and the candidate's pose in
the observation frame): by default its base drives to the pick's point on the floor and the camera
stays at the start camera's mounting height, tilted toward the pick's viewing direction
(:class:`leapnbv_sim.poses.RobotModel`; ``motion="free"`` puts the camera at the 6-DoF pick
instead), and the scene is rendered there (the same noise draw for every method) and
scored: surface coverage (the headline), raw body coverage and the ground-truth reconstructed area
(:class:`~leapnbv_evaluation.results.ViewMetrics`). Success is decided here, once per method
(``metrics.is_success``). After a graph failure there are no candidates: every method stays.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from leapnbv_common.array_types import FloatArray
from leapnbv_common.conversions import GroundPlaneArrays, TargetGeometryArrays, ViewCandidatesArrays
from leapnbv_evaluation.metrics import body_coverage, is_success, surface_coverage
from leapnbv_evaluation.results import GraphVsTruth, MethodResult, PoseRecord, ViewMetrics
from leapnbv_planner.scoring import choose_best
from leapnbv_sim.poses import CameraPose, RobotModel, pose_in_world
from leapnbv_sim.render import PERSON_ID, RenderedFrame
from leapnbv_sim.scene import Scene

DEFAULT_METHOD = "leap_nbv"
#: Methods that need no score term: the graph's choice, staying, a random feasible move.
BASE_METHODS: Tuple[str, ...] = (DEFAULT_METHOD, "stay", "random")
#: Upper bound (uses the ground truth): the feasible candidate with the best surface coverage.
ORACLE_METHOD = "oracle"
#: Mixed into the per-scene seed of the "random" method.
RANDOM_METHOD_SALT = 7919
#: The evaluation's robot: the base drives, the camera stays at the start camera's height, a pan-tilt head.
DEFAULT_ROBOT = RobotModel()
#: The noise draw of every after-move render (the same for all methods: a fair comparison).
AFTER_FRAME_INDEX = 1

#: Default first stamp: an arbitrary fixed sim time (2023-11-14), so stamps repeat run to run.
DEFAULT_STAMP_BASE_NS = 1_700_000_000_000_000_000
#: Stamps of consecutive scenes lie this far apart: farther than the ground node's
#: mask_max_age_s (1 s), so no scene's start frame ever uses another scene's person mask.
SCENE_STAMP_SPACING_NS = 10_000_000_000
#: Stamps of consecutive frames of one scene (start view, view after the move).
FRAME_STAMP_SPACING_NS = 100_000_000


class EvaluationError(RuntimeError):
    """The evaluation cannot run (graph did not start, bad arguments); the text says why."""


def term_only_method(term: str) -> str:
    """The baseline that scores with one term alone: "<term>_only"."""
    return f"{term}_only"


def method_names(term_names: Sequence[str], oracle: bool) -> List[str]:
    """Every method, in table order: the base methods, one "<term>_only" per score term, the oracle."""
    return list(BASE_METHODS) + [term_only_method(term) for term in term_names] + ([ORACLE_METHOD] if oracle else [])


def choose_method_views(candidates: ViewCandidatesArrays, scene_seed: int) -> Dict[str, int]:
    """Each method's candidate index among the same scored candidates (-1: stays, nothing feasible).

    Args:
        candidates: The graph's scored candidates of the start frame.
        scene_seed: Seeds the "random" method (with RANDOM_METHOD_SALT): same scene, same draw.

    Returns:
        {method: index} for the base methods and one "<term>_only" per term of the candidates.
    """
    here = np.zeros(3)
    feasible = np.asarray(candidates.feasible, dtype=bool)
    choices = {DEFAULT_METHOD: int(candidates.chosen_index)}
    choices["stay"] = 0 if candidates.includes_current_view and len(candidates) else -1
    ring = np.flatnonzero(feasible)
    if candidates.includes_current_view:
        ring = ring[ring > 0]
    rng = np.random.default_rng([int(scene_seed) & 0xFFFFFFFF, RANDOM_METHOD_SALT])
    choices["random"] = int(rng.choice(ring)) if ring.size else -1
    # One-hot weights: the score is the single term itself.
    for term in candidates.term_names:
        values = np.asarray(candidates.term(term), dtype=np.float64)
        choices[term_only_method(term)] = int(choose_best(values, feasible, candidates.positions, here))
    return choices


def view_metrics(scene: Scene, frame: RenderedFrame) -> ViewMetrics:
    """Coverage and area of a rendered frame (noise-free depth for coverage, the sensor's for area).

    Args:
        scene: The scene the frame was rendered from (its body faces).
        frame: The rendered frame.

    Returns:
        The metrics.
    """
    vertices = frame.ground_truth.vertices_camera
    person = frame.object_id == PERSON_ID
    return ViewMetrics(
        surface_coverage=surface_coverage(vertices, scene.body_faces, frame.depth_clean_m, frame.K),
        raw_coverage=body_coverage(vertices, frame.depth_clean_m, frame.K),
        area_px=int(np.count_nonzero(person & (frame.depth_mm > 0))),
        person_pixels=int(np.count_nonzero(person)),
    )


def candidate_world_pose(observation: CameraPose, candidates: ViewCandidatesArrays, index: int,
                         robot: RobotModel = DEFAULT_ROBOT) -> CameraPose:
    """World camera pose the robot reaches when sent to candidate ``index`` (the observation's own pose for -1)."""
    if index < 0:
        return observation.copy()
    return robot.reach(observation, pose_in_world(observation, candidates.rotations[index],
                                                  candidates.positions[index]))


def frame_stamp_ns(stamp_base_ns: int, scene_index: int, frame: int) -> int:
    """Deterministic sim time of frame ``frame`` of scene ``scene_index`` in a run."""
    return int(stamp_base_ns) + int(scene_index) * SCENE_STAMP_SPACING_NS + int(frame) * FRAME_STAMP_SPACING_NS


def method_result(index: int, pose: CameraPose, before: ViewMetrics, after: ViewMetrics) -> MethodResult:
    """A method's move, with success decided by ``metrics.is_success`` (surface and raw coverage)."""
    return MethodResult(
        chosen_index=int(index), pose=PoseRecord.of(pose), before=before, after=after,
        success=is_success(before.surface_coverage, after.surface_coverage),
        raw_success=is_success(before.raw_coverage, after.raw_coverage),
    )


@dataclass
class MethodViews:
    """Every method's move in one scene, and the renders behind them.

    Attributes:
        per_method: Method -> its move (success decided), in table order.
        rendered: Candidate index (-1: staying) -> (after-view render, its metrics).
        candidate_views: Metrics of every candidate's view when all were rendered, else None.
    """

    per_method: Dict[str, MethodResult]
    rendered: Dict[int, Tuple[RenderedFrame, ViewMetrics]]
    candidate_views: Optional[List[ViewMetrics]]


def score_methods(scene: Scene, before: ViewMetrics, candidates: Optional[ViewCandidatesArrays], seed: int,
                  score_all_candidates: bool, methods_when_staying: Sequence[str],
                  robot: RobotModel = DEFAULT_ROBOT) -> MethodViews:
    """Every method's pick among the candidates, rendered from the start camera's view of them and scored.

    Args:
        scene: The scene.
        before: Metrics of the start view.
        candidates: The graph's candidates of the start view; None after a graph failure (every
            method of ``methods_when_staying`` then stays).
        seed: The scene's seed (the random method's draw).
        score_all_candidates: Render every candidate too and add the oracle.
        methods_when_staying: The methods to record when there are no candidates.
        robot: How the robot reaches a pick (default: base motion, camera at its mounting height).

    Returns:
        The moves and renders.
    """
    start = scene.start_camera
    rendered: Dict[int, Tuple[RenderedFrame, ViewMetrics]] = {}
    candidate_views: Optional[List[ViewMetrics]] = None
    if candidates is None:
        choices = {method: -1 for method in methods_when_staying}
    else:
        choices = choose_method_views(candidates, seed)
        if score_all_candidates:
            for index in range(len(candidates)):
                frame = scene.render(candidate_world_pose(start, candidates, index, robot),
                                     frame_index=AFTER_FRAME_INDEX)
                rendered[index] = (frame, view_metrics(scene, frame))
            candidate_views = [rendered[index][1] for index in range(len(candidates))]
            coverage = np.array([view.surface_coverage for view in candidate_views])
            choices[ORACLE_METHOD] = int(choose_best(coverage, candidates.feasible, candidates.positions, np.zeros(3)))
    per_method: Dict[str, MethodResult] = {}
    for method, index in choices.items():
        pose = candidate_world_pose(start, candidates, index, robot) if candidates is not None else start
        if index not in rendered:
            frame = scene.render(pose, frame_index=AFTER_FRAME_INDEX)
            rendered[index] = (frame, view_metrics(scene, frame))
        per_method[method] = method_result(index, pose, before, rendered[index][1])
    return MethodViews(per_method, rendered, candidate_views)


def graph_vs_truth(scene: Scene, target: Optional[TargetGeometryArrays], ground: Optional[GroundPlaneArrays],
                   candidates: Optional[ViewCandidatesArrays]) -> GraphVsTruth:
    """The graph's target centroid and ground plane next to the truth (start camera's optical frame)."""
    camera = scene.start_camera
    body = camera.world_to_camera(scene.body_vertices_world)
    # The floor z = 0 in the camera frame: n_c = R^T e_z, offset = camera height.
    up = camera.rotation.T @ np.array([0.0, 0.0, 1.0])
    record = GraphVsTruth(
        truth_body_centre_m=_rounded(0.5 * (body.min(axis=0) + body.max(axis=0)), 4),
        truth_body_median_m=_rounded(np.median(body, axis=0), 4),
        truth_ground_normal=_rounded(up, 5),
        truth_ground_offset_m=round(float(camera.position[2]), 4),
    )
    if target is not None:
        record.target_valid = bool(target.valid)
        record.target_centroid_m = _rounded(target.centroid, 4)
        record.target_depth_offset_m = round(float(target.depth_offset), 4)
        record.target_visible_fraction = round(float(target.visible_fraction), 4)
    if ground is not None:
        normal = np.asarray(ground.normal, dtype=np.float64)
        cosine = normal @ up / max(np.linalg.norm(normal), 1e-12)
        record.ground_valid = bool(ground.valid)
        record.ground_normal = _rounded(normal, 5)
        record.ground_offset_m = round(float(ground.offset), 4)
        record.ground_inlier_ratio = round(float(ground.inlier_ratio), 4)
        record.ground_tilt_error_deg = round(float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))), 3)
    if candidates is not None:
        record.ring_center_m = _rounded(candidates.ring_center, 4)
    return record


def _rounded(values: FloatArray, digits: int) -> List[float]:
    return [round(float(v), digits) for v in values]
