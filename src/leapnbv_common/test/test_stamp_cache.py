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


def test_companion_wait_pairs_only_the_same_stamp_and_keeps_the_newest_frame():
    from leapnbv_common.stamp_cache import CompanionWait

    drops = []
    wait = CompanionWait(wait_ns=100, frame_name="target", companion_name="plane",
                         on_drop=lambda reason, stamp: drops.append((reason, stamp)), restart_ns=40)
    assert wait.add_companion(10, "g10") is None
    assert wait.add_frame(10, "f10", now_ns=0) == ("f10", "g10")
    assert wait.add_frame(20, "f20", now_ns=0) is None
    assert wait.add_companion(20, "g20") == ("f20", "g20")
    # A frame whose plane never comes goes back alone: never with another stamp's plane.
    assert wait.add_frame(30, "f30", now_ns=1000) is None
    assert wait.expire(now_ns=1050) == []
    assert wait.expire(now_ns=1100) == [(30, "f30")]
    assert wait.expire(now_ns=2000) == []
    # Frames leave in stamp order: serving one drops the older ones still waiting; an older or
    # repeated one is refused; all counted.
    assert wait.add_frame(40, "f40", now_ns=2000) is None
    assert wait.add_frame(45, "f45", now_ns=2000) is None
    assert wait.add_frame(50, "f50", now_ns=2000) is None
    assert wait.add_companion(45, "g45") == ("f45", "g45")
    assert wait.waiting() == [50]
    assert wait.add_companion(40, "g40") is None  # its frame was superseded
    assert wait.add_frame(20, "f20 again", now_ns=2000) is None
    assert wait.add_companion(50, "g50") == ("f50", "g50")
    assert drops == [("target_superseded", 40), ("target_older_than_served", 20)]
    # Stamps far behind the newest served one: a replay started over; served as new.
    assert wait.add_companion(1, "g1") is None
    assert wait.add_frame(1, "f1", now_ns=3000) == ("f1", "g1")
    assert wait.restarts == 1


def test_every_item_leaving_a_cache_unused_is_reported():
    from leapnbv_common.stamp_cache import ExactStampPairer, StampCache

    drops = []
    cache = StampCache(2, "depth_evicted", lambda reason, stamp: drops.append((reason, stamp)))
    for stamp in (1, 2, 3, 4):
        cache.put(stamp, stamp)
    assert cache.pop(4) == 4  # taken for use: not a drop
    assert cache.drop_older_than(5, "depth_skipped") == 1
    assert drops == [("depth_evicted", 1), ("depth_evicted", 2), ("depth_skipped", 3)]
    drops.clear()
    pairer = ExactStampPairer(2, "image", "ground_truth", lambda reason, stamp: drops.append((reason, stamp)))
    for stamp in (1, 2, 3):
        pairer.add_first(stamp, stamp)
    pairer.add_second(7, "t7")
    assert pairer.drop_older_than(3) == 1
    assert drops == [("image_unpaired", 1), ("image_superseded", 2)] and pairer.unpaired_dropped == 1
