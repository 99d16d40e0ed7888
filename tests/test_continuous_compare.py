"""Two continuous runs compared: continuous_results.compare_runs and scripts/experiments/continuous_compare.py.

The same seeds on sim time give the same episodes, whatever the machine's speed changed.
"""
from __future__ import annotations

import copy
import os
import pathlib
import subprocess
import sys
from typing import List, Tuple

from leapnbv_evaluation.continuous_results import (
    FLOAT_TOLERANCE,
    OUTCOME_ARRIVED,
    OUTCOME_TIME_LIMIT,
    ContinuousEpisode,
    ContinuousRun,
    compare_runs,
    run_differences,
)

REPO = pathlib.Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts/experiments/continuous_compare.py"


def _episode(seed: int, outcome: str, start: float, end: float, time_s: float) -> ContinuousEpisode:
    frames = int(time_s * 5) + 1
    return ContinuousEpisode(
        seed=seed, scene_index=seed % 10, start_stamp_ns=1_000_000_000 + 40_000_000_000 * (seed % 10),
        outcome=outcome, coverage_start=start, coverage_end=end, coverage_best=max(start, end) + 0.012345,
        success=ContinuousEpisode.decide_success(start, end), time_s=time_s, distance_m=0.73 * time_s,
        first_path_m=2.481 if outcome == OUTCOME_ARRIVED else None, first_goal_s=0.2, goal_switches=1,
        withdrawals=0, reversals=0, target_swaps=1 if seed == 11 else 0, frames=frames, frames_planned=frames - 2,
        frames_failed=1, commit_reasons={"FIRST_GOAL": 1, "KEPT": frames - 4, "SWITCHED": 1},
        frames_ticked=3, wall_s=0.7 * frames,
        frames_other_person=2 if seed == 11 else 0, frames_target_unseen=1,
        other_person_frames=[{"frame": 7, "person": 2, "detections": [1, 2], "state": 2, "reason": "gated",
                              "track_xy": [1.83, -0.42]}] if seed == 11 else [],
        target_track=[[k, 1, 2, 1, 0, round(1.0 + 0.05 * k, 2), round(-0.5 + 0.01 * k, 2)] for k in range(6)]
        + [[6, None, None, None, None, None, None]])


def _run() -> ContinuousRun:
    return ContinuousRun(room="corridor", obstacle_map=True, clock="lockstep", camera_rate_hz=5.0,
                         time_limit_s=30.0, commit_hold_s=1.0, total_wall_s=812.4, obstacle_memory=False,
                         episodes=[_episode(10, OUTCOME_ARRIVED, 0.412, 0.803, 8.4),
                                   _episode(11, OUTCOME_TIME_LIMIT, 0.355, 0.371, 30.0),
                                   _episode(12, OUTCOME_ARRIVED, 0.501, 0.764, 11.2)])


def _by_seed(run: ContinuousRun, seed: int) -> ContinuousEpisode:
    return next(e for e in run.episodes if e.seed == seed)


def test_identical_runs_and_the_machine_speed_fields_compare_the_same() -> None:
    a = _run()
    assert compare_runs(a, _run()) == []
    assert compare_runs(a, a) == []
    b = _run()
    b.total_wall_s = 95.0
    for episode in b.episodes:
        episode.wall_s *= 3.0
        episode.frames_ticked += 7
    assert compare_runs(a, b) == []
    # Matched by seed, not by position.
    b.episodes.reverse()
    assert compare_runs(a, b) == []


def test_floats_within_the_tolerance_are_the_same_past_it_a_difference() -> None:
    a, b = _run(), _run()
    _by_seed(b, 12).coverage_end += FLOAT_TOLERANCE / 10
    _by_seed(b, 10).distance_m *= 1 + 1e-12
    assert compare_runs(a, b) == []
    _by_seed(b, 12).coverage_end = 0.765
    assert compare_runs(a, b) == ["seed 12: coverage_end: 0.764 != 0.765"]
    # An int is exact, and a None against a float is a difference.
    _by_seed(b, 10).frames += 1
    _by_seed(b, 10).first_path_m = None
    assert compare_runs(a, b) == ["seed 10: first_path_m: 2.481 != None", "seed 10: frames: 43 != 44",
                                  "seed 12: coverage_end: 0.764 != 0.765"]


def test_nested_values_are_reported_with_their_path() -> None:
    a, b = _run(), _run()
    _by_seed(b, 10).target_track[3][5] = 1.3
    _by_seed(b, 11).other_person_frames[0]["reason"] = "nearest"
    _by_seed(b, 11).commit_reasons["KEPT"] += 1
    del _by_seed(b, 11).commit_reasons["SWITCHED"]
    assert compare_runs(a, b) == [
        "seed 10: target_track[3][5]: 1.15 != 1.3",
        "seed 11: commit_reasons['KEPT']: 147 != 148",  # 151 frames, 147 kept
        "seed 11: commit_reasons['SWITCHED']: only in A",
        "seed 11: other_person_frames[0]['reason']: 'gated' != 'nearest'",
    ]
    # A track one frame longer: the lengths, then the items they share.
    c = _run()
    _by_seed(c, 12).target_track.append([7, 1, 2, 1, 0, 1.4, -0.4])
    assert compare_runs(a, c) == ["seed 12: target_track: 7 items != 8 items"]


