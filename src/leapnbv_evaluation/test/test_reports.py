"""Tests of the demo report and evaluation outputs (overlay, ground map, task table, chosen views, atomic writes)."""

from __future__ import annotations

import json
import os

import cv2
import numpy as np
import pytest

from leapnbv_common.conversions import GroundPlaneArrays, ViewCandidatesArrays
from leapnbv_evaluation import demo_report, report_files
from leapnbv_evaluation.demo_report import (
    DemoFrame,
    ground_frame,
    overlay_person,
    plot_ring_top_down,
    to_ground_2d,
    write_demo_report,
)
from leapnbv_evaluation.results import EvaluationRun, GraphVsTruth, MethodResult, PoseRecord, SceneResult, ViewMetrics
from leapnbv_evaluation.task_report import (
    aggregate_task_results,
    chosen_views_record,
    evaluation_summary_markdown,
    task_table_markdown,
    write_evaluation_outputs,
    write_task_table,
)

# A camera 1.2 m above a level floor, looking horizontally: the floor is y = 1.2 (y down),
# so n = (0, -1, 0) points up and d = 1.2.
LEVEL_NORMAL = np.array([0.0, -1.0, 0.0])
LEVEL_OFFSET = 1.2


def _rotation_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rotation_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


# ---------------------------------------------------------------------------------------------
# Overlay
# ---------------------------------------------------------------------------------------------


def test_overlay_changes_exactly_mask_and_box_pixels():
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, size=(240, 320, 3), dtype=np.uint8)
    original = rgb.copy()
    mask = np.zeros((240, 320), dtype=bool)
    mask[100:180, 40:90] = True
    box = (150.0, 80.0, 260.0, 200.0)

    out = overlay_person(rgb, box, mask, label="person 0.87")

    assert out.shape == rgb.shape and out.dtype == np.uint8
    np.testing.assert_array_equal(rgb, original)  # input untouched
    # Mask pixels are the blend with the tint, to rounding.
    alpha = demo_report.MASK_TINT_ALPHA
    expected = (1.0 - alpha) * original[mask].astype(np.float64) + alpha * np.array(
        demo_report.MASK_TINT_RGB, dtype=np.float64
    )
    assert np.max(np.abs(out[mask].astype(np.float64) - expected)) <= 0.5 + 1e-6
    # The box outline has the box colour on all four sides.
    for y, x in ((80, 200), (200, 200), (140, 150), (140, 260)):
        assert tuple(out[y, x]) == demo_report.BOX_COLOUR_RGB
    # The box interior away from the label strip keeps its pixels.
    np.testing.assert_array_equal(out[120:190, 160:250], original[120:190, 160:250])
    # Far from both (the label strip sits just above the box): unchanged.
    far = np.ones((240, 320), dtype=bool)
    far[95:185, 35:95] = False  # mask + margin
    far[40:205, 145:320] = False  # box + label strip + margin
    np.testing.assert_array_equal(out[far], original[far])
    # Something did change outside the mask: the box and label.
    assert np.any(out[~mask] != original[~mask])


def test_overlay_without_box_or_mask_is_a_copy():
    rgb = np.full((20, 30, 3), 7, dtype=np.uint8)
    out = overlay_person(rgb, None, None)
    np.testing.assert_array_equal(out, rgb)
    assert out is not rgb


def test_overlay_rejects_mismatched_mask():
    with pytest.raises(report_files.ReportError, match="mask"):
        overlay_person(np.zeros((10, 10, 3), np.uint8), None, np.zeros((10, 11), bool))


# ---------------------------------------------------------------------------------------------
# Ground frame
# ---------------------------------------------------------------------------------------------


def test_ground_frame_level_camera_point_ahead_maps_to_0_1():
    frame = ground_frame(LEVEL_NORMAL, LEVEL_OFFSET)
    np.testing.assert_allclose(frame.origin, [0.0, 1.2, 0.0], atol=1e-12)
    points = np.array([[0.0, 1.2, 1.0], [0.5, 1.2, 0.0], [-2.0, 1.2, 3.0], [0.0, 0.0, 2.0]])
    np.testing.assert_allclose(
        to_ground_2d(points, frame), [[0.0, 1.0], [0.5, 0.0], [-2.0, 3.0], [0.0, 2.0]], atol=1e-12
    )


