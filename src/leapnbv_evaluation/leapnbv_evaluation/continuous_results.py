"""What a continuous evaluation produces: one record per episode, the run, its table, and the counts they use.

A continuous episode (:mod:`leapnbv_evaluation.continuous`) drives the robot while the graph plans from
every frame; its :class:`ContinuousEpisode` says how it ended (arrived at a goal committed long enough,
time limit, no plan), the coverage at the start, at arrival (or the episode's last frame) and the best
on the way, the time and distance to arrival against the first plan's path length, and what the goal
and the target did on the way (goal switches, direction reversals, target swaps, frames on another
person, frames without the target in view, frames planned).
The JSON form is lossless (``from_json(to_json(x)) == x``).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Dict, List, Mapping, Optional, Sequence

import numpy as np

from leapnbv_common.array_types import FloatArray
from leapnbv_evaluation.metrics import is_success
from leapnbv_evaluation.report_files import write_json_atomically
from leapnbv_sim.render import PERSON_ID

#: How an episode ended.
OUTCOME_ARRIVED = "arrived"
OUTCOME_TIME_LIMIT = "time_limit"
OUTCOME_NO_PLAN = "no_plan"
#: Travel is cut into pieces of this length to find where it turned back (:func:`count_reversals`) ...
REVERSAL_SEGMENT_M = 0.10
#: ... and a turn of more than this between two consecutive pieces is a reversal.
REVERSAL_ANGLE_RAD = math.radians(135.0)
#: Version of the JSON layout of :class:`ContinuousRun`.
CONTINUOUS_FORMAT = 1


def count_reversals(xy: FloatArray, segment_m: float = REVERSAL_SEGMENT_M,
                    angle_rad: float = REVERSAL_ANGLE_RAD) -> int:
    """How often the base's travel turned back: consecutive ``segment_m`` pieces of it more than ``angle_rad`` apart.

    The positions (one per frame) are walked in order; a piece ends where the travel since the last
    piece's end reaches ``segment_m`` (standing and turning in place make no piece). Following a
    path around an obstacle turns gradually; dropping a goal for one behind the robot turns back.

    Args:
        xy: (N, 2) base positions in time order.
        segment_m: Piece length (m), > 0.
        angle_rad: Least turn between two pieces that counts.

    Returns:
        The number of reversals.
    """
    points = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if len(points) < 3:
        return 0
    anchor = points[0]
    previous: Optional[FloatArray] = None
    reversals = 0
    for point in points[1:]:
        step = point - anchor
        length = float(np.hypot(step[0], step[1]))
        if length < segment_m:
            continue
        direction = step / length
        if previous is not None:
            cosine = float(np.clip(direction @ previous, -1.0, 1.0))
            if math.acos(cosine) > angle_rad:
                reversals += 1
        previous, anchor = direction, point
    return reversals


def count_swaps(values: Sequence[Optional[int]], target: int = PERSON_ID) -> int:
    """Target swaps: how often the graph took a person other than ``target``, frame by frame.

    A swap is a frame whose person is not the target while the frame before it that had a person
    (Nones, frames without one, are skipped) had another one, or none before it: taking a wrong person
    at the first frame is a swap, staying on it is the same swap, moving on to a third person another.
    So a run that only ever followed the target counts 0, whatever frames it lost it in.
    """
    swaps = 0
    previous: Optional[int] = None
    for value in values:
        if value is None:
            continue
        if value != target and value != previous:
            swaps += 1
        previous = value
    return swaps


@dataclass
class ContinuousEpisode:
    """One continuous episode.

    Attributes:
        seed: Scene seed.
        scene_index: Its place in the run (its stamps).
        start_stamp_ns: Sim time of its first frame.
        outcome: OUTCOME_ARRIVED, OUTCOME_TIME_LIMIT or OUTCOME_NO_PLAN.
        coverage_start: Surface coverage of the start view.
        coverage_end: Of the view at arrival (or at the episode's last frame when it did not arrive).
        coverage_best: The best of every frame's view on the way (start and end included).
        success: ``metrics.is_success(coverage_start, coverage_end)``.
        time_s: Sim time from the first frame to arrival (or to the last frame).
        distance_m: Metres the base travelled in that time.
        first_path_m: Length of the first plan's base path (None: no plan gave a path).
        first_goal_s: Sim time from the first frame to the first goal (None: no goal).
        goal_switches: Goals after the first one that were another place (goal_status.goal_changed).
        withdrawals: Goals withdrawn while the robot followed them (STALE, NONE, empty path).
        reversals: :func:`count_reversals` of the base's track.
        target_swaps: :func:`count_swaps` of the person the graph followed, frame by frame (the person under
            most of its person mask): how often it took a person other than the target (id 1).
        frames: Frames rendered and published.
        frames_planned: Frames whose plan chose a view (view_candidates.chosen_index >= 0).
        frames_failed: Frames the graph answered with no plan (no person, timeout ...).
        commit_reasons: goal_status.commitment of every CURRENT status, counted by name.
        frames_ticked: Frames the graph answered only after sim time ticked on within their period (a companion
            found by a stage's wait-check timer).
        wall_s: Wall seconds the episode took.
        frames_other_person: Frames in which the graph followed a person other than the target.
        frames_target_unseen: Frames in which no pixel of the target was in view (it was out of the
            image or wholly hidden).
        other_person_frames: For each frame that followed another person, what explains it
            (:func:`leapnbv_evaluation.continuous.other_person_record`: frame, person, the person each
            detection was, the target track's state, detection index and reason).
        target_track: Per frame, [frame, person the graph followed (None: none), track state, track_id,
            detection index, x, y of the track's place in its fixed frame] (None entries: no track message):
            how a track drifted before a wrong-person frame.
    """

    seed: int
    scene_index: int
    start_stamp_ns: int
    outcome: str
    coverage_start: float
    coverage_end: float
    coverage_best: float
    success: bool
    time_s: float
    distance_m: float
    first_path_m: Optional[float]
    first_goal_s: Optional[float]
    goal_switches: int
    withdrawals: int
    reversals: int
    target_swaps: int
    frames: int
    frames_planned: int
    frames_failed: int
    commit_reasons: Dict[str, int] = field(default_factory=dict)
    frames_ticked: int = 0
    wall_s: float = 0.0
    frames_other_person: int = 0
    frames_target_unseen: int = 0
    other_person_frames: List[Dict[str, Any]] = field(default_factory=list)
    target_track: List[List[Any]] = field(default_factory=list)

    @property
    def arrived(self) -> bool:
        return self.outcome == OUTCOME_ARRIVED

    @property
    def path_ratio(self) -> Optional[float]:
        """Distance driven to arrival over the first plan's path length (None: no first path, or not arrived)."""
        if not self.arrived or self.first_path_m is None or self.first_path_m <= 1e-6:
            return None
        return self.distance_m / self.first_path_m

    def to_json(self) -> Dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> ContinuousEpisode:
        names = {f.name for f in fields(cls)}
        values = {key: value for key, value in data.items() if key in names}
        values["commit_reasons"] = {str(k): int(v) for k, v in dict(values.get("commit_reasons", {})).items()}
        return cls(**values)

    @staticmethod
    def decide_success(coverage_start: float, coverage_end: float) -> bool:
        """The task's success rule (one move's), applied to the view the episode ended in."""
        return is_success(coverage_start, coverage_end)


@dataclass
class ContinuousRun:
    """A continuous evaluation: its settings and one episode per scene, in seed order."""

    room: str
    obstacle_map: bool
    clock: str
    camera_rate_hz: float
    time_limit_s: float
    commit_hold_s: float
    episodes: List[ContinuousEpisode]
    total_wall_s: float = 0.0
    obstacle_memory: bool = False

    def to_json(self) -> Dict[str, Any]:
        data = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "episodes"}
        data["format"] = CONTINUOUS_FORMAT
        data["episodes"] = [episode.to_json() for episode in self.episodes]
        return data

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> ContinuousRun:
        if int(data.get("format", -1)) != CONTINUOUS_FORMAT:
            raise ValueError(f"continuous run format {data.get('format')!r}, expected {CONTINUOUS_FORMAT}")
        return cls(room=str(data["room"]), obstacle_map=bool(data["obstacle_map"]), clock=str(data["clock"]),
                   camera_rate_hz=float(data["camera_rate_hz"]), time_limit_s=float(data["time_limit_s"]),
                   commit_hold_s=float(data["commit_hold_s"]),
                   episodes=[ContinuousEpisode.from_json(e) for e in data["episodes"]],
                   total_wall_s=float(data.get("total_wall_s", 0.0)),
                   obstacle_memory=bool(data.get("obstacle_memory", False)))

    def write(self, path: str) -> str:
        """Write the run's JSON (atomically); the path."""
        return write_json_atomically(path, self.to_json())


def _percentile(values: Sequence[float], q: float) -> float:
    return float(np.percentile(np.asarray(values, dtype=np.float64), q)) if len(values) else math.nan


def aggregate_continuous(run: ContinuousRun) -> Dict[str, float]:
    """The run's headline figures (rates in %, medians and p95 over the episodes; NaN where none apply)."""
    eps = run.episodes
    n = len(eps)
    arrived = [e for e in eps if e.arrived]
    ratios = [r for r in (e.path_ratio for e in eps) if r is not None]

    def share(flags: Sequence[bool]) -> float:
        return 100.0 * sum(flags) / n if n else math.nan

    switches = [float(e.goal_switches) for e in eps]
    return {
        "episodes": float(n),
        "success_pct": share([e.success for e in eps]),
        "arrived_pct": share([e.arrived for e in eps]),
        "coverage_start": float(np.mean([e.coverage_start for e in eps])) if n else math.nan,
        "coverage_end": float(np.mean([e.coverage_end for e in eps])) if n else math.nan,
        "coverage_best": float(np.mean([e.coverage_best for e in eps])) if n else math.nan,
        "time_to_arrival_median_s": _percentile([e.time_s for e in arrived], 50),
        "time_to_arrival_p95_s": _percentile([e.time_s for e in arrived], 95),
        "path_ratio_median": _percentile(ratios, 50),
        "path_ratio_p95": _percentile(ratios, 95),
        "goal_switches_median": _percentile(switches, 50),
        "goal_switches_p95": _percentile(switches, 95),
        "goal_switches_max": max(switches) if switches else math.nan,
        "reversals_total": float(sum(e.reversals for e in eps)),
        "episodes_with_reversal_pct": share([e.reversals > 0 for e in eps]),
        "target_swaps_total": float(sum(e.target_swaps for e in eps)),
        "episodes_with_swap_pct": share([e.target_swaps > 0 for e in eps]),
        "frames_other_person_total": float(sum(e.frames_other_person for e in eps)),
        "frames_target_unseen_total": float(sum(e.frames_target_unseen for e in eps)),
        "frames_total": float(sum(e.frames for e in eps)),
        "withdrawals_total": float(sum(e.withdrawals for e in eps)),
        "frames_planned_median": _percentile([float(e.frames_planned) for e in eps], 50),
        "frames_median": _percentile([float(e.frames) for e in eps], 50),
    }


def _fmt(value: float, digits: int = 2) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def continuous_table_markdown(run: ContinuousRun) -> str:
    """The continuous results table (one row per run), beside the one-shot table's success and coverage."""
    a = aggregate_continuous(run)
    mapping = "with map" if run.obstacle_map else ("map from the obstacle memory" if run.obstacle_memory else "no map")
    lines = [
        f"Continuous closed loop: {run.room}, {mapping}, {run.clock} clock, camera {run.camera_rate_hz:g} Hz, "
        f"arrival at a goal committed >= {run.commit_hold_s:g} s, limit {run.time_limit_s:g} s",
        "",
        "| episodes | success | arrived | coverage start -> end (best) | time to arrival s (median / p95) | "
        "distance / first path (median / p95) | goal switches (median / p95 / max) | reversals (total, % eps) | "
        "target swaps (% eps) | frames on another person | frames without the target in view | "
        "frames planned (median of frames) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
        f"| {int(a['episodes'])} | {_fmt(a['success_pct'], 1)} % | {_fmt(a['arrived_pct'], 1)} % | "
        f"{_fmt(a['coverage_start'], 3)} -> {_fmt(a['coverage_end'], 3)} ({_fmt(a['coverage_best'], 3)}) | "
        f"{_fmt(a['time_to_arrival_median_s'], 1)} / {_fmt(a['time_to_arrival_p95_s'], 1)} | "
        f"{_fmt(a['path_ratio_median'])} / {_fmt(a['path_ratio_p95'])} | "
        f"{_fmt(a['goal_switches_median'], 0)} / {_fmt(a['goal_switches_p95'], 1)} / "
        f"{_fmt(a['goal_switches_max'], 0)} | {int(a['reversals_total'])}, "
        f"{_fmt(a['episodes_with_reversal_pct'], 1)} % | {int(a['target_swaps_total'])} "
        f"({_fmt(a['episodes_with_swap_pct'], 1)} %) | {int(a['frames_other_person_total'])} of "
        f"{int(a['frames_total'])} | {int(a['frames_target_unseen_total'])} of {int(a['frames_total'])} | "
        f"{_fmt(a['frames_planned_median'], 0)} of {_fmt(a['frames_median'], 0)} |",
        "",
    ]
    return "\n".join(lines)


def per_episode_markdown(run: ContinuousRun) -> str:
    """One row per episode."""
    lines = ["| seed | outcome | coverage start / end / best | time s | distance m | first path m | switches | "
             "reversals | swaps | frames on another person | frames target unseen | planned / frames | wall s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for e in run.episodes:
        lines.append(f"| {e.seed} | {e.outcome} | {e.coverage_start:.3f} / {e.coverage_end:.3f} / "
                     f"{e.coverage_best:.3f} | {e.time_s:.1f} | {e.distance_m:.2f} | "
                     f"{_fmt(e.first_path_m) if e.first_path_m is not None else '-'} | {e.goal_switches} | "
                     f"{e.reversals} | {e.target_swaps} | {e.frames_other_person} | {e.frames_target_unseen} | "
                     f"{e.frames_planned} / {e.frames} | {e.wall_s:.0f} |")
    return "\n".join(lines) + "\n"
