"""Tests of S_v, S_a, S_o, the weighted score and the choice of the next-best view."""

from __future__ import annotations

import numpy as np
import pytest

from leapnbv_planner.candidates import (
    CandidateRingParams,
    FeasibilityReason,
    camera_look_at,
    check_feasibility,
    generate_candidates,
)
from leapnbv_planner.score_terms.area import bounding_box_area_fraction
from leapnbv_planner.scoring import choose_best
from leapnbv_planner.scoring import score_candidates as _score_candidates

LEVEL_NORMAL = np.array([0.0, -1.0, 0.0])
FLOOR_Y = 1.2  # camera 1.2 m above a level floor: plane n.x + d = 0 with d = 1.2
WIDTH, HEIGHT = 320, 240
K_SMALL = np.array([[300.0, 0.0, 160.0], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]])
IDENTITY_POSE = (np.eye(3)[None], np.zeros((1, 3)))




# The paper's three terms, which these tests check (the deployed default scores body_occlusion instead of occlusion).
PAPER_TERMS = [("visibility", 0.03), ("area", 0.14), ("occlusion", 0.83)]


def score_candidates(*args, **kwargs):
    kwargs.setdefault("terms", PAPER_TERMS)
    return _score_candidates(*args, **kwargs)

def single_ring(**values) -> CandidateRingParams:
    """One ring, no path search: the geometry these tests check by hand (the robot's defaults add rings and
    reachability, tested in test_planner_reachability)."""
    return CandidateRingParams(**{"num_rings": 1, "reachability": False, **values})

def person_cloud(rng, center_xz=(0.0, 3.0), count=3000):
    """Points filling a 0.2 m-radius, 1.7 m-tall cylinder standing on the floor."""
    angle = rng.uniform(0, 2 * np.pi, count)
    radius = 0.2 * np.sqrt(rng.uniform(0, 1, count))
    y = rng.uniform(FLOOR_Y - 1.7, FLOOR_Y, count)
    return np.stack([center_xz[0] + radius * np.cos(angle), y,
                     center_xz[1] + radius * np.sin(angle)], axis=1)


def test_no_background_means_nothing_is_hidden():
    rng = np.random.default_rng(1)
    target = person_cloud(rng)
    candidates = generate_candidates(np.median(target, axis=0), LEVEL_NORMAL, FLOOR_Y,
                                     single_ring(radius=2.5))
    scores = score_candidates(target, np.zeros((0, 3)), candidates.rotations,
                              candidates.positions, K_SMALL, WIDTH, HEIGHT)
    assert (scores.term("visibility") > 0.5).all()
    np.testing.assert_array_equal(scores.term("occlusion"), 1.0)


def test_wall_hides_the_target_from_half_the_ring_and_the_open_side_wins():
    rng = np.random.default_rng(2)
    target = person_cloud(rng)
    centroid = np.median(target, axis=0)
    params = single_ring(num_candidates=16, radius=1.5, max_travel=10.0)
    candidates = generate_candidates(centroid, LEVEL_NORMAL, FLOOR_Y, params)
    center = candidates.ring_center
    # A curved wall, radius 0.9 m around the target, over the +x half (-80..80 deg), from
    # the floor to 1.5 m above the camera, sampled every ~1.5 cm: dense enough that every
    # target pixel of a view through it has a wall pixel within 4 px.
    angles = np.arange(-np.deg2rad(80), np.deg2rad(80), 0.015 / 0.9)
    heights = np.arange(-1.5, FLOOR_Y, 0.015)
    angle_grid, y_grid = np.meshgrid(angles, heights)
    wall = np.stack([center[0] + 0.9 * np.cos(angle_grid).ravel(), y_grid.ravel(),
                     center[2] + 0.9 * np.sin(angle_grid).ravel()], axis=1)
    scores = score_candidates(target, wall, candidates.rotations, candidates.positions,
                              K_SMALL, WIDTH, HEIGHT)
    foot_x = candidates.foot_points[:, 0] - center[0]
    behind_wall = foot_x > 1.5 * np.cos(np.deg2rad(60))
    open_side = foot_x < -0.3
    assert behind_wall.sum() >= 5 and open_side.sum() >= 5
    assert (scores.term("occlusion")[behind_wall] < 0.05).all()
    assert (scores.term("occlusion")[open_side] > 0.95).all()

    feasible, _ = check_feasibility(candidates, wall, LEVEL_NORMAL, FLOOR_Y, params)
    assert feasible.all()  # the wall is 0.6 m inside the ring: no footprint touches it
    chosen = choose_best(scores.score, feasible, candidates.positions, np.zeros(3))
    assert open_side[chosen]
    assert scores.term("occlusion")[chosen] > 0.95