@pytest.mark.parametrize("pitch_deg, yaw_deg", [(25.0, 0.0), (-10.0, 40.0), (60.0, -120.0)])
def test_ground_frame_tilted_camera_forward_and_distances(pitch_deg, yaw_deg):
    # World: z up, floor z = 0, camera at height 1.1 m. Camera optical axes in world coordinates:
    # a level camera looking along world +x has x_cam = -y_w, y_cam = -z_w, z_cam = +x_w; then
    # pitch down about its own x axis and yaw about the world vertical.
    level = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # columns: cam axes in world
    yaw = np.deg2rad(yaw_deg)
    world_yaw = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
    R_world_cam = world_yaw @ level @ _rotation_x(-np.deg2rad(pitch_deg))
    camera = np.array([0.3, -0.7, 1.1])

    def to_cam(points_world):
        return (np.asarray(points_world) - camera) @ R_world_cam

    normal_cam = R_world_cam.T @ np.array([0.0, 0.0, 1.0])
    offset = float(camera[2])  # n.x + d = 0 with x in camera coords: d = height
    frame = ground_frame(normal_cam, offset)

    np.testing.assert_allclose(np.linalg.norm(frame.e1), 1.0)
    np.testing.assert_allclose(np.linalg.norm(frame.e2), 1.0)
    assert abs(frame.e1 @ normal_cam) < 1e-12 and abs(frame.e2 @ normal_cam) < 1e-12
    np.testing.assert_allclose(np.cross(frame.e2, frame.e1), normal_cam, atol=1e-12)  # map seen from above
    # 1 m ahead of the camera (its heading on the floor) -> (0, 1); 1 m to its right -> (1, 0).
    heading = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    foot = np.array([camera[0], camera[1], 0.0])
    mapped = to_ground_2d(to_cam([foot + heading, foot + right, foot]), frame)
    np.testing.assert_allclose(mapped, [[0.0, 1.0], [1.0, 0.0], [0.0, 0.0]], atol=1e-9)
    # Distances between floor points are preserved.
    rng = np.random.default_rng(3)
    floor = np.concatenate([rng.uniform(-3, 3, size=(20, 2)), np.zeros((20, 1))], axis=1)
    floor_2d = to_ground_2d(to_cam(floor), frame)
    d3 = np.linalg.norm(floor[:, None, :] - floor[None, :, :], axis=2)
    d2 = np.linalg.norm(floor_2d[:, None, :] - floor_2d[None, :, :], axis=2)
    np.testing.assert_allclose(d2, d3, atol=1e-9)


