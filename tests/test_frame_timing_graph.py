"""One frame, one set of inputs, through ground_node, raster_node and nbv_node as processes (stamps from the
clock, a rendered scene): every output records the stamps of what it used, and they are the frame's; with
ground_node stopped (SIGSTOP) the frames that have no plane of their own are dropped and counted, never
planned with another frame's plane, and the last goal is withdrawn once it is older than max_goal_age_s;
after SIGCONT the graph plans again."""
from __future__ import annotations

import os
import signal

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

import node_harness as harness  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from node_harness import NS, diag_value, read_log  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402

from leapnbv_bringup.frame_chains import ChainVerdict, check_goal_chain  # noqa: E402
from leapnbv_common.conversions import (  # noqa: E402
    HumanMeshArrays,
    arrays_to_human_mesh,
    box_to_detection,
    header_with_stamp,
    input_stamps,
    make_camera_info,
    numpy_to_image,
    stamp_to_ns,
)
from leapnbv_common.qos import latched_goal_qos, stage_output_qos  # noqa: E402
from leapnbv_msgs.msg import (  # noqa: E402
    GoalStatus,
    GroundPlane,
    HumanMesh,
    InputStamp,
    PersonDetections,
    TargetGeometry,
    ViewCandidates,
)
from leapnbv_perception.smplx_layer import SMPLXModel  # noqa: E402
from leapnbv_planner.params import default_nbv_params  # noqa: E402
from leapnbv_sim.generation import SceneConfig, generate_scene  # noqa: E402
from leapnbv_stand_ins.files import ensure_stand_in_body_model  # noqa: E402

pytestmark = [pytest.mark.ros]

FRAME_ID = "camera_color_optical_frame"
SAME = InputStamp.SAME_FRAME
MAX_CARRY_NS = int(default_nbv_params().ground_max_age_s * 1e9)


@pytest.fixture(scope="module")
def scene():
    body = SMPLXModel.load(ensure_stand_in_body_model("small"))
    scene = generate_scene(SceneConfig(seed=6), body)
    return {"frame": scene.render(frame_index=0), "faces": body.faces.reshape(-1, 3)}


def frame_messages(scene, stamp_ns: int) -> dict:
    """What the camera, the detector and hmr_node would publish for one frame (a perfect mesh)."""
    frame, header = scene["frame"], header_with_stamp(stamp_ns, FRAME_ID)
    truth = frame.ground_truth
    params, k = truth.body_params_camera, frame.K
    box = np.array([*truth.person_box_xyxy, 1.0], np.float32)
    mesh = arrays_to_human_mesh(HumanMeshArrays(
        vertices=truth.vertices_camera.astype(np.float32), faces=scene["faces"],
        virtual_intrinsics=(k[0, 0], k[1, 1], k[0, 2], k[1, 2]), image_size=(640, 480), detection=box,
        processed_box=np.zeros(4, np.float32), root_pose=params.root_pose, body_pose=params.body_pose,
        left_hand_pose=params.left_hand_pose, right_hand_pose=params.right_hand_pose, jaw_pose=params.jaw_pose,
        betas=params.betas, expression=params.expression, cam_translation=truth.translation_camera,
        model_id="ground_truth"), header)
    detections = PersonDetections(header=header, image_width=640, image_height=480, backend="ground_truth")
    detections.detections = [box_to_detection(box)]
    return {"info": make_camera_info(k, 640, 480, header), "depth": numpy_to_image(frame.depth_mm, "16UC1", header),
            "detections": detections, "mesh": mesh}


