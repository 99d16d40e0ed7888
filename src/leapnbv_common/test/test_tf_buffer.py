"""The ROS-free TF buffer: interpolation, chains of static and dynamic links and its errors, against poses by hand."""
from __future__ import annotations

import numpy as np
import pytest

from leapnbv_common.tf_buffer import (
    ExtrapolationError,
    MissingTransformError,
    StampedTransform,
    Transform,
    TransformBuffer,
    slerp,
)

S = 1_000_000_000  # ns per s


def yaw(angle: float) -> np.ndarray:
    """(x, y, z, w) of a rotation by ``angle`` about z."""
    return np.array([0.0, 0.0, np.sin(angle / 2), np.cos(angle / 2)])


def link(parent: str, child: str, stamp_ns: int, rotation, translation) -> StampedTransform:
    return StampedTransform(parent, child, stamp_ns, Transform.checked(rotation, translation))


def matrix(rotation_xyzw, translation) -> np.ndarray:
    """4x4 of a transform, written out from the quaternion formula independently of tf_buffer."""
    x, y, z, w = rotation_xyzw
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = translation
    return m


def as_matrix(t: Transform) -> np.ndarray:
    return matrix(t.rotation, t.translation)


# The optical frame of a camera whose body frame is x forward, y left, z up (REP 103): x right, y down, z forward.
OPTICAL = np.array([-0.5, 0.5, -0.5, 0.5])


def robot(buffer: TransformBuffer) -> None:
    """map -> odom (dynamic), odom -> base_link (dynamic), base_link -> camera_link -> optical (static)."""
    buffer.set_transform(link("base_link", "camera_link", 0, yaw(0.0), [0.1, 0.0, 1.2]), static=True)
    buffer.set_transform(link("camera_link", "camera_color_optical_frame", 0, OPTICAL, [0.0, 0.0, 0.0]), static=True)
    for stamp, angle, x in ((0, 0.0, 1.0), (10 * S, np.pi / 2, 3.0)):
        buffer.set_transform(link("odom", "base_link", stamp, yaw(angle), [x, 0.0, 0.0]))
    for stamp in (0, 5 * S, 10 * S):
        buffer.set_transform(link("map", "odom", stamp, yaw(0.1), [0.5, -0.5, 0.0]))


def test_interpolation_at_a_quarter_is_the_hand_computed_pose() -> None:
    buffer = TransformBuffer()
    robot(buffer)
    # 2.5 s of 10: a quarter of the way: yaw 22.5 deg, x = 1 + 0.25 * 2 = 1.5.
    t = buffer.lookup("odom", "base_link", 2_500_000_000)
    np.testing.assert_allclose(t.rotation, [0.0, 0.0, np.sin(np.pi / 16), np.cos(np.pi / 16)], atol=1e-12)
    np.testing.assert_allclose(t.translation, [1.5, 0.0, 0.0], atol=1e-12)
    # exactly on a sample: that sample
    np.testing.assert_allclose(buffer.lookup("odom", "base_link", 10 * S).rotation, yaw(np.pi / 2), atol=1e-12)


def test_slerp_takes_the_shorter_arc_and_keeps_unit_length() -> None:
    q = slerp(yaw(0.0), -yaw(np.pi / 2), 0.5)  # -q is the same rotation: still 45 deg, not the long way round
    np.testing.assert_allclose(q, yaw(np.pi / 4), atol=1e-12)
    assert np.isclose(np.linalg.norm(slerp(yaw(0.3), yaw(0.3 + 1e-6), 0.5)), 1.0)


def test_a_chain_of_static_and_dynamic_links_composes_like_matrices() -> None:
    buffer = TransformBuffer()
    robot(buffer)
    stamp = 7_500_000_000
    fraction = 0.75
    expected = (matrix(yaw(0.1), [0.5, -0.5, 0.0])  # map -> odom: the same at every sample
                @ matrix(yaw(fraction * np.pi / 2), [1.0 + fraction * 2.0, 0.0, 0.0])
                @ matrix(yaw(0.0), [0.1, 0.0, 1.2]) @ matrix(OPTICAL, [0.0, 0.0, 0.0]))
    t = buffer.lookup("map", "camera_color_optical_frame", stamp)
    np.testing.assert_allclose(as_matrix(t), expected, atol=1e-12)
    # The optical axis (z) is the robot's heading, level: yaw 0.1 + 67.5 deg.
    heading = 0.1 + fraction * np.pi / 2
    np.testing.assert_allclose(t.rotation_matrix()[:, 2], [np.cos(heading), np.sin(heading), 0.0], atol=1e-12)
    assert t.translation[2] == pytest.approx(1.2)
    # The other way round, and between two frames below the root (through their common ancestor).
    np.testing.assert_allclose(as_matrix(buffer.lookup("camera_color_optical_frame", "map", stamp)),
                               np.linalg.inv(expected), atol=1e-12)
    np.testing.assert_allclose(as_matrix(buffer.lookup("base_link", "camera_color_optical_frame", 123)),
                               matrix(yaw(0.0), [0.1, 0.0, 1.2]) @ matrix(OPTICAL, [0, 0, 0]), atol=1e-12)