def test_ground_frame_camera_looking_straight_down_uses_image_up():
    # Optical z = down: the floor normal (up) is -z in camera coordinates; image up (-y) is forward.
    frame = ground_frame([0.0, 0.0, -2.0], 3.0)  # non-unit normal: d scales with it
    np.testing.assert_allclose(frame.origin, [0.0, 0.0, 1.5], atol=1e-12)
    np.testing.assert_allclose(frame.e1, [0.0, -1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(to_ground_2d(np.array([0.0, -1.0, 1.5]), frame), [[0.0, 1.0]], atol=1e-12)


def test_ground_frame_rejects_zero_normal():
    with pytest.raises(report_files.ReportError, match="degenerate"):
        ground_frame([0.0, 0.0, 0.0], 1.0)


# ---------------------------------------------------------------------------------------------
# Ring map and demo report
# ---------------------------------------------------------------------------------------------


def _ring_candidates(count: int = 9, radius: float = 1.5):
    """Candidate 0 = the camera (origin); the rest on a ring around a target 3 m ahead, camera height."""
    center = np.array([0.0, LEVEL_OFFSET, 3.0])
    angles = np.linspace(0.0, 2.0 * np.pi, count - 1, endpoint=False) + np.pi
    ring = np.stack([radius * np.sin(angles), np.zeros_like(angles), center[2] + radius * np.cos(angles)], axis=1)
    positions = np.concatenate([np.zeros((1, 3)), ring], axis=0)
    rotations = np.stack([_rotation_y(a) for a in np.concatenate([[0.0], angles + np.pi])])
    scores = np.linspace(0.2, 0.9, count)
    feasible = np.ones(count, dtype=bool)
    feasible[[2, 5]] = False
    return positions, rotations, scores, feasible, center


def _scene_points():
    rng = np.random.default_rng(0)
    target = np.array([0.0, 0.4, 3.0]) + rng.normal(scale=[0.15, 0.4, 0.1], size=(800, 3))
    wall = np.stack([rng.uniform(-1, 1, 3000), rng.uniform(0.0, 1.2, 3000), np.full(3000, 2.2)], axis=1)
    floor = np.stack([rng.uniform(-3, 3, 30000), np.full(30000, 1.19), rng.uniform(0, 6, 30000)], axis=1)
    return target, np.concatenate([wall, floor])


def test_plot_ring_top_down_writes_png(tmp_path):
    positions, rotations, scores, feasible, center = _ring_candidates()
    target, background = _scene_points()
    path = str(tmp_path / "ring.png")
    returned = plot_ring_top_down(
        path, positions, scores, feasible, 7, center, target, background, LEVEL_NORMAL, LEVEL_OFFSET,
        title="ring", candidate_rotations=rotations,
    )
    assert returned == path
    image = cv2.imread(path)
    assert image is not None and image.shape[0] >= 400 and image.shape[1] >= 400
    assert image.std() > 10  # not a blank canvas
    assert sorted(os.listdir(tmp_path)) == ["ring.png"]  # no temporary left behind


def test_plot_ring_rejects_bad_chosen_index(tmp_path):
    positions, _, scores, feasible, center = _ring_candidates()
    with pytest.raises(report_files.ReportError, match="chosen_index"):
        plot_ring_top_down(
            str(tmp_path / "x.png"), positions, scores, feasible, 99, center, None, None, LEVEL_NORMAL, LEVEL_OFFSET
        )


def _demo_candidates(chosen: int = 7) -> ViewCandidatesArrays:
    positions, rotations, scores, feasible, center = _ring_candidates()
    count = len(scores)
    terms = np.stack([np.linspace(0.5, 1.0, count), np.linspace(0.01, 0.09, count), np.linspace(0.3, 0.95, count)],
                     axis=1)
    return ViewCandidatesArrays(
        rotations=rotations, positions=positions, term_names=["visibility", "area", "occlusion"],
        term_weights=np.array([0.2, 0.3, 0.5]), term_scores=terms, score=scores, feasible=feasible,
        infeasible_reason=(~feasible).astype(np.uint8), chosen_index=chosen, includes_current_view=True,
        ring_center=center, ring_radius=1.5)


def _demo_frames():
    target, background = _scene_points()
    rgb = np.full((120, 160, 3), 90, dtype=np.uint8)
    mask = np.zeros((120, 160), dtype=bool)
    mask[30:90, 60:100] = True
    goal_frame = DemoFrame(
        index=4, stamp_ns=1_700_000_000_123_456_789, rgb=rgb, box=(55, 25, 105, 95), mask=mask,
        candidates=_demo_candidates(), ground=GroundPlaneArrays(LEVEL_NORMAL, LEVEL_OFFSET, True),
        target_points=target, background_points=background, latency_ms=123.4)
    no_goal_frame = DemoFrame(
        index=5, stamp_ns=1_700_000_000_223_456_789, rgb=rgb, background_points=background, latency_ms=80.0,
        ground=GroundPlaneArrays(LEVEL_NORMAL, LEVEL_OFFSET, False))
    return [goal_frame, no_goal_frame]


def test_write_demo_report(tmp_path):
    frames = _demo_frames()
    path = write_demo_report(str(tmp_path), frames, {"bag": "demo.mcap", "frames": 2, "fps": 3.61})
    assert path == str(tmp_path / "report.md")
    text = open(path, encoding="utf-8").read()
    assert "| bag | demo.mcap |" in text and "| fps | 3.61 |" in text
    candidates = frames[0].candidates
    chosen = 7
    assert "- chosen view: 7" in text
    x, y, z = candidates.positions[chosen]
    assert f"({x:.3f}, {y:.3f}, {z:.3f}) m" in text
    assert (
        f"visibility {candidates.term('visibility')[chosen]:.3f} / area {candidates.term('area')[chosen]:.3f} / "
        f"occlusion {candidates.term('occlusion')[chosen]:.3f} / score {candidates.score[chosen]:.3f}"
    ) in text
    gain = candidates.score[chosen] - candidates.score[0]
    assert f"gain over the current view: {gain:+.3f}" in text
    assert "candidates: 9 (7 feasible)" in text
    assert "## Frame 5" in text and "no goal for this frame" in text.split("## Frame 5")[1]
    # Pictures: embedded relative links, and valid PNGs on disk.
    for name in ("frame_004_overlay.png", "frame_004_ring.png", "frame_005_overlay.png"):
        assert f"]({name})" in text
        image = cv2.imread(str(tmp_path / name))
        assert image is not None and min(image.shape[:2]) >= 100
    assert not (tmp_path / "frame_005_ring.png").exists()
    # The overlay PNG is the RGB overlay stored as BGR: the tint is green in both.
    overlay_bgr = cv2.imread(str(tmp_path / "frame_004_overlay.png"))
    assert overlay_bgr[60, 80, 1] > overlay_bgr[60, 80, 0] and overlay_bgr[60, 80, 1] > overlay_bgr[60, 80, 2]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["summary"]["fps"] == 3.61
    first, second = summary["frames"]
    assert first["chosen_index"] == 7 and first["goal"] is True
    assert first["chosen_scores"]["score"] == pytest.approx(candidates.score[chosen])
    assert first["chosen_scores"]["s_area"] == pytest.approx(candidates.term("area")[chosen])
    assert list(first["chosen_scores"]) == ["s_visibility", "s_area", "s_occlusion", "score"]
    assert first["score_gain"] == pytest.approx(gain)
    assert second["goal"] is False and second["chosen_index"] is None
    assert not [name for name in os.listdir(tmp_path) if ".tmp" in name]


def test_write_demo_report_infeasible_everywhere_says_no_goal(tmp_path):
    frames = _demo_frames()[:1]
    frames[0].candidates = _demo_candidates(chosen=-1)
    text = open(write_demo_report(str(tmp_path), frames, {}), encoding="utf-8").read()
    assert "no goal for this frame**: no feasible candidate" in text
    assert "chosen view" not in text


def test_write_demo_report_names_a_bad_chosen_index(tmp_path):
    frame = _demo_frames()[0]
    frame.candidates = _demo_candidates(chosen=42)
    frame.ground = None
    with pytest.raises(report_files.ReportError, match="frame 4: chosen_index 42"):
        write_demo_report(str(tmp_path), [frame], {})


# ---------------------------------------------------------------------------------------------
# Task table
# ---------------------------------------------------------------------------------------------


def _crafted_run() -> EvaluationRun:
    def row(before, after, area_before, area_after, error, success, raw=(0.2, 0.3, False)):
        return MethodResult(
            chosen_index=3, pose=PoseRecord([0.0, 0.0, 1.2], 0.0, 5.0),
            before=ViewMetrics(before, raw[0], area_before, area_before + 500),
            after=ViewMetrics(after, raw[1], area_after, area_after + 500), success=success, raw_success=raw[2],
            pa_mpvpe_mm=error)

    def scene(seed, occlusion, leap, stay, latency):
        return SceneResult(
            seed=seed, scene_index=seed - 11, stamp_ns=seed, start_occlusion=occlusion,
            start_pose=PoseRecord([0.0, 0.0, 1.2], 0.0, 5.0), graph_failure=None, graph_area_before_px=9000,
            before=leap.before, pa_mpvpe_before_mm=float(seed) * 5.0,
            graph_vs_truth=GraphVsTruth([0.0] * 3, [0.0] * 3, [0.0] * 3, 1.2),
            candidates=None, candidate_views=None, per_method={"leap_nbv": leap, "stay": stay}, latency_ms=latency)

    # Success comes with each row, decided when the episode was scored (here: by hand, on purpose
    # not the rule for seed 12's leap_nbv, to show the report never recomputes it).
    scenes = [
        scene(11, 0.40, row(0.50, 0.60, 10000, 20000, 40.0, True, raw=(0.2, 0.35, True)),
              row(0.50, 0.50, 10000, 10000, None, False), {"detector": [10.0, 20.0], "end_to_end": [100.0] * 5}),
        scene(12, 0.55, row(0.50, 0.59, 12000, 15000, 50.0, True), row(0.50, 0.51, 12000, 12000, None, False),
              {"detector": [30.0], "end_to_end": [100.0] * 4}),
        scene(13, 0.20, row(0.85, 0.90, 14000, 25000, None, True), row(0.85, 0.86, 14000, 14000, None, False),
              {"detector": [40.0], "end_to_end": [200.0]}),
    ]
    return EvaluationRun(methods=["leap_nbv", "stay"], default_method="leap_nbv", stages=["detector", "end_to_end"],
                         scenes=scenes, ready_s=3.5, scenes_wall_s=30.0, total_wall_s=40.0)


def test_task_table_aggregates_match_hand_computed(tmp_path):
    run = _crafted_run()
    path = write_task_table(str(tmp_path), run)
    assert path == str(tmp_path / "results.md")
    payload = json.loads((tmp_path / "results.json").read_text())
    leap = payload["per_method"]["leap_nbv"]
    # Hand-computed: coverage (50+50+85)/3 = 61.667 -> (60+59+90)/3 = 69.667; area 12k -> 20k;
    # PA-MPVPE over the two scenes that have it: 45; successes as flagged: 3 of 3.
    assert leap["scenes"] == 3
    assert leap["coverage_before_pct"] == pytest.approx(185.0 / 3.0)
    assert leap["coverage_after_pct"] == pytest.approx(209.0 / 3.0)
    assert leap["area_before_kpx"] == pytest.approx(12.0)
    assert leap["area_after_kpx"] == pytest.approx(20.0)
    assert leap["pa_mpvpe_mm"] == pytest.approx(45.0) and leap["pa_mpvpe_scenes"] == 2
    # Before: the start views' meshes of the same two scenes (seeds 11 and 12: 55 and 60 mm).
    assert leap["pa_mpvpe_before_mm"] == pytest.approx(57.5)
    assert leap["successes"] == 3 and leap["success_rate_pct"] == pytest.approx(100.0)
    stay = payload["per_method"]["stay"]
    assert stay["successes"] == 0 and stay["success_rate_pct"] == 0.0
    assert stay["pa_mpvpe_mm"] is None and stay["pa_mpvpe_before_mm"] is None  # NaN becomes null: plain JSON
    assert stay["coverage_after_pct"] == pytest.approx((50 + 51 + 86) / 3.0)
    assert [scene["per_method"]["leap_nbv"]["success"] for scene in payload["scenes"]] == [True, True, True]
    # Latency: numpy linear percentiles over every scene's samples.
    assert payload["latency_ms"]["detector"]["p50"] == pytest.approx(25.0)
    assert payload["latency_ms"]["detector"]["n"] == 4
    assert payload["latency_ms"]["end_to_end"]["p95"] == pytest.approx(155.0)

    text = open(path, encoding="utf-8").read()
    assert "| leap_nbv | 3 | 61.7 -> 69.7 | 12.0 -> 20.0 | 57.5 -> 45.0 | 100.0 |" in text
    assert "| stay | 3 | 61.7 -> 62.3 | 12.0 -> 12.0 | n/a | 0.0 |" in text
    assert "| detector | 25.0 | 38.5 | 39.7 | 25.0 | 4 |" in text
    assert "| 12 | 55 | 50.0 -> 59.0 ok | 50.0 -> 51.0 |" in text
    assert "| 11 | 40 | 50.0 -> 60.0 ok |" in text
    headline = task_table_markdown(run)
    assert headline in text and headline.count("\n") == 4  # header, rule, two methods
    for name in ("coverage_per_scene.png", "success_rate.png", "latency.png"):
        image = cv2.imread(str(tmp_path / name))
        assert image is not None and image.shape[0] >= 200 and image.shape[1] >= 300
        assert f"]({name})" in text


def test_raw_coverage_table_reads_the_raw_coverage_and_its_success():
    run = _crafted_run()
    raw = aggregate_task_results(run, coverage="raw")["per_method"]["leap_nbv"]
    assert raw["coverage_before_pct"] == pytest.approx(20.0)
    assert raw["coverage_after_pct"] == pytest.approx(100.0 * (0.35 + 0.3 + 0.3) / 3.0)
    assert raw["successes"] == 1
    assert "| leap_nbv | 3 | 20.0 -> 31.7 |" in task_table_markdown(run, coverage="raw")
    with pytest.raises(report_files.ReportError, match="coverage"):
        aggregate_task_results(run, coverage="volume")


def test_evaluation_outputs(tmp_path):
    run = _crafted_run()
    run.scenes[1].graph_failure = "no person detected"
    write_evaluation_outputs(str(tmp_path), run)
    for name in ("results.md", "results.json", "chosen_views.json", "evaluation.md", "run.json"):
        assert (tmp_path / name).exists(), name
    assert EvaluationRun.read(str(tmp_path / "run.json")) == run
    summary = (tmp_path / "evaluation.md").read_text()
    assert summary == evaluation_summary_markdown(run)
    assert "Scenes: 3 (seeds 11, 12, 13)" in summary
    assert "wall time 40.0 s (graph ready in 3.5 s, scenes 30.0 s)" in summary
    assert "- seed 12: no person detected" in summary
    views = json.loads((tmp_path / "chosen_views.json").read_text())
    assert views[0] == json.loads(json.dumps(chosen_views_record(run.scenes[0])))
    assert list(views[0]) == ["seed", "stamp_ns", "start_occlusion", "start_pose", "graph_failure",
                              "graph_area_before_px", "before", "pa_mpvpe_before_mm", "graph_vs_truth", "per_method"]
    assert views[0]["per_method"]["leap_nbv"] == {"chosen_index": 3, "pose": {"position_m": [0.0, 0.0, 1.2],
                                                                               "heading_deg": 0.0, "pitch_deg": 5.0},
                                                  "after": {"surface_coverage": 0.6, "raw_coverage": 0.35,
                                                            "area_px": 20000, "person_pixels": 20500},
                                                  "success": True}


def test_task_table_rejects_an_unknown_default_method(tmp_path):
    run = _crafted_run()
    run.default_method = "oracle"
    with pytest.raises(report_files.ReportError, match="default method 'oracle'"):
        write_task_table(str(tmp_path), run)


# ---------------------------------------------------------------------------------------------
# Atomic writes
# ---------------------------------------------------------------------------------------------


def test_failing_plot_leaves_previous_png_intact(tmp_path, monkeypatch):
    positions, _, scores, feasible, center = _ring_candidates()
    path = str(tmp_path / "ring.png")
    plot_ring_top_down(path, positions, scores, feasible, 3, center, None, None, LEVEL_NORMAL, LEVEL_OFFSET)
    good = open(path, "rb").read()

    from matplotlib.figure import Figure

    def broken_savefig(self, filename, **kwargs):
        with open(filename, "wb") as stream:
            stream.write(b"\x89PNG half")  # a partial file, then the failure
        raise RuntimeError("disk full")

    monkeypatch.setattr(Figure, "savefig", broken_savefig)
    with pytest.raises(RuntimeError, match="disk full"):
        plot_ring_top_down(path, positions, scores[::-1], feasible, 5, center, None, None, LEVEL_NORMAL, LEVEL_OFFSET)
    assert open(path, "rb").read() == good
    assert cv2.imread(path) is not None
    assert os.listdir(tmp_path) == ["ring.png"]


def test_failing_image_write_leaves_previous_overlay_intact(tmp_path, monkeypatch):
    frames = _demo_frames()[1:]
    write_demo_report(str(tmp_path), frames, {})
    overlay = tmp_path / "frame_005_overlay.png"
    good = overlay.read_bytes()
    monkeypatch.setattr(report_files.cv2, "imwrite", lambda *args, **kwargs: False)
    frames[0].rgb = np.zeros_like(frames[0].rgb)
    with pytest.raises(report_files.ReportError, match="imwrite"):
        write_demo_report(str(tmp_path), frames, {})
    assert overlay.read_bytes() == good
    assert not [name for name in os.listdir(tmp_path) if ".tmp" in name]
