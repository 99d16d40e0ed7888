"""The regression's comparison on constructed goldens (ties, the goal of a tied view) and its golden files' bytes."""
from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest

from leapnbv_bringup import regression
from leapnbv_bringup.regression import (
    TIE_TOLERANCE,
    candidate_goal,
    compare_outputs,
    format_report,
    golden_json_bytes,
    golden_npz_bytes,
    load_golden,
    save_golden,
)
from leapnbv_planner.plan import base_goal_frame

STAMP = 1_700_000_000_000_000_000
RING_CENTER = np.array([0.0, 1.0, 3.0])
UP = np.array([0.0, -1.0, 0.0])  # the optical frame's y points down
FLOOR_POINT = np.array([0.0, 1.0, 0.0])  # the floor 1 m below the camera


def camera_at(angle: float) -> tuple:
    """A candidate camera 2 m from the ring centre at ``angle``, 1 m above the floor, looking at the centre."""
    position = RING_CENTER + np.array([2.0 * np.cos(angle), -1.0, 2.0 * np.sin(angle)])
    forward = RING_CENTER - position
    forward /= np.linalg.norm(forward)
    right = np.cross(-UP, forward)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return np.stack([right, down, forward], axis=1), position


def base_at(position: np.ndarray) -> tuple:
    return base_goal_frame(position - float(UP @ (position - FLOOR_POINT)) * UP, RING_CENTER, UP)


def frame_outputs(scores, chosen: int, goal_index=None):
    """One frame's outputs: view candidates with ``scores``, the goal of candidate ``goal_index`` (default chosen)."""
    poses = [camera_at(angle) for angle in (0.0, 0.4, 2.0)]
    goal = poses[chosen if goal_index is None else goal_index]
    base_rotation, base_position = base_at(goal[1])
    views = {"score": np.array(scores, np.float64), "feasible": np.ones(3, bool), "chosen_index": np.array(chosen),
             "s_area": np.full(3, 0.1),
             "positions": np.stack([p for _, p in poses]), "rotations": np.stack([r for r, _ in poses]),
             "ring_center": RING_CENTER.copy()}
    return {"view_candidates": {STAMP: views},
            "next_best_view": {STAMP: {"rotation": goal[0], "position": goal[1]}},
            "base_goal": {STAMP: {"rotation": base_rotation, "position": base_position}},
            "markers": {STAMP: {"marker_count": np.array(4)}}}


def problems(findings):
    return [f for f in findings if f.status not in regression.PASSING_STATUSES]


def test_a_swap_within_the_tie_tolerance_passes_and_is_reported_with_both_scores():
    golden = frame_outputs([0.5000, 0.4996, 0.2], chosen=0)
    got = frame_outputs([0.4998, 0.4999, 0.2], chosen=1)  # the two views swapped places, 4e-4 / 1e-4 apart
    findings = compare_outputs(got, golden)
    assert problems(findings) == []
    ties = [f for f in findings if f.status == "tie"]
    assert len(ties) == 1 and ties[0].topic == "view_candidates" and ties[0].field == "chosen_index"
    assert "chose candidate 0 (score 0.500000; candidate 1: 0.499600)" in ties[0].detail
    assert "this run chose 1 (0.499900; 0: 0.499800)" in ties[0].detail
    text, failures = format_report(findings, [STAMP])
    assert failures == 0 and "frame 0 (stamp 1700000000000000000) chosen_index: tie - a tie" in text
    assert "ok   next_best_view: 1 frames match" in text and "ok   base_goal: 1 frames match" in text


