"""The evaluation's joules per frame: measured where the board has power rails, carried through the
results JSON, reported in results.md; absent (and the outputs unchanged) without rails."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from leapnbv_common.power_monitor import RAIL_TOTAL, PowerMonitor
from leapnbv_evaluation.harness import FrameOutputs
from leapnbv_evaluation.results import EvaluationRun, GraphVsTruth, MethodResult, PoseRecord, SceneResult, ViewMetrics
from leapnbv_evaluation.task_report import aggregate_task_results, write_task_table
from leapnbv_sim.poses import look_at_pose

pytestmark = pytest.mark.ros


class ConstantRail:
    def __init__(self, watts: float) -> None:
        self.watts = watts

    def read_power_w(self) -> float:
        return self.watts


def test_frame_energy_from_publication_to_candidates() -> None:
    now = [0.0]
    power = PowerMonitor({RAIL_TOTAL: ConstantRail(6.0)}, rate_hz=100.0, clock=lambda: now[0])
    for step in range(300):  # 0 .. 3 s on the monotonic clock the harness stamps frames with
        now[0] = step / 100.0
        power.sample()
    frame = FrameOutputs(stamp_ns=1, published_ns=1_000_000_000)
    assert frame.energy_j(power) is None  # no candidates came
    frame.received_ns["view_candidates"] = 1_276_000_000  # 276 ms later
    assert frame.energy_j(power) == pytest.approx(6.0 * 0.276, rel=1e-9)
    assert frame.energy_j(None) is None


def _scene(energy: list) -> SceneResult:
    rng = np.random.default_rng(1)
    view = ViewMetrics(0.5, 0.2, 20000, 35000)
    pose = PoseRecord.of(look_at_pose(rng.normal(size=3), np.array([0.0, 0.0, 1.0])))
    result = MethodResult(chosen_index=1, pose=pose, before=view, after=ViewMetrics(0.8, 0.1, 25000, 35000),
                          success=True, raw_success=True)
    return SceneResult(seed=3, scene_index=0, stamp_ns=10**18, start_occlusion=0.3, start_pose=pose,
                       graph_failure=None, graph_area_before_px=12345, before=view, pa_mpvpe_before_mm=None,
                       graph_vs_truth=GraphVsTruth([0.1, 0.2, 2.3], [0.0, -0.2, 2.4], [0.0, -1.0, 0.0], 1.25),
                       candidates=None, candidate_views=None, per_method={"leap_nbv": result},
                       latency_ms={"end_to_end": [270.0, 280.0]}, energy_j=energy)


def _run(energy: list) -> EvaluationRun:
    return EvaluationRun(methods=["leap_nbv"], default_method="leap_nbv", stages=["end_to_end"],
                         scenes=[_scene(energy)])


def test_energy_goes_through_the_results_and_the_report(tmp_path: Path) -> None:
    run = _run([2.5, 2.7])
    data = json.loads(json.dumps(run.to_json()))
    assert data["scenes"][0]["energy_j"] == [2.5, 2.7]
    assert EvaluationRun.from_json(data) == run and run.energy_j() == [2.5, 2.7]
    assert aggregate_task_results(run)["energy_j_per_frame"]["p50"] == pytest.approx(2.6)
    markdown = Path(write_task_table(str(tmp_path / "with"), run)).read_text()
    assert "Energy per frame (VDD_IN, from a frame's publication to its view candidates): median 2.600 J" in markdown


def test_without_rails_the_outputs_are_as_before() -> None:
    run = _run([])
    assert "energy_j" not in run.to_json()["scenes"][0]
    assert "energy_j_per_frame" not in aggregate_task_results(run)  # and so no line in results.md
    assert EvaluationRun.from_json(run.to_json()).scenes[0].energy_j == []
