"""raster_node with the mesh registration on, as a process over DDS.

A mesh 30 % too far is registered to the depth (the target, the mask and the metric mesh are the registered
mesh's), and a mesh over background only gives no target and a counted reason.
"""
from __future__ import annotations

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

import node_harness as harness  # noqa: E402
from diagnostic_msgs.msg import DiagnosticStatus  # noqa: E402
from node_harness import NS, by_stamp, diag_value, send_until, stamp_key  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402

from leapnbv_common.conversions import (  # noqa: E402
    HumanMeshArrays,
    arrays_to_human_mesh,
    human_mesh_to_arrays,
    make_camera_info,
    numpy_to_image,
    point_to_numpy,
)
from leapnbv_common.qos import stage_output_qos  # noqa: E402
from leapnbv_msgs.msg import GroundPlane, HumanMesh, TargetGeometry  # noqa: E402
from leapnbv_perception.smplx_layer import SMPLXModel  # noqa: E402
from leapnbv_sim.generation import SceneConfig, generate_scene  # noqa: E402
from leapnbv_stand_ins.files import ensure_stand_in_body_model  # noqa: E402

pytestmark = [pytest.mark.ros]

FRAME_ID = "camera_depth_optical_frame"
make_header = harness.header_factory(FRAME_ID)


@pytest.fixture(scope="module")
def scene():
    body = SMPLXModel.load(ensure_stand_in_body_model("small"))
    scene = generate_scene(SceneConfig(seed=6), body)
    return {"frame": scene.render(frame_index=0), "faces": body.faces.reshape(-1, 3)}


@pytest.fixture(scope="module")
def graph(tmp_path_factory):
    logs = tmp_path_factory.mktemp("registration_logs")
    procs = {
        f"{NS}/raster_node": harness.start_node("leapnbv_geometry.nodes.raster_node", str(logs / "raster.log"),
                                                params={"registration_enabled": "true"}),
        f"{NS}/ground_node": harness.start_node("leapnbv_geometry.nodes.ground_node", str(logs / "ground.log"),
                                                params={"fit_detected_frames_only": "false"}),
    }
    with harness.running_graph("raster_registration_test", procs) as probe:
        g = {
            "probe": probe,
            "depth_pub": probe.node.create_publisher(Image, f"{NS}/depth", stage_output_qos(5)),
            "info_pub": probe.node.create_publisher(CameraInfo, f"{NS}/depth/camera_info", stage_output_qos(1)),
            "mesh_pub": probe.node.create_publisher(HumanMesh, f"{NS}/human_mesh", stage_output_qos(5)),
            "targets": probe.collect(TargetGeometry, f"{NS}/target_geometry"),
            "planes": probe.collect(GroundPlane, f"{NS}/ground_plane"),
            "metric_meshes": probe.collect(HumanMesh, f"{NS}/human_mesh_metric"),
        }
        harness.wait_ready(probe, procs)
        assert probe.spin_until(lambda: g["depth_pub"].get_subscription_count() >= 2
                                and g["mesh_pub"].get_subscription_count() >= 1, 10.0)
        yield g


def mesh_message(frame, faces: np.ndarray, vertices: np.ndarray, box, header) -> HumanMesh:
    """A HumanMesh with the given camera-frame vertices, the real K as virtual K."""
    truth = frame.ground_truth
    params = truth.body_params_camera
    k = frame.K
    arrays = HumanMeshArrays(
        vertices=vertices.astype(np.float32), faces=faces, virtual_intrinsics=(k[0, 0], k[1, 1], k[0, 2], k[1, 2]),
        image_size=(640, 480), detection=np.array([*box, 1.0], np.float32), processed_box=np.zeros(4, np.float32),
        root_pose=params.root_pose, body_pose=params.body_pose, left_hand_pose=params.left_hand_pose,
        right_hand_pose=params.right_hand_pose, jaw_pose=params.jaw_pose, betas=params.betas,
        expression=params.expression, cam_translation=truth.translation_camera, model_id="ground_truth")
    return arrays_to_human_mesh(arrays, header)


