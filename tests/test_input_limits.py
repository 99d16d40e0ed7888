"""The input limits of the stage nodes, through the nodes over DDS.

A stamp from the future, a camera pose that is refused (and the goal that says it was planned without the
obstacle map), boxes far beyond the image, meshes above the vertex limit, an obstacle map above the voxel limit,
and goal_status's valid_until checked on a consumer's clock while nbv_node is frozen.
"""
from __future__ import annotations

import os
import signal

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

import node_harness as harness  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from node_harness import NS, diag_value, read_log  # noqa: E402
from sensor_msgs.msg import Image, PointCloud2  # noqa: E402
from std_msgs.msg import Header  # noqa: E402
from test_nbv_node import CAMERA_IN_MAP, MAP_FRAME, observation, to_map, voxel_box  # noqa: E402

from leapnbv_common.contracts import MAX_MESH_VERTICES  # noqa: E402
from leapnbv_common.conversions import (  # noqa: E402
    HumanMeshArrays,
    arrays_to_human_mesh,
    numpy_to_image,
    pose_msg,
    pose_to_numpy,
    set_stamp,
    stamp_to_ns,
    xyz_to_pointcloud2,
)
from leapnbv_common.params import MAX_STAMP_AHEAD_S  # noqa: E402
from leapnbv_common.qos import latched_goal_qos, latched_map_qos, stage_output_qos  # noqa: E402
from leapnbv_msgs.msg import (  # noqa: E402
    GoalStatus,
    GroundPlane,
    HumanMesh,
    PersonDetection,
    PersonDetections,
    TargetGeometry,
    ViewCandidates,
)
from leapnbv_planner.params import default_nbv_params  # noqa: E402
from leapnbv_stand_ins.files import ensure_contract_models, ensure_stand_in_body_model  # noqa: E402

pytestmark = [pytest.mark.ros]

NBV = f"{NS}/nbv_node"
FRAME_ID = "camera_color_optical_frame"
WIDTH, HEIGHT = 640, 480
# Longer than the default 1 s: a loaded test machine may take a while to plan; the rule is the same.
MAX_GOAL_AGE_S = 3.0
YEAR_NS = 365 * 24 * 3600 * 1_000_000_000


def header_at(stamp_ns: int, frame_id: str = FRAME_ID) -> Header:
    header = Header(frame_id=frame_id)
    set_stamp(header.stamp, stamp_ns)
    return header


def counter(probe, node: str, key: str) -> int:
    status = probe.status_where(node, lambda s: True)
    return int(diag_value(status, key)) if status else 0


def counter_reaches(probe, node: str, key: str, value: int, timeout_s: float = 10.0) -> bool:
    return probe.spin_until(lambda: counter(probe, node, key) >= value, timeout_s)


def last_rejection(probe, node: str) -> str:
    status = probe.status_where(node, lambda s: True)
    return diag_value(status, "last_rejection", "") if status else ""


def big_mesh(header: Header, vertices: int) -> HumanMesh:
    """A HumanMesh of ``vertices`` vertices (one face): well-formed but for its size."""
    mesh = HumanMeshArrays(
        vertices=np.random.default_rng(3).normal(0.0, 0.3, (vertices, 3)).astype(np.float32),
        faces=np.array([[0, 1, 2]], np.uint32), virtual_intrinsics=(5000.0, 5000.0, 320.0, 240.0),
        image_size=(WIDTH, HEIGHT), detection=np.array([200, 100, 300, 400, 0.9], np.float32),
        processed_box=np.zeros(4), root_pose=np.zeros(3), body_pose=np.zeros(63), left_hand_pose=np.zeros(45),
        right_hand_pose=np.zeros(45), jaw_pose=np.zeros(3), betas=np.zeros(10), expression=np.zeros(10),
        cam_translation=np.array([0.0, 0.0, 20.0]), model_id="too_large")
    return arrays_to_human_mesh(mesh, header)


def consumer_may_act(status: GoalStatus, goal: PoseStamped, now_ns: int) -> bool:
    """The rule README's "Subscribing to the goal" gives a motion stack, on the consumer's own clock."""
    valid_until = stamp_to_ns(status.valid_until)
    return (bool(goal.header.frame_id) and status.state == GoalStatus.STATE_CURRENT
            and stamp_to_ns(status.goal_stamp) == stamp_to_ns(goal.header.stamp)
            and (valid_until == 0 or now_ns < valid_until))


