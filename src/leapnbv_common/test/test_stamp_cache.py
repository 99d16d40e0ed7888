"""The bounded stamp cache matches exactly or within a slop, and never grows past capacity."""
from __future__ import annotations

from leapnbv_common.stamp_cache import StampCache


def test_exact_and_nearest_matching_with_eviction():
    cache = StampCache(capacity=3)
    for stamp in (100, 200, 300, 400):
        cache.put(stamp, f"m{stamp}")
    assert len(cache) == 3 and cache.evicted == 1
    assert cache.get_exact(100) is None and cache.get_exact(300) == "m300"
    assert cache.find_nearest(310, slop_ns=20) == (300, "m300")
    assert cache.find_nearest(350, slop_ns=49) is None
    assert cache.find_nearest(350, slop_ns=50) == (300, "m300")  # tie goes to the earlier
    assert cache.drop_older_than(400) == 2 and len(cache) == 1


def test_exact_pairer_pairs_in_either_order_and_bounds_memory():
    from leapnbv_common.stamp_cache import ExactStampPairer

    pairer = ExactStampPairer(capacity=2)
    assert pairer.add_first(1, "a1") is None
    assert pairer.add_second(1, "b1") == ("a1", "b1")
    assert pairer.add_second(2, "b2") is None
    assert pairer.add_first(2, "a2") == ("a2", "b2")
    for stamp in (3, 4, 5):
        assert pairer.add_first(stamp, f"a{stamp}") is None
    assert pairer.unpaired_dropped == 1
    assert pairer.add_second(3, "b3") is None  # a3 fell out of the cache: never mismatched


def test_companion_wait_prefers_same_stamp_then_falls_back_to_latest():
    from leapnbv_common.stamp_cache import CompanionWait

    wait = CompanionWait(wait_ns=100)
    assert wait.add_companion(10, "g10") is None
    assert wait.add_frame(10, "f10", now_ns=0) == ("f10", "g10")
    assert wait.add_frame(20, "f20", now_ns=0) is None
    assert wait.add_companion(20, "g20") == ("f20", "g20")
    assert wait.add_frame(30, "f30", now_ns=1000) is None
    assert wait.expire(now_ns=1050) == []
    assert wait.expire(now_ns=1100) == [("f30", "g20")]
    assert wait.expire(now_ns=2000) == []
