"""Timing invariants of nbv_node as a process over DDS, with stamps from the clock: a frame is planned
only with its own ground plane (or an older one carried by the camera-pose delta), never with another
frame's; a goal older than max_goal_age_s is never published and goal_status says so; a burst of
targets is served newest-first with every skipped one counted."""
from __future__ import annotations

import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

import node_harness as harness  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from node_harness import NS, diag_value, read_log, set_parameters  # noqa: E402

from leapnbv_bringup.frame_chains import ChainVerdict, check_goal_chain  # noqa: E402
from leapnbv_common.camera_pose import StampedCameraPose  # noqa: E402
from leapnbv_common.conversions import (  # noqa: E402
    header_with_stamp,
    input_stamps,
    make_camera_info,
    point_msg,
    pose_msg,
    pose_to_numpy,
    stamp_to_ns,
    xyz_to_pointcloud2,
)
from leapnbv_common.qos import latched_goal_qos, stage_output_qos  # noqa: E402
from leapnbv_msgs.msg import (  # noqa: E402
    GoalStatus,
    GroundPlane,
    InputStamp,
    TargetGeometry,
    TargetTrack,
    ViewCandidates,
)
from leapnbv_planner.params import default_nbv_params  # noqa: E402

pytestmark = [pytest.mark.ros]

FRAME_ID = "camera_color_optical_frame"
MAP = "map"
K = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])
NODE = f"{NS}/nbv_node"
MAX_GOAL_AGE_S = 1.0  # the node's default
MAX_CARRY_NS = int(default_nbv_params().ground_max_age_s * 1e9)  # the node's default, 0.5 s


def camera_in_map(height: float, pitch_down_deg: float) -> tuple:
    """T_map_cameraOptical of a camera at (0, 0, height) looking along map +x, pitched down."""
    pitch = np.radians(pitch_down_deg)
    forward = np.array([np.cos(pitch), 0.0, -np.sin(pitch)])
    right = np.array([0.0, -1.0, 0.0])
    down = np.cross(forward, right)
    return np.column_stack([right, down, forward]), np.array([0.0, 0.0, height])


def floor_in_camera(rotation: np.ndarray, position: np.ndarray) -> tuple:
    """The floor z = 0 in the camera frame: n = R^T e_z (up), d = height."""
    return rotation.T @ np.array([0.0, 0.0, 1.0]), float(position[2])


def observation(stamp_ns: int, rotation: np.ndarray, position: np.ndarray) -> tuple:
    """(TargetGeometry, GroundPlane) of a person 3 m ahead on the floor of this camera pose."""
    header = header_with_stamp(stamp_ns, FRAME_ID)
    rng = np.random.default_rng(5)
    n = 2000
    # The person and floor in the map, seen from the camera.
    person_map = np.column_stack([rng.uniform(2.85, 3.15, n), rng.uniform(-0.25, 0.25, n), rng.uniform(0.0, 1.7, n)])
    floor_map = np.column_stack([rng.uniform(0.5, 6, 400), rng.uniform(-3, 3, 400), np.zeros(400)])
    to_camera = lambda p: (p - position) @ rotation  # noqa: E731
    person, floor = to_camera(person_map).astype(np.float32), to_camera(floor_map).astype(np.float32)
    target = TargetGeometry(header=header, valid=True, mask_pixel_count=n, visible_fraction=0.7)
    target.target_points = xyz_to_pointcloud2(person, header)
    target.background_points = xyz_to_pointcloud2(floor, header)
    target.centroid = point_msg(np.median(person, axis=0))
    target.bbox_min, target.bbox_max = point_msg(person.min(axis=0)), point_msg(person.max(axis=0))
    target.camera_info = make_camera_info(K, 640, 480, header)
    normal, offset = floor_in_camera(rotation, position)
    plane = GroundPlane(header=header, offset=offset, inlier_count=400, inlier_ratio=0.3, valid=True)
    plane.normal.x, plane.normal.y, plane.normal.z = (float(v) for v in normal)
    return target, plane


def send_observation(graph, stamp_ns: int, rotation: np.ndarray, position: np.ndarray) -> tuple:
    """Publish the frame's ground plane, then its target (as ground_node and raster_node would); returns both."""
    target, plane = observation(stamp_ns, rotation, position)
    graph["ground_pub"].publish(plane)
    graph["probe"].spin_for(0.05)
    graph["target_pub"].publish(target)
    return target, plane


def pose_message(stamp_ns: int, rotation: np.ndarray, position: np.ndarray) -> PoseStamped:
    return PoseStamped(header=header_with_stamp(stamp_ns, MAP), pose=pose_msg(rotation, position))