# ----------------------------------------------------------------------------- nbv_node


@pytest.fixture(scope="module")
def nbv(tmp_path_factory):
    logs = tmp_path_factory.mktemp("input_limits_nbv")
    procs = {NBV: harness.start_node("leapnbv_planner.nodes.nbv_node", str(logs / "nbv.log"),
                                     params={"max_goal_age_s": str(MAX_GOAL_AGE_S)})}
    with harness.running_graph("input_limits_nbv", procs) as probe:
        g = {
            "probe": probe, "procs": procs,
            "target_pub": probe.node.create_publisher(TargetGeometry, f"{NS}/target_geometry", stage_output_qos(5)),
            "ground_pub": probe.node.create_publisher(GroundPlane, f"{NS}/ground_plane", stage_output_qos(5)),
            "pose_pub": probe.node.create_publisher(PoseStamped, f"{NS}/camera_pose", stage_output_qos(10)),
            "map_pub": probe.node.create_publisher(PointCloud2, f"{NS}/obstacle_map", latched_map_qos()),
            "candidates": probe.collect(ViewCandidates, f"{NS}/view_candidates"),
            "goals": probe.collect(PoseStamped, f"{NS}/next_best_view", latched_goal_qos()),
            "status": probe.collect(GoalStatus, f"{NS}/goal_status", latched_goal_qos()),
        }
        harness.wait_ready(probe, procs)
        assert probe.spin_until(lambda: all(g[k].get_subscription_count() >= 1
                                            for k in ("target_pub", "ground_pub", "pose_pub", "map_pub")), 10.0)
        probe.spin_for(0.3)
        yield g


def now_ns(g) -> int:
    return int(g["probe"].node.get_clock().now().nanoseconds)


def send(g, stamp_ns: int, pose=None) -> None:
    """One frame: its camera pose (a PoseStamped's pose, or none), its ground plane, then its target."""
    header = header_at(stamp_ns)
    target, plane = observation(header)
    if pose is not None:
        g["pose_pub"].publish(PoseStamped(header=header_at(stamp_ns, MAP_FRAME), pose=pose))
    g["ground_pub"].publish(plane)
    g["probe"].spin_for(0.05)
    g["target_pub"].publish(target)


def of_stamp(messages: list, stamp_ns: int) -> list:
    return [m for m in messages if stamp_to_ns(m.header.stamp) == stamp_ns and m.header.frame_id]


def current_status(g, stamp_ns: int):
    return next((m for m in g["status"] if m.state == GoalStatus.STATE_CURRENT
                 and stamp_to_ns(m.goal_stamp) == stamp_ns), None)


def planned(g, stamp_ns: int, timeout_s: float = 15.0) -> ViewCandidates:
    """The candidates of a frame, once its goal and its CURRENT status came."""
    ok = g["probe"].spin_until(lambda: of_stamp(g["candidates"], stamp_ns) and of_stamp(g["goals"], stamp_ns)
                               and current_status(g, stamp_ns), timeout_s)
    assert ok, f"no goal of {stamp_ns}:\n{read_log(g['procs'][NBV])[-3000:]}"
    return of_stamp(g["candidates"], stamp_ns)[0]


@pytest.fixture(scope="module")
def plain(nbv):
    """A frame planned before any map came (the view a pillar is put on below)."""
    stamp = now_ns(nbv)
    send(nbv, stamp)
    return planned(nbv, stamp)


def test_a_target_stamped_a_year_ahead_gives_no_goal_and_the_next_frame_plans(nbv, plain):
    probe = nbv["probe"]
    before = counter(probe, NBV, "rejected.stamp_in_future")
    future = now_ns(nbv) + YEAR_NS
    send(nbv, future)
    assert counter_reaches(probe, NBV, "rejected.stamp_in_future", before + 1)
    assert "ahead of the node clock" in last_rejection(probe, NBV)
    probe.spin_for(0.5)
    assert not of_stamp(nbv["candidates"], future) and not of_stamp(nbv["goals"], future)
    assert all(stamp_to_ns(m.goal_stamp) != future for m in nbv["status"])
    # Refused before it was remembered: the next frame of the real clock is not "older than published".
    stamp = now_ns(nbv)
    send(nbv, stamp)
    planned(nbv, stamp)
    assert counter(probe, NBV, "dropped.older_than_published") == 0


