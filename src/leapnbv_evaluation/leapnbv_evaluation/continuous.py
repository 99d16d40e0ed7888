"""The continuous episode: the robot drives while the graph plans from every frame it renders on the way.

The one-shot episode (:mod:`leapnbv_evaluation.closed_loop`) stops the world: one frame, one move, one
look. Here the simulator runs its motion stack (``SimulatorParams.motion_stack``,
:class:`leapnbv_sim.simulator.DrivenRobot`): it follows the latest CURRENT goal's base path at the
base's limits and renders a frame every camera period from where the robot is, and the graph plans
from each frame; the goal commitment in nbv_node decides whether the goal stays.

Clock (``EvaluationOptions.clock``):

* ``lockstep`` (the default, for numbers): the simulator owns sim time (``/clock``; every graph node runs
  with ``use_sim_time``). Sim time advances by one camera period only when the graph has answered the
  frame in flight (its view candidates, or a certain failure) and that frame's goal topics have arrived;
  the robot then drives on for one period with whatever goal it holds. So the goal of a frame takes
  effect one camera period after the frame (the planning latency is one period, whatever this machine's
  speed), every frame is planned, and two runs of the same seeds give the same episodes: nothing in
  the loop reads a wall clock (a frame the graph has not answered within ``frame_timeout_s`` of wall time
  is a failed frame and the clock moves on: the only wall-time guard, which a healthy graph never hits).
  A fixed wall budget per sim step would instead make the episode depend on the machine's load. While a
  frame is in flight the clock ticks on by the stages' wait-check period (their timers run on sim time: a
  companion that came after its frame is found when one fires), never up to the next frame's stamp; every
  wait limit of the graph is at least a camera period, so how far it ticked decides nothing. The one
  deadline that can fall inside a period, a goal's ``valid_until`` (a goal planned five frames ago at 5 Hz
  and 1 s), is the motion stack's: it brakes there on its own clock, and the planner's STALE status,
  which comes when its age check runs, only confirms it (``SimulatorNode``).
* ``real_time``: sim time follows the wall clock; frames go out at the camera rate whether or not the
  graph kept up, and the graph plans from whatever frames it admits (its frame dropping and latencies
  are the machine's). Not reproducible; for watching the loop as a robot runs it. A frame's plan and mask
  count when they came before the next frame went out (frames planned are counted at the episode's end).

An episode ends when the robot has arrived (base at the path's end, facing it, standing, the head
aligned) at a goal that stayed committed at least ``commit_hold_s`` (``goal_status.committed_since``),
at ``time_limit_s`` of sim time, or (``no_plan``) when no goal came within ``no_plan_limit_s``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Dict, List, Optional, Protocol, Tuple

import numpy as np

from leapnbv_common.array_types import FloatArray, IntArray
from leapnbv_common.conversions import ConversionError, detections_to_boxes, image_to_numpy
from leapnbv_common.topics import DETECTIONS, PERSON_MASK, TARGET_TRACK
from leapnbv_evaluation.continuous_results import (
    OUTCOME_ARRIVED,
    OUTCOME_NO_PLAN,
    OUTCOME_TIME_LIMIT,
    ContinuousEpisode,
    count_reversals,
    count_swaps,
)
from leapnbv_evaluation.episode import view_metrics
from leapnbv_evaluation.frame_outputs import FrameOutputs
from leapnbv_evaluation.options import EvaluationOptions
from leapnbv_perception.target_tracking import (
    LAYER_BIN_M,
    TrackerConfig,
    box_depth_layers,
    box_places_camera,
    person_fit_depth,
)
from leapnbv_sim.motion_stack import path_length
from leapnbv_sim.render import PERSON_ID, RenderedFrame
from leapnbv_sim.scene import Scene
from leapnbv_sim.simulator import DrivenRobot

#: Sim time between two scenes' episodes beyond the time limit (the ground node's mask_max_age_s is 1 s).
EPISODE_GAP_NS = 10_000_000_000
#: goal_status.state CURRENT (leapnbv_msgs/GoalStatus), as the session's records carry it.
STATE_CURRENT = 1


@dataclass(frozen=True)
class StatusRecord:
    """One goal_status the simulator received (the fields the episode reads)."""

    state: int
    goal_stamp_ns: int
    goal_changed: bool
    commitment: str
    committed_since_ns: int
    reason: str = ""  # goal_status.reason: one line on why the goal is what it is


class ContinuousSession(Protocol):
    """What a continuous episode needs of the running graph and the simulator with its motion stack."""

    def set_scene(self, scene: Scene) -> None:
        """Put the simulator in a scene, the robot standing at its start view."""

    def forget_last_scene(self) -> None:
        """Make the graph forget the last scene: nbv_node its committed goal, hmr_node its target and people."""

    def run_frame(self, stamp_ns: int) -> Tuple[RenderedFrame, FrameOutputs]:
        """Advance the robot and sim time to ``stamp_ns``, render and publish; the graph's outputs of it."""

    def settle_goal(self, stamp_ns: int, outputs: FrameOutputs) -> None:
        """Wait until the goal topics of the frame of ``stamp_ns`` have reached the simulator."""

    def run_frame_real_time(self, stamp_ns: int, until_wall_s: float) -> Tuple[RenderedFrame, FrameOutputs]:
        """Publish the view at ``stamp_ns`` and let the graph work until the wall time ``until_wall_s``."""

    def ticked_between(self, first_ns: int, last_ns: int) -> int:
        """How many frames stamped in [first_ns, last_ns] needed sim time to tick on before the graph answered."""

    def driven_robot(self) -> DrivenRobot:
        """The simulator's robot (continuous mode)."""

    def goal_statuses(self) -> List[StatusRecord]:
        """Every goal status the simulator received in this scene, in order."""

    def last_path(self) -> Optional[Tuple[int, FloatArray]]:
        """(stamp, (P, 3) world points) of the latest base path the robot took in this scene."""


