"""What an evaluation run produces, as typed records with a lossless JSON form.

One :class:`EvaluationRun` holds one :class:`SceneResult` per benchmark scene (in seed order);
each scene holds the graph's scored candidates (``ViewCandidatesArrays``, the one shape of
candidates), the start view's :class:`ViewMetrics`, and one :class:`MethodResult` per method
(the chosen candidate, its world pose, the view metrics before and after the move, success,
PA-MPVPE, and for ``leap_nbv`` the :class:`ClosedLoopResult` of the robot following the goal).
Success is decided once, when the episode is scored (``metrics.is_success``); readers never
recompute it.

``to_json()`` gives plain JSON types (numbers, strings, lists, dicts; no NaN) and ``from_json``
reads them back to an equal object: a run written with :meth:`EvaluationRun.write` and read with
:meth:`EvaluationRun.read` compares equal to the original (floats are written with Python's
shortest round-trip repr). Worker processes of a parallel run hand their runs to the parent this
way (:func:`EvaluationRun.merge`).
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from typing import Any, Dict, List, Mapping, Optional, Sequence

import numpy as np

from leapnbv_common.atomic_files import write_file_atomically
from leapnbv_common.conversions import ViewCandidatesArrays
from leapnbv_sim.poses import CameraPose

#: Version of the JSON layout of :class:`EvaluationRun`.
RUN_FORMAT = 1


class ResultsError(ValueError):
    """A results JSON is malformed or two runs cannot be merged; the text says why."""


@dataclass
class ViewMetrics:
    """What one rendered view shows of the person.

    Attributes:
        surface_coverage: Share of the self-visible body surface that this view sees, 0-1.
        raw_coverage: Share of all body vertices this view sees, 0-1 (docs/ALGORITHMS.md §8).
        area_px: Person pixels with a depth return (ground-truth reconstructed area).
        person_pixels: Person pixels, with or without depth.
    """

    surface_coverage: float
    raw_coverage: float
    area_px: int
    person_pixels: int

    def to_json(self) -> Dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> ViewMetrics:
        return cls(float(data["surface_coverage"]), float(data["raw_coverage"]), int(data["area_px"]),
                   int(data["person_pixels"]))


@dataclass
class PoseRecord:
    """A world camera pose as logged: optical centre (m, 6 decimals), heading and pitch of the optical axis (deg, 4)."""

    position_m: List[float]
    heading_deg: float
    pitch_deg: float

    @classmethod
    def of(cls, pose: CameraPose) -> PoseRecord:
        """The record of a T_world_camera (heading from world +x about +z, pitch down positive)."""
        forward = pose.rotation[:, 2]
        return cls(
            position_m=[round(float(v), 6) for v in pose.position],
            heading_deg=round(float(np.degrees(np.arctan2(forward[1], forward[0]))), 4),
            pitch_deg=round(float(np.degrees(np.arcsin(np.clip(-forward[2], -1.0, 1.0)))), 4),
        )

    def to_json(self) -> Dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> PoseRecord:
        return cls([float(v) for v in data["position_m"]], float(data["heading_deg"]), float(data["pitch_deg"]))


@dataclass
class ClosedLoopResult:
    """The robot following the graph's goal over DDS and the graph observing again (``leap_nbv`` only).

    Attributes:
        goal_received: The simulator node got the goal (else it was moved to the candidate directly).
        goal_position_error_m: Distance of the camera after the move from the chosen candidate's pose.
        graph_area_after_px: The graph's reconstructed area of the after-view (mask pixels with depth).
        after_stamp_ns: Stamp of the after-view.
        after_graph_failure: Why the graph planned nothing for the after-view, or None.
        after_graph_chosen_index: The graph's choice in the after-view (None: no candidates).
        closed_loop_matches_render: The node's after-view is the in-process render of the pick.
        steps: The further moves (2, 3, ...) of a multi-move episode (``max_moves`` > 1), in order.
        stop_reason: Why the episode ended after its last move ("" for a one-move episode).
    """

    goal_received: bool
    goal_position_error_m: float
    graph_area_after_px: Optional[int]
    after_stamp_ns: int
    after_graph_failure: Optional[str]
    after_graph_chosen_index: Optional[int]
    closed_loop_matches_render: bool
    steps: List[MoveStep] = field(default_factory=list)
    stop_reason: str = ""

    def to_json(self) -> Dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> ClosedLoopResult:
        return cls(bool(data["goal_received"]), float(data["goal_position_error_m"]),
                   _optional(int, data["graph_area_after_px"]), int(data["after_stamp_ns"]),
                   _optional(str, data["after_graph_failure"]), _optional(int, data["after_graph_chosen_index"]),
                   bool(data["closed_loop_matches_render"]),
                   [MoveStep.from_json(step) for step in data.get("steps", [])], str(data.get("stop_reason", "")))


@dataclass
class MoveStep:
    """One further move of a multi-move episode: the graph planned on the previous view, the robot moved.

    Attributes:
        move: 2 for the second move, and so on.
        stamp_ns: Stamp of the view after this move.
        planned_from_stamp_ns: Stamp of the view the move was planned on.
        chosen_index: The graph's pick on that view.
        predicted_gain: Its score minus the current view's (candidate 0's) score.
        travel_m: Distance the camera moved (its foot point on the floor).
        surface_coverage: Coverage of the view after the move.
        end_to_end_ms: The view's time through the graph (None when it did not answer).
    """

    move: int
    stamp_ns: int
    planned_from_stamp_ns: int
    chosen_index: int
    predicted_gain: float
    travel_m: float
    surface_coverage: float
    end_to_end_ms: Optional[float] = None

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> MoveStep:
        return cls(int(data["move"]), int(data["stamp_ns"]), int(data["planned_from_stamp_ns"]),
                   int(data["chosen_index"]), float(data["predicted_gain"]), float(data["travel_m"]),
                   float(data["surface_coverage"]), _optional(float, data.get("end_to_end_ms")))


@dataclass
class MethodResult:
    """One method's move in one scene.

    Attributes:
        chosen_index: The candidate it picked (-1: it stays, nothing was feasible or the graph failed).
        pose: World pose of the pick.
        before: The start view's metrics.
        after: The metrics of the view from the pick.
        success: ``metrics.is_success`` on the surface coverage before and after.
        raw_success: The same rule on the raw body coverage (for the raw-coverage table).
        pa_mpvpe_mm: PA-MPVPE of the graph's metric mesh after the move (real models, leap_nbv), or None.
        closed_loop: The closed loop through the graph (leap_nbv with a pick), or None.
    """

    chosen_index: int
    pose: PoseRecord
    before: ViewMetrics
    after: ViewMetrics
    success: bool
    raw_success: bool
    pa_mpvpe_mm: Optional[float] = None
    closed_loop: Optional[ClosedLoopResult] = None

    @property
    def graph_area_after(self) -> Optional[int]:
        """The graph's own area after the move (closed loop only)."""
        return self.closed_loop.graph_area_after_px if self.closed_loop is not None else None

    def to_json(self) -> Dict[str, Any]:
        return {
            "chosen_index": self.chosen_index,
            "pose": self.pose.to_json(),
            "before": self.before.to_json(),
            "after": self.after.to_json(),
            "success": self.success,
            "raw_success": self.raw_success,
            "pa_mpvpe_mm": self.pa_mpvpe_mm,
            "closed_loop": self.closed_loop.to_json() if self.closed_loop is not None else None,
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> MethodResult:
        return cls(
            chosen_index=int(data["chosen_index"]),
            pose=PoseRecord.from_json(data["pose"]),
            before=ViewMetrics.from_json(data["before"]),
            after=ViewMetrics.from_json(data["after"]),
            success=bool(data["success"]),
            raw_success=bool(data["raw_success"]),
            pa_mpvpe_mm=_optional(float, data["pa_mpvpe_mm"]),
            closed_loop=ClosedLoopResult.from_json(data["closed_loop"]) if data["closed_loop"] is not None else None,
        )


@dataclass
class GraphVsTruth:
    """The graph's target and ground plane of the start view next to the truth (start camera's optical frame).

    Values are rounded as logged (positions 4 decimals, normals 5). The graph's fields are None
    when the graph published no such output for the frame.
    """

    truth_body_centre_m: List[float]
    truth_body_median_m: List[float]
    truth_ground_normal: List[float]
    truth_ground_offset_m: float
    target_valid: Optional[bool] = None
    target_centroid_m: Optional[List[float]] = None
    target_depth_offset_m: Optional[float] = None
    target_visible_fraction: Optional[float] = None
    ground_valid: Optional[bool] = None
    ground_normal: Optional[List[float]] = None
    ground_offset_m: Optional[float] = None
    ground_inlier_ratio: Optional[float] = None
    ground_tilt_error_deg: Optional[float] = None
    ring_center_m: Optional[List[float]] = None

    def to_json(self) -> Dict[str, Any]:
        """The fields that hold a value, in declaration order (absent outputs are left out)."""
        return {key: value for key, value in asdict(self).items() if value is not None}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> GraphVsTruth:
        return cls(**{key: data[key] for key in cls.__dataclass_fields__ if key in data})


def candidates_to_json(views: ViewCandidatesArrays) -> Dict[str, Any]:
    """ViewCandidatesArrays as plain JSON types (full precision)."""
    return {
        "rotations": views.rotations.tolist(),
        "positions": views.positions.tolist(),
        "term_names": list(views.term_names),
        "term_weights": views.term_weights.tolist(),
        "term_scores": views.term_scores.tolist(),
        "score": views.score.tolist(),
        "feasible": views.feasible.tolist(),
        "infeasible_reason": views.infeasible_reason.tolist(),
        "chosen_index": int(views.chosen_index),
        "includes_current_view": bool(views.includes_current_view),
        "ring_center": views.ring_center.tolist(),
        "ring_radius": float(views.ring_radius),
    }


def candidates_from_json(data: Mapping[str, Any]) -> ViewCandidatesArrays:
    """The inverse of :func:`candidates_to_json`."""
    count = len(data["score"])
    names = [str(name) for name in data["term_names"]]
    return ViewCandidatesArrays(
        rotations=np.asarray(data["rotations"], dtype=np.float64).reshape(count, 3, 3),
        positions=np.asarray(data["positions"], dtype=np.float64).reshape(count, 3),
        term_names=names,
        term_weights=np.asarray(data["term_weights"], dtype=np.float64).reshape(len(names)),
        term_scores=np.asarray(data["term_scores"], dtype=np.float64).reshape(count, len(names)),
        score=np.asarray(data["score"], dtype=np.float64).reshape(count),
        feasible=np.asarray(data["feasible"], dtype=bool).reshape(count),
        infeasible_reason=np.asarray(data["infeasible_reason"], dtype=np.uint8).reshape(count),
        chosen_index=int(data["chosen_index"]),
        includes_current_view=bool(data["includes_current_view"]),
        ring_center=np.asarray(data["ring_center"], dtype=np.float64).reshape(3),
        ring_radius=float(data["ring_radius"]),
    )


@dataclass(eq=False)
class SceneResult:
    """One benchmark scene: the start view through the graph, then every method's move.

    Attributes:
        seed: Scene seed.
        scene_index: Position in the run (decides the stamps).
        stamp_ns: Stamp of the start view.
        start_occlusion: The scene's occluder share in the start view.
        start_pose: The start camera.
        graph_failure: Why the graph planned nothing for the start view (then every method stays), or None.
        graph_area_before_px: The graph's reconstructed area of the start view, if it got that far.
        before: The start view's metrics.
        pa_mpvpe_before_mm: PA-MPVPE of the graph's metric mesh of the start view (real models), or None.
        graph_vs_truth: The graph's target and ground plane next to the truth.
        candidates: The graph's scored candidates of the start view (None after a graph failure).
        candidate_views: Metrics of the view from every candidate, in candidate order, when the
            run scored them all (the oracle), else None.
        per_method: Method name -> its move, in the run's method order.
        latency_ms: Stage -> latency samples of this scene's frames through the graph (start view,
            then the after-view of the closed loop), in the run's stage order.
        energy_j: Joules of the board's input rail (VDD_IN) per frame of this scene, from its
            publication to its view candidates; empty where the machine has no power rails.
    """

    seed: int
    scene_index: int
    stamp_ns: int
    start_occlusion: float
    start_pose: PoseRecord
    graph_failure: Optional[str]
    graph_area_before_px: Optional[int]
    before: ViewMetrics
    pa_mpvpe_before_mm: Optional[float]
    graph_vs_truth: GraphVsTruth
    candidates: Optional[ViewCandidatesArrays]
    candidate_views: Optional[List[ViewMetrics]]
    per_method: Dict[str, MethodResult]
    latency_ms: Dict[str, List[float]] = field(default_factory=dict)
    energy_j: List[float] = field(default_factory=list)

    def __eq__(self, other: object) -> bool:
        # The candidates hold arrays: compare the lossless JSON forms.
        return isinstance(other, SceneResult) and self.to_json() == other.to_json()

    def to_json(self) -> Dict[str, Any]:
        return {
            "seed": self.seed,
            "scene_index": self.scene_index,
            "stamp_ns": self.stamp_ns,
            "start_occlusion": self.start_occlusion,
            "start_pose": self.start_pose.to_json(),
            "graph_failure": self.graph_failure,
            "graph_area_before_px": self.graph_area_before_px,
            "before": self.before.to_json(),
            "pa_mpvpe_before_mm": self.pa_mpvpe_before_mm,
            "graph_vs_truth": self.graph_vs_truth.to_json(),
            "candidates": candidates_to_json(self.candidates) if self.candidates is not None else None,
            "candidate_views": ([view.to_json() for view in self.candidate_views]
                                if self.candidate_views is not None else None),
            "per_method": {method: result.to_json() for method, result in self.per_method.items()},
            "latency_ms": {stage: list(samples) for stage, samples in self.latency_ms.items()},
            **({"energy_j": list(self.energy_j)} if self.energy_j else {}),
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> SceneResult:
        return cls(
            seed=int(data["seed"]),
            scene_index=int(data["scene_index"]),
            stamp_ns=int(data["stamp_ns"]),
            start_occlusion=float(data["start_occlusion"]),
            start_pose=PoseRecord.from_json(data["start_pose"]),
            graph_failure=_optional(str, data["graph_failure"]),
            graph_area_before_px=_optional(int, data["graph_area_before_px"]),
            before=ViewMetrics.from_json(data["before"]),
            pa_mpvpe_before_mm=_optional(float, data["pa_mpvpe_before_mm"]),
            graph_vs_truth=GraphVsTruth.from_json(data["graph_vs_truth"]),
            candidates=candidates_from_json(data["candidates"]) if data["candidates"] is not None else None,
            candidate_views=([ViewMetrics.from_json(view) for view in data["candidate_views"]]
                             if data["candidate_views"] is not None else None),
            per_method={str(method): MethodResult.from_json(result) for method, result in data["per_method"].items()},
            latency_ms={str(stage): [float(v) for v in samples] for stage, samples in data["latency_ms"].items()},
            energy_j=[float(v) for v in data.get("energy_j", [])],
        )


@dataclass(eq=False)
class EvaluationRun:
    """A whole evaluation run.

    Attributes:
        methods: Method names, in table order.
        default_method: The method of the per-scene coverage plot (LEAP-NBV itself).
        stages: Latency stages, in table order.
        scenes: One result per scene, in the order of the seeds asked for.
        perception: "ground_truth" or the real models' backend.
        room: "furnished" or "open".
        obstacle_map: The planner had the room's obstacle map.
        workers: How many worker processes (each with its own graph) ran the scenes.
        ready_s: Seconds until the graph was up (the slowest worker's), None if unknown.
        scenes_wall_s: Seconds the scenes took (the slowest worker's).
        total_wall_s: Seconds the whole run took, set when it ends.
    """

    methods: List[str]
    default_method: str
    stages: List[str]
    scenes: List[SceneResult]
    perception: str = "ground_truth"
    room: str = "furnished"
    obstacle_map: bool = True
    workers: int = 1
    ready_s: Optional[float] = None
    scenes_wall_s: float = 0.0
    total_wall_s: float = 0.0

    def __eq__(self, other: object) -> bool:
        return isinstance(other, EvaluationRun) and self.to_json() == other.to_json()

    @property
    def seeds(self) -> List[int]:
        return [scene.seed for scene in self.scenes]

    def latency_ms(self) -> Dict[str, List[float]]:
        """Stage -> every scene's samples, in scene order (every stage of ``stages``, possibly empty)."""
        merged: Dict[str, List[float]] = {stage: [] for stage in self.stages}
        for scene in self.scenes:
            for stage, samples in scene.latency_ms.items():
                merged.setdefault(stage, []).extend(samples)
        return merged

    def energy_j(self) -> List[float]:
        """Joules per frame (VDD_IN) of every scene, in scene order; empty without power rails."""
        return [joules for scene in self.scenes for joules in scene.energy_j]

    def to_json(self) -> Dict[str, Any]:
        return {
            "format": RUN_FORMAT,
            "methods": list(self.methods),
            "default_method": self.default_method,
            "stages": list(self.stages),
            "perception": self.perception,
            "room": self.room,
            "obstacle_map": self.obstacle_map,
            "workers": self.workers,
            "ready_s": self.ready_s,
            "scenes_wall_s": self.scenes_wall_s,
            "total_wall_s": self.total_wall_s,
            "scenes": [scene.to_json() for scene in self.scenes],
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> EvaluationRun:
        if data.get("format") != RUN_FORMAT:
            raise ResultsError(f"run format {data.get('format')!r}, this reader knows {RUN_FORMAT}")
        try:
            return cls(
                methods=[str(m) for m in data["methods"]],
                default_method=str(data["default_method"]),
                stages=[str(s) for s in data["stages"]],
                scenes=[SceneResult.from_json(scene) for scene in data["scenes"]],
                perception=str(data["perception"]),
                room=str(data["room"]),
                obstacle_map=bool(data["obstacle_map"]),
                workers=int(data["workers"]),
                ready_s=_optional(float, data["ready_s"]),
                scenes_wall_s=float(data["scenes_wall_s"]),
                total_wall_s=float(data["total_wall_s"]),
            )
        except (KeyError, TypeError, ValueError) as error:
            raise ResultsError(f"malformed run JSON: {error!r}") from error

    def write(self, path: str) -> str:
        """Write the JSON form atomically; returns ``path``."""
        text = json.dumps(self.to_json(), allow_nan=False)

        def write(temporary: str) -> None:
            with open(temporary, "w", encoding="utf-8") as stream:
                stream.write(text + "\n")

        return write_file_atomically(path, write)

    @classmethod
    def read(cls, path: str) -> EvaluationRun:
        with open(path, encoding="utf-8") as stream:
            return cls.from_json(json.load(stream))

    @classmethod
    def merge(cls, parts: Sequence[EvaluationRun]) -> EvaluationRun:
        """One run of the parts' scenes, in the parts' order (workers' runs, given in seed order).

        Raises:
            ResultsError: No parts, or parts that ran different methods, stages or setups.
        """
        if not parts:
            raise ResultsError("nothing to merge")
        first = parts[0]
        for part in parts[1:]:
            for name in ("methods", "default_method", "stages", "perception", "room", "obstacle_map"):
                if getattr(part, name) != getattr(first, name):
                    raise ResultsError(f"runs differ in {name}: {getattr(first, name)!r} vs {getattr(part, name)!r}")
        ready = [part.ready_s for part in parts if part.ready_s is not None]
        return cls(
            methods=list(first.methods), default_method=first.default_method, stages=list(first.stages),
            scenes=[scene for part in parts for scene in part.scenes], perception=first.perception,
            room=first.room, obstacle_map=first.obstacle_map, workers=len(parts),
            ready_s=max(ready) if ready else None, scenes_wall_s=max(part.scenes_wall_s for part in parts),
        )


def _optional(kind: Any, value: Any) -> Any:
    return None if value is None else kind(value)