def send_frame(graph, frame, mesh_msg: HumanMesh, key) -> bool:
    def send() -> None:
        header = mesh_msg.header
        graph["info_pub"].publish(make_camera_info(frame.K, 640, 480, header))
        graph["probe"].spin_for(0.05)
        graph["depth_pub"].publish(numpy_to_image(frame.depth_mm, "16UC1", header))
        graph["probe"].spin_for(0.05)
        graph["mesh_pub"].publish(mesh_msg)

    return send_until(graph["probe"], send, lambda: by_stamp(graph["targets"], key), 15.0)


def raster_status(graph, predicate) -> DiagnosticStatus:
    probe = graph["probe"]
    assert probe.spin_until(lambda: probe.status_where(f"{NS}/raster_node", predicate) is not None, 6.0)
    return probe.status_where(f"{NS}/raster_node", predicate)


def test_a_mesh_too_far_is_registered_to_the_depth(graph, scene):
    frame = scene["frame"]
    truth = frame.ground_truth
    header = make_header(300, 0)
    key = stamp_key(header)
    far = truth.vertices_camera * 1.3  # same image, 30 % too far
    assert send_frame(graph, frame, mesh_message(frame, scene["faces"], far, truth.person_box_xyxy, header), key)
    target = by_stamp(graph["targets"], key)[0]
    assert target.valid
    # The depth the registration found: the true mesh's (depth noise only), not 30 % farther.
    visible = truth.vertices_camera[truth.visible_vertices]
    assert np.linalg.norm(point_to_numpy(target.centroid) - np.median(visible, axis=0)) < 0.15
    true_z, far_z = truth.vertices_camera[:, 2].mean(), far[:, 2].mean()
    assert abs(target.depth_offset - (true_z - far_z)) < 0.05
    assert probe_metric(graph, key, truth.vertices_camera)
    status = raster_status(graph, lambda s: "ok=True" in diag_value(s, "info.registration", ""))
    assert "inlier_share=" in diag_value(status, "info.registration")


def probe_metric(graph, key, true_vertices: np.ndarray) -> bool:
    """The metric mesh is the true one: at its depth and of its size (a z shift alone keeps it 30 % too big)."""
    probe = graph["probe"]
    assert probe.spin_until(lambda: by_stamp(graph["metric_meshes"], key), 5.0)
    vertices = human_mesh_to_arrays(by_stamp(graph["metric_meshes"], key)[0], without_faces=True).vertices
    vertices = np.asarray(vertices).reshape(-1, 3)
    extent, true_extent = np.ptp(vertices[:, :2], axis=0), np.ptp(true_vertices[:, :2], axis=0)
    return abs(float(vertices[:, 2].mean()) - true_vertices[:, 2].mean()) < 0.05 and \
        bool(np.all(np.abs(extent / true_extent - 1.0) < 0.02))


def test_a_mesh_over_background_only_gives_no_target_and_a_counted_reason(graph, scene):
    frame = scene["frame"]
    truth = frame.ground_truth
    header = make_header(301, 0)
    key = stamp_key(header)
    x0, y0, x1, y1 = truth.person_box_xyxy
    # Moved sideways by 1.5 box widths at its depth: over whatever is beside the person.
    shift = 1.5 * (x1 - x0) * truth.vertices_camera[:, 2].mean() / frame.K[0, 0]
    side = 1.0 if x0 < 640 - x1 else -1.0
    moved = truth.vertices_camera + np.array([side * shift, 0.0, 0.0])
    box = (x0 + side * 1.5 * (x1 - x0), y0, x1 + side * 1.5 * (x1 - x0), y1)
    assert send_frame(graph, frame, mesh_message(frame, scene["faces"], moved, box, header), key)
    target = by_stamp(graph["targets"], key)[0]
    assert not target.valid and target.mask_pixel_count == 0
    status = raster_status(graph, lambda s: int(diag_value(s, "rejected.mesh_not_registered")) >= 1)
    assert "ok=False" in diag_value(status, "info.registration")