def person_ids(scene: Scene) -> List[int]:
    """The object ids of the scene's people (objects named "person...")."""
    return sorted(i for i, name in scene.object_names.items() if name.startswith("person"))


def target_person(scene: Scene, rendered: RenderedFrame, outputs: FrameOutputs) -> Optional[int]:
    """The person the graph's target is: the person object under most of the graph's person mask.

    None: no mask, or no person under it. The target is ``PERSON_ID`` (1); any other is a swap.
    """
    mask_msg = outputs.messages.get(PERSON_MASK)
    if mask_msg is None:
        return None
    try:
        mask = image_to_numpy(mask_msg) > 0
    except ConversionError:
        return None
    ids = np.asarray(rendered.object_id)
    if mask.shape != ids.shape or not mask.any():
        return None
    people = person_ids(scene)
    counts = [int(np.count_nonzero(mask & (ids == person))) for person in people]
    if not counts or max(counts) == 0:
        return None
    return people[int(np.argmax(counts))]


def detected_people(scene: Scene, rendered: RenderedFrame, outputs: FrameOutputs) -> List[Optional[int]]:
    """The person each of the frame's detections is: the person object with most pixels in its box (None: none)."""
    msg = outputs.messages.get(DETECTIONS)
    if msg is None:
        return []
    try:
        boxes = detections_to_boxes(msg)
    except ConversionError:
        return []
    ids = np.asarray(rendered.object_id)
    height, width = ids.shape[:2]
    people = person_ids(scene)
    found: List[Optional[int]] = []
    for box in boxes:
        x0, y0 = int(np.clip(np.floor(box[0]), 0, width)), int(np.clip(np.floor(box[1]), 0, height))
        x1, y1 = int(np.clip(np.ceil(box[2]), 0, width)), int(np.clip(np.ceil(box[3]), 0, height))
        inside = ids[y0:y1, x0:x1]
        counts = [int(np.count_nonzero(inside == person)) for person in people]
        found.append(people[int(np.argmax(counts))] if counts and max(counts) > 0 else None)
    return found


def _whose(ids: IntArray, depth: FloatArray, people: List[int], near: float, far: float) -> Optional[int]:
    """The person object with most of the pixels whose depth is in [near, far] (None: no person's)."""
    with np.errstate(invalid="ignore"):
        at = (depth >= near) & (depth <= far)
    counts = [int(np.count_nonzero(at & (ids == person))) for person in people]
    return people[int(np.argmax(counts))] if counts and max(counts) > 0 else None


