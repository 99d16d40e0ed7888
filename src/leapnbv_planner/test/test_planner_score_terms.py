"""Tests of the score-term registry: the built-in terms, one kernel call per scoring, summation order,
and a new term added from this file alone (module + weight + test: nothing else edited)."""

from __future__ import annotations

import pkgutil

import numpy as np
import pytest

import leapnbv_planner.score_terms as score_terms_package
from leapnbv_planner.inputs import PlanFloor, PlanTarget
from leapnbv_planner.params import DEFAULT_SCORE_TERMS, nbv_params_class
from leapnbv_planner.plan import plan_views
from leapnbv_planner.score_terms import (
    ScoreTerm,
    ScoringContext,
    get_term,
    register_term,
    registered_terms,
    unregister_term,
)
from leapnbv_planner.scoring import score_candidates

K = np.array([[300.0, 0.0, 160.0], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]])
WIDTH, HEIGHT = 320, 240
UP = np.array([0.0, -1.0, 0.0])
CAMERA_HEIGHT = 1.2


def person_and_clutter(seed=0):
    rng = np.random.default_rng(seed)
    person = np.column_stack([rng.uniform(-0.2, 0.2, 1500), rng.uniform(-0.5, 1.2, 1500), rng.uniform(2.9, 3.1, 1500)])
    clutter = np.column_stack([rng.uniform(-0.5, 0.5, 800), rng.uniform(0.3, 1.2, 800), rng.uniform(1.8, 2.0, 800)])
    return person, clutter


def frame(seed=0):
    """The planner's message-free target and floor (what TargetGeometryArrays / GroundPlaneArrays carry)."""
    person, clutter = person_and_clutter(seed)
    target = PlanTarget(target_points=person.astype(np.float32), background_points=clutter.astype(np.float32),
                        centroid=np.median(person, axis=0), k=K, width=WIDTH, height=HEIGHT)
    ground = PlanFloor(normal=UP, offset=CAMERA_HEIGHT)
    return target, ground


def ring_poses(count=6):
    angles = np.linspace(0, 2 * np.pi, count, endpoint=False)
    from leapnbv_planner.candidates import camera_look_at

    positions = np.column_stack([2.0 * np.sin(angles), np.zeros(count), 3.0 - 2.0 * np.cos(angles)])
    rotations = np.array([camera_look_at(p, np.array([0.0, 0.3, 3.0]), UP) for p in positions])
    return rotations, positions


def test_built_in_terms_have_todays_names_and_default_weights():
    assert {term.name: term.default_weight for term in registered_terms()} == {
        "visibility": 0.03, "area": 0.14, "occlusion": 0.83, "travel": 0.05, "body_occlusion": 0.83}
    defaults = nbv_params_class()()
    assert defaults.term_weights() == [("visibility", 0.03), ("area", 0.14), ("body_occlusion", 0.83),
                                       ("travel", 0.05)]
    assert defaults.score_terms == DEFAULT_SCORE_TERMS == ["visibility", "area", "body_occlusion", "travel"]


def test_every_module_of_the_package_registers_the_term_it_is_named_after():
    modules = sorted(m.name for m in pkgutil.iter_modules(score_terms_package.__path__) if m.name != "base")
    assert modules == sorted(term.name for term in registered_terms())
    for name in modules:
        assert get_term(name).compute.__module__ == f"leapnbv_planner.score_terms.{name}"


def test_visibility_and_occlusion_share_one_kernel_call():
    person, clutter = person_and_clutter()
    context = ScoringContext(person, clutter, *ring_poses(), K, WIDTH, HEIGHT)
    assert context.kernel_calls == 0  # lazily: area alone never runs the kernel
    get_term("area").compute(context)
    assert context.kernel_calls == 0
    occlusion = get_term("occlusion").compute(context)
    visibility = get_term("visibility").compute(context)
    assert context.kernel_calls == 1
    in_view, not_hidden = context.visible_counts()
    np.testing.assert_array_equal(visibility, in_view / len(person))
    # S_v alone (S_o not scored) projects the targets only: the same counts, without the background.
    alone = ScoringContext(person, clutter, *ring_poses(), K, WIDTH, HEIGHT)
    np.testing.assert_array_equal(get_term("visibility").compute(alone), visibility)
    assert alone.kernel_calls == 1 and alone._counts is None
    # score_candidates runs S_o's kernel first whatever the order of the terms: one call.
    scores = score_candidates(person, clutter, *ring_poses(), K, WIDTH, HEIGHT, [("visibility", 1.0),
                                                                                  ("occlusion", 1.0)])
    np.testing.assert_array_equal(scores.term("visibility"), visibility)
    np.testing.assert_array_equal(occlusion, np.where(in_view > 0, not_hidden / np.maximum(in_view, 1), 0.0))
    assert 0.0 < occlusion.min() < occlusion.max()  # the clutter hides the person from some views only


