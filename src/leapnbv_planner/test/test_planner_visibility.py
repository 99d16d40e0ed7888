"""Tests of S_v over the whole predicted body (``visibility_points: body_mesh``) beside the paper's S_v.

A near view that cuts the legs off at the image border scores the share it keeps; the fallback without a mesh
(the observed points), the depth range, the framing kernel against the plain projection, and the parameters.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from reference_planner_kernels import count_framed

from leapnbv_common.params import ParamsError, param_specs, params_from_values, replace_params
from leapnbv_planner.candidates import camera_look_at
from leapnbv_planner.inputs import PlanFloor, PlanInputs, PlanTarget
from leapnbv_planner.occlusion_kernel import POINTS_PER_BOX, RUN_LENGTH, bucket_points, count_framed_bucketed
from leapnbv_planner.params import DEFAULT_VISIBILITY_POINTS, default_nbv_params, nbv_params_class
from leapnbv_planner.plan import mesh_vertex_normals, plan_views
from leapnbv_planner.requirements import BODY_MESH, SurfacePoints
from leapnbv_planner.score_terms import (
    ScoreTerm,
    declared_requirements,
    get_term,
    missing_requirement_detail,
)
from leapnbv_planner.scoring import score_candidates

WIDTH, HEIGHT = 640, 480
K = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])
FX, SKEW, CX, FY, CY = 615.0, 0.0, 320.0, 615.0, 240.0
CAMERA_HEIGHT = 1.2  # the floor is y = 1.2 in the current camera's optical frame (y down)
UP = np.array([0.0, -1.0, 0.0])
BODY_DEPTH = 3.5  # the body's plane, metres ahead of the current camera
# The body: a 1.7 m tall, 0.4 m wide sheet facing the current camera, feet on the floor: 170 rows of 21 vertices,
# row k at y = -0.495 + 0.01 k (the head at -0.495, the feet at 1.195), each row 0.005 m from a whole centimetre,
# so that no row lies within a pixel of an image border below.
ROWS, COLUMNS = 170, 21
ROW_Y = -0.5 + 0.005 + 0.01 * np.arange(ROWS)


def body_sheet(depth: float = BODY_DEPTH):
    """(vertices (V, 3), faces (F, 3)) of the sheet at z = depth, wound so its normals face the current camera."""
    y, x = np.meshgrid(ROW_Y, np.linspace(-0.2, 0.2, COLUMNS), indexing="ij")
    vertices = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, depth)])
    index = np.arange(ROWS * COLUMNS).reshape(ROWS, COLUMNS)
    a, b, c, d = index[:-1, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel()
    faces = np.concatenate([np.column_stack([a, c, b]), np.column_stack([b, c, d])])
    return vertices, faces


def rows_in_image(distance: float) -> int:
    """How many of the sheet's rows a level camera ``distance`` in front of the sheet frames.

    The camera at the sheet's height 0 (1.2 m above the floor): 0 <= v = fy y / distance + cy < H, written out by rows.
    """
    v = FY * ROW_Y / distance + CY
    return int(np.count_nonzero((v >= 0.0) & (v < HEIGHT)))


def views(*distances: float):
    """Level cameras looking along +z from ``distance`` in front of the sheet, on the current camera's line."""
    positions = np.array([[0.0, 0.0, BODY_DEPTH - distance] for distance in distances])
    return np.repeat(np.eye(3)[None], len(distances), axis=0), positions


def params(points: str, **changes):
    return dataclasses.replace(default_nbv_params(), visibility_points=points, **changes)


def test_a_near_view_that_cuts_the_legs_off_scores_the_share_it_keeps():
    vertices, faces = body_sheet()
    mesh = SurfacePoints(vertices, mesh_vertex_normals(vertices, faces))
    # The start view saw the upper body only (an occluder hid everything below y = 0.4): the observed points.
    observed = vertices[vertices[:, 1] < 0.4] - np.array([0.0, 0.0, 0.01])
    rotations, positions = views(BODY_DEPTH, 2.0, 1.6)
    # The image at 2.0 m ends 0.7805 m below the camera (240 / 615 x 2.0), at 1.6 m 0.6244 m: rows 0-127 and 0-111.
    assert [rows_in_image(d) for d in (BODY_DEPTH, 2.0, 1.6)] == [170, 128, 112]
    terms = [("visibility", 1.0)]
    body = score_candidates(observed, np.zeros((0, 3)), rotations, positions, K, WIDTH, HEIGHT, terms,
                            given={"body_mesh": mesh}, params=params("body_mesh"))
    np.testing.assert_array_equal(body.term("visibility"), [1.0, 128 / 170, 112 / 170])  # 24.7 % and 34.1 % cut
    # The paper's S_v counts only what the start view saw, which every one of these views frames: 1.0.
    paper = score_candidates(observed, np.zeros((0, 3)), rotations, positions, K, WIDTH, HEIGHT, terms,
                             given={"body_mesh": mesh}, params=params("observed"))
    np.testing.assert_array_equal(paper.term("visibility"), [1.0, 1.0, 1.0])