def test_obstacle_at_the_best_candidate_moves_the_choice():
    rng = np.random.default_rng(3)
    target = person_cloud(rng)
    params = single_ring(num_candidates=16, radius=1.5, max_travel=10.0)
    candidates = generate_candidates(np.median(target, axis=0), LEVEL_NORMAL, FLOOR_Y, params)
    scores = score_candidates(target, np.zeros((0, 3)), candidates.rotations,
                              candidates.positions, K_SMALL, WIDTH, HEIGHT)
    free = np.ones(len(candidates), dtype=bool)
    best = choose_best(scores.score, free, candidates.positions, np.zeros(3))
    assert best > 0  # a ring view (closer, larger S_a) beats the current one
    # A 1 m tall post 0.1 m from that candidate's foot point (points above the clearance).
    post = candidates.foot_points[best] + np.array([0.1, 0.0, 0.0]) + np.outer(
        np.linspace(0.1, 1.0, 10), LEVEL_NORMAL)
    scores_with_post = score_candidates(target, post, candidates.rotations,
                                        candidates.positions, K_SMALL, WIDTH, HEIGHT)
    assert scores_with_post.score[best] == pytest.approx(scores.score[best])  # still scores best
    feasible, reasons = check_feasibility(candidates, post, LEVEL_NORMAL, FLOOR_Y, params)
    assert not feasible[best] and reasons[best] == FeasibilityReason.OBSTACLE
    assert feasible.sum() == len(candidates) - 1
    chosen = choose_best(scores_with_post.score, feasible, candidates.positions, np.zeros(3))
    assert chosen != best and feasible[chosen]
    # Out of range too: with a 1 m travel limit only the current view remains.
    short = single_ring(num_candidates=16, radius=1.5, max_travel=1.0)
    feasible_short, reasons_short = check_feasibility(candidates, post, LEVEL_NORMAL, FLOOR_Y,
                                                      short)
    assert feasible_short.tolist() == [True] + [False] * 16
    assert (reasons_short[1:] == FeasibilityReason.OUT_OF_TRAVEL_RANGE).all()
    assert choose_best(scores_with_post.score, feasible_short, candidates.positions,
                       np.zeros(3)) == 0


def test_closer_ring_raises_area_score():
    rng = np.random.default_rng(4)
    # A 0.3 m cube of points 3 m ahead, so the projected box stays inside the image.
    target = rng.uniform(-0.15, 0.15, size=(2000, 3)) + np.array([0.0, 0.4, 3.0])
    centroid = np.median(target, axis=0)
    near = generate_candidates(centroid, LEVEL_NORMAL, FLOOR_Y, single_ring(radius=1.0))
    far = generate_candidates(centroid, LEVEL_NORMAL, FLOOR_Y, single_ring(radius=2.0))
    s_near = score_candidates(target, np.zeros((0, 3)), near.rotations, near.positions,
                              K_SMALL, WIDTH, HEIGHT).term("area")[1:]
    s_far = score_candidates(target, np.zeros((0, 3)), far.rotations, far.positions,
                             K_SMALL, WIDTH, HEIGHT).term("area")[1:]
    assert (s_near < 1.0).all() and (s_far > 0.0).all()
    assert (s_near > 1.5 * s_far).all()


def test_visibility_weight_alone_follows_visibility():
    rng = np.random.default_rng(5)
    target = person_cloud(rng, count=2000)
    centroid = np.median(target, axis=0)
    # Poses at assorted distances and aims: some see the whole person, some only part.
    rotations, positions = [], []
    for _ in range(24):
        bearing = rng.uniform(0, 2 * np.pi)
        distance = rng.uniform(0.6, 3.0)
        position = centroid + np.array([distance * np.cos(bearing), rng.uniform(-0.6, 0.3),
                                        distance * np.sin(bearing)])
        aim = centroid + rng.normal(scale=0.5, size=3)
        rotations.append(camera_look_at(position, aim, LEVEL_NORMAL))
        positions.append(position)
    rotations, positions = np.array(rotations), np.array(positions)
    scores = score_candidates(target, rng.uniform(-3, 3, size=(3000, 3)), rotations, positions,
                              K_SMALL, WIDTH, HEIGHT, terms=[("visibility", 1.0), ("area", 0.0), ("occlusion", 0.0)])
    np.testing.assert_array_equal(scores.score, scores.term("visibility"))
    assert np.ptp(scores.term("visibility")) > 0.3
    feasible = rng.uniform(size=24) < 0.6
    feasible[int(np.argmax(scores.term("visibility")))] = False  # the overall best is ruled out
    chosen = choose_best(scores.score, feasible, positions, np.zeros(3))
    assert feasible[chosen]
    assert scores.term("visibility")[chosen] == scores.term("visibility")[feasible].max()


