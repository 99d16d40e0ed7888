"""The message contracts (leapnbv_common.contracts): each check on values that pass and values that must not."""
from __future__ import annotations

import array
from types import SimpleNamespace

import numpy as np
import pytest

from leapnbv_common import contracts as c

NAN = float("nan")
K = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])
SOURCES = (0, 1)
UP = np.array([0.0, -0.96, -0.28])  # the floor seen by a camera pitched down 16 degrees


def test_a_ground_plane_must_have_a_unit_normal_pointing_up_toward_the_camera():
    c.check_ground_plane(UP / np.linalg.norm(UP), 1.2, True, 0, SOURCES)
    c.check_ground_plane([NAN, NAN, NAN], NAN, False, 1, SOURCES)  # "no floor": no geometry to check
    cases = [
        (-UP / np.linalg.norm(UP), 1.2, "points down"),             # flipped normal (goal rolled 180 deg)
        (2.0 * UP / np.linalg.norm(UP), 1.2, r"not unit length \(\|n\| = 2.0000"),
        (0.9 * UP / np.linalg.norm(UP), 1.2, "not unit length"),
        (UP / np.linalg.norm(UP), -1.2, "on or below the floor"),   # camera under the floor
        (UP / np.linalg.norm(UP), 0.0, "on or below the floor"),
        ([0.0, NAN, 0.0], 1.2, "not finite"),
        (UP / np.linalg.norm(UP), float("inf"), "not finite"),
        ([0.0, 0.0, -1.0], 1.2, "points down"),                      # unit, but along the optical axis
    ]
    for normal, offset, message in cases:
        with pytest.raises(c.ContractError, match=message):
            c.check_ground_plane(normal, offset, True, 0, SOURCES)
    with pytest.raises(c.ContractError, match="source 7 is none of"):
        c.check_ground_plane(UP, 1.2, False, 7, SOURCES)


def test_a_quaternion_must_be_unit_and_a_camera_pose_above_the_floor():
    c.check_unit_quaternion([0.0, 0.0, 0.0, 1.0])
    c.check_unit_quaternion([0.0, 0.0, 0.0, 1.0 + 0.9e-3])
    for q in ([0.0, 0.0, 0.0, 2.0], [0.0, 0.0, 0.0, 0.0], [NAN, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 1.002]):
        with pytest.raises(c.ContractError, match="not a unit quaternion"):
            c.check_unit_quaternion(q)
    c.check_camera_pose([0.0, 0.0, 0.0, 1.0], [1.0, 2.0, 0.8])
    with pytest.raises(c.ContractError, match=r"not above the floor: z = -0.300"):
        c.check_camera_pose([0.0, 0.0, 0.0, 1.0], [1.0, 2.0, -0.3])
    with pytest.raises(c.ContractError, match="position is not finite"):
        c.check_camera_pose([0.0, 0.0, 0.0, 1.0], [NAN, 2.0, 0.8])
    with pytest.raises(c.ContractError, match=r"\|q\| = 2.0000"):
        c.check_camera_pose([0.0, 0.0, 0.0, 2.0], [1.0, 2.0, 0.8])


def test_intrinsics_boxes_sizes_and_frames():
    c.check_intrinsics(K, 640, 480)
    for k, width, height, message in [
        (np.where(np.eye(3) == 1, 0.0, K), 640, 480, "not a valid pinhole"),
        (np.full((3, 3), NAN), 640, 480, "not a valid pinhole"),
        (K, 0, 480, "is empty"),
        (K, 300, 200, "principal point"),  # K of a 640x480 camera on a 300x200 image
    ]:
        with pytest.raises(c.ContractError, match=message):
            c.check_intrinsics(k, width, height)

    good = np.array([[10, 20, 200, 400, 0.9], [-5, -5, 30, 30, 0.0], [600, 400, 700, 500, 1.0]])
    np.testing.assert_array_equal(c.check_boxes(good, (640, 480)), good.astype(np.float32))
    assert c.check_boxes(np.zeros((0, 5)), (640, 480)).shape == (0, 5)
    for row, message in [
        ([10, 20, 200, 400, NAN], "not finite"), ([10, NAN, 200, 400, 0.5], "not finite"),
        ([10, 20, float("inf"), 400, 0.5], "not finite"), ([10, 20, 200, 400, 1.5], r"outside \[0, 1\]"),
        ([10, 20, 200, 400, -0.1], r"outside \[0, 1\]"), ([200, 20, 10, 400, 0.5], "empty or inverted"),
        ([10, 20, 10, 400, 0.5], "empty or inverted"), ([700, 20, 800, 400, 0.5], "outside the 640x480 image"),
        ([-1e9, -1e9, 1e9, 1e9, 0.5], "beyond the 640x480 image"), ([10, -481, 200, 400, 0.5], "beyond"),
        ([10, 20, 1281, 400, 0.5], "beyond"),
    ]:
        with pytest.raises(c.ContractError, match=message):
            c.check_boxes(np.array([good[0], row]), (640, 480))

    c.check_same_size("colour", (640, 480), "depth", (640, 480))
    with pytest.raises(c.ContractError, match="colour is 640x480 but depth is 320x240") as error:
        c.check_same_size("colour", (640, 480), "depth", (320, 240))
    assert error.value.reason == c.IMAGE_SIZE_MISMATCH
    c.check_same_frame("a", "camera_color_optical_frame", "b", "camera_color_optical_frame")
    with pytest.raises(c.ContractError, match="a is in frame 'x' but b in ''") as error:
        c.check_same_frame("a", "x", "b", "")
    assert error.value.reason == c.FRAME_ID_MISMATCH


