"""nbv_node's obstacle memory as a process over DDS.

Without a map, furniture a frame showed keeps the views off it after it left the view; a frame without its
camera pose is planned without the memory; turning the memory off forgets it.
"""
from __future__ import annotations

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

import node_harness as harness  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from node_harness import NS, by_stamp, diag_value, read_log, set_parameters, stamp_key  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from leapnbv_common.conversions import (  # noqa: E402
    input_stamps,
    make_camera_info,
    point_msg,
    pose_msg,
    pose_to_numpy,
    xyz_to_pointcloud2,
)
from leapnbv_common.qos import stage_output_qos  # noqa: E402
from leapnbv_msgs.msg import GroundPlane, TargetGeometry, ViewCandidates  # noqa: E402

pytestmark = [pytest.mark.ros]

FRAME_ID = "camera_color_optical_frame"
MAP_FRAME = "map"
CAMERA_HEIGHT = 1.2
K = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])
# The camera at (0, 0, 1.2) of the map looking along +x, level (optical z = x, x = -y, y = -z).
ROTATION = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
POSITION = np.array([0.0, 0.0, CAMERA_HEIGHT])

make_header = harness.header_factory(FRAME_ID)


def optical(points_map: np.ndarray) -> np.ndarray:
    return (np.asarray(points_map, float) - POSITION) @ ROTATION


def frame(header: Header, pillar_xy=None) -> tuple:
    """(TargetGeometry, GroundPlane): a person 3 m ahead, the floor, a far wall; a pillar at ``pillar_xy`` (map)."""
    rng = np.random.default_rng(11)
    person = np.column_stack([rng.uniform(-0.25, 0.25, 3000), rng.uniform(-0.5, 1.15, 3000),
                              rng.uniform(2.85, 3.15, 3000)])
    floor = np.column_stack([rng.uniform(-3, 3, 400), np.full(400, CAMERA_HEIGHT), rng.uniform(0.5, 6, 400)])
    wall = np.column_stack([rng.uniform(-3, 3, 400), rng.uniform(-1.0, CAMERA_HEIGHT, 400), np.full(400, 6.0)])
    parts = [floor, wall]
    if pillar_xy is not None:
        g = np.linspace(-0.15, 0.15, 7)
        xs, ys, zs = np.meshgrid(g, g, np.linspace(0.2, 1.9, 18), indexing="ij")
        pillar = np.column_stack([xs.ravel() + pillar_xy[0], ys.ravel() + pillar_xy[1], zs.ravel()])
        parts.append(optical(pillar))
    background = np.concatenate(parts).astype(np.float32)
    person = person.astype(np.float32)
    target = TargetGeometry(header=header, valid=True, mask_pixel_count=3000, visible_fraction=0.7)
    target.target_points = xyz_to_pointcloud2(person, header)
    target.background_points = xyz_to_pointcloud2(background, header)
    target.centroid = point_msg(np.median(person, axis=0))
    target.bbox_min, target.bbox_max = point_msg(person.min(axis=0)), point_msg(person.max(axis=0))
    target.camera_info = make_camera_info(K, 640, 480, header)
    plane = GroundPlane(header=header, offset=CAMERA_HEIGHT, inlier_count=400, inlier_ratio=0.3, valid=True)
    plane.normal.x, plane.normal.y, plane.normal.z = 0.0, -1.0, 0.0
    return target, plane


