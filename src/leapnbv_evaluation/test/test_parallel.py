"""Parallel evaluation without starting workers (leapnbv_evaluation.parallel): shares of the seeds, ROS domains."""

from __future__ import annotations

import os

import pytest

from leapnbv_evaluation.episode import EvaluationError
from leapnbv_evaluation.parallel import (
    DOMAIN_BASE_ENV,
    claim_domains,
    explicit_domain_base,
    own_domain,
    release_domains,
    shares,
    worker_dir,
)


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


def test_a_given_domain_base_comes_from_the_argument_or_the_variable() -> None:
    assert explicit_domain_base(40, {DOMAIN_BASE_ENV: "60"}) == 40
    assert explicit_domain_base(None, {DOMAIN_BASE_ENV: "60", "ROS_DOMAIN_ID": "23"}) == 60
    assert explicit_domain_base(None, {"ROS_DOMAIN_ID": "23"}) is None
    with pytest.raises(EvaluationError, match=DOMAIN_BASE_ENV):
        explicit_domain_base(None, {DOMAIN_BASE_ENV: "many"})


def test_claimed_domains_skip_the_own_and_the_locked_ones_and_are_released(tmp_path) -> None:
    environ = {"TMPDIR": str(tmp_path), "ROS_DOMAIN_ID": "23"}
    held, held_handles = claim_domains(1, dict(environ, ROS_DOMAIN_ID="24"))  # someone else's run
    assert held == [25]
    domains, handles = claim_domains(3, environ)
    assert domains == [24, 26, 27]  # upward from the own domain, 25 is taken
    again, again_handles = claim_domains(2, environ)
    assert again == [28, 29]
    release_domains(handles)
    later, later_handles = claim_domains(2, environ)
    assert later == [24, 26]
    release_domains(held_handles + again_handles + later_handles)
    # Near the top of the range the search wraps around to 1.
    top, top_handles = claim_domains(2, dict(environ, ROS_DOMAIN_ID="101"))
    assert top == [1, 2]
    release_domains(top_handles)
    with pytest.raises(EvaluationError, match="free"):
        claim_domains(500, environ)


def test_each_worker_has_its_own_folder() -> None:
    assert worker_dir("out/eval", 0) != worker_dir("out/eval", 1)
    assert worker_dir("out/eval", 1).startswith("out/eval")


def test_a_one_process_run_gets_a_domain_of_its_own(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.delenv(DOMAIN_BASE_ENV, raising=False)
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    others = {"TMPDIR": str(tmp_path), "ROS_DOMAIN_ID": "0"}
    with own_domain() as domain:  # nobody chose: a free one, locked, in the environment the graph inherits
        assert domain == 1 and os.environ["ROS_DOMAIN_ID"] == "1"
        taken, handles = claim_domains(1, others)
        assert taken == [2]
        release_domains(handles)
    assert "ROS_DOMAIN_ID" not in os.environ
    freed, handles = claim_domains(1, others)
    assert freed == [1]
    release_domains(handles)
    monkeypatch.setenv("ROS_DOMAIN_ID", "23")  # the caller chose (the test suite does)
    with own_domain() as domain:
        assert domain == 23
    with own_domain(40) as domain:  # --domain-base
        assert domain == 40 and os.environ["ROS_DOMAIN_ID"] == "40"
    assert os.environ["ROS_DOMAIN_ID"] == "23"
    with pytest.raises(EvaluationError, match="outside"):
        with own_domain(500):
            pass