class _Stamp(SimpleNamespace):
    pass


class _Msg:
    """A stand-in with the rclpy message protocol (get_fields_and_field_types) for the fingerprint."""

    _fields = {"header": "std_msgs/Header", "data": "sequence<uint8>", "compute_time_ms": "float",
               "boxes": "sequence<float>"}

    def __init__(self, sec, data, compute_time_ms=0.0, boxes=(1.0, 2.0)):
        self.header = SimpleNamespace(stamp=_Stamp(sec=sec, nanosec=0), frame_id="cam")
        self.data = array.array("B", data)
        self.compute_time_ms = compute_time_ms
        self.boxes = list(boxes)

    @classmethod
    def get_fields_and_field_types(cls):
        return dict(cls._fields)


def test_a_second_different_message_with_a_seen_stamp_is_refused_and_a_resend_is_not():
    guard = c.DuplicateStampGuard(capacity=2)
    guard.check("depth", _Msg(1, b"abc"))
    guard.check("depth", _Msg(1, b"abc", compute_time_ms=5.0))  # the same content computed again
    assert guard.repeats == 1
    with pytest.raises(c.ContractError, match="second, different depth message with stamp 1000000000") as error:
        guard.check("depth", _Msg(1, b"abd"))
    assert error.value.reason == c.DUPLICATE_STAMP
    with pytest.raises(c.ContractError):
        guard.check("depth", _Msg(1, b"abc", boxes=(1.0, NAN)))
    guard.check("colour", _Msg(1, b"xyz"))  # streams are apart
    guard.check("depth", _Msg(2, b"abd"))
    guard.check("depth", _Msg(3, b"abe"))
    guard.check("depth", _Msg(1, b"zzz"))  # stamp 1 fell out of the two remembered
    assert c.fingerprint(_Msg(1, b"abc")) != c.fingerprint(_Msg(1, b"ab", boxes=(1.0, 2.0)))


def test_refused_counts_under_the_contract_or_the_callers_reason():
    rejected = []
    diagnostics = SimpleNamespace(reject=lambda reason, detail: rejected.append((reason, detail)))
    assert not c.refused(diagnostics, "bad_depth", c.check_same_size, "a", (1, 1), "b", (1, 1))
    assert c.refused(diagnostics, "bad_depth", c.check_same_size, "a", (1, 1), "b", (2, 1))
    assert c.refused(diagnostics, "bad_depth", c.check_finite, "depth offset", [NAN])
    assert rejected == [("image_size_mismatch", "a is 1x1 but b is 2x1"),
                        ("bad_depth", "depth offset has 1 non-finite value(s) (NaN or inf)")]


def test_boxes_may_reach_one_image_size_beyond_the_edges():
    edge = np.array([[-640, -480, 1280, 960, 0.5], [-100, -50, 200, 400, 0.9]])
    np.testing.assert_array_equal(c.check_boxes(edge, (640, 480)), edge.astype(np.float32))


def test_a_mesh_above_the_vertex_or_face_limit_is_too_large():
    c.check_mesh_size("mesh", 10_475, 20_908)
    c.check_mesh_size("mesh", c.MAX_MESH_VERTICES, c.MAX_MESH_FACES)
    for vertices, faces in [(c.MAX_MESH_VERTICES + 1, 1), (3, c.MAX_MESH_FACES + 1)]:
        with pytest.raises(c.ContractError, match="limit 100000 vertices, 200000 faces") as error:
            c.check_mesh_size("mesh", vertices, faces)
        assert error.value.reason == c.MESH_TOO_LARGE


def test_a_stamp_ahead_of_the_clock_beyond_the_tolerance_is_in_the_future():
    now = 1_800_000_000 * 10**9
    c.check_stamp_not_ahead("image", now + 500_000_000, now, 0.5)  # at the tolerance: accepted
    c.check_stamp_not_ahead("image", now - 10**12, now, 0.5)  # the past: always
    c.check_stamp_not_ahead("image", now + 10**18, now, 0.0)  # 0: no limit
    c.check_stamp_not_ahead("image", now, 0, 0.5)  # a clock at 0 (sim time before /clock): no check
    with pytest.raises(c.ContractError, match=r"image stamped 0.501 s ahead of the node clock \(limit 0.5 s") as error:
        c.check_stamp_not_ahead("image", now + 501_000_000, now, 0.5)
    assert error.value.reason == c.STAMP_IN_FUTURE