@pytest.fixture(scope="module")
def graph(tmp_path_factory):
    logs = tmp_path_factory.mktemp("frame_timing_logs")
    # No obstacle map: the camera poses serve only to carry a plane into a frame that lacks its own.
    procs = {NODE: harness.start_node("leapnbv_planner.nodes.nbv_node", str(logs / "nbv.log"),
                                      params={"use_obstacle_map": "false", "ground_wait_s": "0.3"})}
    with harness.running_graph("frame_timing_test", procs) as probe:
        g = {
            "probe": probe, "procs": procs,
            "target_pub": probe.node.create_publisher(TargetGeometry, f"{NS}/target_geometry", stage_output_qos(10)),
            "ground_pub": probe.node.create_publisher(GroundPlane, f"{NS}/ground_plane", stage_output_qos(10)),
            "pose_pub": probe.node.create_publisher(PoseStamped, f"{NS}/camera_pose", stage_output_qos(10)),
            "candidates": probe.collect(ViewCandidates, f"{NS}/view_candidates"),
            "goals": probe.collect(PoseStamped, f"{NS}/next_best_view", latched_goal_qos()),
            "base_goals": probe.collect(PoseStamped, f"{NS}/base_goal", latched_goal_qos()),
            "status": probe.collect(GoalStatus, f"{NS}/goal_status", latched_goal_qos()),
        }
        harness.wait_ready(probe, procs)
        assert probe.spin_until(lambda: all(g[k].get_subscription_count() >= 1
                                            for k in ("target_pub", "ground_pub", "pose_pub")), 10.0)
        probe.spin_for(0.3)
        yield g


def now_ns(graph) -> int:
    return graph["probe"].node.get_clock().now().nanoseconds


def counter(graph, key: str) -> int:
    status = graph["probe"].status_where(NODE, lambda s: True)
    return int(diag_value(status, key)) if status else 0


def counter_reaches(graph, key: str, value: int, timeout_s: float = 5.0) -> bool:
    return graph["probe"].spin_until(lambda: counter(graph, key) >= value, timeout_s)


def status_of(graph, goal_stamp: int, state: int):
    """The first goal_status of this goal stamp in this state, or None."""
    return next((m for m in graph["status"] if stamp_to_ns(m.goal_stamp) == goal_stamp and m.state == state), None)


def real_goals(graph) -> list:
    """The goals published (an empty frame_id is the "no goal" that replaces a stale one)."""
    return [g for g in graph["goals"] if g.header.frame_id]


def of_stamp(messages: list, stamp_ns: int) -> list:
    return [m for m in messages if stamp_to_ns(m.header.stamp) == stamp_ns and m.header.frame_id]


def chain_records(views: ViewCandidates, target: TargetGeometry, plane: GroundPlane) -> dict:
    """The recorded inputs for the shared mixed-frame check (bench_load.py's): nbv_node's candidates and the target
    and plane this test published (as raster_node and ground_node would, without inputs of their own)."""
    return {"view_candidates": {stamp_to_ns(views.header.stamp): input_stamps(views)},
            "target_geometry": {stamp_to_ns(target.header.stamp): input_stamps(target)},
            "ground_plane": {stamp_to_ns(plane.header.stamp): input_stamps(plane)}}


def test_a_frame_older_than_max_goal_age_gives_no_goal(graph):
    """First in the file: no frame was planned yet, so the only thing wrong with this one is its age."""
    probe = graph["probe"]
    before = counter(graph, "dropped.too_old_to_plan")
    goals_before = len(real_goals(graph))
    rotation, position = camera_in_map(1.2, 10.0)
    old = now_ns(graph) - int(1.5 * MAX_GOAL_AGE_S * 1e9)  # a frame that spent 1.5 s somewhere upstream
    send_observation(graph, old, rotation, position)
    assert counter_reaches(graph, "dropped.too_old_to_plan", before + 1)
    probe.spin_for(0.2)
    assert len(real_goals(graph)) == goals_before and not of_stamp(graph["candidates"], old)