def test_a_frame_half_the_tolerance_ahead_is_planned(nbv, plain):
    """Clocks a few ms apart (two synchronised hosts) are inside the tolerance."""
    stamp = now_ns(nbv) + int(0.5 * MAX_STAMP_AHEAD_S * 1e9)
    send(nbv, stamp)
    planned(nbv, stamp)
    assert nbv["probe"].spin_until(lambda: now_ns(nbv) > stamp, 2.0)  # the next frames are newer


def test_valid_until_is_the_goal_stamp_plus_the_limit(nbv, plain):
    stamp = now_ns(nbv)
    send(nbv, stamp)
    planned(nbv, stamp)
    status = current_status(nbv, stamp)
    assert stamp_to_ns(status.valid_until) == stamp + int(MAX_GOAL_AGE_S * 1e9)
    assert status.max_goal_age_s == pytest.approx(MAX_GOAL_AGE_S)
    # The statuses without a goal carry no valid_until: a consumer never acts on them.
    assert all(stamp_to_ns(m.valid_until) == 0 for m in nbv["status"] if m.state != GoalStatus.STATE_CURRENT)


def test_a_zero_quaternion_pose_is_refused_and_the_goal_says_it_was_planned_without_the_map(nbv, plain):
    probe = nbv["probe"]
    chosen = plain.chosen_index
    _, chosen_position = pose_to_numpy(plain.poses[chosen])
    nbv["map_pub"].publish(xyz_to_pointcloud2(voxel_box(to_map(chosen_position)[:2], 0.1, 2.0).astype(np.float32),
                                              Header(frame_id=MAP_FRAME)))
    assert probe.spin_until(lambda: "obstacle map:" in read_log(nbv["procs"][NBV]), 10.0)
    good_pose = pose_msg(*CAMERA_IN_MAP)

    # With its pose, the frame is planned with the map: the pillar blocks the view chosen without it.
    stamp = now_ns(nbv)
    send(nbv, stamp, good_pose)
    mapped = planned(nbv, stamp)
    assert not mapped.feasible[chosen] and mapped.infeasible_reason[chosen] == 2  # OBSTACLE
    assert list(current_status(nbv, stamp).planned_without) == []

    bad_before = counter(probe, NBV, "rejected.bad_camera_pose")
    without_before = counter(probe, NBV, "counted.planned_without.obstacle_map")
    zero = pose_msg(*CAMERA_IN_MAP)
    zero.orientation.x = zero.orientation.y = zero.orientation.z = zero.orientation.w = 0.0
    stamp = now_ns(nbv)
    send(nbv, stamp, zero)
    unmapped = planned(nbv, stamp)
    assert unmapped.feasible[chosen]  # planned without the map: the pillar is not there
    status = current_status(nbv, stamp)
    assert list(status.planned_without) == ["obstacle_map"]
    assert "planned without obstacle_map" in status.reason and "refused" in status.reason
    assert "not a unit quaternion (|q| = 0.0000" in status.reason
    assert counter_reaches(probe, NBV, "rejected.bad_camera_pose", bad_before + 1)
    assert counter_reaches(probe, NBV, "counted.planned_without.obstacle_map", without_before + 1)

    # A NaN quaternion: the same.
    nan = pose_msg(*CAMERA_IN_MAP)
    nan.orientation.w = float("nan")
    stamp = now_ns(nbv)
    send(nbv, stamp, nan)
    planned(nbv, stamp)
    status = current_status(nbv, stamp)
    assert list(status.planned_without) == ["obstacle_map"] and "|q| = nan" in status.reason

    # A frame whose pose never came says that instead.
    stamp = now_ns(nbv)
    send(nbv, stamp)
    planned(nbv, stamp)
    assert "no camera pose with this frame's stamp came" in current_status(nbv, stamp).reason