def test_the_same_swap_outside_the_tie_tolerance_fails():
    golden = frame_outputs([0.5000, 0.5000 - 2 * TIE_TOLERANCE, 0.2], chosen=0)
    got = frame_outputs([0.5000 - 2 * TIE_TOLERANCE, 0.5000, 0.2], chosen=1)
    findings = problems(compare_outputs(got, golden))
    assert {(f.topic, f.field) for f in findings} >= {("view_candidates", "chosen_index"),
                                                       ("next_best_view", "position"), ("base_goal", "position")}
    assert not any(f.status == "tie" for f in compare_outputs(got, golden))
    # Scores within the tolerance in the golden run but not in this one: no tie either.
    got = frame_outputs([0.4996 - 2 * TIE_TOLERANCE, 0.4996, 0.2], chosen=1)
    assert ("view_candidates", "chosen_index") in {(f.topic, f.field)
                                                   for f in problems(compare_outputs(got, frame_outputs(
                                                       [0.5000, 0.4996, 0.2], chosen=0)))}


def test_a_tie_whose_goal_is_not_the_tied_views_fails():
    golden = frame_outputs([0.5000, 0.4996, 0.2], chosen=0)
    got = frame_outputs([0.4998, 0.4999, 0.2], chosen=1, goal_index=2)  # chose 1, published 2's goal
    changed = {(f.topic, f.field) for f in problems(compare_outputs(got, golden))}
    assert changed == {("next_best_view", "position"), ("next_best_view", "heading"), ("base_goal", "position"),
                       ("base_goal", "heading")}


def test_an_infeasible_view_or_a_golden_without_candidate_poses_is_never_a_tie():
    golden = frame_outputs([0.5000, 0.4996, 0.2], chosen=0)
    got = frame_outputs([0.4998, 0.4999, 0.2], chosen=1)
    golden["view_candidates"][STAMP]["feasible"][1] = False
    got["view_candidates"][STAMP]["feasible"][1] = False
    assert ("view_candidates", "chosen_index") in {(f.topic, f.field) for f in problems(compare_outputs(got, golden))}
    golden = frame_outputs([0.5000, 0.4996, 0.2], chosen=0)
    for key in ("positions", "rotations", "ring_center"):  # a golden written before candidate poses were kept
        del golden["view_candidates"][STAMP][key]
    assert ("next_best_view", "position") in {(f.topic, f.field) for f in problems(compare_outputs(got, golden))}


def test_other_fields_keep_their_tolerances_in_a_tied_frame():
    golden = frame_outputs([0.5000, 0.4996, 0.2], chosen=0)
    got = frame_outputs([0.4998, 0.4999, 0.2], chosen=1)
    got["view_candidates"][STAMP]["positions"][2] += [0.02, 0.0, 0.0]  # an untied candidate moved 2 cm
    got["markers"][STAMP]["marker_count"] = np.array(5)
    assert {(f.topic, f.field) for f in problems(compare_outputs(got, golden))} == {
        ("view_candidates", "positions"), ("markers", "marker_count")}


def two_frames(first, second):
    """Outputs of two frames: ``first`` at STAMP, ``second`` 0.1 s later (each from frame_outputs)."""
    out = {topic: dict(frames) for topic, frames in first.items()}
    for topic, frames in second.items():
        out[topic][STAMP + 100_000_000] = frames[STAMP]
    return out


def test_a_tie_carries_to_the_frames_whose_committed_goal_it_chose_and_only_as_it_was():
    # Frame 0 a tie (this run took view 1, the golden view 0); frame 1: both plans agree on view 2, both runs
    # keep their committed goal (the commitment): this run's goal is still view 1's, the golden's view 0's.
    golden = two_frames(frame_outputs([0.5000, 0.4996, 0.2], chosen=0),
                        frame_outputs([0.3, 0.3, 0.5], chosen=2, goal_index=0))
    got = two_frames(frame_outputs([0.4998, 0.4999, 0.2], chosen=1),
                     frame_outputs([0.3, 0.3, 0.5], chosen=2, goal_index=1))
    findings = compare_outputs(got, golden)
    assert problems(findings) == []
    carried = [f for f in findings if f.status == "tie" and f.topic != "view_candidates"]
    assert {(f.topic, f.stamp_ns) for f in carried} == {("next_best_view", STAMP + 100_000_000),
                                                         ("base_goal", STAMP + 100_000_000)}
    assert "committed at the tie of frame" in carried[0].detail
    # The same second frame without the tie before it (this run took the golden's view 0 there): a changed goal.
    untied = two_frames(frame_outputs([0.5000, 0.4996, 0.2], chosen=0),
                        frame_outputs([0.3, 0.3, 0.5], chosen=2, goal_index=1))
    assert ("next_best_view", "position") in {(f.topic, f.field) for f in problems(compare_outputs(untied, golden))}
    # After the tie, a goal that is neither the golden's nor the tied one's: a changed goal.
    moved = two_frames(frame_outputs([0.4998, 0.4999, 0.2], chosen=1),
                       frame_outputs([0.3, 0.3, 0.5], chosen=2, goal_index=2))
    assert {("next_best_view", "position"), ("base_goal", "position")} <= {
        (f.topic, f.field) for f in problems(compare_outputs(moved, golden))}