def test_a_frame_is_planned_with_its_own_plane_and_records_it(graph):
    probe = graph["probe"]
    rotation, position = camera_in_map(1.2, 10.0)
    stamp = now_ns(graph)
    target, plane = send_observation(graph, stamp, rotation, position)
    # the goal first, then the candidates
    assert probe.spin_until(lambda: of_stamp(graph["goals"], stamp) and of_stamp(graph["candidates"], stamp), 10.0), \
        read_log(graph["procs"][NODE])[-2000:]
    (views,) = of_stamp(graph["candidates"], stamp)
    assert input_stamps(views) == [("target_geometry", stamp, InputStamp.SAME_FRAME),
                                   ("ground_plane", stamp, InputStamp.SAME_FRAME)]
    assert check_goal_chain(chain_records(views, target, plane), stamp, MAX_CARRY_NS) == ChainVerdict(True, False)
    assert probe.spin_until(lambda: status_of(graph, stamp, GoalStatus.STATE_CURRENT), 5.0)
    status = status_of(graph, stamp, GoalStatus.STATE_CURRENT)
    assert 0.0 <= status.goal_age_s < MAX_GOAL_AGE_S and status.max_goal_age_s == pytest.approx(MAX_GOAL_AGE_S)
    assert status.header.frame_id == FRAME_ID


def test_a_stalled_ground_plane_drops_the_frame_never_pairs_another_frames_plane(graph):
    """The next frame's plane never comes (ground_node stalled) while the previous frame's is at hand and
    the camera moved 0.3 m up: the frame is dropped and counted, not planned with the old plane."""
    probe = graph["probe"]
    rotation, position = camera_in_map(1.2, 10.0)
    first = now_ns(graph)
    old_target, old_plane = observation(first, rotation, position)
    graph["ground_pub"].publish(old_plane)
    probe.spin_for(0.05)
    graph["target_pub"].publish(old_target)
    assert probe.spin_until(lambda: of_stamp(graph["candidates"], first), 10.0)
    before = counter(graph, "rejected.ground_plane_late")
    moved_rotation, moved_position = camera_in_map(1.5, 20.0)
    stalled = now_ns(graph)
    target, _ = observation(stalled, moved_rotation, moved_position)
    graph["target_pub"].publish(target)  # its plane never comes; no camera poses either
    assert counter_reaches(graph, "rejected.ground_plane_late", before + 1)
    probe.spin_for(0.2)
    assert not of_stamp(graph["candidates"], stalled) and not of_stamp(graph["goals"], stalled)
    assert not of_stamp(graph["base_goals"], stalled)
    assert graph["procs"][NODE].poll() is None


def test_an_older_plane_is_carried_by_the_camera_pose_delta_and_recorded_as_carried(graph):
    """With the camera poses of both stamps, the previous frame's plane is moved into the frame: the base
    goal lies on the frame's true floor (0.3 m higher camera, 10 deg more pitch), not on the old one."""
    probe = graph["probe"]
    # Commitment off: frame b would keep the goal committed on frame a (the same person); the checks below are of
    # the goal frame b's own plan chose on the carried floor.
    assert set_parameters(probe, NODE, commit_goals=False)[0].successful
    rotation_a, position_a = camera_in_map(1.2, 10.0)
    rotation_b, position_b = camera_in_map(1.5, 20.0)
    stamp_a = now_ns(graph)
    target_a, plane_a = observation(stamp_a, rotation_a, position_a)
    graph["pose_pub"].publish(pose_message(stamp_a, rotation_a, position_a))
    graph["ground_pub"].publish(plane_a)
    probe.spin_for(0.05)
    graph["target_pub"].publish(target_a)
    assert probe.spin_until(lambda: of_stamp(graph["candidates"], stamp_a), 10.0)
    stamp_b = stamp_a + 100_000_000  # 0.1 s later: within ground_max_age_s (0.5 s)
    target_b, _ = observation(stamp_b, rotation_b, position_b)
    graph["pose_pub"].publish(pose_message(stamp_b, rotation_b, position_b))
    probe.spin_for(0.05)
    graph["target_pub"].publish(target_b)  # its own plane never comes
    assert probe.spin_until(lambda: of_stamp(graph["base_goals"], stamp_b) and of_stamp(graph["candidates"], stamp_b),
                            10.0), \
        read_log(graph["procs"][NODE])[-2000:]
    (views,) = of_stamp(graph["candidates"], stamp_b)
    assert input_stamps(views) == [("target_geometry", stamp_b, InputStamp.SAME_FRAME),
                                   ("ground_plane", stamp_a, InputStamp.CARRIED),
                                   ("camera_pose", stamp_a, InputStamp.CARRIED),
                                   ("camera_pose", stamp_b, InputStamp.SAME_FRAME)]
    records = chain_records(views, target_b, plane_a)
    assert check_goal_chain(records, stamp_b, MAX_CARRY_NS) == ChainVerdict(True, False,
                                                                            "carried ground_plane,camera_pose")
    assert check_goal_chain(records, stamp_b, 50_000_000).mixed  # a 0.1 s carry is too old for a 50 ms limit
    normal_b, offset_b = floor_in_camera(rotation_b, position_b)
    normal_a, offset_a = floor_in_camera(rotation_a, position_a)
    _, goal = pose_to_numpy(of_stamp(graph["base_goals"], stamp_b)[0].pose)
    assert abs(normal_b @ goal + offset_b) < 1e-3  # on the frame's own floor
    assert abs(normal_a @ goal + offset_a) > 0.1  # the uncarried old plane would be 0.1 m+ off
    assert set_parameters(probe, NODE, commit_goals=True)[0].successful