@pytest.fixture(scope="module")
def graph(tmp_path_factory):
    logs = tmp_path_factory.mktemp("nbv_memory_logs")
    procs = {f"{NS}/nbv_node": harness.start_node(
        "leapnbv_planner.nodes.nbv_node", str(logs / "nbv.log"),
        params={"max_goal_age_s": "0.0", "use_obstacle_map": "false", "obstacle_memory": "true",
                "commit_goals": "false"})}
    with harness.running_graph("nbv_memory_test", procs) as probe:
        g = {
            "probe": probe, "procs": procs,
            "target_pub": probe.node.create_publisher(TargetGeometry, f"{NS}/target_geometry", stage_output_qos(5)),
            "ground_pub": probe.node.create_publisher(GroundPlane, f"{NS}/ground_plane", stage_output_qos(5)),
            "pose_pub": probe.node.create_publisher(PoseStamped, f"{NS}/camera_pose", stage_output_qos(10)),
            "candidates": probe.collect(ViewCandidates, f"{NS}/view_candidates"),
        }
        harness.wait_ready(probe, procs)
        assert probe.spin_until(lambda: all(g[k].get_subscription_count() >= 1
                                            for k in ("target_pub", "ground_pub", "pose_pub")), 10.0)
        probe.spin_for(0.2)
        yield g


def plan(graph: dict, sec: int, pillar_xy=None, with_pose: bool = True) -> ViewCandidates:
    probe = graph["probe"]
    header = make_header(sec, 0)
    if with_pose:
        graph["pose_pub"].publish(PoseStamped(header=Header(frame_id=MAP_FRAME, stamp=header.stamp),
                                              pose=pose_msg(ROTATION, POSITION)))
        probe.spin_for(0.05)
    target, plane = frame(header, pillar_xy)
    graph["ground_pub"].publish(plane)
    probe.spin_for(0.05)
    graph["target_pub"].publish(target)
    key = stamp_key(header)
    assert probe.spin_until(lambda: by_stamp(graph["candidates"], key), 10.0), \
        read_log(graph["procs"][NS + "/nbv_node"])[-3000:]
    (views,) = by_stamp(graph["candidates"], key)
    return views


def foot_xy(views: ViewCandidates, index: int) -> np.ndarray:
    _, position = pose_to_numpy(views.poses[index])
    return (ROTATION @ position + POSITION)[:2]


def test_an_obstacle_seen_once_keeps_its_views_off_it_after_it_left_the_view_until_the_memory_is_off(graph):
    probe = graph["probe"]
    first = plan(graph, 100)
    chosen = first.chosen_index
    assert chosen >= 1 and first.feasible[chosen]
    assert "obstacle_memory" in {name for name, *_ in input_stamps(first)}
    pillar = foot_xy(first, chosen)
    clear = 0.3 + 0.15  # the robot's radius (the default) + the pillar's half width

    def off_pillar(views: ViewCandidates) -> bool:  # the view moved off the pillar (fit_to_free_space) or is out
        return not views.feasible[chosen] or float(np.linalg.norm(foot_xy(views, chosen) - pillar)) >= clear - 0.05

    seen = plan(graph, 101, pillar_xy=pillar)  # this frame shows a pillar where the chosen view stood
    assert off_pillar(seen)
    # The next frames no longer show it (it left the view): the memory still has it.
    for sec in (102, 103):
        later = plan(graph, sec)
        assert off_pillar(later)
        np.testing.assert_allclose(foot_xy(later, chosen), foot_xy(seen, chosen), atol=0.05)

    # A frame without its camera pose: planned from itself alone (the pillar is not in it), and counted.
    def without() -> int:
        status = probe.status_where(f"{NS}/nbv_node", lambda s: True)
        return int(diag_value(status, "counted.planned_without.obstacle_memory")) if status else 0

    before = without()
    unposed = plan(graph, 104, with_pose=False)
    np.testing.assert_allclose(foot_xy(unposed, chosen), pillar, atol=1e-3)
    assert "obstacle_memory" not in {name for name, *_ in input_stamps(unposed)}
    assert probe.spin_until(lambda: without() >= before + 1, 5.0)

    # Off and on again: forgotten.
    for value in (False, True):
        (result,) = set_parameters(probe, f"{NS}/nbv_node", obstacle_memory=value)
        assert result.successful, result.reason
    fresh = plan(graph, 105)
    np.testing.assert_allclose(foot_xy(fresh, chosen), pillar, atol=1e-3)
    assert fresh.chosen_index == chosen
