"""The planner's fast kernels give what their straightforward references give, bit for bit, on random scenes.

The references are the per-point occlusion kernel (``count_visible_targets`` of reference_planner_kernels, itself
checked against the definition in test_planner_scoring), the plain line-of-sight walk (``segments_clear``, there
too), numpy's cross products and bincount sums for the mesh normals, and a point-by-point footprint test.
"""

from __future__ import annotations

import numpy as np
import pytest
from reference_planner_kernels import count_visible_targets, segments_clear

from leapnbv_planner.candidates import camera_look_at
from leapnbv_planner.mesh_kernel import face_normal_sums
from leapnbv_planner.occlusion_kernel import (
    bucket_points,
    count_visible_targets_bucketed,
    run_facing_bounds,
)

UP = np.array([0.0, -1.0, 0.0])
NONE = np.zeros((0, 3))


def random_views(rng, count, centre):
    """The identity view, views round the centre at 0.5-3 m, one inside the clutter and one looking away."""
    rotations, positions = [np.eye(3)], [np.zeros(3)]
    for _ in range(count):
        position = centre + rng.uniform([-3.0, -0.6, -3.0], [3.0, 0.6, 3.0])
        aim = centre + rng.normal(scale=0.5, size=3)
        rotations.append(camera_look_at(position, aim, UP))
        positions.append(position)
    rotations.append(camera_look_at(centre + [0.1, 0.0, -0.4], centre + [0.0, 0.0, 2.0], UP))
    positions.append(centre + [0.1, 0.0, -0.4])
    rotations.append(camera_look_at(np.zeros(3), [0.0, 0.0, -3.0], UP))
    positions.append(np.zeros(3))
    return np.ascontiguousarray(rotations), np.ascontiguousarray(positions)


