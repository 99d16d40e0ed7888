"""nbv_node as a process with ``camera_pose_source:=tf``: its camera pose from real TFMessages on /tf and /tf_static.

The probe publishes a robot's tree (``map -> odom -> base_link`` on /tf at each frame's stamp,
``base_link -> camera_link -> camera_color_optical_frame`` on /tf_static) and an obstacle map in
``map`` with a pillar on the foot point of the view the node chooses without a map. A frame whose
transforms came is planned with the map (that view is blocked); a frame whose transforms did not
come (an extrapolation), whose optical frame is not in the tree (a missing transform), or whose base
was re-parented away from the map (a parent that changes) is planned without it and counted as
``no_camera_pose``, with the reason in the node's log.
"""
from __future__ import annotations

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

import node_harness as harness  # noqa: E402
from node_harness import NS, by_stamp, diag_value, read_log, stamp_key  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from std_msgs.msg import Header  # noqa: E402
from test_nbv_node import CAMERA_HEIGHT, FRAME_ID, MAP_FRAME, observation, to_map, voxel_box  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402

from leapnbv_common.camera_pose.tf_messages import tf_message  # noqa: E402
from leapnbv_common.conversions import pose_to_numpy, xyz_to_pointcloud2  # noqa: E402
from leapnbv_common.qos import latched_map_qos, stage_output_qos, tf_qos, tf_static_qos  # noqa: E402
from leapnbv_common.tf_buffer import StampedTransform, Transform  # noqa: E402
from leapnbv_common.topics import TF_STATIC_TOPIC, TF_TOPIC  # noqa: E402
from leapnbv_msgs.msg import GroundPlane, TargetGeometry, ViewCandidates  # noqa: E402

pytestmark = [pytest.mark.ros]

S = 1_000_000_000
IDENTITY = [0.0, 0.0, 0.0, 1.0]
OPTICAL = [-0.5, 0.5, -0.5, 0.5]  # camera_link (x forward, z up) -> optical (x right, y down, z forward)
OBSTACLE = 2  # ViewCandidates.infeasible_reason of a view inside the obstacle map


def link(parent: str, child: str, stamp_ns: int, rotation, translation) -> StampedTransform:
    return StampedTransform(parent, child, stamp_ns, Transform.checked(rotation, translation))


def base_links(sec: int, parent: str = "odom") -> TFMessage:
    """The camera of test_nbv_node's CAMERA_IN_MAP: base at the map origin facing +x, the head 1.2 m above it."""
    return tf_message([link(MAP_FRAME, "odom", sec * S, IDENTITY, [0.0, 0.0, 0.0]),
                       link(parent, "base_link", sec * S, IDENTITY, [0.0, 0.0, 0.0])])


@pytest.fixture(scope="module")
def graph(tmp_path_factory):
    logs = tmp_path_factory.mktemp("nbv_tf_logs")
    procs = {f"{NS}/nbv_node": harness.start_node(
        "leapnbv_planner.nodes.nbv_node", str(logs / "nbv.log"),
        # commit_goals off: the commitment would look frame 100's pose up too, and its warning (one a period per
        # kind) would hold back the "not connected" one this test reads.
        params={"max_goal_age_s": "0.0", "camera_pose_source": "tf", "camera_pose_fixed_frame": MAP_FRAME,
                "commit_goals": "false"})}
    with harness.running_graph("nbv_node_tf_test", procs) as probe:
        g = {
            "probe": probe, "procs": procs,
            "target_pub": probe.node.create_publisher(TargetGeometry, f"{NS}/target_geometry", stage_output_qos(5)),
            "ground_pub": probe.node.create_publisher(GroundPlane, f"{NS}/ground_plane", stage_output_qos(5)),
            "map_pub": probe.node.create_publisher(PointCloud2, f"{NS}/obstacle_map", latched_map_qos()),
            "tf_pub": probe.node.create_publisher(TFMessage, TF_TOPIC, tf_qos()),
            "static_pub": probe.node.create_publisher(TFMessage, TF_STATIC_TOPIC, tf_static_qos(1)),
            "candidates": probe.collect(ViewCandidates, f"{NS}/view_candidates"),
        }
        g["static_pub"].publish(tf_message([link("base_link", "camera_link", 0, IDENTITY, [0.0, 0.0, CAMERA_HEIGHT]),
                                            link("camera_link", FRAME_ID, 0, OPTICAL, [0.0, 0.0, 0.0])]))
        harness.wait_ready(probe, procs)
        assert probe.spin_until(lambda: g["target_pub"].get_subscription_count() >= 1
                                and g["tf_pub"].get_subscription_count() >= 1, 10.0)
        probe.spin_for(0.2)
        yield g