def box_place_people(scene: Scene, rendered: RenderedFrame, boxes: FloatArray) -> List[List[Dict[str, object]]]:
    """Per box, the tracker's candidate places of it (default TrackerConfig) and whose pixels each place is.

    Each place: its floor position in the world ("xy", m) and the person object with most of the box's pixels
    within LAYER_BIN_M of its depth ("person"; None: no person's). The evaluation's view of what the tracker
    measured: a place of one person's box that is another person's pixels is how a box gets taken for the wrong
    person. The last entry of each box's list is {"layers": [[z, columns, extent, behind_a_filler, person]]},
    every depth layer of it (:func:`leapnbv_perception.target_tracking.box_depth_layers`).
    """
    ids = np.asarray(rendered.object_id)
    depth = np.asarray(rendered.depth_m, dtype=np.float64)
    height, width = ids.shape[:2]
    people = person_ids(scene)
    rotation, position = rendered.camera_pose.rotation, rendered.camera_pose.position
    out: List[List[Dict[str, object]]] = []
    for box, places in zip(boxes, box_places_camera(boxes, (width, height), depth, rendered.K, TrackerConfig())):
        x0, y0 = int(np.clip(np.floor(box[0]), 0, width)), int(np.clip(np.floor(box[1]), 0, height))
        x1, y1 = int(np.clip(np.ceil(box[2]), 0, width)), int(np.clip(np.ceil(box[3]), 0, height))
        inside_ids, inside_depth = ids[y0:y1, x0:x1], depth[y0:y1, x0:x1]
        records: List[Dict[str, object]] = []
        for place in places:
            world = rotation @ place + position
            records.append({"xy": [round(float(world[0]), 2), round(float(world[1]), 2)],
                            "person": _whose(inside_ids, inside_depth, people, place[2] - LAYER_BIN_M,
                                             place[2] + LAYER_BIN_M)})
        box = np.asarray(box, dtype=np.float64)
        config = TrackerConfig()
        _, layers = box_depth_layers(box, (1.0, 1.0), depth, config, person_fit_depth(box, (1.0, 1.0), rendered.K,
                                                                                        config))
        records.append({"layers": [[round(layer.z, 2), round(layer.columns, 2), round(layer.extent, 2),
                                    layer.behind_a_filler,
                                    _whose(inside_ids, inside_depth, people, layer.near, layer.far)]
                                   for layer in layers]})
        out.append(records)
    return out


def other_person_record(frame: int, person: int, scene: Scene, rendered: RenderedFrame,
                        outputs: FrameOutputs) -> Dict[str, object]:
    """What explains a frame whose target was another person: the tracker's decision and who each detection was.

    "places" lists each box's candidate places and whose pixels they are (:func:`box_place_people`),
    "track_xy" the tracker's (predicted or filtered) target position in its fixed frame.
    """
    track = outputs.messages.get(TARGET_TRACK)
    record: Dict[str, object] = {"frame": int(frame), "person": int(person),
                                 "detections": detected_people(scene, rendered, outputs)}
    msg = outputs.messages.get(DETECTIONS)
    if msg is not None:
        try:
            boxes = detections_to_boxes(msg)
            record["boxes"] = [[round(float(v), 1) for v in box[:4]] for box in boxes]
            record["places"] = box_place_people(scene, rendered, np.asarray(boxes, dtype=np.float64))
        except ConversionError:
            pass
    record["target_box"] = rendered.ground_truth.person_box_xyxy
    if track is not None:
        record.update(track_id=int(track.track_id), state=int(track.state),
                      detection_index=int(track.detection_index), reason=str(track.reason),
                      track_xy=[round(float(track.position.x), 2), round(float(track.position.y), 2)])
    return record


def target_track_row(frame: int, person: Optional[int], outputs: FrameOutputs) -> List[object]:
    """[frame, person, state, track_id, detection index, x, y] of a frame's target track (Nones: no message)."""
    track = outputs.messages.get(TARGET_TRACK)
    if track is None:
        return [int(frame), person, None, None, None, None, None]
    return [int(frame), person, int(track.state), int(track.track_id), int(track.detection_index),
            round(float(track.position.x), 2), round(float(track.position.y), 2)]