def both(targets, normals, background, rotations, positions, camera, half_window, points_per_box, run_length=16):
    fx, skew, cx, fy, cy, width, height = camera
    reference = count_visible_targets(targets, background, rotations, positions, fx, skew, cx, fy, cy, width,
                                      height, half_window, normals)
    t_points, t_normals, *t_boxes = bucket_points(targets, normals, points_per_box, run_length)
    b_points, _, *b_boxes = bucket_points(background, NONE, points_per_box, run_length)
    facing = run_facing_bounds(t_points, t_normals, t_boxes[2]) if len(t_normals) else np.zeros((0, 7))
    fast = count_visible_targets_bucketed(t_points, t_normals, *t_boxes, facing, b_points, *b_boxes, rotations,
                                          positions, fx, skew, cx, fy, cy, width, height, half_window)
    return reference, fast


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bucketed_counts_equal_the_per_point_kernel(seed):
    rng = np.random.default_rng(seed)
    centre = np.array([0.0, 0.3, 3.0])
    camera = (250.0, 1.5 * seed, 150.0, 240.0, 95.0, 300, 200)
    targets = rng.normal(size=(3000, 3)) * [0.3, 0.6, 0.2] + centre
    normals = rng.normal(size=(3000, 3))
    outward = targets - centre  # coherent normals: whole runs face away from a camera
    background = np.concatenate([
        rng.uniform([-4, -2, -1], [4, 2, 7], size=(6000, 3)),  # everywhere, behind the cameras too
        rng.normal(size=(6000, 3)) * [0.5, 0.7, 0.6] + centre - [0.0, 0.0, 0.8],  # in front of the target
        rng.uniform([-4, -2, 6.9], [4, 2, 7.0], size=(4000, 3)),  # a wall
        rng.normal(scale=1e-4, size=(50, 3)),  # at the identity view's centre
    ])
    rotations, positions = random_views(rng, 12, centre)
    for half_window in (0, 2, 4):
        for points_per_box, run_length in ((1, 1), (16, 4), (64, 16), (100000, 100000)):
            for target_normals in (NONE, normals, outward):
                reference, fast = both(targets, target_normals, background, rotations, positions, camera,
                                       half_window, points_per_box, run_length)
                np.testing.assert_array_equal(fast[0], reference[0])
                np.testing.assert_array_equal(fast[1], reference[1])
            # In view only (S_v's call): whole boxes are counted without projecting their points.
            reference, fast = both(targets, NONE, NONE, rotations, positions, camera, half_window, points_per_box,
                                   run_length)
            np.testing.assert_array_equal(fast[0], reference[0])
    # The scene is not trivial: one view sees none of the target, others part of it or nearly all of it, and
    # some views see points both hidden and not hidden.
    in_view = reference[0]
    assert in_view[-1] == 0 and np.any((in_view > 0) & (in_view < len(targets) // 2))
    assert in_view.max() > 0.9 * len(targets)
    reference, _ = both(targets, NONE, background, rotations, positions, camera, 4, 64)
    assert np.any((reference[1] > 0) & (reference[1] < reference[0]))


def test_bucketing_keeps_every_point_in_a_box_that_bounds_it():
    rng = np.random.default_rng(3)
    points = rng.normal(size=(5000, 3)) * [2.0, 0.01, 1.0] + [1e3, 0.0, 0.0]
    normals = rng.normal(size=(5000, 3))
    sorted_points, sorted_normals, cell_runs, cell_boxes, run_starts, run_boxes = bucket_points(points, normals, 32, 7)
    assert run_starts[0] == 0 and run_starts[-1] == len(points) and np.all(np.diff(run_starts) > 0)
    assert np.all(np.diff(run_starts) <= 7) and cell_runs[0] == 0 and cell_runs[-1] == len(run_boxes)
    np.testing.assert_array_equal(np.sort(sorted_points.view("f8,f8,f8"), axis=0),
                                  np.sort(points.view("f8,f8,f8"), axis=0))
    pairs = {tuple(p): tuple(n) for p, n in zip(points, normals)}
    assert all(pairs[tuple(p)] == tuple(n) for p, n in zip(sorted_points, sorted_normals))
    def holds_tightly(box, inside):
        # Every point inside; no larger than the points' own bounds but for the growth (1e-8 m here).
        return (np.all(np.abs(inside - box[:3]) <= box[3:])
                and np.all(box[3:] - 0.5 * (inside.max(axis=0) - inside.min(axis=0)) < 1e-8))

    for cell in range(len(cell_boxes)):
        runs = range(cell_runs[cell], cell_runs[cell + 1])
        assert holds_tightly(cell_boxes[cell], sorted_points[run_starts[runs[0]]:run_starts[runs[-1] + 1]])
        for run in runs:
            assert holds_tightly(run_boxes[run], sorted_points[run_starts[run]:run_starts[run + 1]])
    empty = bucket_points(NONE, NONE, 32, 16)
    assert empty[0].shape == (0, 3) and list(empty[2]) == [0] and list(empty[4]) == [0]


def test_face_normal_sums_equal_numpy_cross_and_bincount():
    rng = np.random.default_rng(4)
    vertices = rng.normal(size=(2000, 3)) * [0.3, 0.8, 0.2]
    faces = rng.integers(0, len(vertices), size=(5000, 3))
    corners = vertices[faces]
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    expected = np.zeros_like(vertices)
    for axis in range(3):
        expected[:, axis] = np.bincount(faces.reshape(-1), weights=np.repeat(face_normals[:, axis], 3),
                                        minlength=len(vertices))
    np.testing.assert_array_equal(face_normal_sums(vertices, faces), expected)


def test_footprints_blocked_equals_every_point_against_every_foot():
    from leapnbv_planner.footprint_kernel import footprints_blocked

    rng = np.random.default_rng(5)
    normal = np.array([0.0, -1.0, 0.0])
    offset, clearance, radius = 1.2, 0.05, 0.3
    axis_u, axis_v = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    angles = np.linspace(0.0, 2 * np.pi, 48, endpoint=False)
    feet_u = np.ascontiguousarray(2.0 * np.cos(angles))
    feet_v = np.ascontiguousarray(3.0 + 2.0 * np.sin(angles))
    points = rng.uniform([-3.0, -1.0, 0.5], [3.0, 1.3, 5.5], size=(60, 3))
    # Points exactly one radius from a foot (on the boundary: blocked) and just beyond it.
    for index in range(0, 48, 10):
        points[index] = [feet_u[index] + radius, 0.0, feet_v[index]]
        points[index + 1] = [feet_u[index + 1] - radius * (1 + 1e-15), 0.0, feet_v[index + 1]]
    for radius_here in (radius, 0.05, 0.0):
        blocked = footprints_blocked(points, normal, offset, clearance, axis_u, axis_v, feet_u, feet_v,
                                     radius_here)
        height = normal[0] * points[:, 0] + normal[1] * points[:, 1] + normal[2] * points[:, 2] + offset
        u = axis_u[0] * points[:, 0] + axis_u[1] * points[:, 1] + axis_u[2] * points[:, 2]
        v = axis_v[0] * points[:, 0] + axis_v[1] * points[:, 1] + axis_v[2] * points[:, 2]
        du = u[:, None] - feet_u[None, :]
        dv = v[:, None] - feet_v[None, :]
        expected = np.any((du * du + dv * dv <= radius_here * radius_here) & (height > clearance)[:, None], axis=0)
        np.testing.assert_array_equal(blocked, expected)
        if radius_here == radius:
            assert 0 < expected.sum() < len(expected)


def test_the_floor_grid_from_plane_points_equals_the_one_from_the_cloud():
    # plan_views makes the obstacles' plane coordinates once (elevated_plane_points) for the footprint tests and the
    # grid: the grid must be the one build_occupancy_grid makes from the points themselves, cell for cell.
    from leapnbv_planner.candidates import plane_basis
    from leapnbv_planner.footprint_kernel import elevated_plane_points
    from leapnbv_planner.reachability import build_occupancy_grid

    rng = np.random.default_rng(11)
    normal = np.array([0.05, -0.99, 0.1])
    normal /= np.linalg.norm(normal)
    offset, clearance, cell = 1.2, 0.05, 0.1
    points = rng.uniform([-4.0, -1.0, 0.5], [4.0, 1.3, 8.0], size=(20000, 3))
    points[::97] = np.nan
    person = rng.uniform([-0.3, -0.5, 2.8], [0.3, 1.1, 3.2], size=(500, 3))
    cover = rng.uniform([-3.0, 1.2, 0.5], [3.0, 1.2, 6.0], size=(30, 3))
    e1, e2 = plane_basis(normal)
    plane_points = elevated_plane_points(points, normal, offset, clearance, e1, e2)
    height = points @ normal + offset
    assert len(plane_points) == np.count_nonzero(height > clearance) < len(points)
    from_points = build_occupancy_grid(points, person, normal, offset, cover, cell, 0.3, clearance)
    from_plane = build_occupancy_grid(np.zeros((0, 3)), person, normal, offset, cover, cell, 0.3, clearance,
                                      obstacle_plane_points=plane_points)
    assert from_points.occupied.any() and not from_points.occupied.all()
    np.testing.assert_array_equal(from_plane.occupied, from_points.occupied)
    np.testing.assert_array_equal(from_plane.free, from_points.free)


@pytest.mark.parametrize("density", [0.002, 0.02, 0.2])
def test_segment_walk_with_empty_box_skipping_equals_the_plain_walk(density):
    from leapnbv_planner.obstacle_map import segments_clear_skipping_empty, voxel_map_from_centres

    rng = np.random.default_rng(int(density * 1000))
    resolution = 0.1
    occupied = rng.random((40, 20, 40)) < density
    occupied[5:9, :, 20:22] = True  # a wall
    lower = np.array([-20, -10, 0])
    centres = (np.argwhere(occupied) + lower + 0.5) * resolution
    obstacle_map = voxel_map_from_centres(centres, resolution)
    origins = rng.uniform([-2.2, -1.2, -0.2], [2.2, 1.2, 4.2], (15, 3))
    # Segments along cell boundaries and through cell corners, where the walk's rounding matters most.
    origins[0] = [0.3, 0.2, 0.0]
    origins[1] = [-1.0, -0.5, 0.5]
    targets = rng.uniform([-2.2, -1.2, -0.2], [2.2, 1.2, 4.2], (120, 3))
    targets[0] = [0.3, 0.2, 3.9]
    targets[1] = [1.0, 0.5, 2.5]
    targets[2] = [0.3, 0.2, 0.05]  # shorter than the margin
    args = (obstacle_map.lower_index.astype(np.float64), resolution, origins, targets)
    for margin in (0.1, 0.0):
        expected = segments_clear(obstacle_map.occupied, *args, margin)
        fast = segments_clear_skipping_empty(obstacle_map.occupied, obstacle_map.occupied_prefix_sums(), *args,
                                             margin)
        np.testing.assert_array_equal(fast, expected)
        assert 0.0 < expected.mean() < 1.0
    prefix = obstacle_map.occupied_prefix_sums()
    assert prefix[-1, -1, -1] == obstacle_map.occupied.sum() and prefix is obstacle_map.occupied_prefix_sums()


def test_mesh_vertex_normals_equal_the_numpy_expression():
    from leapnbv_planner.plan import mesh_vertex_normals

    rng = np.random.default_rng(6)
    for vertices, faces in ((rng.normal(size=(3000, 3)), rng.integers(0, 3000, size=(6000, 3))),
                            (rng.normal(size=(50, 3)), np.zeros((0, 3), dtype=np.int64))):
        faces = np.vstack([faces, [[0, 0, 0]]])  # a degenerate face: a zero normal stays zero
        corners = vertices[faces]
        sums = np.zeros_like(vertices)
        face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        for axis in range(3):
            sums[:, axis] = np.bincount(faces.reshape(-1), weights=np.repeat(face_normals[:, axis], 3),
                                        minlength=len(vertices))
        lengths = np.linalg.norm(sums, axis=1)
        expected = np.where(lengths[:, None] > 0, sums / np.maximum(lengths, 1e-300)[:, None], 0.0)
        if float(np.sum(expected * (vertices - vertices.mean(axis=0)))) < 0.0:
            expected = -expected
        np.testing.assert_array_equal(mesh_vertex_normals(vertices, faces), expected)


def test_possible_occluders_leave_out_only_points_that_hide_nothing():
    # A point in the window of a target point and nearer than it must stay, also just outside the box of cameras and
    # targets (at the window's edge beside an outermost target point); far walls and the ceiling go.
    from leapnbv_planner.occlusion_kernel import possible_occluders

    rng = np.random.default_rng(5)
    centre = np.array([0.0, 0.3, 3.0])
    fx, skew, cx, fy, cy, width, height = 250.0, 3.0, 150.0, 240.0, 95.0, 300, 200
    targets = rng.normal(size=(2000, 3)) * [0.3, 0.6, 0.2] + centre
    rotations, positions = random_views(rng, 10, centre)
    half_window = 4
    edge = half_window + 0.99
    edge_points = []
    for c in range(len(positions)):
        local = (targets - positions[c]) @ rotations[c]  # camera coordinates of every target point
        local = local[local[:, 2] > 0.0]
        for du, dv in ((edge, 0.0), (-edge, 0.0), (0.0, edge), (0.0, -edge), (edge, edge), (-edge, -edge)):
            # the pixel (u_t + du, v_t + dv) at 0.999 of t's depth: in t's window unless floor() moves it out
            yn = local[:, 1] / local[:, 2] + dv / fy
            xn = local[:, 0] / local[:, 2] + (du - skew * dv / fy) / fx
            z = 0.999 * local[:, 2]
            edge_points.append(positions[c] + np.column_stack([xn * z, yn * z, z]) @ rotations[c].T)
    edge_points = np.concatenate(edge_points)
    low, high = np.min(np.vstack([positions, targets]), axis=0), np.max(np.vstack([positions, targets]), axis=0)
    outside = ~np.all((edge_points >= low) & (edge_points <= high), axis=1)
    assert outside.sum() >= 20  # the margin is exercised: some lie outside the box itself
    assert len(possible_occluders(edge_points, positions, [targets], fx, skew, fy, half_window)) == len(edge_points)
    assert len(possible_occluders(edge_points, positions, [targets], fx, skew, fy, 0)) < len(edge_points)

    # The counts: the same with and without the points left out, where the edge points do hide some targets.
    background = np.concatenate([rng.uniform([-9, -5, -6], [9, 5, 12], size=(20000, 3)), edge_points[::97]])
    kept = possible_occluders(background, positions, [targets], fx, skew, fy, half_window)
    assert len(kept) < len(background) - 12000  # most of the far volume goes
    camera = (fx, skew, cx, fy, cy, width, height)
    reference = count_visible_targets(targets, background, rotations, positions, fx, skew, cx, fy, cy, width, height,
                                      half_window, NONE)
    filtered = count_visible_targets(targets, kept, rotations, positions, fx, skew, cx, fy, cy, width, height,
                                     half_window, NONE)
    np.testing.assert_array_equal(filtered[1], reference[1])
    _, fast = both(targets, NONE, kept, rotations, positions, camera, half_window, 64)
    np.testing.assert_array_equal(fast[1], reference[1])
    volume_only = count_visible_targets(targets, background[:20000], rotations, positions, fx, skew, cx, fy, cy,
                                        width, height, half_window, NONE)
    assert np.any(volume_only[1] != reference[1])