def test_score_is_the_weighted_sum_in_term_order_bit_for_bit():
    person, clutter = person_and_clutter()
    scores = score_candidates(person, clutter, *ring_poses(), K, WIDTH, HEIGHT,
                              terms=[("visibility", 0.03), ("area", 0.14), ("occlusion", 0.83)])
    assert scores.term_names == ["visibility", "area", "occlusion"]
    s_v, s_a, s_o = (scores.term(name) for name in scores.term_names)
    np.testing.assert_array_equal(scores.score, 0.03 * s_v + 0.14 * s_a + 0.83 * s_o)
    # Another order is another (equally valid) sum; the term values do not change with it.
    reordered = score_candidates(person, clutter, *ring_poses(), K, WIDTH, HEIGHT,
                                 terms=[("occlusion", 0.83), ("visibility", 0.03), ("area", 0.14)])
    np.testing.assert_array_equal(reordered.term_scores, scores.term_scores[:, [2, 0, 1]])
    np.testing.assert_array_equal(reordered.score, 0.83 * s_o + 0.03 * s_v + 0.14 * s_a)


def test_unknown_and_duplicate_registrations_are_refused():
    with pytest.raises(KeyError, match="unknown score term 'sharpness'"):
        get_term("sharpness")
    person, clutter = person_and_clutter()
    with pytest.raises(KeyError, match="sharpness"):
        score_candidates(person, clutter, *ring_poses(), K, WIDTH, HEIGHT, terms=[("sharpness", 1.0)])
    with pytest.raises(ValueError, match="already registered"):
        register_term(ScoreTerm("area", 0.5, "again", lambda context: np.zeros(context.num_candidates)))
    with pytest.raises(ValueError, match="identifier"):
        register_term(ScoreTerm("two words", 0.5, "bad name", lambda context: np.zeros(context.num_candidates)))


# A new term, defined here and nowhere else: closeness of the candidate camera to the target (a
# stand-in for any new criterion). Registering it is all the planner needs.
def closeness(context: ScoringContext) -> np.ndarray:
    centroid = np.median(context.targets, axis=0)
    return 1.0 / (1.0 + np.linalg.norm(context.positions - centroid, axis=1))


@pytest.fixture
def closeness_term():
    term = register_term(ScoreTerm("closeness", 0.25, "closeness of the camera to the target", closeness))
    yield term
    unregister_term("closeness")


def test_a_term_registered_from_a_test_file_gets_its_weight_parameter_and_is_planned_with(closeness_term):
    params_class = nbv_params_class()
    spec = {f.name: f for f in __import__("dataclasses").fields(params_class)}["weight_closeness"]
    assert spec.default == 0.25 and "closeness" in spec.metadata["description"]
    target, ground = frame()
    base = plan_views(target, ground, params_class(score_terms=["visibility", "area", "occlusion"],
                                                   score_infeasible=True))
    params = params_class(score_terms=["visibility", "area", "occlusion", "closeness"], weight_closeness=0.5,
                          score_infeasible=True)
    plan = plan_views(target, ground, params)
    assert plan.scores.term_names == ["visibility", "area", "occlusion", "closeness"]
    np.testing.assert_array_equal(plan.scores.term_weights, [0.03, 0.14, 0.83, 0.5])
    values = closeness(ScoringContext(target.target_points, np.zeros((0, 3)), plan.candidates.rotations,
                                      plan.candidates.positions, K, WIDTH, HEIGHT))
    np.testing.assert_allclose(plan.scores.term("closeness"), values, rtol=1e-12)
    np.testing.assert_array_equal(plan.scores.score, base.scores.score + 0.5 * values)
    assert plan.chosen_index >= 0
    # Only the new term: the nearest feasible view wins (the current one is 3 m away).
    alone = plan_views(target, ground, params_class(score_terms=["closeness"], weight_closeness=1.0))
    feasible = alone.feasibility.feasible
    # The choice ties scores within 1e-9 (then the nearest wins): the inner ring's views nearly tie here.
    assert alone.scores.term("closeness")[alone.chosen_index] >= alone.scores.score[feasible].max() - 1e-9
    assert alone.chosen_index != 0


def test_unregistered_term_leaves_no_parameter_behind(closeness_term):
    with_term = nbv_params_class()
    unregister_term("closeness")
    without = nbv_params_class()
    assert hasattr(with_term(), "weight_closeness") and not hasattr(without(), "weight_closeness")
    register_term(closeness_term)  # the fixture unregisters it again
