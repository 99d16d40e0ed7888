"""The benchmark set (leapnbv_evaluation.benchmark_set): committed seeds, the endless seed sequence, rooms."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from leapnbv_evaluation.benchmark_set import (
    BENCHMARK_CONFIG,
    BENCHMARK_SEEDS,
    UNQUALIFIED_SEEDS,
    VERIFIED_BELOW,
    benchmark_config,
    benchmark_scene,
    benchmark_seeds,
    checked_seed_count,
    load_benchmark_scenes,
    select_benchmark_seeds,
)
from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_sim.generation import generate_scene
from leapnbv_sim.render import PERSON_ID
from leapnbv_stand_ins.stand_in_body_model import build_stand_in_body_model


@pytest.fixture(scope="module")
def body_model() -> SMPLXModel:
    return SMPLXModel(build_stand_in_body_model("small"), source="stand_in_small")


def test_benchmark_seeds_start_occluded_within_range(body_model: SMPLXModel) -> None:
    assert len(BENCHMARK_SEEDS) >= 60 and len(set(BENCHMARK_SEEDS)) == len(BENCHMARK_SEEDS)
    for scene in load_benchmark_scenes(3, body_model):
        frame = scene.render()
        assert scene.config.clutter_count_range == BENCHMARK_CONFIG.clutter_count_range
        assert 0.2 <= scene.start_occluder_share <= 0.6
        assert frame.ground_truth.occluder_share == pytest.approx(scene.start_occluder_share)
        assert frame.ground_truth.person_box_xyxy is not None
        assert scene.object_names[PERSON_ID] == "person"
        assert any(name.startswith("occluder") for name in scene.object_names.values())


def _clutter_count(scene) -> int:
    return sum(1 for name in scene.object_names.values() if name.startswith("clutter"))


def test_sample_of_benchmark_seeds_under_the_benchmark_config(body_model: SMPLXModel) -> None:
    low, high = BENCHMARK_CONFIG.clutter_count_range
    assert low >= 1  # the benchmark rooms are furnished
    for seed in BENCHMARK_SEEDS[::9]:
        scene = generate_scene(dataclasses.replace(BENCHMARK_CONFIG, seed=seed), body_model)
        share, _ = scene.occluder_share(scene.start_camera)
        assert 0.2 <= share <= 0.6, seed
        assert share == scene.start_occluder_share
        assert low <= _clutter_count(scene) <= high, seed


def test_the_first_seeds_are_the_committed_ones() -> None:
    # The README's tables are over the first 50: they must never change.
    assert benchmark_seeds(50) == list(range(50)) == BENCHMARK_SEEDS[:50]
    assert benchmark_seeds(len(BENCHMARK_SEEDS)) == BENCHMARK_SEEDS
    assert benchmark_seeds(3, offset=10) == [10, 11, 12]


def test_any_count_continues_the_sequence_deterministically() -> None:
    seeds = benchmark_seeds(1000)
    assert seeds == benchmark_seeds(1000)
    assert seeds[: len(BENCHMARK_SEEDS)] == BENCHMARK_SEEDS
    assert len(seeds) == 1000 and seeds == sorted(set(seeds))
    assert not set(seeds) & UNQUALIFIED_SEEDS
    # Any slice is the same part of the one sequence.
    assert benchmark_seeds(10, offset=60) == seeds[60:70]
    assert benchmark_seeds(300, offset=700) == seeds[700:]


def test_the_continuation_is_what_the_selection_rule_finds(body_model: SMPLXModel) -> None:
    first_later = BENCHMARK_SEEDS[-1] + 1
    count = len(BENCHMARK_SEEDS)
    assert select_benchmark_seeds(4, body_model, first_seed=first_later) == benchmark_seeds(4, offset=count)


def test_past_the_checked_seeds_the_body_model_checks_them(body_model: SMPLXModel) -> None:
    known = checked_seed_count()
    assert known == len(benchmark_seeds(known)) and benchmark_seeds(1, offset=known - 1)[0] < VERIFIED_BELOW
    with pytest.raises(ValueError, match="body model"):
        benchmark_seeds(2, offset=known)
    later = benchmark_seeds(2, offset=known, body_model=body_model)
    assert VERIFIED_BELOW <= later[0] < later[1]
    assert later == select_benchmark_seeds(2, body_model, first_seed=VERIFIED_BELOW)


@pytest.mark.parametrize("count, offset", [(0, 0), (-3, 0), (5, -1)])
def test_bad_counts_are_refused(count: int, offset: int) -> None:
    with pytest.raises(ValueError, match="count"):
        benchmark_seeds(count, offset)


def test_rooms(body_model: SMPLXModel) -> None:
    assert benchmark_config(7).clutter_count_range == BENCHMARK_CONFIG.clutter_count_range
    assert benchmark_config(7, "open").clutter_count_range == (0, 0) and benchmark_config(7, "open").seed == 7
    with pytest.raises(ValueError, match="room"):
        benchmark_config(7, "garden")
    furnished, empty = benchmark_scene(7, body_model), benchmark_scene(7, body_model, "open")
    assert _clutter_count(furnished) >= 2 and _clutter_count(empty) == 0
    # The furniture keeps off the start view: the same seed starts with the same occlusion in both rooms.
    assert furnished.start_occluder_share == empty.start_occluder_share
    np.testing.assert_array_equal(furnished.start_camera.as_matrix(), empty.start_camera.as_matrix())


def test_families_change_the_benchmark_config_and_have_committed_seeds():
    import dataclasses as _dc

    from leapnbv_evaluation.benchmark_set import (
        BENCHMARK_CONFIG,
        FAMILY_CHANGES,
        FAMILY_GRAPH_PARAMETERS,
        FAMILY_SEEDS,
        ROOMS,
        benchmark_config,
        room_seeds,
    )

    assert set(FAMILY_CHANGES) <= set(ROOMS) and {"furnished", "open"} <= set(ROOMS)
    assert all(len(FAMILY_SEEDS[family]) >= 30 for family in FAMILY_CHANGES)
    corridor = benchmark_config(5, "corridor")
    assert (corridor.seed, corridor.room_layout, corridor.clutter_count_range) == (5, "corridor", (0, 0))
    assert benchmark_config(1, "heavy_occlusion").occluder_share_range == (0.60, 0.80)
    assert benchmark_config(1, "far").person_distance_range == (4.0, 6.0)
    assert benchmark_config(1, "camera_0.6").camera_height_range == (0.6, 0.6)
    noisy = benchmark_config(1, "noise_3x").noise
    assert noisy.sigma_quadratic_per_m == pytest.approx(3 * BENCHMARK_CONFIG.noise.sigma_quadratic_per_m)
    # Everything a family does not change is the benchmark's.
    assert _dc.replace(benchmark_config(2, "far"), person_distance_range=BENCHMARK_CONFIG.person_distance_range) == \
        _dc.replace(BENCHMARK_CONFIG, seed=2)
    assert room_seeds("far", 3, 4) == FAMILY_SEEDS["far"][4:7]
    assert "ground_node.min_camera_height=0.3" in FAMILY_GRAPH_PARAMETERS["camera_0.6"]
    with pytest.raises(ValueError, match="room must be one of"):
        benchmark_config(1, "attic")
    with pytest.raises(ValueError, match="give the body model"):
        room_seeds("corner", 5, len(FAMILY_SEEDS["corner"]))
