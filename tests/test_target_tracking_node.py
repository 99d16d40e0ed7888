"""hmr_node keeps the same person by place (depth + camera pose), as a process over DDS.

Two people stand 0.8 m apart in front of a camera that drives toward them; their boxes come in either order.
hmr_node must follow the one it took first (TargetTrack on target_track, the mesh of that box), say NOT_SEEN
and publish no mesh while the target is out of the detections even though the other person is in view, and
take the target back, with the same track_id, when it shows again.
"""
from __future__ import annotations

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

import node_harness as harness  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from node_harness import by_stamp, diag_value  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402

from leapnbv_common.conversions import human_mesh_to_arrays, make_camera_info, numpy_to_image, pose_msg  # noqa: E402
from leapnbv_common.mesh_faces import KnownMeshFaces  # noqa: E402
from leapnbv_common.qos import camera_input_qos, latched_mesh_faces_qos, stage_output_qos  # noqa: E402
from leapnbv_msgs.msg import HumanMesh, MeshFaces, PersonDetection, PersonDetections, TargetTrack  # noqa: E402
from leapnbv_stand_ins.files import ensure_contract_models, ensure_stand_in_body_model  # noqa: E402

pytestmark = [pytest.mark.ros]

NS = "/leapnbv_target"
FRAME_ID = "camera_color_optical_frame"
WIDTH, HEIGHT = 320, 240
K = np.array([[250.0, 0.0, 160.0], [0.0, 250.0, 120.0], [0.0, 0.0, 1.0]])
# The optical frame of a camera looking along the map's +x (z forward, x right = map -y, y down = map -z).
LOOK_X = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
TARGET, OTHER = (3.0, 0.0), (3.0, 0.8)  # map x, y of the two people
make_header = harness.header_factory(FRAME_ID)


