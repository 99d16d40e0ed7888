"""Tests of goal commitment: the pure decision (near ties, margins, gates, the last bit) and the tracker on plans."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest
from test_planner_plan import CAMERA_HEIGHT, CAMERA_IN_MAP, UP, frame

from leapnbv_common.params import ParamsError, param_specs, replace_params, validate_params
from leapnbv_planner.candidates import FeasibilityReason
from leapnbv_planner.commitment import (
    CommitmentParams,
    CommitReason,
    GoalCommitment,
    HeldView,
    Verdict,
    decide,
    margin_in_force,
)
from leapnbv_planner.inputs import CameraInMap, PlanInputs
from leapnbv_planner.params import PlannerParams, nbv_params_class
from leapnbv_planner.plan import Plan, plan_views

PARAMS = CommitmentParams()
MARGIN = PARAMS.commit_margin
OK = int(FeasibilityReason.OK)
FAR = 1.0  # metres: farther than commit_same_goal_m


def held(score, reason=OK, moved=0.0, best_distance=FAR, current_distance=FAR, blocked_s=0.0):
    return HeldView(score=score, reason=reason, person_moved_m=moved, best_distance_m=best_distance,
                    current_distance_m=current_distance, blocked_s=blocked_s)


def _same_commit(a, b) -> bool:
    """The same committed goal (the commit's place and frame; its last path and blocked time move on)."""
    return a is not None and b is not None and a.stamp_ns == b.stamp_ns and a.index == b.index \
        and np.array_equal(a.foot_point, b.foot_point) and np.array_equal(a.camera_position, b.camera_position)


# --- the decision ---

def test_defaults_ranges_and_descriptions_are_declared_as_every_parameter():
    specs = {spec.name: spec for spec in param_specs(CommitmentParams)}
    assert set(specs) == {"commit_goals", "commit_margin", "commit_margin_without_map", "commit_person_moved_m",
                          "commit_same_goal_m",
                          "commit_blocked_s", "commit_dropped_s", "commit_dropped_radius_m"}
    assert (PARAMS.commit_dropped_s, PARAMS.commit_dropped_radius_m) == (5.0, 1.0)
    assert (PARAMS.commit_goals, MARGIN, PARAMS.commit_margin_without_map, PARAMS.commit_person_moved_m,
            PARAMS.commit_same_goal_m, PARAMS.commit_blocked_s) == (True, 0.02, 0.05, 0.5, 0.25, 0.6)
    assert (specs["commit_blocked_s"].min, specs["commit_blocked_s"].max) == (0.0, 10.0)
    assert all(spec.description and not spec.read_only for spec in specs.values())  # all change at runtime
    assert (specs["commit_margin"].min, specs["commit_margin"].max) == (0.0, 1.0)
    validate_params(PARAMS)
    with pytest.raises(ParamsError, match="commit_margin"):
        replace_params(PARAMS, {"commit_margin": -0.1})
    # They are nbv node parameters, declared as every other (ranges, live updates), once.
    node_specs = {spec.name: spec for spec in param_specs(nbv_params_class())}
    assert {name: (node_specs[name].min, node_specs[name].max, node_specs[name].read_only) for name in specs} == \
        {name: (spec.min, spec.max, spec.read_only) for name, spec in specs.items()}
    assert issubclass(PlannerParams, CommitmentParams)
    assert [field.name for field in dataclasses.fields(PlannerParams)].count("commit_margin") == 1


def test_near_ties_never_flip_the_goal():
    # Two views, A and B, 0.95 m apart, whose scores trade places every plan by less than the margin (what
    # bags/sample_a's candidates 34 and 35 do): the plan's choice flips 19 times, the goal never.
    rng = np.random.default_rng(3)
    committed, switches, plan_flips, previous_best = None, 0, 0, None
    for k in range(20):
        gap = (MARGIN - 1e-4) * (1.0 if k % 2 else -1.0) * rng.uniform(0.2, 1.0)
        scores = {"A": 0.90 + gap / 2, "B": 0.90 - gap / 2}
        best = max(scores, key=lambda name: scores[name])
        plan_flips += previous_best is not None and best != previous_best
        previous_best = best
        view = None if committed is None else held(scores[committed])
        verdict = decide(PARAMS, 1 if best == "A" else 2, scores[best], view, current_score=0.7)
        if committed is None:
            assert verdict.reason == CommitReason.FIRST_GOAL
            committed = best
        else:
            assert verdict == Verdict(CommitReason.KEPT, -1)
        switches += verdict.reason.replaces
    assert plan_flips == 19 and switches == 0


def test_a_view_better_by_more_than_the_margin_wins():
    assert decide(PARAMS, 7, 0.90 + MARGIN + 1e-6, held(0.90)) == Verdict(CommitReason.BEATEN_BY_MARGIN, 7)
    assert decide(PARAMS, 7, 0.90 + MARGIN, held(0.90)).keep  # exactly the margin is not more
    assert decide(PARAMS, 7, 0.95, held(0.90), current_score=0.5).reason == CommitReason.BEATEN_BY_MARGIN
    # The same goal (a foot point within commit_same_goal_m of the committed one) never replaces it.
    assert decide(PARAMS, 7, 0.99, held(0.90, best_distance=0.2)).keep
    # A committed goal better than the plan's best stays (it is not on the ring, so it can be).
    assert decide(PARAMS, 7, 0.80, held(0.90)).keep
    # A smaller margin switches on a smaller gain.
    assert decide(dataclasses.replace(PARAMS, commit_margin=0.001), 7, 0.905, held(0.90)).reason == \
        CommitReason.BEATEN_BY_MARGIN


@pytest.mark.parametrize("reason, expected", [
    (FeasibilityReason.OBSTACLE, CommitReason.INFEASIBLE),
    (FeasibilityReason.OUT_OF_TRAVEL_RANGE, CommitReason.INFEASIBLE),
    (FeasibilityReason.UNREACHABLE, CommitReason.UNREACHABLE),
])
def test_an_infeasible_or_unreachable_committed_goal_is_replaced(reason, expected):
    # Once blocked for commit_blocked_s: even by a view that scores less than the committed goal did, and by nothing
    # when the plan has nothing.
    limit = PARAMS.commit_blocked_s
    assert decide(PARAMS, 4, 0.5, held(0.9, reason=int(reason), blocked_s=limit)) == Verdict(expected, 4)
    assert decide(PARAMS, -1, math.nan, held(0.9, reason=int(reason), blocked_s=limit)) == Verdict(expected, -1)
    assert decide(PARAMS, 4, 0.5, held(math.nan, blocked_s=limit)).reason == CommitReason.INFEASIBLE  # no score
    # Before that it is kept, on its last path (KEPT_BLOCKED), also against a far better view ...
    for blocked in (0.0, 0.2, limit - 1e-6):
        assert decide(PARAMS, 4, 0.99, held(0.0, reason=int(reason), blocked_s=blocked)) == \
            Verdict(CommitReason.KEPT_BLOCKED, -1)
    # ... the gate replaces to the last bit (0.6 s from whole nanoseconds), and 0 replaces at once.
    assert decide(PARAMS, 4, 0.5, held(0.9, reason=int(reason), blocked_s=600_000_000 * 1e-9)).reason == expected
    at_once = dataclasses.replace(PARAMS, commit_blocked_s=0.0)
    assert decide(at_once, 4, 0.5, held(0.9, reason=int(reason))) == Verdict(expected, 4)
    # A person who moved is planned anew at once, blocked or not.
    assert decide(PARAMS, 4, 0.5, held(0.9, reason=int(reason), moved=1.0)).reason == CommitReason.PERSON_MOVED


def test_a_view_near_a_goal_dropped_lately_does_not_beat_the_goal_by_the_margin():
    near = dataclasses.replace(held(0.70), best_near_dropped=True)
    assert decide(PARAMS, 7, 0.99, near) == Verdict(CommitReason.KEPT, -1)
    assert decide(PARAMS, 7, 0.99, held(0.70)) == Verdict(CommitReason.BEATEN_BY_MARGIN, 7)
    # The other rules stand: blocked long enough, the person moved, staying as good.
    blocked = dataclasses.replace(near, reason=int(FeasibilityReason.UNREACHABLE), blocked_s=1.0)
    assert decide(PARAMS, 7, 0.99, blocked) == Verdict(CommitReason.UNREACHABLE, 7)
    assert decide(PARAMS, 7, 0.99, dataclasses.replace(near, person_moved_m=1.0)).reason == CommitReason.PERSON_MOVED
    assert decide(PARAMS, 7, 0.99, near, current_score=0.99).reason == CommitReason.STAYING_AS_GOOD


def test_a_person_who_moved_past_the_distance_resets_the_goal():
    limit = PARAMS.commit_person_moved_m
    assert decide(PARAMS, 3, 0.5, held(0.9, moved=limit + 1e-6)) == Verdict(CommitReason.PERSON_MOVED, 3)
    assert decide(PARAMS, 3, 0.5, held(0.9, moved=limit)).keep
    # Before feasibility: a moved person's goal is planned anew whatever its state.
    assert decide(PARAMS, 3, 0.5, held(0.9, reason=int(FeasibilityReason.OBSTACLE), moved=0.8)).reason == \
        CommitReason.PERSON_MOVED


def test_staying_is_as_good_when_the_current_view_is_within_the_margin():
    # The robot on its way: its current view scores within the margin of the committed goal and of the best.
    assert decide(PARAMS, 9, 0.91, held(0.90), current_score=0.91 - MARGIN) == \
        Verdict(CommitReason.STAYING_AS_GOOD, 0)
    assert decide(PARAMS, 9, 0.91, held(0.90), current_score=0.91 - MARGIN - 1e-6).keep
    # ... also when the best beats the committed goal by the margin: staying is as good as going there.
    assert decide(PARAMS, 9, 0.95, held(0.90), current_score=0.94).reason == CommitReason.STAYING_AS_GOOD
    # Arrived (the current view is the committed goal's): kept, no switch to the same place.
    assert decide(PARAMS, 9, 0.91, held(0.90, current_distance=0.1), current_score=0.90).keep
    # The plan chose the current view and it beats the committed goal: staying.
    assert decide(PARAMS, 0, 0.95, held(0.90), current_score=0.95) == Verdict(CommitReason.STAYING_AS_GOOD, 0)
    # No feasible view but the current one is as good as the committed goal: staying.
    assert decide(PARAMS, -1, math.nan, held(0.90), current_score=0.89).reason == CommitReason.STAYING_AS_GOOD


def test_a_plan_without_an_obstacle_map_holds_the_goal_by_its_own_margin():
    # A rival 0.03 above the committed goal: it beats a goal by commit_margin (0.02), not by the map-less 0.05.
    assert margin_in_force(PARAMS) == MARGIN and margin_in_force(PARAMS, used_obstacle_map=False) == 0.05
    assert decide(PARAMS, 9, 0.93, held(0.90)).reason == CommitReason.BEATEN_BY_MARGIN
    assert decide(PARAMS, 9, 0.93, held(0.90), used_obstacle_map=False).keep
    assert decide(PARAMS, 9, 0.95, held(0.90), used_obstacle_map=False).keep  # exactly the margin: kept
    assert decide(PARAMS, 9, 0.9501, held(0.90), used_obstacle_map=False).reason == CommitReason.BEATEN_BY_MARGIN
    # Staying is as good within the same margin: 0.04 under the best.
    assert decide(PARAMS, 9, 0.93, held(0.90), current_score=0.89).reason == CommitReason.BEATEN_BY_MARGIN
    assert decide(PARAMS, 9, 0.93, held(0.90), current_score=0.89, used_obstacle_map=False).reason == \
        CommitReason.STAYING_AS_GOOD
    # On a real plan (these have no map): the decision weighs and reports the map-less margin.
    commitment = GoalCommitment()
    plan, first = _step(commitment, 0.0, params=PARAMS)
    assert not plan.used_obstacle_map and first.margin == 0.05
    plan, kept = _step(commitment, 0.3, params=PARAMS, stamp=1)
    assert kept.margin == 0.05 and "margin 0.05" in kept.describe()


def test_first_goal_no_goal_and_off():
    assert decide(PARAMS, 5, 0.7, None) == Verdict(CommitReason.FIRST_GOAL, 5)
    assert decide(PARAMS, -1, math.nan, None) == Verdict(CommitReason.NO_GOAL, -1)
    off = dataclasses.replace(PARAMS, commit_goals=False)
    assert decide(off, 5, 0.7, held(0.99)) == Verdict(CommitReason.DISABLED, 5)


def test_decisions_do_not_depend_on_the_last_bit():
    # Scores on a 0.001 grid put differences at exactly the margin (0.02) and the distances at exactly their
    # thresholds; a 1e-12 change of any input (one CPU's rounding against another's) never changes the verdict.
    rng = np.random.default_rng(11)
    same, moved = PARAMS.commit_same_goal_m, PARAMS.commit_person_moved_m
    checked = {reason: 0 for reason in CommitReason}
    for _ in range(400):
        held_score = round(float(rng.uniform(0.5, 0.95)), 3)
        best_score = held_score + float(rng.choice([-0.01, 0.0, 0.019, 0.02, 0.021, 0.05]))
        current_score = max(best_score, held_score) - float(rng.choice([0.0, 0.01, 0.02, 0.021, 0.3]))
        distances = [float(rng.choice([0.1, same, 0.6])) for _ in range(2)]
        person = float(rng.choice([0.0, moved, 0.7]))
        base = decide(PARAMS, 2, best_score, held(held_score, moved=person, best_distance=distances[0],
                                                  current_distance=distances[1]), current_score)
        checked[base.reason] += 1
        for signs in itertools.product((-1e-12, 1e-12), repeat=3):
            tweaked = decide(PARAMS, 2, best_score + signs[0],
                             held(held_score + signs[1], moved=person + signs[2], best_distance=distances[0] - signs[2],
                                  current_distance=distances[1] + signs[0]), current_score - signs[1])
            assert tweaked == base, (held_score, best_score, current_score, distances, person, signs)
    assert all(checked[reason] > 10 for reason in (CommitReason.KEPT, CommitReason.BEATEN_BY_MARGIN,
                                                   CommitReason.STAYING_AS_GOOD, CommitReason.PERSON_MOVED))


# --- the tracker on real plans ---

PLANNER = nbv_params_class()(min_radius=1.0)
# These plans have no obstacle map; the tests of the other rules hold them to commit_margin (the map-less margin has
# its own test).
ON_PLANS = dataclasses.replace(PARAMS, commit_margin_without_map=MARGIN)


def _moved(target, shift, person_shift=0.0):
    """The frame seen from a camera moved by ``shift`` along its level x axis; the person moved too."""
    offset = np.array([shift, 0.0, 0.0])
    person = np.array([person_shift, 0.0, 0.0])
    return dataclasses.replace(
        target, target_points=(target.target_points - offset + person).astype(np.float32),
        background_points=(target.background_points - offset).astype(np.float32),
        centroid=target.centroid - offset + person)


def _pose(shift):
    rotation, position = CAMERA_IN_MAP
    return CameraInMap(rotation, position + rotation @ np.array([shift, 0.0, 0.0]))


def _step(commitment, shift, params=ON_PLANS, person_shift=0.0, extra_background=None, fixed_frame="map",
          with_pose=True, stamp=0):
    target, ground = frame()
    target = _moved(target, shift, person_shift)
    if extra_background is not None:
        target = dataclasses.replace(target, background_points=np.concatenate(
            [target.background_points, extra_background.astype(np.float32)]))
    pose = _pose(shift) if with_pose else None
    feet = commitment.extra_foot_points(params, pose, fixed_frame)
    plan = plan_views(PlanInputs(target, ground, PLANNER, extra_foot_points=feet))
    return plan, commitment.update(params, plan, pose, fixed_frame, stamp)


def _in_map(point):
    rotation, position = CAMERA_IN_MAP
    return rotation @ point + position


def test_the_goal_is_committed_in_the_fixed_frame_and_kept_while_the_robot_moves():
    commitment = GoalCommitment()
    plan, first = _step(commitment, 0.0)
    assert first.reason == CommitReason.FIRST_GOAL and not first.changed and first.index == plan.chosen_index >= 1
    goal = commitment.goal
    assert goal is not None and goal.fixed_frame == "map" and goal.stamp_ns == 0
    np.testing.assert_allclose(goal.foot_point, _in_map(plan.candidates.foot_points[plan.chosen_index]), atol=1e-12)
    np.testing.assert_allclose(goal.camera_position, _in_map(plan.candidates.positions[plan.chosen_index]),
                               atol=1e-12)
    np.testing.assert_allclose(goal.person_position, _in_map(plan.candidates.ring_center), atol=1e-12)
    assert first.goal is not None and first.base_goal is not None
    np.testing.assert_array_equal(first.goal[1], plan.chosen_pose()[1])
    np.testing.assert_array_equal(first.base_path, plan.base_path)
    # The robot drives 0.3, 0.6, 0.9 m sideways: the plan's own choice changes, the goal stays where it was.
    choices = [plan.chosen_index]
    for step, shift in enumerate([0.3, 0.6, 0.9], start=1):
        plan, decision = _step(commitment, shift, stamp=step)
        choices.append(plan.chosen_index)
        assert decision.reason == CommitReason.KEPT and not decision.changed and decision.index == -1
        assert _same_commit(commitment.goal, goal)
        extra = plan.extra
        assert extra is not None and len(extra) == 1
        # The committed foot point in this frame: where the map puts it.
        np.testing.assert_allclose(extra.candidates.foot_points[0], goal_in_frame(goal.foot_point, shift), atol=1e-9)
        np.testing.assert_array_equal(decision.goal[1], extra.candidates.positions[0])
        np.testing.assert_array_equal(decision.base_goal[1], extra.candidates.foot_points[0])
        assert decision.base_path is not None
        np.testing.assert_array_equal(decision.base_path[-1], extra.candidates.foot_points[0])
        assert decision.score == decision.held_score == extra.scores.score[0]
        assert decision.best_index == plan.chosen_index and decision.best_score <= decision.score + MARGIN
        assert "goal kept" in decision.describe()
    assert len(set(choices)) > 1  # without commitment the goal would have changed


def goal_in_frame(point, shift):
    rotation, position = CAMERA_IN_MAP
    return rotation.T @ (point - position) - np.array([shift, 0.0, 0.0])


def test_an_obstacle_on_the_committed_goal_keeps_it_on_its_last_path_then_replaces_it():
    commitment = GoalCommitment()
    plan, first = _step(commitment, 0.0)
    foot = plan.candidates.foot_points[plan.chosen_index]
    first_path = first.base_path
    assert first_path is not None and len(first_path) > 3
    rng = np.random.default_rng(5)
    # A box 0.4 m high on the committed foot point (seen in the next frames, 0.2 s apart).
    box = foot + np.column_stack([rng.uniform(-0.2, 0.2, 200), -rng.uniform(0.1, 0.4, 200),
                                  rng.uniform(-0.2, 0.2, 200)])
    for stamp in (200_000_000, 400_000_000):  # blocked for 0 s, then 0.2 s: less than commit_blocked_s (0.6)
        plan, decision = _step(commitment, 0.0, extra_background=box, stamp=stamp)
        assert plan.extra.feasibility.reasons[0] == int(FeasibilityReason.OBSTACLE)
        assert decision.reason == CommitReason.KEPT_BLOCKED and not decision.changed and decision.index == -1
        assert decision.blocked_s == pytest.approx((stamp - 200_000_000) * 1e-9)
        assert f"for {decision.blocked_s:.2f} s, less than commit_blocked_s" in decision.describe()
        # The last path, from the robot's foot point (the camera did not move: the path's first point) on.
        np.testing.assert_allclose(decision.base_path, first_path, atol=1e-9)
        np.testing.assert_allclose(decision.base_goal[1], foot, atol=1e-9)
    plan, decision = _step(commitment, 0.0, extra_background=box, stamp=800_000_000)  # 0.6 s blocked
    assert plan.extra.feasibility.reasons[0] == int(FeasibilityReason.OBSTACLE)
    assert decision.reason == CommitReason.INFEASIBLE and decision.changed
    assert len(commitment.dropped) == 1
    assert commitment.dropped[0][0] == "map" and commitment.dropped[0][2] == 800_000_000
    np.testing.assert_allclose(commitment.dropped[0][1], _in_map(foot), atol=1e-9)
    assert decision.index == plan.chosen_index >= 0
    assert np.linalg.norm(plan.candidates.foot_points[plan.chosen_index] - foot) > 0.3  # another goal
    assert commitment.goal is not None and commitment.goal.index == plan.chosen_index
    # The box goes: the dropped place is the plan's best again (the new goal is its mirror image, 2e-5 below it: a
    # margin of 0 lets it beat that), but does not take the goal back within commit_dropped_s (5 s) of the drop;
    # after that it does.
    no_margin = dataclasses.replace(PARAMS, commit_margin=0.0, commit_margin_without_map=0.0)
    plan, decision = _step(commitment, 0.0, params=no_margin, stamp=1_000_000_000)
    assert np.linalg.norm(plan.candidates.foot_points[plan.chosen_index] - foot) < 1e-9
    assert decision.best_score > decision.held_score + 1e-6
    assert decision.reason == CommitReason.KEPT and decision.best_near_dropped
    assert "near a goal dropped as blocked within commit_dropped_s" in decision.describe()
    plan, decision = _step(commitment, 0.0, params=no_margin, stamp=5_800_000_000)  # 5.0 s after: past it
    assert decision.reason == CommitReason.BEATEN_BY_MARGIN and not commitment.dropped


def test_a_committed_goal_on_the_edge_of_an_obstacle_moves_within_the_same_goal_distance_and_is_kept():
    # A post 0.22 m beside the committed foot point (the robot's radius is 0.3): the foot point itself is blocked,
    # one 0.1 m away is free, well within commit_same_goal_m (0.25). The goal is kept there, its committed foot point
    # unchanged (the next frame starts from it again, so that nudges do not add up), and goal_status says so.
    commitment = GoalCommitment()
    plan, _ = _step(commitment, 0.0)
    goal = commitment.goal
    foot = plan.candidates.foot_points[plan.chosen_index]
    side = np.cross(UP, foot - plan.candidates.ring_center)
    side /= np.linalg.norm(side)
    rng = np.random.default_rng(3)
    post = foot + 0.22 * side + np.column_stack([rng.uniform(-0.01, 0.01, 100), -rng.uniform(0.1, 0.6, 100),
                                                 rng.uniform(-0.01, 0.01, 100)])
    plan, decision = _step(commitment, 0.0, extra_background=post, stamp=1)
    extra = plan.extra
    assert extra is not None and extra.nudged_m is not None
    assert extra.feasibility.reasons[0] == int(FeasibilityReason.OK)
    assert 0.05 <= extra.nudged_m[0] <= 0.25 + 1e-12
    assert decision.reason == CommitReason.KEPT and not decision.changed and _same_commit(commitment.goal, goal)
    assert decision.nudged_m == extra.nudged_m[0]
    moved = extra.candidates.foot_points[0]
    assert float(np.min(np.linalg.norm((post - moved)[:, [0, 2]], axis=1))) >= 0.3  # clear of the post
    assert decision.base_path is not None
    np.testing.assert_array_equal(decision.base_path[-1], moved)
    np.testing.assert_array_equal(decision.base_goal[1], moved)
    assert f"goal kept ({decision.nudged_m:.2f} m from its foot point, in free space)" in decision.describe()
    # Without the post: back at its own foot point.
    plan, decision = _step(commitment, 0.0, stamp=2)
    assert decision.reason == CommitReason.KEPT and decision.nudged_m == 0.0
    np.testing.assert_allclose(plan.extra.candidates.foot_points[0], foot, atol=1e-9)
    assert decision.describe().startswith("goal kept: ")


def test_a_person_who_moved_resets_and_a_still_one_does_not():
    commitment = GoalCommitment()
    _step(commitment, 0.0)
    plan, decision = _step(commitment, 0.0, person_shift=0.1)
    assert decision.reason == CommitReason.KEPT
    assert decision.person_moved_m == pytest.approx(0.1, abs=1e-6)
    commitment = GoalCommitment()
    _step(commitment, 0.0)
    plan, decision = _step(commitment, 0.0, person_shift=0.6)
    assert decision.reason == CommitReason.PERSON_MOVED and decision.changed
    assert decision.person_moved_m == pytest.approx(0.6, abs=1e-6)
    np.testing.assert_allclose(commitment.goal.person_position, _in_map(plan.candidates.ring_center), atol=1e-12)


def test_staying_as_good_then_arrived():
    commitment = GoalCommitment()
    # Every view is as good as any other.
    loose = dataclasses.replace(PARAMS, commit_margin=1.0, commit_margin_without_map=1.0)
    _step(commitment, 0.0, loose)
    plan, decision = _step(commitment, 0.3, loose)
    assert decision.reason == CommitReason.STAYING_AS_GOOD and decision.changed and decision.index == 0
    np.testing.assert_array_equal(decision.goal[1], np.zeros(3))  # the current view
    np.testing.assert_allclose(commitment.goal.foot_point, _in_map(np.array([0.3, CAMERA_HEIGHT, 0.0])), atol=1e-9)
    # The next frame from the same place: the robot is at its goal, which stays.
    plan, decision = _step(commitment, 0.3, loose)
    assert decision.reason == CommitReason.KEPT
    # Staying where the current view scores far below: the best view beats the staying goal by the margin.
    plan, decision = _step(commitment, 0.3)
    assert decision.reason == CommitReason.BEATEN_BY_MARGIN and decision.index == plan.chosen_index
    assert decision.best_score > decision.held_score + MARGIN


def test_without_a_fixed_frame_each_plan_is_the_goal():
    commitment = GoalCommitment()
    plan, decision = _step(commitment, 0.0, with_pose=False)
    assert decision.reason == CommitReason.NO_FIXED_FRAME and commitment.goal is None and not decision.changed
    assert decision.index == plan.chosen_index and plan.extra is None
    _step(commitment, 0.0)
    assert commitment.goal is not None
    assert commitment.extra_foot_points(PARAMS, None, "map") is None
    plan, decision = _step(commitment, 0.0, with_pose=False)
    assert decision.reason == CommitReason.NO_FIXED_FRAME and decision.changed and commitment.goal is None
    # A pose in another fixed frame: the goal cannot be placed there; committed anew.
    _step(commitment, 0.0)
    plan, decision = _step(commitment, 0.0, fixed_frame="odom")
    assert decision.reason == CommitReason.FIXED_FRAME_CHANGED and decision.changed and plan.extra is None
    assert commitment.goal.fixed_frame == "odom"


def test_commitment_off_costs_nothing_and_follows_the_plan():
    commitment = GoalCommitment()
    off = dataclasses.replace(PARAMS, commit_goals=False)
    _step(commitment, 0.0)
    assert commitment.extra_foot_points(off, _pose(0.0), "map") is None
    plan, decision = _step(commitment, 0.3, off)
    assert plan.extra is None and decision.reason == CommitReason.DISABLED and decision.index == plan.chosen_index
    assert commitment.goal is None


def test_a_plan_made_without_the_committed_goal_is_refused():
    commitment = GoalCommitment()
    _step(commitment, 0.0)
    target, ground = frame()
    plan: Plan = plan_views(PlanInputs(target, ground, PLANNER))
    with pytest.raises(ValueError, match="extra_foot_points"):
        commitment.update(PARAMS, plan, _pose(0.0), "map", 1)


def test_no_feasible_view_commits_nothing():
    commitment = GoalCommitment()
    target, ground = frame()
    plan = plan_views(PlanInputs(target, ground, nbv_params_class()(include_current=False, max_travel=0.0)))
    decision = commitment.update(PARAMS, plan, _pose(0.0), "map", 0)
    assert decision.reason == CommitReason.NO_GOAL and decision.goal is None and commitment.goal is None
    assert math.isnan(decision.score) and "no feasible view" in decision.describe()
    assert UP[1] == -1.0  # the frame's floor: y down in the optical frame
