"""Tests of the floor fusion in leapnbv_geometry.ground: RANSAC checked against the camera pose's floor,
the first frame's person boxes left out, the mounting priors, the quality figure."""

from __future__ import annotations

import numpy as np
import pytest

from leapnbv_geometry.ground import (
    FLOOR_NONE,
    FLOOR_POSE_NO_RANSAC,
    FLOOR_POSE_REFUSED_RANSAC,
    FLOOR_RANSAC,
    FLOOR_RANSAC_CONFIRMED,
    GroundPlaneError,
    GroundPlaneResult,
    box_exclusion_mask,
    expected_up,
    fit_ground_plane,
    floor_quality,
    fuse_floor,
    mounting_priors,
)


def ransac(normal, offset, valid=True, ratio=0.1) -> GroundPlaneResult:
    normal = np.asarray(normal, dtype=np.float64)
    normal = normal / np.linalg.norm(normal)
    return GroundPlaneResult(valid, normal, offset, np.zeros(0, bool), int(ratio * 1000), ratio, 0.0)


LEVEL = np.array([0.0, -1.0, 0.0])


def tilted(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([0.0, -np.cos(a), np.sin(a)])


def test_a_ransac_plane_that_agrees_with_the_pose_is_kept_and_scores_above_one_half():
    fit = ransac(tilted(1.0), 1.22, ratio=0.1)
    floor = fuse_floor(fit, (LEVEL, 1.20))
    assert floor.valid and not floor.from_pose and floor.decision == FLOOR_RANSAC_CONFIRMED
    np.testing.assert_allclose(floor.normal, fit.normal)  # RANSAC's own plane, not the pose's
    assert floor.offset == pytest.approx(1.22)
    assert floor.angle_to_pose_deg == pytest.approx(1.0, abs=1e-9)
    assert floor.height_to_pose_m == pytest.approx(0.02)
    assert floor.quality == pytest.approx(0.5 + 0.5 * 0.1 / 0.2)


@pytest.mark.parametrize("normal, offset", [(tilted(8.0), 1.20), (LEVEL, 1.30), (tilted(2.5), 1.20)])
def test_a_ransac_plane_that_disagrees_with_the_pose_is_refused(normal, offset):
    floor = fuse_floor(ransac(normal, offset), (LEVEL, 1.20))
    assert floor.valid and floor.from_pose and floor.decision == FLOOR_POSE_REFUSED_RANSAC
    np.testing.assert_allclose(floor.normal, LEVEL)
    assert floor.offset == 1.20
    assert floor.quality == 0.5


def test_the_tolerances_are_parameters():
    floor = fuse_floor(ransac(tilted(2.5), 1.20), (LEVEL, 1.20), max_angle_deg=3.0)
    assert floor.decision == FLOOR_RANSAC_CONFIRMED
    floor = fuse_floor(ransac(LEVEL, 1.30), (LEVEL, 1.20), max_height_m=0.15)
    assert floor.decision == FLOOR_RANSAC_CONFIRMED


def test_no_pose_keeps_ransac_and_no_ransac_takes_the_pose():
    alone = fuse_floor(ransac(tilted(8.0), 1.1, ratio=0.4), None)
    assert alone.valid and alone.decision == FLOOR_RANSAC and alone.quality == pytest.approx(0.5)
    assert np.isnan(alone.angle_to_pose_deg)
    pose = fuse_floor(ransac(LEVEL, 0.0, valid=False, ratio=0.0), (tilted(5.0), 1.4))
    assert pose.valid and pose.from_pose and pose.decision == FLOOR_POSE_NO_RANSAC and pose.offset == 1.4
    none = fuse_floor(ransac(LEVEL, 0.0, valid=False), None)
    assert not none.valid and none.decision == FLOOR_NONE and none.quality == 0.0


def test_quality_orders_the_sources():
    assert floor_quality(FLOOR_RANSAC, 0.05) == pytest.approx(0.125)
    assert floor_quality(FLOOR_RANSAC, 1.0) == 0.5
    assert floor_quality(FLOOR_RANSAC_CONFIRMED, 0.0) == 0.5
    assert floor_quality(FLOOR_RANSAC_CONFIRMED, 0.2) == 1.0
    assert floor_quality(FLOOR_NONE, 0.3) == 0.0


def test_expected_up_of_a_pitched_camera_and_the_mounting_priors():
    np.testing.assert_allclose(expected_up(0.0), [0.0, -1.0, 0.0], atol=1e-12)
    # looking 30 deg down, up leans back toward the camera: (0, -cos, -sin)
    np.testing.assert_allclose(expected_up(30.0), [0.0, -np.cos(np.pi / 6), -0.5], atol=1e-12)
    assert mounting_priors(0.6, 0.3) == pytest.approx((0.3, 0.9))
    assert mounting_priors(0.2, 0.3) == pytest.approx((0.0, 0.5))


def test_the_pitch_prior_finds_the_floor_of_a_camera_pitched_beyond_the_tilt_limit():
    rng = np.random.default_rng(4)
    up = expected_up(35.0)
    # floor points of a camera 1.2 m up, pitched 35 deg down: n.x + 1.2 = 0
    a = rng.uniform(-2, 2, 3000)
    b = rng.uniform(0.5, 4, 3000)
    side = np.array([1.0, 0.0, 0.0])
    along = np.cross(up, side)
    floor = a[:, None] * side + b[:, None] * along - 1.2 * up
    floor += rng.normal(0, 0.003, floor.shape)
    level = fit_ground_plane(floor, max_tilt_deg=25.0)
    assert not level.valid  # the floor is 35 deg from -y: refused by the tilt prior about -y
    pitched = fit_ground_plane(floor, max_tilt_deg=25.0, up=up)
    assert pitched.valid and pitched.offset == pytest.approx(1.2, abs=0.01)
    assert np.degrees(np.arccos(pitched.normal @ up)) < 0.5


def test_box_exclusion_mask_covers_the_grown_boxes_only():
    mask = box_exclusion_mask((40, 60), np.array([[10.0, 5.0, 20.0, 15.0, 0.9]]), grow_px=2.0)
    assert mask.shape == (40, 60) and mask.dtype == bool
    rows, cols = np.nonzero(mask)
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (3, 16, 8, 21)
    assert box_exclusion_mask((40, 60), np.zeros((0, 5))).sum() == 0
    edge = box_exclusion_mask((40, 60), np.array([[50.0, 30.0, 70.0, 50.0]]), grow_px=0.0)
    assert edge[30:, 50:].all() and edge.sum() == 10 * 10
    top = box_exclusion_mask((40, 60), np.array([[10.0, 10.0, 20.0, 30.0]]), grow_px=2.0, top_share=0.5)
    rows, cols = np.nonzero(top)
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (8, 19, 8, 21)  # the lower half stays in the fit
    with pytest.raises(GroundPlaneError, match="boxes must be"):
        box_exclusion_mask((40, 60), np.zeros((2, 3)))