def stamp(k: int) -> tuple:
    """(sec, nanosec) of frame k: 10 frames a second."""
    return (100 + k // 10, (k % 10) * 100_000_000)


def camera_position(k: int) -> np.ndarray:
    return np.array([0.05 * k, 0.0, 1.2])  # driving toward them, 5 cm a frame


def view(k: int, people) -> tuple:
    """(boxes (N, 5), depth (H, W) float32 m) of flat 0.5 x 1.7 m people standing at map (x, y), wall at 7 m."""
    depth = np.full((HEIGHT, WIDTH), 7.0, np.float32)
    boxes = []
    for x, y in people:
        centre = LOOK_X.T @ (np.array([x, y, 0.9]) - camera_position(k))
        z = centre[2]
        u0, u1 = (K[0, 0] * (centre[0] + s * 0.25) / z + K[0, 2] for s in (-1, 1))
        v0, v1 = (K[1, 1] * (centre[1] + s * 0.85) / z + K[1, 2] for s in (-1, 1))
        boxes.append([u0, v0, u1, v1, 0.9])
        depth[int(np.ceil(v0)):int(np.floor(v1)), int(np.ceil(u0)):int(np.floor(u1))] = z
    return np.array(boxes).reshape(-1, 5), depth


@pytest.fixture(scope="module")
def graph(tmp_path_factory):
    detector, hmr = ensure_contract_models()
    logs = tmp_path_factory.mktemp("target_tracking_logs")
    procs = {f"{NS}/hmr_node": harness.start_node(
        "leapnbv_perception.nodes.hmr_node", str(logs / "hmr.log"), namespace=NS,
        params={"backend": "onnxruntime", "precision": "fp32", "intra_op_threads": "1", "model_file_path": hmr,
                "body_model_path": ensure_stand_in_body_model("small"), "target_input_wait_s": "0.5"})}
    with harness.running_graph("target_tracking_node_test", procs) as probe:
        pubs = {
            "detections": probe.node.create_publisher(PersonDetections, f"{NS}/detections", stage_output_qos(5)),
            "image": probe.node.create_publisher(Image, f"{NS}/image", camera_input_qos(5)),
            "depth": probe.node.create_publisher(Image, f"{NS}/depth", camera_input_qos(5)),
            "depth/camera_info": probe.node.create_publisher(CameraInfo, f"{NS}/depth/camera_info",
                                                             camera_input_qos(5)),
            "camera_pose": probe.node.create_publisher(PoseStamped, f"{NS}/camera_pose", stage_output_qos(10)),
        }
        tracks = probe.collect(TargetTrack, f"{NS}/target_track")
        meshes = probe.collect(HumanMesh, f"{NS}/human_mesh")
        faces = probe.collect(MeshFaces, f"{NS}/mesh_faces", latched_mesh_faces_qos())
        harness.wait_ready(probe, procs)
        assert probe.spin_until(lambda: all(p.get_subscription_count() >= 1 for p in pubs.values()), 10.0), \
            {name: p.get_subscription_count() for name, p in pubs.items()}
        probe.spin_for(0.5)
        yield {"probe": probe, "procs": procs, "pubs": pubs, "tracks": tracks, "meshes": meshes, "faces": faces}


def send_frame(graph, k: int, people) -> np.ndarray:
    """Publish frame k (camera inputs first, then its detections, as a detector would); its boxes."""
    pubs, header = graph["pubs"], make_header(*stamp(k))
    boxes, depth = view(k, people)
    pubs["image"].publish(numpy_to_image(np.full((HEIGHT, WIDTH, 3), 100, np.uint8), "rgb8", header))
    pubs["depth"].publish(numpy_to_image(depth, "32FC1", header))
    pubs["depth/camera_info"].publish(make_camera_info(K, WIDTH, HEIGHT, header))
    pose = PoseStamped()
    pose.header = make_header(*stamp(k))
    pose.header.frame_id = "map"
    pose.pose = pose_msg(LOOK_X, camera_position(k))
    pubs["camera_pose"].publish(pose)
    graph["probe"].spin_for(0.05)
    msg = PersonDetections(header=header, image_width=WIDTH, image_height=HEIGHT, backend="test")
    msg.detections = [PersonDetection(x_min=b[0], y_min=b[1], x_max=b[2], y_max=b[3], score=b[4]) for b in boxes]
    pubs["detections"].publish(msg)
    return boxes


def track_of(graph, k: int) -> TargetTrack:
    key = stamp(k)
    assert graph["probe"].spin_until(lambda: by_stamp(graph["tracks"], key), 10.0), f"no target_track of frame {k}"
    return by_stamp(graph["tracks"], key)[0]


def test_the_same_person_by_place_hidden_and_found_again(graph):
    probe = graph["probe"]
    # Frame 0: both in view; the acquisition rule takes the target (its box is nearer the image centre).
    boxes = send_frame(graph, 0, [OTHER, TARGET])
    first = track_of(graph, 0)
    assert (first.state, first.detection_index, first.track_id) == (TargetTrack.STATE_TRACKED, 1, 1), first.reason
    assert first.fixed_frame == "map"
    np.testing.assert_allclose([first.position.x, first.position.y], TARGET, atol=0.03)
    assert probe.spin_until(lambda: by_stamp(graph["meshes"], stamp(0)), 10.0), "no mesh of frame 0"
    # Frames 1-5: the order of the boxes alternates; the target's row is followed, the mesh is its box.
    for k in range(1, 6):
        order = [TARGET, OTHER] if k % 2 else [OTHER, TARGET]
        boxes = send_frame(graph, k, order)
        track = track_of(graph, k)
        row = order.index(TARGET)
        assert (track.state, track.detection_index, track.track_id) == (TargetTrack.STATE_TRACKED, row, 1), \
            track.reason
        assert probe.spin_until(lambda k=k: by_stamp(graph["meshes"], stamp(k)), 10.0), f"no mesh of frame {k}"
        known = KnownMeshFaces()
        for faces in graph["faces"]:
            known.add(faces.faces_id, np.frombuffer(faces.faces, np.uint32))
        mesh = human_mesh_to_arrays(by_stamp(graph["meshes"], stamp(k))[0], known)
        np.testing.assert_allclose(mesh.detection[:4], boxes[row, :4], atol=1e-3)
    # Frames 6-8: the target is hidden, the other person (0.8 m away, inside a grown gate) still in view.
    for k in range(6, 9):
        send_frame(graph, k, [OTHER])
        track = track_of(graph, k)
        assert (track.state, track.detection_index, track.track_id) == (TargetTrack.STATE_NOT_SEEN, -1, 1), \
            track.reason
    probe.spin_for(0.5)
    assert not any(by_stamp(graph["meshes"], stamp(k)) for k in range(6, 9))  # never a mesh of the other
    # Diagnostics come once a second: wait for a status that counts the three frames.
    assert probe.spin_until(lambda: probe.status_where(
        f"{NS}/hmr_node", lambda s: int(diag_value(s, "rejected.target_not_seen")) >= 3) is not None, 5.0)
    # Frame 9: back in view, listed first: the same track.
    send_frame(graph, 9, [TARGET, OTHER])
    back = track_of(graph, 9)
    assert (back.state, back.detection_index, back.track_id) == (TargetTrack.STATE_TRACKED, 0, 1), back.reason
    assert "nearest detection to the predicted place" in back.reason


def test_a_frame_without_depth_or_pose_is_decided_in_the_image_and_says_so(graph):
    probe, pubs = graph["probe"], graph["pubs"]
    k = 20
    header = make_header(*stamp(k))
    boxes, _ = view(9, [TARGET, OTHER])  # the boxes of the last frame: overlap continues the target
    pubs["image"].publish(numpy_to_image(np.full((HEIGHT, WIDTH, 3), 100, np.uint8), "rgb8", header))
    probe.spin_for(0.05)
    msg = PersonDetections(header=header, image_width=WIDTH, image_height=HEIGHT, backend="test")
    msg.detections = [PersonDetection(x_min=b[0], y_min=b[1], x_max=b[2], y_max=b[3], score=b[4]) for b in boxes]
    pubs["detections"].publish(msg)
    track = track_of(graph, k)  # waited target_input_wait_s for its depth and pose, then decided without
    assert (track.state, track.detection_index, track.track_id) == (TargetTrack.STATE_TRACKED, 0, 1), track.reason
    assert "image only" in track.reason


def test_switching_the_tracking_off_and_on_forgets_the_target(graph):
    probe = graph["probe"]
    k = 30
    send_frame(graph, k, [TARGET, OTHER])  # 1 s after frame 20: the target is followed, the same track
    kept = track_of(graph, k)
    assert (kept.state, kept.detection_index, kept.track_id) == (TargetTrack.STATE_TRACKED, 0, 1), kept.reason
    assert "acquired" not in kept.reason
    results = harness.set_parameters(probe, f"{NS}/hmr_node", track_previous_target=False)
    results += harness.set_parameters(probe, f"{NS}/hmr_node", track_previous_target=True)
    assert all(r.successful for r in results), [r.reason for r in results]
    send_frame(graph, k + 1, [OTHER, TARGET])  # what a new scene or an operator's reset gives: a new acquisition
    fresh = track_of(graph, k + 1)
    assert fresh.state == TargetTrack.STATE_TRACKED and fresh.reason.startswith("acquired"), fresh.reason
    assert fresh.track_id > 1 and fresh.detection_index == 1, fresh.reason