@pytest.fixture(scope="module")
def graph(tmp_path_factory):
    logs = tmp_path_factory.mktemp("frame_timing_graph_logs")
    procs = {
        f"{NS}/ground_node": harness.start_node("leapnbv_geometry.nodes.ground_node", str(logs / "ground.log")),
        f"{NS}/raster_node": harness.start_node("leapnbv_geometry.nodes.raster_node", str(logs / "raster.log")),
        f"{NS}/nbv_node": harness.start_node("leapnbv_planner.nodes.nbv_node", str(logs / "nbv.log"),
                                             params={"use_obstacle_map": "false"}),
    }
    with harness.running_graph("frame_timing_graph_test", procs) as probe:
        node = probe.node
        g = {
            "probe": probe, "procs": procs,
            "info_pub": node.create_publisher(CameraInfo, f"{NS}/depth/camera_info", stage_output_qos(5)),
            "depth_pub": node.create_publisher(Image, f"{NS}/depth", stage_output_qos(5)),
            "detections_pub": node.create_publisher(PersonDetections, f"{NS}/detections", stage_output_qos(5)),
            "mesh_pub": node.create_publisher(HumanMesh, f"{NS}/human_mesh", stage_output_qos(5)),
            "planes": probe.collect(GroundPlane, f"{NS}/ground_plane"),
            "targets": probe.collect(TargetGeometry, f"{NS}/target_geometry"),
            "candidates": probe.collect(ViewCandidates, f"{NS}/view_candidates"),
            "goals": probe.collect(PoseStamped, f"{NS}/next_best_view", latched_goal_qos()),
            "status": probe.collect(GoalStatus, f"{NS}/goal_status", latched_goal_qos()),
        }
        harness.wait_ready(probe, procs)
        assert probe.spin_until(lambda: g["depth_pub"].get_subscription_count() >= 2
                                and g["info_pub"].get_subscription_count() >= 2
                                and g["detections_pub"].get_subscription_count() >= 1
                                and g["mesh_pub"].get_subscription_count() >= 1, 10.0)
        probe.spin_for(0.3)
        yield g


def of_stamp(messages: list, stamp_ns: int) -> list:
    return [m for m in messages if stamp_to_ns(m.header.stamp) == stamp_ns and m.header.frame_id]


def send(graph, scene) -> int:
    """One frame, stamped now, in a camera's order: camera_info and depth, detections, then the mesh."""
    probe = graph["probe"]
    stamp = probe.node.get_clock().now().nanoseconds
    messages = frame_messages(scene, stamp)
    graph["info_pub"].publish(messages["info"])
    graph["depth_pub"].publish(messages["depth"])
    probe.spin_for(0.02)
    graph["detections_pub"].publish(messages["detections"])
    probe.spin_for(0.03)
    graph["mesh_pub"].publish(messages["mesh"])
    return stamp


def planned_frame(graph, scene, attempts: int = 3) -> int:
    """Send frames until one gets its goal and candidates (a best-effort depth frame can be lost on a busy machine;
    nbv_node publishes the goal first)."""
    for _ in range(attempts):
        stamp = send(graph, scene)
        if graph["probe"].spin_until(lambda stamp=stamp: of_stamp(graph["goals"], stamp)
                                     and of_stamp(graph["candidates"], stamp), 8.0):
            return stamp
    raise AssertionError("no goal for any frame: " + "\n".join(read_log(p)[-1500:] for p in graph["procs"].values()))


def chain_records(graph, mesh_stamps) -> dict:
    """The recorded inputs of every output received, for the shared mixed-frame check (bench_load.py's); this test
    plays hmr_node, whose meshes (of `mesh_stamps`) list no inputs."""
    records = {name: {stamp_to_ns(m.header.stamp): input_stamps(m) for m in graph[key] if m.header.frame_id}
               for name, key in (("view_candidates", "candidates"), ("target_geometry", "targets"),
                                 ("ground_plane", "planes"))}
    records["human_mesh"] = {stamp: [] for stamp in mesh_stamps}
    return records


def counter(graph, node: str, key: str) -> int:
    status = graph["probe"].status_where(f"{NS}/{node}", lambda s: True)
    return int(diag_value(status, key)) if status else 0


def not_planned(graph) -> int:
    return (counter(graph, "nbv_node", "rejected.ground_plane_late")
            + counter(graph, "nbv_node", "dropped.too_old_to_plan"))


