"""What a continuous evaluation produces: one record per episode, the run, its table, and the counts they use.

A continuous episode (:mod:`leapnbv_evaluation.continuous`) drives the robot while the graph plans from
every frame; its :class:`ContinuousEpisode` says how it ended (arrived at a goal committed long enough,
time limit, no plan), the coverage at the start, at arrival (or the episode's last frame) and the best
on the way, the time and distance to arrival against the first plan's path length, and what the goal
and the target did on the way (goal switches, direction reversals, target swaps, frames on another
person, frames without the target in view, frames planned).
The JSON form is lossless (``from_json(to_json(x)) == x``). :func:`compare_runs` says whether two runs hold the
same episodes (their settings, and each seed's episode field by field, leaving out what depends on the
machine's speed): two runs of the same seeds on sim time should.
"""
from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Dict, FrozenSet, List, Mapping, Optional, Sequence

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
#: Fields that depend on how fast the machine is, left out of :func:`compare_runs`: the episode's wall seconds
#: (``wall_s``) and frames a stage's wait-check timer found after sim time ticked on (``frames_ticked``: whether
#: a stage was done before the tick depends on the CPU), and the run's ``total_wall_s``.
WALL_CLOCK_FIELDS: FrozenSet[str] = frozenset({"wall_s", "frames_ticked", "total_wall_s"})
#: Absolute and relative tolerance of floats in :func:`compare_runs`: the coverages are computed in float64
#: from the same frames, so a difference past this is a different episode, not rounding.
FLOAT_TOLERANCE = 1e-6
FLOAT_REL_TOLERANCE = 1e-9
#: :func:`compare_runs` lists at most this many differences of one seed's episode, then how many more.
MAX_LINES_PER_EPISODE = 5


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
        goal_changes: [frame, goal_status.commitment, goal_status.reason] of each goal the graph committed or
            changed to (the first goal and every switch): why the goal moved, in the planner's words.
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
    goal_changes: List[List[Any]] = field(default_factory=list)

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