def test_stamp_zero_is_the_latest_stamp_the_whole_chain_covers() -> None:
    buffer = TransformBuffer()
    robot(buffer)
    buffer.set_transform(link("map", "odom", 12 * S, yaw(0.1), [0.5, -0.5, 0.0]))
    assert buffer.latest_common_stamp("map", "camera_color_optical_frame") == 10 * S  # odom -> base ends at 10 s
    np.testing.assert_allclose(as_matrix(buffer.lookup("map", "camera_color_optical_frame", 0)),
                               as_matrix(buffer.lookup("map", "camera_color_optical_frame", 10 * S)))
    assert buffer.latest_common_stamp("base_link", "camera_color_optical_frame") == 0  # static only


def test_a_missing_frame_and_unconnected_trees_are_missing_transforms() -> None:
    buffer = TransformBuffer()
    robot(buffer)
    with pytest.raises(MissingTransformError, match="source frame 'camera_depth_optical_frame' does not exist"):
        buffer.lookup("map", "camera_depth_optical_frame", 5 * S)
    buffer.set_transform(link("world", "table", 0, yaw(0.0), [1.0, 0.0, 0.0]), static=True)
    with pytest.raises(MissingTransformError, match="'table' and 'base_link' are not connected: 'table' is in the "
                                                    "tree of 'world', 'base_link' in the tree of 'map'"):
        buffer.lookup("table", "base_link", 5 * S)
    assert not buffer.can_transform("table", "base_link", 5 * S)
    assert buffer.can_transform("map", "base_link", 5 * S)


def test_extrapolation_says_which_link_and_by_how_much() -> None:
    buffer = TransformBuffer()
    robot(buffer)
    with pytest.raises(ExtrapolationError) as future:
        buffer.lookup("map", "camera_color_optical_frame", 10 * S + 500_000_000)
    assert future.value.by_ns == 500_000_000
    assert "extrapolation into the future" in str(future.value)
    assert "0.500 s after its buffered time" in str(future.value)
    buffer.set_transform(link("odom", "base_link", 20 * S, yaw(0.0), [0.0, 0.0, 0.0]))  # 0 s and 10 s fall out
    with pytest.raises(ExtrapolationError) as past:
        buffer.lookup("odom", "base_link", 9 * S)
    assert past.value.by_ns == -1 * S and "into the past: 'odom' -> 'base_link'" in str(past.value)
    assert "1.000 s before its buffered time [10000000000, 20000000000] ns" in str(past.value)


def test_samples_beyond_the_cache_time_are_pruned_and_late_old_ones_ignored() -> None:
    buffer = TransformBuffer(cache_time_ns=2 * S)
    for stamp in range(0, 6 * S, S):
        buffer.set_transform(link("odom", "base_link", stamp, yaw(0.0), [stamp / S, 0.0, 0.0]))
    assert buffer.can_transform("odom", "base_link", 3 * S) and not buffer.can_transform("odom", "base_link", 2 * S)
    buffer.set_transform(link("odom", "base_link", 1 * S, yaw(0.0), [0.0, 0.0, 0.0]))  # tf2's TF_OLD_DATA
    assert buffer.old_samples_ignored == 1 and not buffer.can_transform("odom", "base_link", 1 * S)
    buffer.set_transform(link("odom", "base_link", 4 * S, yaw(0.0), [9.0, 0.0, 0.0]))  # the same stamp again
    assert buffer.lookup("odom", "base_link", 4 * S).translation[0] == 9.0


def test_a_new_parent_wins_and_the_old_link_is_forgotten() -> None:
    buffer = TransformBuffer()
    robot(buffer)
    # base_link is re-parented (another localization takes over): the newest message wins.
    buffer.set_transform(link("world", "base_link", 11 * S, yaw(0.0), [4.0, 4.0, 0.0]))
    assert buffer.parent_changes == 1 and buffer.parent_of("base_link") == "world"
    np.testing.assert_allclose(buffer.lookup("world", "camera_link", 11 * S).translation, [4.1, 4.0, 1.2])
    with pytest.raises(ExtrapolationError):  # the odom-parented samples (0 s and 10 s) are gone with their parent
        buffer.lookup("world", "base_link", 10 * S)
    with pytest.raises(MissingTransformError, match="'map' and 'camera_link' are not connected"):
        buffer.lookup("map", "camera_link", 11 * S)
    # and back: odom -> base_link again replaces the world link
    buffer.set_transform(link("odom", "base_link", 12 * S, yaw(0.0), [1.0, 2.0, 0.0]))
    assert buffer.parent_changes == 2
    np.testing.assert_allclose(buffer.lookup("odom", "camera_link", 12 * S).translation, [1.1, 2.0, 1.2])


def test_published_values_are_checked_and_self_links_refused() -> None:
    with pytest.raises(ValueError, match=r"not a unit quaternion \(\|q\| = 2.0000"):
        Transform.checked([0.0, 0.0, 0.0, 2.0], [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="not a unit quaternion"):
        Transform.checked([np.nan, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="translation is not finite"):
        Transform.checked([0.0, 0.0, 0.0, 1.0], [np.inf, 0.0, 0.0])
    with pytest.raises(ValueError, match="to itself"):
        TransformBuffer().set_transform(link("a", "a", 0, yaw(0.0), [0, 0, 0]))
    buffer = TransformBuffer()
    buffer.set_transform(link("/map", "/odom", 0, yaw(0.0), [1, 0, 0]), static=True)  # tf2 drops a leading slash
    assert buffer.frames() == ["map", "odom"]