def test_choose_best_ties_go_to_the_nearest_and_nothing_feasible_gives_minus_one():
    positions = np.array([[0.0, 0, 0], [3.0, 0, 0], [1.0, 0, 0], [0.5, 0, 0]])
    scores = np.array([0.2, 0.9, 0.9 - 1e-12, 0.95])
    feasible = np.array([True, True, True, False])
    assert choose_best(scores, feasible, positions, np.zeros(3)) == 2
    assert choose_best(scores, np.zeros(4, dtype=bool), positions, np.zeros(3)) == -1
    assert choose_best(np.array([np.nan, 0.1]), np.ones(2, dtype=bool), positions[:2],
                       np.zeros(3)) == 1


def test_visibility_closed_form():
    target = np.array([[0.0, 0.0, 2.0], [0.1, 0.1, 3.0], [-0.2, 0.1, 2.5], [0.0, 0.0, 4.0]])
    full = score_candidates(target, np.zeros((0, 3)), *IDENTITY_POSE, K_SMALL, WIDTH, HEIGHT)
    assert full.term("visibility")[0] == 1.0
    # Two points behind the camera, one to the right outside the image (u = 160 + 300*2 > W).
    mixed = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, -2.0], [0.1, 0.0, -1.0], [2.0, 0.0, 1.0]])
    partial = score_candidates(mixed, np.zeros((0, 3)), *IDENTITY_POSE, K_SMALL, WIDTH, HEIGHT)
    assert partial.term("visibility")[0] == 0.25
    assert partial.term("occlusion")[0] == 1.0  # over in-view points only
    none = score_candidates(mixed[1:3], np.zeros((0, 3)), *IDENTITY_POSE, K_SMALL, WIDTH, HEIGHT)
    assert none.term("visibility")[0] == 0.0 and none.term("occlusion")[0] == 0.0


def box_corners(lower, upper):
    """The 8 corners of an axis-aligned box as points."""
    return np.array([[x, y, z] for x in (lower[0], upper[0]) for y in (lower[1], upper[1])
                     for z in (lower[2], upper[2])])


K_AREA = np.array([[100.0, 0.0, 100.0], [0.0, 100.0, 50.0], [0.0, 0.0, 1.0]])


def test_area_of_a_box_in_front_is_its_known_rectangle():
    # Box x in [-1, 1], y in [-0.5, 0.5], z in [2, 3]: its near face projects to
    # u in [50, 150], v in [25, 75] -> 100 x 50 px of a 200 x 100 image = 0.25.
    points = box_corners([-1.0, -0.5, 2.0], [1.0, 0.5, 3.0])
    area = bounding_box_area_fraction(points, *IDENTITY_POSE, K_AREA, 200, 100)
    assert area[0] == pytest.approx(0.25, abs=1e-12)
    # The same box seen from 1 m further back: u in [100 - 100/3, 100 + 100/3], v in
    # [50 - 50/3, 50 + 50/3] -> (200/3) * (100/3) / 20000.
    shifted = bounding_box_area_fraction(points, np.eye(3)[None], np.array([[0.0, 0.0, -1.0]]),
                                         K_AREA, 200, 100)
    assert shifted[0] == pytest.approx((200 / 3) * (100 / 3) / 20000, abs=1e-12)


def test_area_of_a_box_reaching_behind_the_camera_extends_to_the_border():
    # x in [0.5, 1], z in [-1, 2]: clipped at the near plane the box runs off to u -> +inf,
    # and v -> +-inf, so the rectangle is u in [100 + 100*0.5/2, 200] x v in [0, 100].
    points = box_corners([0.5, -0.5, -1.0], [1.0, 0.5, 2.0])
    area = bounding_box_area_fraction(points, *IDENTITY_POSE, K_AREA, 200, 100)
    assert area[0] == pytest.approx(75 * 100 / 20000, abs=1e-9)
    behind = bounding_box_area_fraction(points - [0, 0, 5], *IDENTITY_POSE, K_AREA, 200, 100)
    assert behind[0] == 0.0
    around = bounding_box_area_fraction(box_corners([-5, -5, 0.5], [5, 5, 1]), *IDENTITY_POSE,
                                        K_AREA, 200, 100)
    assert around[0] == 1.0


def test_occlusion_definition_on_hand_placed_points():
    # Target at pixel (160, 120), depth 2, plus a far point at pixel (235, 120), depth 4,
    # which nothing below hides (so every answer is 1 or 0.5). K_SMALL: 1 px at depth z is
    # z/300 m.
    target = np.array([[0.0005, 0.0005, 2.0], [1.0005, 0.0005, 4.0]])

    def s_o(background):
        both = score_candidates(target, np.array(background), *IDENTITY_POSE, K_SMALL,
                                WIDTH, HEIGHT, delta_px=4.0).term("occlusion")[0]
        return 2.0 * both - 1.0  # S_o of the first point alone

    px = 1.0 / 300.0  # metres per pixel at depth 1
    assert s_o([[0.0005, 0.0005, 2.0]]) == 1.0  # same depth: not hidden (<=)
    assert s_o([[0.0005, 0.0005, 1.999]]) == 0.0  # nearer, same pixel: hidden
    assert s_o([[4 * px + 0.0005, -4 * px + 0.0005, 1.0]]) == 0.0  # 4 px diagonal: in window
    assert s_o([[5 * px + 0.0005, 0.0005, 1.0]]) == 1.0  # 5 px right: outside the window
    assert s_o([[0.0005, 0.0005, -1.0]]) == 1.0  # behind the camera: ignored
    assert s_o([[0.0005, 0.0005, 3.0]]) == 1.0  # farther: no effect


