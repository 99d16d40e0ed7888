"""Parallel evaluation without starting workers (leapnbv_evaluation.parallel): shares of the seeds, ROS domains."""

from __future__ import annotations

import pytest

from leapnbv_evaluation.episode import EvaluationError
from leapnbv_evaluation.parallel import DOMAIN_BASE_ENV, domain_base, shares, worker_dir


@pytest.mark.parametrize("count, workers", [(10, 1), (10, 2), (10, 3), (7, 7), (3, 5), (1000, 2)])
def test_shares_are_contiguous_near_equal_and_keep_each_seeds_place(count: int, workers: int) -> None:
    seeds = [100 + 3 * i for i in range(count)]
    parts = shares(seeds, workers)
    assert len(parts) == min(count, workers)
    sizes = [len(share) for _, share in parts]
    assert max(sizes) - min(sizes) <= 1 and min(sizes) >= 1
    # Concatenated in order they are the seeds, and each share starts at its first seed's place.
    assert [seed for _, share in parts for seed in share] == seeds
    for first_index, share in parts:
        assert seeds[first_index] == share[0]


def test_domain_base_comes_from_the_argument_the_variable_or_the_parents_domain() -> None:
    assert domain_base(40, {DOMAIN_BASE_ENV: "60", "ROS_DOMAIN_ID": "23"}) == 40
    assert domain_base(None, {DOMAIN_BASE_ENV: "60", "ROS_DOMAIN_ID": "23"}) == 60
    assert domain_base(None, {"ROS_DOMAIN_ID": "23"}) == 23
    assert domain_base(None, {}) == 0
    with pytest.raises(EvaluationError, match="ROS_DOMAIN_ID"):
        domain_base(None, {"ROS_DOMAIN_ID": "many"})


def test_each_worker_has_its_own_folder() -> None:
    assert worker_dir("out/eval", 0) != worker_dir("out/eval", 1)
    assert worker_dir("out/eval", 1).startswith("out/eval")