def test_the_depth_range_bounds_what_is_framed():
    vertices, faces = body_sheet()
    mesh = SurfacePoints(vertices, mesh_vertex_normals(vertices, faces))
    rotations, positions = views(BODY_DEPTH, 2.0)
    terms = [("visibility", 1.0)]

    def shares(near: float, far: float) -> np.ndarray:
        return score_candidates(vertices, np.zeros((0, 3)), rotations, positions, K, WIDTH, HEIGHT, terms,
                                given={"body_mesh": mesh},
                                params=params("body_mesh", visibility_min_depth=near, visibility_max_depth=far)
                                ).term("visibility")

    np.testing.assert_array_equal(shares(0.1, 10.0), [1.0, 128 / 170])
    np.testing.assert_array_equal(shares(0.1, 3.0), [0.0, 128 / 170])  # the sheet is 3.5 m from the first camera
    np.testing.assert_array_equal(shares(2.5, 10.0), [1.0, 0.0])  # and 2.0 m from the second
    np.testing.assert_array_equal(shares(2.0, 3.5), [1.0, 128 / 170])  # both ends count


def plan_frame():
    """The sheet as a frame: the start view's target points (its upper part), a floor, the sheet as the mesh."""
    vertices, faces = body_sheet()
    observed = vertices[vertices[:, 1] < 0.4] - np.array([0.0, 0.0, 0.01])
    target = PlanTarget(target_points=observed.astype(np.float32), background_points=np.zeros((0, 3), np.float32),
                        centroid=np.median(vertices, axis=0), k=K, width=WIDTH, height=HEIGHT)
    return target, PlanFloor(normal=UP, offset=CAMERA_HEIGHT), (vertices, faces)


def test_a_plan_scores_the_mesh_and_falls_back_to_the_observed_points_without_one():
    target, floor, mesh = plan_frame()
    # A level camera on every candidate (the head keeps the current pitch): the rings frame the sheet's upper part
    # and cut its lower part off at the image's bottom, the nearer the more.
    body = params("body_mesh", score_infeasible=True, camera_tilt="fixed")
    paper = params("observed", score_infeasible=True, camera_tilt="fixed")
    with_mesh = plan_views(PlanInputs(target, floor, body, body_mesh=mesh))
    observed = plan_views(PlanInputs(target, floor, paper, body_mesh=mesh))
    rotations, positions = with_mesh.candidates.rotations, with_mesh.candidates.positions
    expected = count_framed(mesh[0], rotations, positions, FX, SKEW, CX, FY, CY, WIDTH, HEIGHT, 0.1, 10.0)
    np.testing.assert_array_equal(with_mesh.scores.term("visibility"), expected / float(len(mesh[0])))
    # Each ring cuts the legs off (1.5 m: the image ends 0.585 m below the camera, 0.615 m above the floor; 2.5 m:
    # 0.224 m); the observed upper part stays framed: the paper's S_v is 1 on every ring.
    rings = [np.arange(1, 17), np.arange(17, 33), np.arange(33, 49)]
    mesh_values = with_mesh.scores.term("visibility")
    assert [round(float(np.median(mesh_values[ring])), 2) for ring in rings] == [0.64, 0.75, 0.87]
    assert np.all(observed.scores.term("visibility")[1:] == 1.0)
    # Observed points: the body mesh is not read for S_v (body_occlusion still reads it).
    assert "body_mesh" in observed.computed and observed.computed["body_mesh"] is not None
    framing_only = dataclasses.replace(paper, score_terms=["visibility", "area"])
    assert plan_views(PlanInputs(target, floor, framing_only, body_mesh=mesh)).computed == {}
    assert set(plan_views(PlanInputs(target, floor, dataclasses.replace(framing_only, visibility_points="body_mesh"),
                                     body_mesh=mesh)).computed) == {"body_mesh"}
    # No mesh in the frame: S_v is the observed points' share, and the plan says the mesh was absent.
    without = plan_views(PlanInputs(target, floor, body))
    np.testing.assert_array_equal(without.scores.term("visibility"), observed.scores.term("visibility"))
    assert without.computed["body_mesh"] is None
    # An empty mesh is no mesh.
    empty = plan_views(PlanInputs(target, floor, body, body_mesh=(np.zeros((0, 3)), np.zeros((0, 3), np.int64))))
    np.testing.assert_array_equal(empty.scores.term("visibility"), observed.scores.term("visibility"))