def test_carry_plane_moves_a_floor_between_camera_poses():
    from leapnbv_planner.floor_carry import carry_plane

    rotation_a, position_a = camera_in_map(1.2, 10.0)
    rotation_b, position_b = camera_in_map(1.5, 20.0)
    position_b = position_b + np.array([0.4, -0.7, 0.0])
    a = StampedCameraPose(1, MAP, rotation_a, position_a)
    b = StampedCameraPose(2, MAP, rotation_b, position_b)
    normal, offset = carry_plane(*floor_in_camera(rotation_a, position_a), a, b)
    expected_normal, expected_offset = floor_in_camera(rotation_b, position_b)
    np.testing.assert_allclose(normal, expected_normal, atol=1e-12)
    assert offset == pytest.approx(expected_offset, abs=1e-12)


def test_a_goal_that_ages_out_is_withdrawn_and_the_status_says_so(graph):
    probe = graph["probe"]
    assert set_parameters(probe, NODE, max_goal_age_s=0.5)[0].successful
    try:
        rotation, position = camera_in_map(1.2, 10.0)
        stamp = now_ns(graph)
        send_observation(graph, stamp, rotation, position)
        assert probe.spin_until(lambda: of_stamp(graph["goals"], stamp), 10.0)
        published = time.monotonic()
        assert probe.spin_until(lambda: status_of(graph, stamp, GoalStatus.STATE_STALE), 5.0)
        waited = time.monotonic() - published
        stale = status_of(graph, stamp, GoalStatus.STATE_STALE)
        assert stale.goal_age_s > 0.5 and "withdrawn" in stale.reason and stale.header.frame_id == ""
        assert waited < 0.5 + 0.5, waited  # the age timer checks every 0.1 s
        # The latched goals were replaced by "no goal" (empty frame_id): a late motion stack gets that.
        late_goals = probe.collect(PoseStamped, f"{NS}/next_best_view", latched_goal_qos())
        late_bases = probe.collect(PoseStamped, f"{NS}/base_goal", latched_goal_qos())
        late_status = probe.collect(GoalStatus, f"{NS}/goal_status", latched_goal_qos())
        assert probe.spin_until(lambda: late_goals and late_bases and late_status, 5.0)
        assert late_goals[-1].header.frame_id == "" and late_bases[-1].header.frame_id == ""
        assert late_status[-1].state == GoalStatus.STATE_STALE
        assert stamp_to_ns(late_status[-1].goal_stamp) == stamp
        assert counter_reaches(graph, "dropped.goal_withdrawn_stale", 1)
        # A fresh frame makes the goal current again.
        fresh = now_ns(graph)
        send_observation(graph, fresh, rotation, position)
        assert probe.spin_until(lambda: status_of(graph, fresh, GoalStatus.STATE_CURRENT), 10.0)
    finally:
        assert set_parameters(probe, NODE, max_goal_age_s=MAX_GOAL_AGE_S)[0].successful


