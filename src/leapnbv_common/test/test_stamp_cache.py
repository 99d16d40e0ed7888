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
