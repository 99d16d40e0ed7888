"""ground_node's floor decision without ROS (leapnbv_geometry.floor_fusion).

Pose floors by stamp, the fusion with the pose floor of exactly the frame's stamp, the planes' tally.
"""

from __future__ import annotations

import numpy as np
import pytest

from leapnbv_geometry.floor_fusion import FALLBACK_LOG_EVERY, FloorTally, PoseFloors, fuse_with_pose_floor
from leapnbv_geometry.ground import (
    FLOOR_POSE_REFUSED_RANSAC,
    FLOOR_RANSAC,
    FLOOR_RANSAC_CONFIRMED,
    GroundPlaneError,
    GroundPlaneResult,
)

# A camera 1.3 m above the floor looking along the world's x axis (optical z forward, y down).
LEVEL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
UP_IN_CAMERA = np.array([0.0, -1.0, 0.0])


def ransac(normal, offset, valid=True) -> GroundPlaneResult:
    normal = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    return GroundPlaneResult(valid, normal, offset, np.zeros(0, bool), 300, 0.3, 0.0)


def test_pose_floors_keep_each_poses_floor_under_its_stamp():
    floors = PoseFloors(capacity=2)
    assert not floors.seen and floors.at(1) is None
    floors.add(1, LEVEL, np.array([0.0, 0.0, 1.3]))
    stamp, normal, offset = floors.at(1)
    assert stamp == 1 and floors.seen
    np.testing.assert_allclose(normal, UP_IN_CAMERA, atol=1e-12)
    assert offset == pytest.approx(1.3)
    floors.add(2, LEVEL, np.array([0.0, 0.0, 1.4]))
    floors.add(3, LEVEL, np.array([0.0, 0.0, 1.5]))
    assert floors.at(1) is None and floors.at(3)[2] == pytest.approx(1.5)  # the newest two


def test_a_camera_below_the_floor_is_refused_and_not_counted_as_seen():
    floors = PoseFloors()
    with pytest.raises(GroundPlaneError):
        floors.add(1, LEVEL, np.array([0.0, 0.0, -0.2]))
    assert not floors.seen and floors.at(1) is None


def test_only_the_pose_floor_of_the_frames_own_stamp_checks_its_plane():
    wrong = ransac([0.0, -1.0, 0.3], 0.6)  # a box top, tilted: the pose refuses it
    pose_floor = (7, UP_IN_CAMERA, 1.3)
    floor, used = fuse_with_pose_floor(wrong, 7, pose_floor, 2.0, 0.05, 0.2)
    assert used == 7 and floor.from_pose and floor.decision == FLOOR_POSE_REFUSED_RANSAC
    assert floor.offset == pytest.approx(1.3)
    floor, used = fuse_with_pose_floor(wrong, 8, pose_floor, 2.0, 0.05, 0.2)  # another frame's pose
    assert used is None and not floor.from_pose and floor.decision == FLOOR_RANSAC
    floor, used = fuse_with_pose_floor(ransac(UP_IN_CAMERA, 1.31), 7, pose_floor, 2.0, 0.05, 0.2)
    assert used == 7 and floor.decision == FLOOR_RANSAC_CONFIRMED and floor.offset == pytest.approx(1.31)


def test_the_tally_counts_sources_and_decisions_and_logs_the_first_fallback_then_every_hundredth():
    tally = FloorTally()
    tally.plane_out("ransac", FLOOR_RANSAC)
    tally.plane_out("camera_pose", FLOOR_POSE_REFUSED_RANSAC)
    tally.plane_out("none", "none")
    assert tally.values() == [
        ("last_plane_source", "none"), ("last_floor_decision", "none"),
        ("planes.camera_pose", "1"), ("floor.camera_pose_refused_ransac", "1"), ("floor.none", "1"),
        ("floor.ransac", "1"), ("planes.none", "1"), ("planes.ransac", "1")]
    logged = [tally.fallback() for _ in range(2 * FALLBACK_LOG_EVERY + 1)]
    assert [i for i, log in enumerate(logged) if log] == [0, FALLBACK_LOG_EVERY, 2 * FALLBACK_LOG_EVERY]
    assert tally.fallbacks == 2 * FALLBACK_LOG_EVERY + 1
