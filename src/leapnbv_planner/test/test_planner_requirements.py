"""Tests of the score terms' requirements: only what the chosen terms declare is computed, an undeclared read
is refused, the PlanInputs form of plan_views is the older form's plan, and a term that needs a NEW input (the
person's velocity) is added from this file alone: a PlanInputs field, a requirement provider and the term."""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
import pytest

from leapnbv_common.params import ParamsError, params_from_values
from leapnbv_planner.arrays import Array
from leapnbv_planner.inputs import CameraInMap, PlanFloor, PlanInputs, PlanTarget
from leapnbv_planner.obstacle_map import voxel_map_from_centres
from leapnbv_planner.params import nbv_params_class
from leapnbv_planner.plan import plan_views
from leapnbv_planner.requirements import (
    PATH_LENGTHS,
    REQUIREMENTS,
    Requirement,
    ScoringInputError,
    register_requirement,
)
from leapnbv_planner.score_terms import ScoringContext, score_term, unregister_term

K = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])
UP = np.array([0.0, -1.0, 0.0])
CAMERA_HEIGHT = 1.2
CAMERA_IN_MAP = CameraInMap(np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
                            np.array([0.0, 0.0, CAMERA_HEIGHT]))


def frame(seed: int = 3):
    """A person 3 m ahead with a low box in front of them; a pillar in the map beside them; a body mesh."""
    rng = np.random.default_rng(seed)
    person = np.column_stack([rng.uniform(-0.25, 0.25, 2000), rng.uniform(-0.5, 1.15, 2000),
                              rng.uniform(2.85, 3.15, 2000)])
    box = np.column_stack([rng.uniform(-0.4, 0.4, 300), rng.uniform(0.2, CAMERA_HEIGHT, 300), np.full(300, 2.0)])
    target = PlanTarget(target_points=person.astype(np.float32), background_points=box.astype(np.float32),
                        centroid=np.median(person, axis=0), k=K, width=640, height=480)
    index = np.stack(np.meshgrid(np.arange(29, 32), np.arange(14, 17), np.arange(0, 20), indexing="ij"),
                     -1).reshape(-1, 3)
    obstacle_map = voxel_map_from_centres((index + 0.5) * 0.1, 0.1)
    # A box-shaped body: the 8 corners of the person's extent, 12 triangles wound outward.
    lo, hi = person.min(axis=0), person.max(axis=0)
    corners = np.array([[(hi if k >> a & 1 else lo)[a] for a in range(3)] for k in range(8)])
    faces = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4], [2, 6, 3], [3, 6, 7],
                      [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])
    return target, PlanFloor(normal=UP, offset=CAMERA_HEIGHT), obstacle_map, (corners, faces)


def test_plan_inputs_is_the_older_call_forms_plan():
    target, floor, obstacle_map, mesh = frame()
    params = nbv_params_class()()
    new = plan_views(PlanInputs(target, floor, params, obstacle_map, CAMERA_IN_MAP, mesh))
    old = plan_views(target, floor, params, obstacle_map, (CAMERA_IN_MAP.rotation, CAMERA_IN_MAP.position), mesh)
    np.testing.assert_array_equal(new.scores.term_scores, old.scores.term_scores)
    np.testing.assert_array_equal(new.scores.score, old.scores.score)
    assert new.chosen_index == old.chosen_index and new.used_obstacle_map and old.used_obstacle_map
    with pytest.raises(TypeError, match="no further arguments"):
        plan_views(PlanInputs(target, floor), floor)  # type: ignore[call-overload]


def test_only_what_the_chosen_terms_declare_and_read_is_computed():
    target, floor, obstacle_map, mesh = frame()
    params = nbv_params_class()()  # visibility, area, body_occlusion, travel; reachability on
    with_mesh = plan_views(PlanInputs(target, floor, params, obstacle_map, CAMERA_IN_MAP, mesh))
    # body_occlusion over the mesh: the mesh's line of sight is walked, the target points' is not.
    assert set(with_mesh.computed) == {"body_mesh", "mesh_line_of_sight", "path_lengths"}
    assert with_mesh.line_of_sight_clear is None and with_mesh.mesh_line_of_sight_clear is not None
    without_mesh = plan_views(PlanInputs(target, floor, params, obstacle_map, CAMERA_IN_MAP))
    assert set(without_mesh.computed) == {"body_mesh", "target_line_of_sight", "path_lengths"}
    assert without_mesh.computed["body_mesh"] is None  # declared, read, absent from this frame
    assert without_mesh.line_of_sight_clear is not None and without_mesh.mesh_line_of_sight_clear is None
    framing = plan_views(PlanInputs(target, floor, dataclasses.replace(params, score_terms=["visibility", "area"],
                                                                       visibility_points="observed"),
                                    obstacle_map, CAMERA_IN_MAP, mesh))
    assert framing.computed == {} and framing.line_of_sight_clear is None and framing.used_obstacle_map
    # S_v over the body mesh reads the mesh and nothing else.
    body_framing = plan_views(PlanInputs(target, floor, dataclasses.replace(
        params, score_terms=["visibility", "area"], visibility_points="body_mesh"), obstacle_map, CAMERA_IN_MAP, mesh))
    assert set(body_framing.computed) == {"body_mesh"} and body_framing.line_of_sight_clear is None
    no_map = plan_views(PlanInputs(target, floor, dataclasses.replace(params, reachability=False)))
    assert no_map.computed["target_line_of_sight"] is None and no_map.computed["path_lengths"] is None


def sneaky(context: ScoringContext) -> Array:
    """Reads the path lengths without declaring them."""
    lengths = context.need(PATH_LENGTHS)
    return np.zeros(context.num_candidates) if lengths is None else np.minimum(lengths, 1.0)