def test_an_obstacle_map_above_the_voxel_limit_is_refused_and_the_previous_map_kept(nbv, plain):
    """After the pose test (its pillar map latched): a map of a million voxels changes nothing."""
    probe = nbv["probe"]
    limit = default_nbv_params().max_obstacle_voxels
    before = counter(probe, NBV, "rejected.obstacle_map_too_large")
    side = 100  # 1e6 voxels: a 10 m cube of 0.1 m voxels
    index = np.stack(np.meshgrid(*(np.arange(side),) * 3, indexing="ij"), -1).reshape(-1, 3)
    huge = ((index + 0.5) * 0.1 + np.array([-5.0, -5.0, 0.0])).astype(np.float32)
    assert len(huge) > limit
    nbv["map_pub"].publish(xyz_to_pointcloud2(huge, Header(frame_id=MAP_FRAME)))
    assert counter_reaches(probe, NBV, "rejected.obstacle_map_too_large", before + 1, 20.0)
    detail = last_rejection(probe, NBV)
    assert f"{len(huge)} voxels" in detail and "the previous map" in detail and "stays in use" in detail
    # The pillar map is still the one planned with (the huge cube would block every view).
    stamp = now_ns(nbv)
    send(nbv, stamp, pose_msg(*CAMERA_IN_MAP))
    views = planned(nbv, stamp)
    assert not views.feasible[plain.chosen_index] and views.infeasible_reason[plain.chosen_index] == 2
    assert int(np.count_nonzero(views.feasible)) >= len(views.poses) // 2


def test_a_body_mesh_above_the_vertex_limit_is_refused_and_the_goal_says_so(nbv, plain):
    probe = nbv["probe"]
    mesh_pub = probe.node.create_publisher(HumanMesh, f"{NS}/human_mesh_metric", stage_output_qos(2))
    try:
        assert probe.spin_until(lambda: mesh_pub.get_subscription_count() >= 1, 10.0)
        probe.spin_for(0.3)
        before = counter(probe, NBV, "rejected.mesh_too_large")
        stamp = now_ns(nbv)
        mesh_pub.publish(big_mesh(header_at(stamp), 1_000_000))
        probe.spin_for(0.2)
        send(nbv, stamp)
        assert counter_reaches(probe, NBV, "rejected.mesh_too_large", before + 1, 20.0)
        planned(nbv, stamp)
        status = current_status(nbv, stamp)
        assert "human_mesh_metric" in list(status.planned_without)
    finally:
        probe.node.destroy_publisher(mesh_pub)


def test_a_consumer_check_fails_after_valid_until_while_nbv_node_is_frozen(nbv, plain):
    """Last: the node is stopped (SIGSTOP); its latched CURRENT status expires on the consumer's clock."""
    probe, proc = nbv["probe"], nbv["procs"][NBV]
    stamp = now_ns(nbv)
    send(nbv, stamp)
    planned(nbv, stamp)
    status, goal = current_status(nbv, stamp), of_stamp(nbv["goals"], stamp)[-1]
    assert consumer_may_act(status, goal, now_ns(nbv))
    os.kill(proc.pid, signal.SIGSTOP)
    try:
        valid_until = stamp_to_ns(status.valid_until)
        probe.spin_until(lambda: now_ns(nbv) > valid_until + 100_000_000, MAX_GOAL_AGE_S + 2.0)
        # Nothing came from the frozen node: the last status the consumer holds is still CURRENT ...
        assert nbv["status"][-1].state == GoalStatus.STATE_CURRENT
        assert stamp_to_ns(nbv["status"][-1].goal_stamp) == stamp
        # ... and the consumer's own clock says the goal may no longer be acted on.
        assert not consumer_may_act(nbv["status"][-1], goal, now_ns(nbv))
    finally:
        os.kill(proc.pid, signal.SIGCONT)
    # Thawed, the node withdraws the goal itself.
    assert probe.spin_until(lambda: nbv["status"][-1].state == GoalStatus.STATE_STALE, 10.0)
    assert stamp_to_ns(nbv["status"][-1].valid_until) == 0


# ----------------------------------------------------------------------------- the other stages' key inputs