def plan(graph, sec: int, frame_id: str = FRAME_ID, tf: TFMessage = None) -> ViewCandidates:
    """Publish a frame's transforms (if any), its ground plane, then its target; the view candidates planned."""
    probe = graph["probe"]
    if tf is not None:
        graph["tf_pub"].publish(tf)
        probe.spin_for(0.05)
    header = Header(frame_id=frame_id)
    header.stamp.sec = sec
    target, plane = observation(header)
    graph["ground_pub"].publish(plane)
    probe.spin_for(0.1)
    graph["target_pub"].publish(target)
    key = stamp_key(header)
    assert probe.spin_until(lambda: by_stamp(graph["candidates"], key), 10.0), \
        read_log(graph["procs"][NS + "/nbv_node"])[-3000:]
    (views,) = by_stamp(graph["candidates"], key)
    return views


def no_pose_count(graph) -> int:
    status = graph["probe"].status_where(f"{NS}/nbv_node", lambda s: True)
    return int(diag_value(status, "rejected.no_camera_pose")) if status else 0


def test_nbv_node_plans_with_its_camera_pose_from_tf(graph):
    probe = graph["probe"]
    plain = plan(graph, 100)  # no obstacle map yet: planned without one
    chosen = plain.chosen_index
    _, chosen_position = pose_to_numpy(plain.poses[chosen])
    graph["map_pub"].publish(xyz_to_pointcloud2(voxel_box(to_map(chosen_position)[:2], 0.1, 2.0).astype(np.float32),
                                                Header(frame_id=MAP_FRAME)))
    probe.spin_for(0.5)

    # The transforms of the frame's stamp came: planned with the map, the pillar blocks the view.
    mapped = plan(graph, 101, tf=base_links(101))
    assert not mapped.feasible[chosen] and mapped.infeasible_reason[chosen] == OBSTACLE
    assert mapped.chosen_index != chosen

    # An extrapolation: the tree ends at 101 s, the frame is of 102 s; after its wait, planned without the map.
    before = no_pose_count(graph)
    late = plan(graph, 102)
    assert late.feasible[chosen] and late.chosen_index == chosen
    assert probe.spin_until(lambda: no_pose_count(graph) >= before + 1, 5.0)

    # A missing transform: the frame's optical frame is in no tree.
    graph["tf_pub"].publish(base_links(103))
    probe.spin_for(0.05)
    unknown = plan(graph, 103, frame_id="camera_depth_optical_frame")
    assert unknown.feasible[chosen] and unknown.chosen_index == chosen
    assert probe.spin_until(lambda: no_pose_count(graph) >= before + 2, 5.0)
    log = read_log(graph["procs"][NS + "/nbv_node"])
    assert "source frame 'camera_depth_optical_frame' does not exist" in log

    # A parent that changes: base_link re-parented under another root, away from the map; the newest wins.
    away = plan(graph, 104, tf=base_links(104, parent="world"))
    assert away.feasible[chosen] and away.chosen_index == chosen
    assert probe.spin_until(lambda: no_pose_count(graph) >= before + 3, 5.0)
    assert probe.spin_until(lambda: "'map' and 'camera_color_optical_frame' are not connected"
                            in read_log(graph["procs"][NS + "/nbv_node"]), 5.0)
    # ... and back under odom: the map is used again.
    back = plan(graph, 105, tf=base_links(105))
    assert not back.feasible[chosen] and back.infeasible_reason[chosen] == OBSTACLE