@pytest.mark.parametrize("bag", ["sample_a", "sample_b", "sample_a.smpler_x_s32_random"])
def test_committed_goldens_tied_goal_of_their_own_choice_is_their_goal_and_their_bytes_are_canonical(repo_root, bag):
    path = repo_root / "bags" / f"{bag}.golden.npz"
    golden = load_golden(str(path))
    # The first frame's goal is its plan's own choice (the commitment's first goal); later frames may keep an
    # earlier goal. Where a goal is the plan's choice, candidate_goal gives it from the candidate's pose.
    own = []
    for stamp, views in sorted(golden["view_candidates"].items()):
        for topic in ("next_best_view", "base_goal"):
            goal = candidate_goal(topic, golden, stamp, int(views["chosen_index"]))
            assert goal is not None
            if regression.goal_is_own_choice(topic, golden, stamp):
                # Within the goal's tolerance (1 cm): the goal is the committed view's, put on the floor again.
                np.testing.assert_allclose(goal["position"], golden[topic][stamp]["position"], atol=0.01)
                np.testing.assert_allclose(goal["rotation"], golden[topic][stamp]["rotation"], atol=0.01)
                own.append(stamp)
    assert min(golden["view_candidates"]) in own
    # What --update-golden writes for these values is the committed file, byte for byte.
    assert golden_npz_bytes(golden) == path.read_bytes()
    assert golden_json_bytes(golden) == path.with_suffix(".json").read_bytes()


def test_golden_bytes_do_not_depend_on_order_or_time(tmp_path, monkeypatch):
    values = frame_outputs([0.5, 0.4, 0.2], chosen=0)
    values["view_candidates"][STAMP + 100_000_000] = dict(values["view_candidates"][STAMP])
    first, second = tmp_path / "a.golden.npz", tmp_path / "b.golden.npz"
    save_golden(str(first), values)
    reordered = {topic: {stamp: dict(reversed(list(fields.items())))
                         for stamp, fields in reversed(list(frames.items()))}
                 for topic, frames in reversed(list(values.items()))}
    reordered["base_goal"][STAMP] = {k: np.asfortranarray(v) for k, v in reordered["base_goal"][STAMP].items()}
    monkeypatch.setattr("time.time", lambda: 2_000_000_000.0)  # another clock: zip entries would carry it
    save_golden(str(second), reordered)
    assert first.read_bytes() == second.read_bytes()
    assert golden_json_bytes(values) == golden_json_bytes(reordered)
    with zipfile.ZipFile(io.BytesIO(first.read_bytes())) as archive:
        names = archive.namelist()
        assert names == sorted(names) and names[0] == f"base_goal|{STAMP}|position.npy"
        assert {info.date_time for info in archive.infolist()} == {(1980, 1, 1, 0, 0, 0)}
    loaded = load_golden(str(first))
    for topic, frames in values.items():
        for stamp, fields in frames.items():
            for key, value in fields.items():
                np.testing.assert_array_equal(loaded[topic][stamp][key], value)
                assert loaded[topic][stamp][key].dtype == np.asarray(value).dtype
