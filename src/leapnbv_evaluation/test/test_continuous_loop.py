"""The continuous episode through the real graph on sim time: two runs of the same seed give the same episode."""
from __future__ import annotations

import time

import pytest

pytest.importorskip("rclpy")

from leapnbv_evaluation.benchmark_set import BENCHMARK_SEEDS  # noqa: E402
from leapnbv_evaluation.continuous_results import (  # noqa: E402
    OUTCOME_ARRIVED,
    OUTCOME_TIME_LIMIT,
    WALL_CLOCK_FIELDS,
    compare_runs,
)
from leapnbv_evaluation.harness import ClosedLoopEvaluator  # noqa: E402
from leapnbv_evaluation.options import EvaluationOptions  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]

def _episode(tmp_path, name: str):
    options = EvaluationOptions(continuous=True, camera_rate_hz=5.0, time_limit_s=3.0, log_dir=str(tmp_path / name),
                                ready_timeout_s=120.0)
    with ClosedLoopEvaluator(options) as evaluator:
        run = evaluator.evaluate_continuous(BENCHMARK_SEEDS[:1])
        statuses = evaluator.goal_statuses()
    return run, statuses


def test_two_runs_of_a_seed_on_sim_time_give_the_same_episode(tmp_path) -> None:
    started = time.monotonic()
    first, first_statuses = _episode(tmp_path, "first")
    second, second_statuses = _episode(tmp_path, "second")
    assert time.monotonic() - started < 400.0
    a, b = first.episodes[0], second.episodes[0]
    assert a.outcome in (OUTCOME_ARRIVED, OUTCOME_TIME_LIMIT)
    # Every frame of the 3 s at 5 Hz (16 frames, or fewer on arrival) went through the graph and was planned.
    assert a.frames == round(a.time_s * 5.0) + 1 and a.frames <= 16
    assert a.frames_planned == a.frames and a.frames_failed == 0
    assert a.first_goal_s == 0.0 and a.first_path_m is not None and a.first_path_m > 0.0
    assert a.commit_reasons.get("FIRST_GOAL") == 1  # the evaluator's warm-up goal was forgotten
    assert a.goal_changes[0][:2] == [0, "FIRST_GOAL"] and a.goal_changes[0][2].startswith("goal committed: view ")
    assert len(a.goal_changes) == a.goal_switches + 1
    assert a.distance_m > 0.1  # it drove
    assert 0.0 < a.coverage_start <= a.coverage_best <= 1.0
    # Not part of what an episode is: how long it took on this machine (WALL_CLOCK_FIELDS); the rest to the bit, and
    # through the comparison tool's tolerance (scripts/experiments/continuous_compare.py).
    same = {k: v for k, v in a.to_json().items() if k not in WALL_CLOCK_FIELDS}
    assert same == {k: v for k, v in b.to_json().items() if k not in WALL_CLOCK_FIELDS}
    assert compare_runs(first, second) == []
    # The goal topics told both runs' robots the same things, status by status.
    assert first_statuses == second_statuses