def test_missing_seeds_settings_and_the_cap_per_episode() -> None:
    a, b = _run(), _run()
    b.episodes = [e for e in b.episodes if e.seed != 11] + [_episode(13, OUTCOME_ARRIVED, 0.4, 0.7, 9.0)]
    b.clock = "wall"
    b.obstacle_memory = True
    assert compare_runs(a, b) == ["clock: 'lockstep' != 'wall'", "obstacle_memory: False != True",
                                  "seed 11: only in A", "seed 13: only in B"]
    found = run_differences(a, b)
    assert found.count == 4 and found.seeds == 4 and sorted(found.episodes) == [11, 13]
    # Many differences in one episode: 5 lines, then how many more.
    c = copy.deepcopy(a)
    for row in _by_seed(c, 12).target_track[:6]:
        row[5] += 1.0
        row[6] += 1.0
    lines = compare_runs(a, c)
    assert len(lines) == 6 and lines[-1] == "seed 12: ... and 7 more differences"
    assert len(compare_runs(a, c, max_per_episode=100)) == 12
    assert run_differences(a, c).count == 12


def _compare(*args: object) -> subprocess.CompletedProcess[str]:
    # The ROS-free cores from the source tree, as pytest.ini puts them on the path.
    paths = [str(p) for p in sorted((REPO / "src").iterdir()) if (p / p.name).is_dir()]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(paths + [os.environ.get("PYTHONPATH", "")]))
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=120)


def _write(run: ContinuousRun, folder: pathlib.Path) -> pathlib.Path:
    folder.mkdir(parents=True, exist_ok=True)
    return pathlib.Path(run.write(str(folder / "continuous.json")))


def test_script_on_two_files(tmp_path: pathlib.Path) -> None:
    a = _write(_run(), tmp_path / "a" / "corridor")
    slower = _run()
    slower.total_wall_s = 2000.0
    _by_seed(slower, 10).wall_s = 99.0
    same = _write(slower, tmp_path / "b" / "corridor")
    result = _compare(a, same)
    assert (result.returncode, result.stdout, result.stderr) == (0, "corridor: same, 3 episodes\n", "")
    other = _run()
    _by_seed(other, 10).target_track[3][5] = 1.3
    _by_seed(other, 12).outcome = OUTCOME_TIME_LIMIT
    _by_seed(other, 12).coverage_end = 0.70
    result = _compare(a, _write(other, tmp_path / "c" / "corridor"))
    assert result.returncode == 1, result.stderr
    assert result.stdout.splitlines() == ["corridor: 3 differences in 2 of 3 episodes",
                                          "  seed 10: target_track[3][5]: 1.15 != 1.3",
                                          "  seed 12: outcome: 'arrived' != 'time_limit'",
                                          "  seed 12: coverage_end: 0.764 != 0.7"]


def test_script_on_two_folders(tmp_path: pathlib.Path) -> None:
    for side in ("a", "b"):
        _write(_run(), tmp_path / side / "corridor")
        furnished = _run()
        furnished.room = "furnished"
        _write(furnished, tmp_path / side / "furnished")
    (tmp_path / "a" / "corridor.log").write_text("a log beside the runs\n")
    result = _compare(tmp_path / "a", tmp_path / "b")
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines() == ["corridor: same, 3 episodes", "furnished: same, 3 episodes"]
    # A run in one folder only, and a setting that differs.
    _write(_run(), tmp_path / "b" / "corridor_nomap")
    changed = _run()
    changed.camera_rate_hz = 10.0
    _write(changed, tmp_path / "b" / "corridor")
    result = _compare(tmp_path / "a", tmp_path / "b")
    assert result.returncode == 1, result.stderr
    assert result.stdout.splitlines() == ["corridor: 1 setting different", "  camera_rate_hz: 5.0 != 10.0",
                                          "corridor_nomap: only in B", "furnished: same, 3 episodes"]


def test_script_usage_and_bad_files_exit_2(tmp_path: pathlib.Path) -> None:
    good = _write(_run(), tmp_path / "a" / "corridor")
    truncated = tmp_path / "b" / "corridor" / "continuous.json"
    truncated.parent.mkdir(parents=True)
    truncated.write_text(good.read_text()[:200])
    wrong = tmp_path / "wrong.json"
    wrong.write_text('{"format": 99, "room": "corridor"}\n')
    listed = tmp_path / "list.json"
    listed.write_text("[1, 2]\n")
    empty = tmp_path / "empty"
    empty.mkdir()
    missing = tmp_path / "missing.json"
    # The arguments, and what the one line on stderr names.
    cases: List[Tuple[List[object], str]] = [
        ([good], "usage"),
        ([good, good, good], "usage"),
        ([good, missing], str(missing)),
        ([good, truncated], str(truncated)),
        ([tmp_path / "a", tmp_path / "b"], str(truncated)),  # the truncated file of a folder pair
        ([good, tmp_path / "b"], str(tmp_path / "b")),  # a file against a folder
        ([good, wrong], str(wrong)),
        ([listed, good], str(listed)),
        ([tmp_path / "a", empty], str(empty)),
    ]
    for args, named in cases:
        result = _compare(*args)
        assert result.returncode == 2, (args, result.stdout, result.stderr)
        assert result.stdout == "" and len(result.stderr.splitlines()) == 1, (args, result.stderr)
        assert named in result.stderr, (args, result.stderr)
