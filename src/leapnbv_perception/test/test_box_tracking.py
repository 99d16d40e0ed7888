"""Carrying a person box between frames with the mesh's image motion (leapnbv_perception.box_tracking)."""

from __future__ import annotations

import numpy as np

from leapnbv_perception.box_tracking import DetectionSchedule, camera_motion, carry_box, project
from leapnbv_perception.target_selection import box_iou

K = np.array([[520.0, 0.0, 320.0], [0.0, 520.0, 240.0], [0.0, 0.0, 1.0]])


def rotation_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def person(rng: np.random.Generator, depth: float = 3.0) -> np.ndarray:
    """A 0.5 x 1.7 x 0.3 m box of points standing 'depth' in front of the camera."""
    return rng.uniform([-0.25, -0.85, -0.15], [0.25, 0.85, 0.15], size=(2000, 3)) + [0.0, 0.0, depth]


def tight_box(points: np.ndarray, K_: np.ndarray = K) -> np.ndarray:
    uv, _ = project(points, K_)
    return np.array([uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max()])


def test_a_still_camera_keeps_the_box() -> None:
    points = person(np.random.default_rng(0))
    box = tight_box(points)
    carried = carry_box(box, points, K, K, (640, 480), camera_motion(None, None))
    np.testing.assert_allclose(carried.box, box, atol=1e-9)
    assert carried.scale == 1.0 and carried.confidence == 1.0


def test_camera_motion_moves_the_box_as_the_person_appears_in_the_new_view() -> None:
    rng = np.random.default_rng(1)
    points_a = person(rng)
    # Camera A at the origin; camera B 0.4 m to the right, 0.5 m closer, turned 5 degrees.
    pose_a = (np.eye(3), np.zeros(3))
    pose_b = (rotation_y(np.radians(5.0)), np.array([0.4, 0.0, 0.5]))
    world = points_a  # A's frame is the world frame here
    points_b = (world - pose_b[1]) @ pose_b[0]  # R_b^T (p - t_b), row vectors
    motion = camera_motion(pose_a, pose_b)
    np.testing.assert_allclose(points_a @ motion[0].T + motion[1], points_b, atol=1e-12)
    carried = carry_box(tight_box(points_a), points_a, K, K, (640, 480), motion)
    truth = tight_box(points_b)
    assert box_iou(carried.box, truth[None])[0] > 0.9, (carried.box, truth)  # scale + shift: not perspective
    assert carried.scale > 1.05  # closer: larger
    # Without the camera's motion the box would stay where it was: far from the truth.
    stay = carry_box(tight_box(points_a), points_a, K, K, (640, 480), camera_motion(None, None))
    assert box_iou(stay.box, truth[None])[0] < 0.7


def test_a_person_leaving_the_image_lowers_the_confidence_and_asks_for_the_detector() -> None:
    points = person(np.random.default_rng(2))
    pose_b = (np.eye(3), np.array([2.0, 0.0, 0.0]))  # the camera moves right: the person half leaves at the left
    carried = carry_box(tight_box(points), points, K, K, (640, 480), camera_motion((np.eye(3), np.zeros(3)), pose_b))
    assert carried is not None and carried.confidence < 0.5
    assert carried.box[2] <= 640 and carried.box[0] == 0.0
    schedule = DetectionSchedule(every_n=5, min_confidence=0.8)
    assert schedule.should_detect(None)  # nothing detected yet
    schedule.record(True)
    assert schedule.should_detect(carried)  # not trusted
    good = carry_box(tight_box(points), points, K, K, (640, 480), camera_motion(None, None))
    decisions = []
    for _ in range(9):
        detect = schedule.should_detect(good)
        decisions.append(detect)
        schedule.record(detect)
    assert decisions == [False, False, False, False, True, False, False, False, False]  # one frame in 5


def test_too_few_points_in_front_gives_no_box() -> None:
    behind = person(np.random.default_rng(3), depth=-3.0)
    assert carry_box([0, 0, 10, 10], behind, K, K, (640, 480), camera_motion(None, None)) is None
