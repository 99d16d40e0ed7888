"""Tests of leapnbv_planner.reachability: the floor grid, shortest free paths, and plan_views with reachability."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from leapnbv_planner.candidates import FeasibilityReason
from leapnbv_planner.inputs import PlanFloor, PlanTarget
from leapnbv_planner.params import default_nbv_params
from leapnbv_planner.path_kernel import grid_distances
from leapnbv_planner.plan import plan_views
from leapnbv_planner.reachability import ReachabilityError, build_occupancy_grid, reachability

UP = np.array([0.0, -1.0, 0.0])  # the floor's up normal of a level camera 1.2 m above it: the floor is y = 1.2
HEIGHT = 1.2
K = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])


def foot(x: float, z: float) -> np.ndarray:
    return np.array([x, HEIGHT, z])


def wall(x0: float, x1: float, z: float, step: float = 0.05) -> np.ndarray:
    """Points of a 1 m high wall along x at depth z (heights 0.1-1.0 m above the floor)."""
    xs, hs = np.meshgrid(np.arange(x0, x1 + 1e-9, step), np.arange(0.1, 1.0, 0.1))
    return np.column_stack([xs.ravel(), HEIGHT - hs.ravel(), np.full(xs.size, z)])


def grid_for(obstacles, feet, unknown="free", camera=None, cell=0.1):
    return build_occupancy_grid(obstacles, np.zeros((0, 3)), UP, HEIGHT, np.vstack([feet, foot(0, 0)[None]]),
                                cell, 0.3, 0.05, unknown, camera)


def test_open_floor_paths_are_straight_distances():
    distances, parents = grid_distances(np.ones((5, 7), dtype=bool), 2, 0, 0.1)
    assert distances[2, 6] == pytest.approx(0.6)
    assert distances[0, 2] == pytest.approx(0.2 * np.sqrt(2.0))
    assert parents[2, 0] == -1 and parents[2, 1] == 2 * 7 + 0
    feet = np.array([foot(0.0, 3.0), foot(2.0, 0.0)])
    reach = reachability(grid_for(np.zeros((0, 3)), feet), foot(0, 0), feet, 6.0, 0.3)
    assert reach.reachable.all()
    np.testing.assert_allclose(reach.path_lengths, [3.0, 2.0], atol=0.1)


def test_a_wall_makes_the_path_go_round_it_and_a_closed_room_blocks_it():
    feet = np.array([foot(0.0, 4.0)])
    reach = reachability(grid_for(wall(-1.0, 1.0, 2.0), feet), foot(0, 0), feet, 8.0, 0.3)
    assert reach.reachable[0]
    around = 2.0 * np.hypot(1.3, 2.0)  # past the wall's end, kept 0.3 m (the robot radius) away
    assert around - 0.1 <= reach.path_lengths[0] <= around + 0.6
    path = reach.path_to(feet[0])
    np.testing.assert_allclose(path[0], foot(0, 0), atol=0.08)
    np.testing.assert_array_equal(path[-1], feet[0])
    near_wall = (np.abs(path[:, 2] - 2.0) < 0.3)
    assert np.all(np.abs(path[near_wall, 0]) > 1.0)  # it passes beyond the wall's ends, not through it
    # The same goal with a hard limit below the detour: unreachable.
    short = reachability(grid_for(wall(-1.0, 1.0, 2.0), feet), foot(0, 0), feet, 4.5, 0.3)
    assert not short.reachable[0] and np.isfinite(short.path_lengths[0])
    # Walled in: no path at all.
    room = np.vstack([wall(-6, 6, 2.0), wall(-6, 6, -2.0)] + [
        np.column_stack([np.full(200, x), np.full(200, HEIGHT - 0.5), np.linspace(-2, 2, 200)]) for x in (-1.0, 1.0)])
    boxed = reachability(grid_for(room, feet), foot(0, 0), feet, 20.0, 0.3)
    assert not boxed.reachable[0] and np.isinf(boxed.path_lengths[0]) and boxed.path_to(feet[0]) is None


def test_unknown_space_outside_the_view_is_a_parameter():
    feet = np.array([foot(0.0, -2.0), foot(0.0, 3.0)])  # behind the camera (unseen), in front (seen)
    free = reachability(grid_for(np.zeros((0, 3)), feet, "free", (K, 640, 480)), foot(0, 0), feet, 6.0, 0.3)
    assert free.reachable.tolist() == [True, True]
    blocked = reachability(grid_for(np.zeros((0, 3)), feet, "occupied", (K, 640, 480)), foot(0, 0), feet, 6.0, 0.3)
    assert blocked.reachable.tolist() == [False, True]
    with pytest.raises(ReachabilityError, match="unknown_space"):
        grid_for(np.zeros((0, 3)), feet, "maybe")


def test_plan_views_marks_candidates_behind_a_wall_unreachable_and_returns_the_path():
    # Person at 3 m in a corridor along z (walls at x = +-1.2): ring candidates beside the person are in the walls
    # or behind them; a candidate beyond the person along the corridor is reached past the person.
    rng = np.random.default_rng(0)
    person = np.column_stack([rng.uniform(-0.2, 0.2, 800), rng.uniform(-0.5, 1.1, 800), rng.uniform(2.9, 3.1, 800)])
    side = [np.column_stack([np.full(3000, x), rng.uniform(-0.5, 1.1, 3000), rng.uniform(-4.0, 9.0, 3000)])
            for x in (-1.2, 1.2)]
    background = np.vstack(side).astype(np.float32)
    target = PlanTarget(centroid=np.array([0.0, 0.3, 3.0]), target_points=person.astype(np.float32),
                        background_points=background, k=K, width=640, height=480)
    ground = PlanFloor(normal=UP, offset=HEIGHT)
    params = default_nbv_params()
    params.reachability = True
    params.num_rings, params.min_radius, params.radius = 3, 1.0, 2.5
    plan = plan_views(target, ground, params)
    reasons = plan.feasibility.reasons
    assert plan.path_lengths.shape == (len(plan.candidates),) and plan.path_lengths[0] == 0.0
    assert np.count_nonzero(reasons == int(FeasibilityReason.UNREACHABLE)) >= 6
    outside = np.abs(plan.candidates.foot_points[:, 0]) > 1.2 - 0.3
    assert not plan.feasibility.feasible[outside].any()  # nothing in or behind the corridor's walls
    assert plan.chosen_index >= 0 and plan.base_path is not None
    np.testing.assert_array_equal(plan.base_path[-1], plan.candidates.foot_points[plan.chosen_index])
    assert np.all(np.abs(plan.base_path[:, 0]) < 1.2 - 0.2)  # the path stays in the corridor
    # The path's poses: level (z up), x along the path toward the next point, right-handed; the goal's own last.
    rotations, points = plan.base_path_frames()
    np.testing.assert_array_equal(points, plan.base_path)
    np.testing.assert_array_equal(rotations[-1], plan.base_goal[0])
    up = np.asarray(UP, dtype=np.float64) / np.linalg.norm(UP)
    step = np.diff(points, axis=0)
    step -= (step @ up)[:, None] * up
    np.testing.assert_allclose(rotations[:-1, :, 0], step / np.linalg.norm(step, axis=1)[:, None], atol=1e-12)
    np.testing.assert_allclose(rotations[:, :, 2], np.broadcast_to(up, points.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-12)
    np.testing.assert_allclose(rotations.transpose(0, 2, 1) @ rotations, np.broadcast_to(np.eye(3), rotations.shape),
                               atol=1e-12)
    # Travel: the term is in the registry; scored when listed, from the path lengths.
    params.score_terms = ["visibility", "area", "occlusion", "travel"]
    plan = plan_views(target, ground, params)
    travel = plan.scores.term("travel")
    finite = np.isfinite(plan.path_lengths)
    scored = plan.feasibility.feasible  # the others are not scored: 0
    np.testing.assert_allclose(travel[scored], 1.0 - np.minimum(1.0, plan.path_lengths[scored] / 6.0))
    assert travel[0] == 1.0 and np.all(travel[~scored] == 0.0) and np.all(scored <= finite)
    every_plan = plan_views(target, ground, dataclasses.replace(params, score_infeasible=True))
    every = every_plan.scores.term("travel")
    np.testing.assert_allclose(every[finite], 1.0 - np.minimum(1.0, plan.path_lengths[finite] / 6.0))
    assert np.all(every[~finite] == 0.0)
    assert np.any(every_plan.scores.term("visibility")[~scored] > 0.0)  # the infeasible ones are scored too


def test_the_ring_rotations_are_camera_look_at_bit_for_bit():
    from leapnbv_planner.candidates import camera_look_at, generate_candidates

    params = default_nbv_params()
    params.num_rings, params.min_radius = 3, 1.5
    normal = np.array([0.0, -0.98, 0.2]) / np.linalg.norm([0.0, -0.98, 0.2])
    centroid = np.array([0.3, 0.2, 3.1])
    candidates = generate_candidates(centroid, normal, 1.25, params)
    for rotation, position in zip(candidates.rotations[1:], candidates.positions[1:]):
        np.testing.assert_array_equal(rotation, camera_look_at(position, centroid, normal))


def test_mounting_height_and_a_fixed_head():
    from leapnbv_planner.candidates import generate_candidates

    params = default_nbv_params()
    pitch = np.radians(12.0)
    up = np.array([0.0, -np.cos(pitch), -np.sin(pitch)])  # the current camera looks 12 deg down
    centroid = np.array([0.2, 0.6, 3.0])
    params.camera_height = 0.9
    candidates = generate_candidates(centroid, up, 1.3, params)
    heights = candidates.positions[1:] @ up + 1.3
    np.testing.assert_allclose(heights, 0.9, atol=1e-12)  # the mounting height, not the current 1.3 m
    params.camera_tilt = "fixed"
    fixed = generate_candidates(centroid, up, 1.3, params)
    axes = fixed.rotations[1:, :, 2]
    np.testing.assert_allclose(np.degrees(np.arcsin(-(axes @ up))), 12.0, atol=1e-9)  # the current pitch
    bearing = centroid - fixed.positions[1:]
    bearing -= (bearing @ up)[:, None] * up
    level_axes = axes - (axes @ up)[:, None] * up
    cosine = np.sum(bearing * level_axes, axis=1) / np.linalg.norm(bearing, axis=1) / np.linalg.norm(level_axes, axis=1)
    np.testing.assert_allclose(cosine, 1.0, atol=1e-12)  # turned toward the target
    np.testing.assert_allclose(fixed.rotations[1:, :, 0] @ up, 0.0, atol=1e-12)  # no roll


def test_candidates_in_the_walls_move_to_free_reachable_floor_within_their_patch():
    # The corridor of the test above (walls at x = +-1.2, person at 3 m): with fit_to_free_space the ring
    # candidates in or behind a wall move to the nearest free, reachable foot point of their patch: radius in their
    # ring's band (never outward), bearing within half the angle between candidates.
    rng = np.random.default_rng(0)
    person = np.column_stack([rng.uniform(-0.2, 0.2, 800), rng.uniform(-0.5, 1.1, 800), rng.uniform(2.9, 3.1, 800)])
    side = [np.column_stack([np.full(3000, x), rng.uniform(-0.5, 1.1, 3000), rng.uniform(-4.0, 9.0, 3000)])
            for x in (-1.2, 1.2)]
    target = PlanTarget(centroid=np.array([0.0, 0.3, 3.0]), target_points=person.astype(np.float32),
                        background_points=np.vstack(side).astype(np.float32), k=K, width=640, height=480)
    ground = PlanFloor(normal=UP, offset=HEIGHT)
    params = dataclasses.replace(default_nbv_params(), num_rings=3, min_radius=1.5, radius=2.5)
    fixed = plan_views(target, ground, dataclasses.replace(params, fit_to_free_space=False))
    fitted = plan_views(target, ground, params)
    moved = np.any(fitted.candidates.foot_points != fixed.candidates.foot_points, axis=1)
    assert moved.sum() >= 8 and not fixed.feasibility.feasible[moved].any() and fitted.feasibility.feasible[moved].all()
    unmoved = ~moved
    np.testing.assert_array_equal(fitted.feasibility.reasons[unmoved], fixed.feasibility.reasons[unmoved])
    np.testing.assert_array_equal(fitted.candidates.rotations[unmoved], fixed.candidates.rotations[unmoved])
    centre = fitted.candidates.ring_center
    half_gap = np.pi / params.num_candidates
    for index in np.flatnonzero(moved):
        ring = (index - 1) // params.num_candidates
        before = fixed.candidates.foot_points[index] - centre
        after = fitted.candidates.foot_points[index] - centre
        lowest = [params.min_free_radius, 1.5, 2.0][ring]
        assert np.isclose(np.linalg.norm(before), [1.5, 2.0, 2.5][ring])
        assert lowest - 1e-9 <= np.linalg.norm(after) <= np.linalg.norm(before) + 1e-9
        turn = np.arccos(np.clip(before @ after / np.linalg.norm(before) / np.linalg.norm(after), -1.0, 1.0))
        assert turn < half_gap
        # the foot clear of the walls by the robot's radius, reached by a path
        assert abs(fitted.candidates.foot_points[index][0]) < 1.2 - params.robot_radius
        assert np.isfinite(fitted.path_lengths[index]) and fitted.path_lengths[index] <= params.max_path_length
        # the camera at the current height above its foot point, looking at the centroid
        np.testing.assert_allclose(fitted.candidates.positions[index],
                                   fitted.candidates.foot_points[index] + HEIGHT * UP, atol=1e-12)
        view = target.centroid - fitted.candidates.positions[index]
        np.testing.assert_allclose(fitted.candidates.rotations[index][:, 2], view / np.linalg.norm(view), atol=1e-12)
    # Nearest: no free foot point of the patch lies much nearer the original one than the chosen (one probe step).
    index = np.flatnonzero(moved)[0]
    shift = np.linalg.norm(fitted.candidates.foot_points[index] - fixed.candidates.foot_points[index])
    assert shift < 1.0


def test_a_moved_candidate_takes_the_nearer_of_mirror_probes_by_its_path_not_by_the_last_bit():
    # A thin pillar on the foot point of the candidate beside the person (bearing +x): the nearest free probes
    # of its patch come in pairs mirrored across the bearing (z = 3 -+ 0.2), equally far from where it stood.
    # Of the pair the one with the shorter path is taken (toward the robot), whatever the floor plane's last
    # bits (1e-12 changes of it ordered the two by rounding before).
    rng = np.random.default_rng(0)
    person = np.column_stack([rng.uniform(-0.2, 0.2, 800), rng.uniform(-0.5, 1.1, 800), rng.uniform(2.9, 3.1, 800)])
    params = default_nbv_params()
    centroid = np.array([0.0, 0.3, 3.0])
    open_floor = plan_views(PlanTarget(centroid=centroid, target_points=person.astype(np.float32),
                                       background_points=np.zeros((0, 3), dtype=np.float32), k=K, width=640,
                                       height=480),
                            PlanFloor(normal=UP, offset=HEIGHT), dataclasses.replace(params, fit_to_free_space=False))
    index = int(np.argmax(open_floor.candidates.foot_points[:, 0]))
    stood = open_floor.candidates.foot_points[index]
    np.testing.assert_allclose(stood, foot(2.5, 3.0), atol=1e-12)
    around = np.arange(16) * np.pi / 8  # symmetric across the bearing
    pillar = np.array([[stood[0] + 0.05 * np.cos(a), HEIGHT - h, stood[2] + 0.05 * np.sin(a)]
                       for a in around for h in np.arange(0.1, 1.0, 0.1)])
    target = PlanTarget(centroid=centroid, target_points=person.astype(np.float32),
                        background_points=pillar.astype(np.float32), k=K, width=640, height=480)
    chosen = []
    for eps in (0.0, 1e-12, -1e-12, 2e-12, -2e-12, 5e-12, -5e-12):
        plan = plan_views(target, PlanFloor(normal=UP + np.array([eps, 0.0, eps]), offset=HEIGHT + eps), params)
        assert plan.feasibility.feasible[index]
        chosen.append(plan.candidates.foot_points[index])
        moved = chosen[-1]
        mirror = np.array([moved[0], moved[1], 2.0 * stood[2] - moved[2]])
        assert abs(moved[2] - stood[2]) > 0.1  # off the bearing: one of a mirrored pair
        assert plan.path_lengths[index] < plan.reach.path_lengths_at(mirror[None])[0]
        assert moved[2] < stood[2]  # the side toward the robot
    np.testing.assert_allclose(chosen, chosen[0][None].repeat(len(chosen), axis=0), atol=1e-9)


def test_grid_cell_edges_stay_off_the_robot_and_the_candidates():
    # Cell edges lie at odd multiples of half a cell in plane coordinates: the robot's foot point (plane coordinates
    # 0, 0) is a cell centre, and the outermost foot point, which sets the grid's extent with a whole number of
    # cells of margin (1.0 m + 0.3 m robot radius = 13 cells), is not on an edge, where rounding would pick its cell.
    tilted = np.array([0.0, -0.98, 0.2]) / np.linalg.norm([0.0, -0.98, 0.2])
    for up, height in ((UP, HEIGHT), (tilted, 1.25)):
        feet = np.array([[1.3, 0.0, 2.0], [-2.2, 0.0, 4.5], [0.4, 0.0, 0.7]])
        feet -= ((feet @ up) + height)[:, None] * up  # onto the floor
        grid = build_occupancy_grid(np.zeros((0, 3)), np.zeros((0, 3)), up, height,
                                    np.vstack([feet, -height * up]), 0.1, 0.3, 0.1)
        uv = (grid.plane_coordinates(np.vstack([feet, -height * up])) - grid.origin) / grid.cell
        np.testing.assert_allclose(uv[-1] - np.floor(uv[-1]), 0.5, atol=1e-9)  # the robot: a cell centre
        fraction = uv - np.floor(uv)
        assert np.all(np.abs(fraction - np.round(fraction)) > 1e-6)  # no foot point on an edge
        assert max(grid.free.shape) <= 400 and np.all(uv >= 13.0) and np.all(uv <= np.array(grid.free.shape)[::-1] - 13)