def test_a_term_that_reads_what_it_did_not_declare_is_refused():
    score_term("sneaky", 0.1, "undeclared path lengths")(sneaky)
    try:
        target, floor, _, _ = frame()
        params = nbv_params_class()(score_terms=["visibility", "sneaky"])
        with pytest.raises(ScoringInputError, match="'path_lengths' was read, but no chosen score term declares"):
            plan_views(PlanInputs(target, floor, params))
        score_term("declared_unknown", 0.1, "a requirement nobody registered", requires=("wind_speed",))(sneaky)
        with pytest.raises(ValueError, match="unknown score-term requirement 'wind_speed'; known: body_mesh"):
            plan_views(PlanInputs(target, floor, nbv_params_class()(score_terms=["declared_unknown"])))
        # The node's parameters refuse it before any frame.
        with pytest.raises(ParamsError, match=r"'declared_unknown' needs the requirements \['wind_speed'\]"):
            params_from_values(nbv_params_class(), {"score_terms": ["declared_unknown"]})
    finally:
        unregister_term("sneaky")
        unregister_term("declared_unknown")


# --- A term that needs a new input: the person's velocity. In the source tree this is three files: the field in
# leapnbv_planner/inputs.py (here the subclass below), one term module in leapnbv_planner/score_terms/ holding the
# requirement and the term (here the fixture), and the nbv node filling the field from its message. Nothing of
# plan_views, the scoring or the context changes.


@dataclasses.dataclass(frozen=True)
class InputsWithVelocity(PlanInputs):
    """PlanInputs with the new field (what one line in inputs.py would add)."""

    person_velocity: Optional[Array] = None  # (3,) m/s, camera optical frame


def heading_alignment(context: ScoringContext) -> Optional[Array]:
    """(C,) cosine between the person's floor velocity and the bearing from the person to each candidate."""
    inputs = context.frame.inputs if context.frame is not None else None
    velocity = getattr(inputs, "person_velocity", None)
    if inputs is None or velocity is None:
        return None
    up = np.asarray(inputs.floor.normal, dtype=np.float64)
    up = up / np.linalg.norm(up)

    def level(vectors: Array) -> Array:
        return vectors - np.outer(vectors @ up, up)

    heading = level(np.asarray(velocity, dtype=np.float64)[None, :])[0]
    bearings = level(context.positions - np.asarray(inputs.target.centroid, dtype=np.float64)[None, :])
    return np.clip(bearings @ heading / np.maximum(np.linalg.norm(bearings, axis=1) * np.linalg.norm(heading),
                                                   1e-12), -1.0, 1.0)


def ahead(context: ScoringContext) -> Array:
    """0.5 (1 + cos): 1 for a view from where the person walks to, 0 from behind; 0.5 without a velocity."""
    alignment = context.need(HEADING)
    if alignment is None:
        return np.full(context.num_candidates, 0.5)
    return 0.5 * (1.0 + alignment)


def check_alignment(value: object, count: int) -> Array:
    """(C,) cosines in [-1, 1]."""
    cosines = np.asarray(value, dtype=np.float64).reshape(-1)
    if cosines.shape != (count,) or not np.all(np.abs(cosines) <= 1.0):
        raise ScoringInputError(f"heading_alignment must be {count} values in [-1, 1], got shape {cosines.shape}")
    return cosines


HEADING = Requirement("heading_alignment", "cosine between the person's walk and the bearing to each candidate",
                      heading_alignment, check_alignment)


@pytest.fixture
def ahead_term():
    register_requirement(HEADING)
    score_term("ahead", 0.2, "views from where the person walks to", requires=(HEADING,))(ahead)
    yield
    unregister_term("ahead")
    REQUIREMENTS.unregister(HEADING.name)


def test_a_term_that_needs_a_new_input_is_planned_with(ahead_term):
    target, floor, obstacle_map, mesh = frame()
    params_class = nbv_params_class()  # the registry gives the new term its weight parameter
    paper = ["visibility", "area", "occlusion"]
    base = plan_views(PlanInputs(target, floor, params_class(score_terms=paper, score_infeasible=True)))
    params = params_class(score_terms=paper + ["ahead"], weight_ahead=0.4, score_infeasible=True)
    walking = np.array([1.0, 0.0, 0.0])  # toward the camera's right (+x)
    plan = plan_views(InputsWithVelocity(target, floor, params, person_velocity=walking))
    positions = plan.candidates.positions
    bearings = positions - target.centroid
    bearings[:, 1] = 0.0  # the floor is level: up is -y
    expected = 0.5 * (1.0 + bearings[:, 0] / np.linalg.norm(bearings, axis=1))
    np.testing.assert_allclose(plan.scores.term("ahead"), expected, rtol=1e-12)
    np.testing.assert_array_equal(plan.scores.score, base.scores.score + 0.4 * plan.scores.term("ahead"))
    np.testing.assert_allclose(plan.computed["heading_alignment"], 2.0 * expected - 1.0, rtol=1e-12)
    # Alone and heavy, the term picks a feasible view on the side the person walks to.
    alone = plan_views(InputsWithVelocity(target, floor, params_class(score_terms=["ahead"]),
                                          person_velocity=walking))
    assert alone.chosen_index > 0 and alone.candidates.positions[alone.chosen_index, 0] > target.centroid[0] + 1.0
    # Without the new input the requirement is absent and the term neutral; the other terms are unchanged.
    still = plan_views(PlanInputs(target, floor, params))
    np.testing.assert_array_equal(still.scores.term("ahead"), 0.5)
    np.testing.assert_array_equal(still.scores.term_scores[:, :3], base.scores.term_scores)