class ContinuousEpisodes:
    """The continuous episodes of an evaluation, one per scene, through one session.

    Args:
        session: The running graph and the simulator with its motion stack.
        options: The run's options (camera rate, time limit, commitment hold).
    """

    def __init__(self, session: ContinuousSession, options: EvaluationOptions) -> None:
        self.session = session
        self.options = options

    def spacing_ns(self) -> int:
        """Sim time between the first frames of two consecutive scenes."""
        return int(round(self.options.time_limit_s * 1e9)) + EPISODE_GAP_NS

    def run(self, scene: Scene, seed: int, scene_index: int, start_stamp_ns: int) -> ContinuousEpisode:
        """One scene's continuous episode from its first frame at ``start_stamp_ns``."""
        o, session = self.options, self.session
        started = time.monotonic()
        session.set_scene(scene)
        session.forget_last_scene()
        period_ns = int(round(1e9 / o.camera_rate_hz))
        limit_ns = int(round(o.time_limit_s * 1e9))
        hold_ns = int(round(o.commit_hold_s * 1e9))
        no_plan_ns = int(round(o.no_plan_limit_s * 1e9))
        coverages: List[float] = []
        targets: List[Optional[int]] = []
        other_frames: List[Dict[str, object]] = []
        track_rows: List[List[object]] = []
        target_unseen = 0
        track: List[FloatArray] = []
        first_path_m: Optional[float] = None
        first_goal_ns: Optional[int] = None
        planned = failed = 0
        outcome = OUTCOME_TIME_LIMIT
        stamp = start_stamp_ns
        real_time = o.clock == "real_time"
        wall0 = time.monotonic()
        all_outputs: List[FrameOutputs] = []
        for k in range(limit_ns // period_ns + 1):
            stamp = start_stamp_ns + k * period_ns
            if real_time:
                rendered, outputs = session.run_frame_real_time(stamp, wall0 + (k + 1) * period_ns * 1e-9)
            else:
                rendered, outputs = session.run_frame(stamp)
                session.settle_goal(stamp, outputs)
            all_outputs.append(outputs)
            robot = session.driven_robot()
            coverages.append(view_metrics(scene, rendered).surface_coverage)
            targets.append(target_person(scene, rendered, outputs))
            if targets[-1] is not None and targets[-1] != PERSON_ID:
                other_frames.append(other_person_record(k, int(targets[-1]), scene, rendered, outputs))
            track_rows.append(target_track_row(k, targets[-1], outputs))
            target_unseen += rendered.ground_truth.person_box_xyxy is None
            track.append(np.array([robot.stack.state.x, robot.stack.state.y]))
            path = session.last_path()
            if first_path_m is None and path is not None:
                first_path_m = path_length(path[1][:, :2])
            statuses = session.goal_statuses()
            latest = statuses[-1] if statuses else None
            if first_goal_ns is None and latest is not None and latest.state == STATE_CURRENT:
                first_goal_ns = stamp - start_stamp_ns
            # The frame was rendered where the robot stood at ``stamp``; its plan has just kept or replaced the goal.
            held = (latest is not None and latest.state == STATE_CURRENT and latest.committed_since_ns > 0
                    and stamp - latest.committed_since_ns >= hold_ns)
            if held and robot.arrived():
                outcome = OUTCOME_ARRIVED
                break
            if first_goal_ns is None and stamp - start_stamp_ns >= no_plan_ns:
                outcome = OUTCOME_NO_PLAN
                break
        for outputs in all_outputs:  # (real time: what came by now, also after its frame's period)
            candidates = outputs.view_candidates
            if outputs.failure is None and candidates is not None and candidates.chosen_index >= 0:
                planned += 1
            elif outputs.failure is not None or (not real_time and candidates is None):
                failed += 1
        statuses = session.goal_statuses()
        current = [s for s in statuses if s.state == STATE_CURRENT]
        reasons: Dict[str, int] = {}
        for s in current:
            reasons[s.commitment] = reasons.get(s.commitment, 0) + 1
        robot = session.driven_robot()
        changed = sum(1 for s in current if s.goal_changed)
        goal_changes: List[List[object]] = [
            [int(round((s.goal_stamp_ns - start_stamp_ns) / period_ns)), s.commitment, s.reason]
            for s in current if s.goal_changed or s.commitment == "FIRST_GOAL"]
        return ContinuousEpisode(
            seed=int(seed), scene_index=int(scene_index), start_stamp_ns=int(start_stamp_ns), outcome=outcome,
            coverage_start=round(coverages[0], 6), coverage_end=round(coverages[-1], 6),
            coverage_best=round(max(coverages), 6),
            success=ContinuousEpisode.decide_success(coverages[0], coverages[-1]),
            time_s=round((stamp - start_stamp_ns) * 1e-9, 6), distance_m=round(robot.stack.travelled_m, 6),
            first_path_m=None if first_path_m is None else round(first_path_m, 6),
            first_goal_s=None if first_goal_ns is None else round(first_goal_ns * 1e-9, 6),
            goal_switches=max(0, changed - 1), withdrawals=int(robot.withdrawals),
            reversals=count_reversals(np.array(track)), target_swaps=count_swaps(targets, PERSON_ID),
            frames_other_person=sum(1 for person in targets if person is not None and person != PERSON_ID),
            frames_target_unseen=int(target_unseen), other_person_frames=other_frames, target_track=track_rows,
            goal_changes=goal_changes,
            frames=len(coverages),
            frames_planned=planned, frames_failed=failed, commit_reasons=reasons,
            frames_ticked=session.ticked_between(start_stamp_ns, stamp),
            wall_s=round(time.monotonic() - started, 3))