def test_what_the_terms_read_follows_the_parameter_and_the_fallback_is_named():
    visibility = get_term("visibility")
    assert declared_requirements([visibility]) == {"body_mesh"}  # without parameters: all it may read
    assert declared_requirements([visibility], params("observed")) == frozenset()
    assert declared_requirements([visibility], params("body_mesh")) == {"body_mesh"}
    assert missing_requirement_detail(BODY_MESH, params("body_mesh")) == \
        "S_v of the observed points; S_o of the observed points"
    assert missing_requirement_detail(BODY_MESH, params("observed")) == "S_o of the observed points"
    paper_terms = params("observed", score_terms=["visibility", "area", "occlusion"])
    assert missing_requirement_detail(BODY_MESH, paper_terms) == ""
    # A term's parameters may only narrow what it declares.
    wrong = ScoreTerm("wrong", 0.1, "reads more than it declares", lambda context: np.zeros(0),
                      frozenset(), lambda p: ("body_mesh",))
    with pytest.raises(ValueError, match=r"reads \['body_mesh'\] with these parameters"):
        wrong.requirements(default_nbv_params())


@pytest.mark.parametrize("near, far", [(0.0, 100.0), (0.1, 10.0), (2.4, 3.1), (0.5, 0.6)])
def test_the_framing_kernel_counts_what_every_point_projected_counts(near, far):
    rng = np.random.default_rng(11)
    person = np.column_stack([rng.normal(0.0, 0.15, 6000), rng.uniform(-0.5, 1.2, 6000),
                              rng.normal(3.0, 0.1, 6000)])
    scattered = rng.uniform([-4.0, -1.0, -2.0], [4.0, 1.2, 7.0], (3000, 3))
    points = np.concatenate([person, scattered])
    centre = np.array([0.0, 0.3, 3.0])
    poses = []
    for radius in (0.4, 1.0, 1.5, 2.5, 4.0):  # the smallest inside the cloud: points behind and beside the camera
        for angle in np.linspace(0.0, 2.0 * np.pi, 7, endpoint=False):
            position = centre + radius * np.array([np.cos(angle), -0.1 * radius, np.sin(angle)])
            poses.append((camera_look_at(position, centre, UP), position))
    poses.append((np.eye(3), np.zeros(3)))
    rotations = np.stack([rotation for rotation, _ in poses])
    positions = np.stack([position for _, position in poses])
    sorted_points, _, cell_runs, cell_boxes, run_starts, run_boxes = bucket_points(points, np.zeros((0, 3)),
                                                                                   POINTS_PER_BOX, RUN_LENGTH)
    fast = count_framed_bucketed(sorted_points, cell_runs, cell_boxes, run_starts, run_boxes, rotations, positions,
                                 FX, SKEW, CX, FY, CY, WIDTH, HEIGHT, near, far)
    reference = count_framed(points, rotations, positions, FX, SKEW, CX, FY, CY, WIDTH, HEIGHT, near, far)
    np.testing.assert_array_equal(fast, reference)
    assert 0 < reference.max() < len(points)
    # Deterministic whatever the order of the points.
    shuffled = bucket_points(points[rng.permutation(len(points))], np.zeros((0, 3)), POINTS_PER_BOX, RUN_LENGTH)
    np.testing.assert_array_equal(count_framed_bucketed(shuffled[0], *shuffled[2:], rotations, positions, FX, SKEW,
                                                        CX, FY, CY, WIDTH, HEIGHT, near, far), fast)


def test_the_parameters_are_validated_and_live():
    spec = {s.name: s for s in param_specs(nbv_params_class())}
    assert spec["visibility_points"].default == DEFAULT_VISIBILITY_POINTS == default_nbv_params().visibility_points
    assert set(spec["visibility_points"].choices) == {"observed", "body_mesh"}
    for name in ("visibility_points", "visibility_min_depth", "visibility_max_depth"):
        assert not spec[name].read_only and spec[name].description
    assert default_nbv_params().visibility_min_depth == 0.1 and default_nbv_params().visibility_max_depth == 10.0
    for values, message in (({"visibility_points": "all"}, "visibility_points = 'all' is not one of"),
                            ({"visibility_min_depth": -0.1}, "visibility_min_depth = -0.1 is below its minimum"),
                            ({"visibility_max_depth": float("nan")}, "visibility_max_depth"),
                            ({"visibility_min_depth": 4.0, "visibility_max_depth": 4.0},
                             r"visibility_min_depth \(4.0\) must be below visibility_max_depth \(4.0\)")):
        with pytest.raises(ParamsError, match=message):
            params_from_values(nbv_params_class(), values)
        with pytest.raises(ParamsError, match=message):
            replace_params(default_nbv_params(), values)
    changed = replace_params(default_nbv_params(), {"visibility_points": "observed", "visibility_max_depth": 6.0})
    assert changed.visibility_points == "observed" and changed.visibility_max_depth == 6.0