@pytest.fixture(scope="module")
def stages(tmp_path_factory):
    logs = tmp_path_factory.mktemp("input_limits_stages")
    detector, hmr = ensure_contract_models()
    body = ensure_stand_in_body_model("small")
    engine = {"backend": "onnxruntime", "precision": "fp32", "intra_op_threads": "1"}
    procs = {
        f"{NS}/detector_node": harness.start_node("leapnbv_perception.nodes.detector_node",
                                                  str(logs / "detector.log"),
                                                  params={**engine, "model_file_path": detector,
                                                          "multi_label": "true"}),
        f"{NS}/hmr_node": harness.start_node("leapnbv_perception.nodes.hmr_node", str(logs / "hmr.log"),
                                             params={**engine, "model_file_path": hmr, "body_model_path": body}),
        f"{NS}/ground_node": harness.start_node("leapnbv_geometry.nodes.ground_node", str(logs / "ground.log")),
        f"{NS}/raster_node": harness.start_node("leapnbv_geometry.nodes.raster_node", str(logs / "raster.log")),
    }
    with harness.running_graph("input_limits_stages", procs) as probe:
        g = {
            "probe": probe, "procs": procs,
            "image_pub": probe.node.create_publisher(Image, f"{NS}/image", stage_output_qos(5)),
            "detections_pub": probe.node.create_publisher(PersonDetections, f"{NS}/detections", stage_output_qos(5)),
            "mesh_pub": probe.node.create_publisher(HumanMesh, f"{NS}/human_mesh", stage_output_qos(2)),
            "detections": probe.collect(PersonDetections, f"{NS}/detections"),
        }
        harness.wait_ready(probe, procs)
        assert probe.spin_until(lambda: g["image_pub"].get_subscription_count() >= 2
                                and g["detections_pub"].get_subscription_count() >= 2
                                and g["mesh_pub"].get_subscription_count() >= 1, 15.0)
        probe.spin_for(0.3)
        yield g


def detections(stamp_ns: int, box) -> PersonDetections:
    msg = PersonDetections(header=header_at(stamp_ns), image_width=WIDTH, image_height=HEIGHT)
    msg.detections = [PersonDetection(x_min=float(box[0]), y_min=float(box[1]), x_max=float(box[2]),
                                      y_max=float(box[3]), score=0.9)]
    return msg


def test_a_colour_frame_stamped_a_year_ahead_is_refused_and_the_next_one_detected(stages):
    from test_perception_nodes import person_blob_image

    probe, name = stages["probe"], f"{NS}/detector_node"
    before = counter(probe, name, "rejected.stamp_in_future")
    rgb, _ = person_blob_image(300, 120)
    future = int(probe.node.get_clock().now().nanoseconds) + YEAR_NS
    stages["image_pub"].publish(numpy_to_image(rgb, "rgb8", header_at(future)))
    assert counter_reaches(probe, name, "rejected.stamp_in_future", before + 1)
    assert not of_stamp(stages["detections"], future)
    stamp = int(probe.node.get_clock().now().nanoseconds)
    good = numpy_to_image(rgb, "rgb8", header_at(stamp))
    assert harness.send_until(probe, lambda: stages["image_pub"].publish(good),
                              lambda: of_stamp(stages["detections"], stamp), 24.0)


@pytest.mark.parametrize("node", ["hmr_node", "ground_node"])
def test_detections_stamped_ahead_or_with_a_box_far_beyond_the_image_are_refused(stages, node):
    probe, name = stages["probe"], f"{NS}/{node}"
    future_before = counter(probe, name, "rejected.stamp_in_future")
    bad_before = counter(probe, name, "rejected.bad_detections")
    now = int(probe.node.get_clock().now().nanoseconds)
    stages["detections_pub"].publish(detections(now + YEAR_NS, (200, 100, 300, 400)))
    assert counter_reaches(probe, name, "rejected.stamp_in_future", future_before + 1)
    # A box of +-1e9 px overlaps the image but is no person in it: refused like a box outside the image.
    stages["detections_pub"].publish(detections(now + 1, (-1e9, -1e9, 1e9, 1e9)))
    assert counter_reaches(probe, name, "rejected.bad_detections", bad_before + 1)
    assert "beyond the 640x480 image" in last_rejection(probe, name)
    # A box of a person cut by the image's edge is a detection.
    stages["detections_pub"].publish(detections(now + 2, (-100, -50, 200, 400)))
    probe.spin_for(1.0)
    assert counter(probe, name, "rejected.bad_detections") == bad_before + 1


def test_raster_refuses_a_mesh_above_the_vertex_limit_and_one_from_the_future(stages):
    probe, name = stages["probe"], f"{NS}/raster_node"
    before = counter(probe, name, "rejected.mesh_too_large")
    now = int(probe.node.get_clock().now().nanoseconds)
    stages["mesh_pub"].publish(big_mesh(header_at(now), 1_000_000))
    assert counter_reaches(probe, name, "rejected.mesh_too_large", before + 1, 20.0)
    assert f"limit {MAX_MESH_VERTICES} vertices" in last_rejection(probe, name)
    future_before = counter(probe, name, "rejected.stamp_in_future")
    stages["mesh_pub"].publish(big_mesh(header_at(now + YEAR_NS), 10_475))
    assert counter_reaches(probe, name, "rejected.stamp_in_future", future_before + 1)