def _show(value: Any, width: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= width else text[:width - 3] + "..."


def _differences(path: str, a: Any, b: Any, abs_tol: float, rel_tol: float, out: List[str]) -> None:
    """Append ``"path: a != b"`` for each difference between ``a`` and ``b``, walking dicts and lists."""
    # bool first: it is an Integral, but True is no 1 here. Tuples are lists (in memory; JSON has only lists).
    a_bool, b_bool = isinstance(a, (bool, np.bool_)), isinstance(b, (bool, np.bool_))
    if a_bool or b_bool:
        same = a_bool and b_bool and bool(a) == bool(b)
    elif isinstance(a, numbers.Integral) and isinstance(b, numbers.Integral):
        same = int(a) == int(b)
    elif isinstance(a, numbers.Real) and isinstance(b, numbers.Real):
        x, y = float(a), float(b)
        same = math.isclose(x, y, rel_tol=rel_tol, abs_tol=abs_tol) or (math.isnan(x) and math.isnan(y))
    elif isinstance(a, Mapping) and isinstance(b, Mapping):
        for key in sorted(set(a) | set(b), key=str):
            where = f"{path}[{key!r}]"
            if key not in b:
                out.append(f"{where}: only in A")
            elif key not in a:
                out.append(f"{where}: only in B")
            else:
                _differences(where, a[key], b[key], abs_tol, rel_tol, out)
        return
    elif isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            out.append(f"{path}: {len(a)} items != {len(b)} items")
        # The common items too: the first one that differs says where the episodes parted.
        for k, (x, y) in enumerate(zip(a, b)):
            _differences(f"{path}[{k}]", x, y, abs_tol, rel_tol, out)
        return
    else:
        same = type(a) is type(b) and a == b
    if not same:
        out.append(f"{path}: {_show(a)} != {_show(b)}")


def episode_differences(a: ContinuousEpisode, b: ContinuousEpisode, abs_tol: float = FLOAT_TOLERANCE,
                        rel_tol: float = FLOAT_REL_TOLERANCE) -> List[str]:
    """Every difference between two episodes, one ``"field path: a != b"`` each (:data:`WALL_CLOCK_FIELDS` left out).

    Args:
        a: The episode of run A.
        b: The episode of run B (the same seed).
        abs_tol: Absolute tolerance of floats (``math.isclose``).
        rel_tol: Relative tolerance of floats.

    Returns:
        The differences, in field order (empty: the same episode).
    """
    out: List[str] = []
    for f in fields(ContinuousEpisode):
        if f.name not in WALL_CLOCK_FIELDS:
            _differences(f.name, getattr(a, f.name), getattr(b, f.name), abs_tol, rel_tol, out)
    return out


@dataclass
class RunDifferences:
    """What differs between two runs (:func:`run_differences`).

    Attributes:
        settings: One line per run setting that differs (``"clock: 'lockstep' != 'wall'"``).
        episodes: Per seed whose episodes differ, every difference (a seed in one run only: one line).
        seeds: Seeds in either run.
    """

    settings: List[str]
    episodes: Dict[int, List[str]]
    seeds: int

    @property
    def count(self) -> int:
        """Differences in all (0: the same runs)."""
        return len(self.settings) + sum(len(lines) for lines in self.episodes.values())

    def lines(self, max_per_episode: int = MAX_LINES_PER_EPISODE) -> List[str]:
        """The settings' lines, then at most ``max_per_episode`` per seed (``"seed 10: ..."``), in seed order."""
        out = list(self.settings)
        for seed in sorted(self.episodes):
            found = self.episodes[seed]
            out.extend(f"seed {seed}: {line}" for line in found[:max_per_episode])
            if len(found) > max_per_episode:
                more = len(found) - max_per_episode
                out.append(f"seed {seed}: ... and {more} more difference{'' if more == 1 else 's'}")
        return out


def run_differences(a: ContinuousRun, b: ContinuousRun, abs_tol: float = FLOAT_TOLERANCE,
                    rel_tol: float = FLOAT_REL_TOLERANCE) -> RunDifferences:
    """What differs between runs A and B: their settings, and their episodes matched by seed (not by position).

    Args:
        a: Run A.
        b: Run B.
        abs_tol: Absolute tolerance of floats (``math.isclose``).
        rel_tol: Relative tolerance of floats.

    Returns:
        The differences, :data:`WALL_CLOCK_FIELDS` left out.
    """
    settings: List[str] = []
    for f in fields(ContinuousRun):
        if f.name != "episodes" and f.name not in WALL_CLOCK_FIELDS:
            _differences(f.name, getattr(a, f.name), getattr(b, f.name), abs_tol, rel_tol, settings)
    by_seed_a: Dict[int, List[ContinuousEpisode]] = {}
    by_seed_b: Dict[int, List[ContinuousEpisode]] = {}
    for episode in a.episodes:
        by_seed_a.setdefault(episode.seed, []).append(episode)
    for episode in b.episodes:
        by_seed_b.setdefault(episode.seed, []).append(episode)
    episodes: Dict[int, List[str]] = {}
    for seed in sorted(set(by_seed_a) | set(by_seed_b)):
        in_a, in_b = by_seed_a.get(seed, []), by_seed_b.get(seed, [])
        if not in_b:
            episodes[seed] = ["only in A"]
            continue
        if not in_a:
            episodes[seed] = ["only in B"]
            continue
        found: List[str] = []
        if len(in_a) != len(in_b):  # a seed run twice: its repeats are compared in order
            found.append(f"{len(in_a)} episodes != {len(in_b)} episodes")
        for x, y in zip(in_a, in_b):
            found.extend(episode_differences(x, y, abs_tol, rel_tol))
        if found:
            episodes[seed] = found
    return RunDifferences(settings=settings, episodes=episodes, seeds=len(set(by_seed_a) | set(by_seed_b)))


def compare_runs(a: ContinuousRun, b: ContinuousRun, abs_tol: float = FLOAT_TOLERANCE,
                 rel_tol: float = FLOAT_REL_TOLERANCE, max_per_episode: int = MAX_LINES_PER_EPISODE) -> List[str]:
    """Whether runs A and B hold the same episodes: one readable line per difference (empty: the same).

    The run settings (room, obstacle map, clock, camera rate, limits, obstacle memory) are compared, then the
    episodes matched by seed: a seed in one run only is a line, and each field of a seed's two episodes that
    differs is one (``"seed 10: target_track[3][5]: 1.2 != 1.3"``, A's value first), walking dicts and lists;
    floats are equal within ``math.isclose(abs_tol, rel_tol)``, ints, strings, bools and None exactly.
    :data:`WALL_CLOCK_FIELDS` depend on the machine's speed and are left out.

    Args:
        a: Run A.
        b: Run B.
        abs_tol: Absolute tolerance of floats.
        rel_tol: Relative tolerance of floats.
        max_per_episode: Lines per seed at most, then ``"seed 10: ... and N more differences"``.

    Returns:
        The lines: the settings', then each seed's in seed order.
    """
    return run_differences(a, b, abs_tol, rel_tol).lines(max_per_episode)


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