def test_a_goal_to_a_target_out_of_view_is_held_longer_and_then_withdrawn(graph):
    # hmr_node says NOT_SEEN (the drive passes behind furniture that hides the person): the goal may grow
    # hidden_target_goal_hold_s older than max_goal_age_s, and valid_until says so; then it is withdrawn.
    probe = graph["probe"]
    track_pub = probe.node.create_publisher(TargetTrack, f"{NS}/target_track", stage_output_qos(5))
    assert probe.spin_until(lambda: track_pub.get_subscription_count() >= 1, 5.0)
    assert set_parameters(probe, NODE, max_goal_age_s=0.5, hidden_target_goal_hold_s=1.0)[0].successful
    try:
        rotation, position = camera_in_map(1.2, 10.0)
        stamp = now_ns(graph)
        send_observation(graph, stamp, rotation, position)
        assert probe.spin_until(lambda: of_stamp(graph["goals"], stamp), 10.0)
        published = time.monotonic()
        track_pub.publish(TargetTrack(header=header_with_stamp(stamp, FRAME_ID), state=TargetTrack.STATE_NOT_SEEN,
                                      track_id=3, reason="not seen: no detections"))
        assert probe.spin_until(lambda: any(stamp_to_ns(m.goal_stamp) == stamp and m.state == GoalStatus.STATE_CURRENT
                                            and m.target.state == TargetTrack.STATE_NOT_SEEN for m in graph["status"]),
                                5.0)
        hidden = [m for m in graph["status"] if stamp_to_ns(m.goal_stamp) == stamp
                  and m.target.state == TargetTrack.STATE_NOT_SEEN][-1]
        assert stamp_to_ns(hidden.valid_until) == stamp + 1_500_000_000  # the age limit and the hold
        probe.spin_for(max(0.0, 1.0 - (time.monotonic() - published)))  # past max_goal_age_s: still held
        assert status_of(graph, stamp, GoalStatus.STATE_STALE) is None
        assert probe.spin_until(lambda: status_of(graph, stamp, GoalStatus.STATE_STALE), 5.0)
        stale = status_of(graph, stamp, GoalStatus.STATE_STALE)
        assert stale.goal_age_s > 1.5 and "1.5 s" in stale.reason, stale.reason
    finally:
        track_pub.publish(TargetTrack(header=header_with_stamp(now_ns(graph), FRAME_ID),
                                      state=TargetTrack.STATE_TRACKED, track_id=3))
        probe.spin_for(0.2)
        assert set_parameters(probe, NODE, max_goal_age_s=MAX_GOAL_AGE_S,
                              hidden_target_goal_hold_s=default_nbv_params().hidden_target_goal_hold_s)[0].successful


def test_a_burst_of_targets_is_served_newest_first_and_every_skipped_one_is_counted(graph):
    """Ten frames at once (as after a stall upstream): the newest is planned, no older one after it,
    and each one not planned is counted on /diagnostics under a reason."""
    probe = graph["probe"]
    rotation, position = camera_in_map(1.2, 10.0)
    reasons = ("dropped.target_geometry_not_taken", "dropped.older_than_published", "dropped.target_superseded",
               "dropped.duplicate_stamp", "dropped.too_old_to_plan")
    before_dropped = sum(counter(graph, key) for key in reasons)
    before_in = counter(graph, "frames_in")
    base = now_ns(graph)
    stamps = [base + i * 33_000_000 for i in range(10)]
    frames = [observation(stamp, rotation, position) for stamp in stamps]
    for _, plane in frames:
        graph["ground_pub"].publish(plane)
    probe.spin_for(0.1)
    for target, _ in frames:
        graph["target_pub"].publish(target)
    assert probe.spin_until(lambda: of_stamp(graph["candidates"], stamps[-1]), 10.0)
    probe.spin_for(1.5)  # the diagnostics of the last second
    planned = [stamp for stamp in stamps if of_stamp(graph["candidates"], stamp)]
    order = [stamp_to_ns(v.header.stamp) for v in graph["candidates"] if stamp_to_ns(v.header.stamp) in stamps]
    assert order == sorted(order) and planned[-1] == stamps[-1]
    dropped = sum(counter(graph, key) for key in reasons) - before_dropped
    taken = counter(graph, "frames_in") - before_in
    not_taken = len(stamps) - taken
    assert len(planned) + dropped == len(stamps), (planned, dropped, taken, not_taken)
    assert len(planned) < len(stamps)  # the node did not plan its way through the backlog


def test_admission_holds_frames_while_one_is_in_flight_and_not_for_long_after_a_refusal():
    from leapnbv_perception.admission import MIN_IN_FLIGHT_TIMEOUT_S, FramesInFlight

    frames = FramesInFlight()
    assert not frames.full(1, now_s=0.0, timeout_s=0.5)  # the planner never answered: no limit yet
    frames.admit(1, now_s=0.0)
    frames.done(1, now_s=0.1)  # answered after 0.1 s
    frames.admit(2, now_s=1.0)
    assert frames.full(1, now_s=1.05, timeout_s=0.5)  # one in flight: the next frame is dropped
    frames.done(2, now_s=1.1)
    assert not frames.full(1, now_s=1.1, timeout_s=0.5)
    frames.admit(3, now_s=2.0)  # refused downstream: it never comes back
    assert frames.full(1, now_s=2.15, timeout_s=0.5)
    assert not frames.full(1, now_s=2.21, timeout_s=0.5)  # 2 x the 0.1 s answer time, not the 0.5 s bound
    assert frames.timed_out == 1 and frames.timeout(0.5) >= MIN_IN_FLIGHT_TIMEOUT_S
    frames.admit(4, now_s=3.0)
    frames.admit(5, now_s=3.01)
    frames.done(5, now_s=3.1)  # an answer for a newer frame completes the older ones too
    assert len(frames) == 0