def test_every_output_records_the_stamps_of_its_own_frame(graph, scene):
    stamps = [planned_frame(graph, scene) for _ in range(2)]
    probe = graph["probe"]
    assert probe.spin_until(lambda: all(of_stamp(graph["planes"], s) and of_stamp(graph["targets"], s)
                                        for s in stamps), 5.0)
    for stamp in stamps:
        (plane,) = of_stamp(graph["planes"], stamp)
        used = input_stamps(plane)
        assert used[:3] == [("depth", stamp, SAME), ("depth/camera_info", stamp, SAME), ("detections", stamp, SAME)]
        for name, input_stamp, relation in used[3:]:  # the previous frame's person mask: an exclusion hint
            assert name == "person_mask" and relation == InputStamp.EXCLUSION_HINT and input_stamp < stamp
        (target,) = of_stamp(graph["targets"], stamp)
        assert input_stamps(target) == [("human_mesh", stamp, SAME), ("depth", stamp, SAME),
                                        ("depth/camera_info", stamp, SAME), ("ground_plane", stamp, SAME)]
        (views,) = of_stamp(graph["candidates"], stamp)
        assert input_stamps(views) == [("target_geometry", stamp, SAME), ("ground_plane", stamp, SAME),
                                       ("human_mesh_metric", stamp, SAME)]  # body_occlusion scores the frame's mesh
        assert check_goal_chain(chain_records(graph, stamps), stamp, MAX_CARRY_NS) == ChainVerdict(True, False, "")
    # The second frame's floor fit left out the first frame's person.
    assert ("person_mask", stamps[0], InputStamp.EXCLUSION_HINT) in input_stamps(of_stamp(graph["planes"],
                                                                                          stamps[1])[0])


def test_a_stopped_ground_node_drops_frames_and_withdraws_the_goal_never_mixes_planes(graph, scene):
    probe = graph["probe"]
    ground = graph["procs"][f"{NS}/ground_node"]
    last = planned_frame(graph, scene)
    raster_late = counter(graph, "raster_node", "rejected.ground_plane_late")
    nbv_late = not_planned(graph)
    os.kill(ground.pid, signal.SIGSTOP)
    try:
        stalled = []
        for _ in range(3):
            stalled.append(send(graph, scene))
            probe.spin_for(0.6)
        # The last goal ages out while ground_node is stopped (max_goal_age_s 1.0 s).
        assert probe.spin_until(lambda: any(m.state == GoalStatus.STATE_STALE and stamp_to_ns(m.goal_stamp) == last
                                            for m in graph["status"]), 5.0)
        # Each stalled frame is counted as not planned: no plane of its own in time (or, on a slow machine,
        # already older than max_goal_age_s when it reached nbv_node).
        assert probe.spin_until(lambda: not_planned(graph) >= nbv_late + len(stalled), 5.0), \
            [(kv.key, kv.value) for kv in probe.status_where(f"{NS}/nbv_node", lambda s: True).values]
    finally:
        os.kill(ground.pid, signal.SIGCONT)
    probe.spin_for(1.0)  # ground_node catches up: its late planes must not be used
    assert counter(graph, "raster_node", "rejected.ground_plane_late") >= raster_late + 2
    for stamp in stalled:
        assert not of_stamp(graph["goals"], stamp) and not of_stamp(graph["candidates"], stamp)
        for target in of_stamp(graph["targets"], stamp):  # served without a plane, never with another frame's
            assert all(name != "ground_plane" for name, _, _ in input_stamps(target))
    assert not graph["goals"][-1].header.frame_id  # the latched goal is "no goal" now
    # Running again: the next frame is planned with its own plane.
    stamp = planned_frame(graph, scene)
    (views,) = of_stamp(graph["candidates"], stamp)
    assert input_stamps(views) == [("target_geometry", stamp, SAME), ("ground_plane", stamp, SAME),
                                   ("human_mesh_metric", stamp, SAME)]  # body_occlusion scores the frame's mesh
    assert check_goal_chain(chain_records(graph, [stamp]), stamp, MAX_CARRY_NS) == ChainVerdict(True, False, "")
    assert probe.spin_until(lambda: any(m.state == GoalStatus.STATE_CURRENT and stamp_to_ns(m.goal_stamp) == stamp
                                        for m in graph["status"]), 5.0)
    for proc in graph["procs"].values():
        assert proc.poll() is None