def brute_force_occlusion(target, background, rotations, positions, K, width, height,
                          half_window):
    """S_o by definition: for each in-view target point, compare with every background point."""
    fx, skew, cx = K[0]
    fy, cy = K[1, 1], K[1, 2]
    result = []
    def project(points, rotation, position):
        cam = (points - position) @ rotation
        with np.errstate(divide="ignore", invalid="ignore"):
            u = fx * (cam[:, 0] / cam[:, 2]) + skew * (cam[:, 1] / cam[:, 2]) + cx
            v = fy * (cam[:, 1] / cam[:, 2]) + cy
        return cam[:, 2], u, v

    for rotation, position in zip(rotations, positions):
        z_t, u_t, v_t = project(target, rotation, position)
        z_b, u_b, v_b = project(background, rotation, position)
        in_front_b = z_b > 0
        in_view = 0
        not_hidden = 0
        for k in range(len(target)):
            if not (z_t[k] > 0 and 0 <= u_t[k] < width and 0 <= v_t[k] < height):
                continue
            in_view += 1
            near = (in_front_b
                    & (np.abs(np.floor(u_b) - np.floor(u_t[k])) <= half_window)
                    & (np.abs(np.floor(v_b) - np.floor(v_t[k])) <= half_window))
            if not near.any() or z_t[k] <= z_b[near].min():
                not_hidden += 1
        result.append(not_hidden / in_view if in_view else 0.0)
    return np.array(result)


@pytest.mark.parametrize("delta_px", [4.0, 2.5, 0.0])
def test_occlusion_matches_brute_force_on_a_random_scene(delta_px):
    rng = np.random.default_rng(6)
    K = np.array([[250.0, 1.5, 150.0], [0.0, 240.0, 95.0], [0.0, 0.0, 1.0]])
    width, height = 300, 200
    target = rng.normal(size=(600, 3)) * [0.3, 0.6, 0.2] + [0.0, 0.2, 3.0]
    # Clutter everywhere: in front of, around and behind the target, behind the cameras,
    # and some just outside the image borders.
    background = np.concatenate([
        rng.uniform([-2, -2, -1], [2, 2, 6], size=(2500, 3)),
        rng.normal(size=(5000, 3)) * [0.4, 0.7, 0.6] + [0.0, 0.2, 2.2],
    ])
    rotations, positions = [np.eye(3)], [np.zeros(3)]
    for _ in range(7):
        position = [0.0, 0.2, 3.0] + rng.uniform([-2.5, -0.5, -2.5], [2.5, 0.5, 2.5])
        aim = np.array([0.0, 0.2, 3.0]) + rng.normal(scale=0.6, size=3)
        rotations.append(camera_look_at(position, aim, LEVEL_NORMAL))
        positions.append(position)
    rotations, positions = np.array(rotations), np.array(positions)
    fast = score_candidates(target, background, rotations, positions, K, width, height,
                            delta_px=delta_px).term("occlusion")
    slow = brute_force_occlusion(target, background, rotations, positions, K, width, height,
                                 int(np.floor(delta_px)))
    # The scene really is partly occluded, differently per view.
    assert (slow < 0.999).sum() >= 5 and slow.min() < 0.9
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-12)


def test_non_finite_points_are_dropped_and_bad_shapes_raise():
    from leapnbv_planner.scoring import ScoringInputError

    target = np.array([[0.0, 0.0, 2.0], [np.nan, 0.0, 2.0]])
    scores = score_candidates(target, np.array([[np.inf, 0, 1.0]]), *IDENTITY_POSE, K_SMALL,
                              WIDTH, HEIGHT)
    assert scores.term("visibility")[0] == 1.0 and scores.term("occlusion")[0] == 1.0
    with pytest.raises(ScoringInputError, match="target_points"):
        score_candidates(np.zeros((3, 2)), np.zeros((0, 3)), *IDENTITY_POSE, K_SMALL, WIDTH,
                         HEIGHT)
    with pytest.raises(ScoringInputError, match="positions"):
        score_candidates(target, np.zeros((0, 3)), np.eye(3)[None], np.zeros((2, 3)), K_SMALL,
                         WIDTH, HEIGHT)
