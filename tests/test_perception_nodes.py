"""detector_node and hmr_node as processes over DDS: every frame served, bad input survived, GT pairing,
parameters changed at runtime."""
from __future__ import annotations

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

import node_harness as harness  # noqa: E402
from diagnostic_msgs.msg import DiagnosticStatus  # noqa: E402
from node_harness import NS, by_stamp, diag_value, read_log, send_until, set_parameters, stamp_key  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from leapnbv_common.conversions import detection_to_box, human_mesh_to_arrays, numpy_to_image  # noqa: E402
from leapnbv_common.mesh_faces import KnownMeshFaces, mesh_faces_id  # noqa: E402
from leapnbv_common.qos import latched_mesh_faces_qos, stage_output_qos  # noqa: E402
from leapnbv_msgs.msg import HumanMesh, MeshFaces, PersonDetection, PersonDetections, SceneGroundTruth  # noqa: E402
from leapnbv_perception.hmr_tail import depth_scale, virtual_intrinsics  # noqa: E402
from leapnbv_perception.smplx_layer import SMPLXModel  # noqa: E402
from leapnbv_stand_ins.files import ensure_contract_models, ensure_stand_in_body_model  # noqa: E402

pytestmark = [pytest.mark.ros]

MISSING_NS = "/leapnbv_missing_model"
GT_NS = "/leapnbv_gt"
TIMED_NS = "/leapnbv_timed"
CARRY_NS = "/leapnbv_carry"
FRAME_ID = "camera_color_optical_frame"
WIDTH, HEIGHT = 640, 480
MISSING_MODEL = "/nonexistent/leapnbv_models/yolov8_missing.onnx"

make_header = harness.header_factory(FRAME_ID)  # headers stamped in this file's camera frame


# ----------------------------------------------------------------------------- scene


def person_blob_image(left: int, top: int) -> tuple:
    """A grey image with a saturated red person-shaped figure (head, torso, legs); returns (rgb, box xyxy)."""
    rgb = np.full((HEIGHT, WIDTH, 3), 90, np.uint8)
    rgb[:, :, 2] = 110
    mask = np.zeros((HEIGHT, WIDTH), bool)
    yy, xx = np.mgrid[:HEIGHT, :WIDTH]
    mask |= (xx - (left + 40)) ** 2 + (yy - (top + 25)) ** 2 <= 22 ** 2          # head
    mask[top + 50: top + 170, left + 10: left + 71] = True                      # torso
    mask[top + 170: top + 300, left + 12: left + 35] = True                     # legs
    mask[top + 170: top + 300, left + 46: left + 69] = True
    rgb[mask] = (230, 10, 10)
    rows, cols = np.nonzero(mask.any(axis=1))[0], np.nonzero(mask.any(axis=0))[0]
    return rgb, np.array([cols[0], rows[0], cols[-1] + 1, rows[-1] + 1], float)


@pytest.fixture(scope="module")
def models():
    detector, hmr = ensure_contract_models()
    body = ensure_stand_in_body_model("small")
    return {"detector": detector, "hmr": hmr, "body": body}


@pytest.fixture(scope="module")
def graph(models, tmp_path_factory):
    logs = tmp_path_factory.mktemp("perception_logs")
    engine = {"backend": "onnxruntime", "precision": "fp32", "intra_op_threads": "1"}
    procs = {
        f"{NS}/detector_node": harness.start_node("leapnbv_perception.nodes.detector_node",
                                                  str(logs / "detector.log"),
                                                  # multi_label: the contract detector's background anchors
                                                  # score person ~0.2 but their best class is another one;
                                                  # counted, they show the runtime threshold change below.
                                                  params={**engine, "model_file_path": models["detector"],
                                                          "multi_label": "true"}),
        f"{NS}/hmr_node": harness.start_node("leapnbv_perception.nodes.hmr_node", str(logs / "hmr.log"),
                                             params={**engine, "model_file_path": models["hmr"],
                                                     "body_model_path": models["body"]}),
        f"{MISSING_NS}/detector_node": harness.start_node(
            "leapnbv_perception.nodes.detector_node", str(logs / "detector_missing.log"), namespace=MISSING_NS,
            params={**engine, "model_file_path": MISSING_MODEL, "configure_retry_period_s": "0.5"}),
        f"{GT_NS}/detector_node": harness.start_node("leapnbv_perception.nodes.detector_node",
                                                     str(logs / "detector_gt.log"), namespace=GT_NS,
                                                     params={"backend": "ground_truth"}),
        # A benchmark's timing stand-in: the contract detector runs on every frame, the truth's boxes go out.
        f"{TIMED_NS}/detector_node": harness.start_node(
            "leapnbv_perception.nodes.detector_node", str(logs / "detector_timed.log"), namespace=TIMED_NS,
            params={"backend": "ground_truth", "timing_stand_in": "true", "model_file_path": models["detector"],
                    "multi_label": "true"}),
        # Detect one frame in three; the others get the target's box carried by its mesh (ground-truth boxes).
        f"{CARRY_NS}/detector_node": harness.start_node(
            "leapnbv_perception.nodes.detector_node", str(logs / "detector_carry.log"), namespace=CARRY_NS,
            params={"backend": "ground_truth", "detect_every_n_frames": "3", "carry_min_confidence": "0.5"}),
    }
    with harness.running_graph("perception_nodes_test", procs) as probe:
        image_pub = probe.node.create_publisher(Image, f"{NS}/image", stage_output_qos(5))
        detections = probe.collect(PersonDetections, f"{NS}/detections")
        meshes = probe.collect(HumanMesh, f"{NS}/human_mesh")
        mesh_faces = probe.collect(MeshFaces, f"{NS}/mesh_faces", latched_mesh_faces_qos())
        harness.wait_ready(probe, procs)
        assert probe.spin_until(lambda: image_pub.get_subscription_count() >= 2, 10.0)
        yield {"probe": probe, "procs": procs, "image_pub": image_pub, "detections": detections,
               "meshes": meshes, "mesh_faces": mesh_faces, "body": SMPLXModel.load(models["body"]), "models": models}


def known_faces(graph) -> KnownMeshFaces:
    """The triangle sets hmr_node sent on mesh_faces, as a reader keeps them (DDS does not order topics: the
    mesh that named them may be taken first)."""
    assert graph["probe"].spin_until(lambda: graph["mesh_faces"], 5.0), "no MeshFaces on mesh_faces"
    known = KnownMeshFaces()
    for msg in graph["mesh_faces"]:
        known.add(msg.faces_id, np.frombuffer(msg.faces, np.uint32))
    return known


def box_iou(a: np.ndarray, b: np.ndarray) -> float:
    w = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    h = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = w * h
    return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


# ----------------------------------------------------------------------------- tests


def test_every_frame_gets_detections_and_mesh_with_its_header(graph):
    probe, pub = graph["probe"], graph["image_pub"]
    body = graph["body"]
    frames = []
    for i in range(5):
        rgb, blob_box = person_blob_image(left=120 + 70 * i, top=60 + 20 * i)
        header = make_header(1000 + i, 1000 * i + 7)
        key = stamp_key(header)
        image = numpy_to_image(rgb, "rgb8", header)
        # Paced like a camera: the engine input keeps the latest frame only (depth 1).
        got = send_until(probe, lambda image=image: pub.publish(image),
                         lambda key=key: by_stamp(graph["detections"], key) and by_stamp(graph["meshes"], key), 24.0)
        assert got, f"frame {i}: detections {len(by_stamp(graph['detections'], key))}, " \
                    f"meshes {len(by_stamp(graph['meshes'], key))}; hmr_node: " \
                    f"{probe.statuses[NS + '/hmr_node'][-1]}\n{read_log(graph['procs'][NS + '/hmr_node'])[-2000:]}"
        frames.append((key, blob_box))
    # The engine says whether it estimates the hands (a contract model has no export metadata: it does).
    assert diag_value(probe.statuses[NS + "/hmr_node"][-1], "info.hands", "") == "estimated"

    for key, blob_box in frames:
        det = by_stamp(graph["detections"], key)[0]
        assert det.header.frame_id == FRAME_ID
        assert (det.image_width, det.image_height) == (WIDTH, HEIGHT)
        assert det.backend == "onnxruntime"
        assert len(det.detections) == 1
        box = detection_to_box(det.detections[0])
        assert box[4] >= 0.25
        # The contract detector's box is the red figure's, snapped to its 8-px cells.
        assert np.all(np.abs(box[:4] - blob_box) <= 8.5), (box, blob_box)
        assert box_iou(box[:4], blob_box) > 0.85, (box, blob_box)

        mesh_msg = by_stamp(graph["meshes"], key)[0]
        assert mesh_msg.header.frame_id == FRAME_ID
        # The triangles are not in the mesh: it names those hmr_node sent once on mesh_faces.
        assert len(mesh_msg.faces) == 0 and mesh_msg.faces_id == mesh_faces_id(body.faces)
        mesh = human_mesh_to_arrays(mesh_msg, known_faces(graph))  # raises on non-finite vertices / bad faces
        assert mesh.vertices.shape == (body.num_vertices, 3)
        assert np.array_equal(mesh.faces, body.faces.reshape(-1, 3))
        assert np.all(np.isfinite(mesh.vertices)) and np.all(mesh.vertices[:, 2] > 0)
        np.testing.assert_allclose(mesh.detection, box, atol=1e-4)  # the mesh names the box it came from
        assert mesh.image_size == (WIDTH, HEIGHT)
        assert mesh.model_id == "contract_smplerx.onnx"
        # The crop is the detection box (SMPLer-X's pixel convention: x .. x + w - 1) grown to 3:4
        # and scaled by box_scale 1.25 about its centre, and the virtual camera is the one of that crop.
        processed = mesh.processed_box
        np.testing.assert_allclose(processed[:2] + processed[2:] / 2, (box[:2] + box[2:4] - 1) / 2, atol=1e-3)
        box_w, box_h = box[2] - box[0] - 1, box[3] - box[1] - 1
        np.testing.assert_allclose(processed[3], 1.25 * max(box_h, box_w * 4 / 3), rtol=1e-5)
        np.testing.assert_allclose(processed[2], processed[3] * 0.75, rtol=1e-5)
        np.testing.assert_allclose(mesh.virtual_intrinsics, virtual_intrinsics(processed), rtol=1e-5)
        # Vertices = body + cam_translation; t_z = k * sigmoid(gamma), gamma bounded by the contract.
        k = depth_scale()
        assert 0.3 * k < mesh.cam_translation[2] < 0.7 * k, mesh.cam_translation
        body_only = mesh.vertices - mesh.cam_translation
        assert 1.0 < np.ptp(body_only[:, 1]) < 2.5 and np.all(np.abs(body_only) < 2.0)
    assert len({stamp_key(m.header) for m in graph["meshes"]}) >= 5
    # Sent once for every mesh of the model (and latched), not once a frame.
    assert [m.faces_id for m in graph["mesh_faces"]] == [mesh_faces_id(body.faces)]
    assert graph["mesh_faces"][0].model_id == "contract_smplerx.onnx"


def test_bad_images_are_rejected_and_the_next_frame_is_served(graph):
    probe, pub = graph["probe"], graph["image_pub"]
    name = f"{NS}/detector_node"

    def bad_image_count() -> int:
        status = probe.status_where(name, lambda s: True)
        return int(diag_value(status, "rejected.bad_image")) if status else 0

    before = bad_image_count()
    yuv = Image(header=make_header(2000), height=HEIGHT, width=WIDTH, encoding="yuv422", step=WIDTH * 2)
    yuv.data = bytes(WIDTH * HEIGHT * 2)
    pub.publish(yuv)
    assert probe.spin_until(lambda: bad_image_count() >= before + 1, 10.0), "yuv422 image not counted"
    short = numpy_to_image(person_blob_image(200, 100)[0], "rgb8", make_header(2001))
    short.data = bytes(short.data[: len(short.data) // 2])  # half the rows missing
    pub.publish(short)
    assert probe.spin_until(lambda: bad_image_count() >= before + 2, 10.0), "truncated image not counted"

    warn = probe.status_where(name, lambda s: s.level == DiagnosticStatus.WARN
                              and int(diag_value(s, "rejected.bad_image")) >= before + 2)
    assert warn is not None and "bad_image" in warn.message and "needs" in warn.message, warn
    assert "yuv422" in diag_value(warn, "last_rejection") or "bytes" in diag_value(warn, "last_rejection")
    assert not by_stamp(graph["detections"], (2000, 0)) and not by_stamp(graph["detections"], (2001, 0))

    rgb, blob_box = person_blob_image(300, 120)
    good = numpy_to_image(rgb, "rgb8", make_header(2002))
    assert send_until(probe, lambda: pub.publish(good), lambda: by_stamp(graph["detections"], (2002, 0))
                      and by_stamp(graph["meshes"], (2002, 0)), 24.0)
    det = by_stamp(graph["detections"], (2002, 0))[0]
    assert len(det.detections) == 1
    assert np.all(np.abs(detection_to_box(det.detections[0])[:4] - blob_box) <= 8.5)
    for proc in graph["procs"].values():
        assert proc.poll() is None


def test_hmr_survives_a_detection_paired_with_an_undecodable_image(graph):
    """hmr_node caches images undecoded; the bad one fails only when its detections come."""
    probe, pub = graph["probe"], graph["image_pub"]
    name = f"{NS}/hmr_node"
    det_pub = probe.node.create_publisher(PersonDetections, f"{NS}/detections", stage_output_qos(5))
    assert probe.spin_until(lambda: det_pub.get_subscription_count() >= 1, 10.0)
    bad = Image(header=make_header(3000), height=HEIGHT, width=WIDTH, encoding="yuv422", step=WIDTH * 2)
    bad.data = bytes(WIDTH * HEIGHT * 2)
    pub.publish(bad)
    probe.spin_for(0.3)
    dets = PersonDetections(header=make_header(3000), image_width=WIDTH, image_height=HEIGHT, backend="test")
    dets.detections = [PersonDetection(x_min=200.0, y_min=100.0, x_max=300.0, y_max=400.0, score=0.9)]
    det_pub.publish(dets)
    assert probe.spin_until(lambda: probe.status_where(
        name, lambda s: int(diag_value(s, "rejected.bad_frame")) >= 1 and s.level == DiagnosticStatus.WARN), 10.0)
    assert not by_stamp(graph["meshes"], (3000, 0))
    probe.node.destroy_publisher(det_pub)

    rgb, _ = person_blob_image(150, 90)
    good = numpy_to_image(rgb, "rgb8", make_header(3001))
    assert send_until(probe, lambda: pub.publish(good), lambda: by_stamp(graph["meshes"], (3001, 0)), 24.0), \
        "hmr_node stopped serving"
    assert graph["procs"][name].poll() is None


def test_hmr_waits_briefly_for_an_image_that_comes_after_its_detections(graph):
    """A fast detector (the simulator's boxes, a carried box) can publish before hmr_node has the image:
    the detections wait for it (IMAGE_WAIT_S); without one they are refused and counted."""
    probe, pub = graph["probe"], graph["image_pub"]
    name = f"{NS}/hmr_node"
    det_pub = probe.node.create_publisher(PersonDetections, f"{NS}/detections", stage_output_qos(5))
    assert probe.spin_until(lambda: det_pub.get_subscription_count() >= 1, 10.0)

    def detections(sec: int) -> PersonDetections:
        msg = PersonDetections(header=make_header(sec), image_width=WIDTH, image_height=HEIGHT, backend="test")
        msg.detections = [PersonDetection(x_min=140.0, y_min=80.0, x_max=260.0, y_max=400.0, score=0.9)]
        return msg

    probe.spin_for(0.5)  # the matching settles on hmr_node's side too (a message before that is lost)
    det_pub.publish(detections(3500))
    probe.spin_for(0.1)  # the detections are at hmr_node before their image is sent (the graph's detector
    # then answers the image with its own detections of the stamp: dropped, the first ones wait)
    pub.publish(numpy_to_image(person_blob_image(150, 90)[0], "rgb8", make_header(3500)))
    assert probe.spin_until(lambda: by_stamp(graph["meshes"], (3500, 0)), 10.0), "no mesh for the late image"
    mesh = human_mesh_to_arrays(by_stamp(graph["meshes"], (3500, 0))[0], known_faces(graph))
    np.testing.assert_allclose(mesh.detection[:4], (140.0, 80.0, 260.0, 400.0), atol=1e-4)  # these detections

    def refused() -> int:
        status = probe.status_where(name, lambda s: True)
        return int(diag_value(status, "rejected.no_matching_image")) if status else 0

    before = refused()
    det_pub.publish(detections(3501))  # its image never comes
    assert probe.spin_until(lambda: refused() >= before + 1, 10.0)
    assert not by_stamp(graph["meshes"], (3501, 0))
    probe.node.destroy_publisher(det_pub)


def test_missing_model_file_leaves_the_detector_unconfigured_with_the_reason(graph):
    probe = graph["probe"]
    name = f"{MISSING_NS}/detector_node"
    proc = graph["procs"][name]
    error = probe.status_where(name, lambda s: s.level == DiagnosticStatus.ERROR)
    assert error is not None, [s.message for s in probe.statuses.get(name, [])]
    assert MISSING_MODEL in error.message
    assert MISSING_MODEL in diag_value(error, "engine_state")

    # A managed node: it stays unconfigured with the reason (retried, never crashing) and takes no frames.
    assert diag_value(error, "lifecycle_state") == "unconfigured"
    assert MISSING_MODEL in diag_value(error, "lifecycle_reason")
    image_pub = probe.node.create_publisher(Image, f"{MISSING_NS}/image", stage_output_qos(5))
    probe.spin_for(3.0)  # longer than a configure retry
    assert image_pub.get_subscription_count() == 0
    latest = probe.statuses[name][-1]
    assert latest.level == DiagnosticStatus.ERROR and MISSING_MODEL in latest.message
    assert diag_value(latest, "lifecycle_state") == "unconfigured"
    assert proc.poll() is None
    assert MISSING_MODEL in read_log(proc)


@pytest.mark.parametrize("namespace", [GT_NS, TIMED_NS])
def test_ground_truth_backend_pairs_image_and_truth_in_either_order(graph, namespace):
    probe = graph["probe"]
    image_pub = probe.node.create_publisher(Image, f"{namespace}/image", stage_output_qos(5))
    truth_pub = probe.node.create_publisher(SceneGroundTruth, f"{namespace}/ground_truth", stage_output_qos(10))
    detections = probe.collect(PersonDetections, f"{namespace}/detections")
    assert probe.spin_until(lambda: image_pub.get_subscription_count() >= 1
                            and truth_pub.get_subscription_count() >= 1, 10.0)
    probe.spin_for(0.3)  # let the node's writer match our reader as well
    small = np.zeros((120, 160, 3), np.uint8)

    def truth(header: Header, box) -> SceneGroundTruth:
        msg = SceneGroundTruth(header=header, body_model_id="stand_in_small")
        msg.person_box = PersonDetection(x_min=box[0], y_min=box[1], x_max=box[2], y_max=box[3], score=1.0)
        return msg

    cases = {  # stamp -> (box, image first?)
        (5000, 1): ((10.0, 20.0, 60.0, 110.0), True),
        (5001, 2): ((40.5, 5.0, 90.25, 100.0), False),
        (5002, 3): ((30.0, 30.0, 30.0, 90.0), True),  # zero-width: person not visible
    }
    for (sec, nsec), (box, image_first) in cases.items():
        header = make_header(sec, nsec)
        image = numpy_to_image(small, "rgb8", header)
        if image_first:
            image_pub.publish(image)
            probe.spin_for(0.2)
            truth_pub.publish(truth(header, box))
        else:
            truth_pub.publish(truth(header, box))
            probe.spin_for(0.2)
            image_pub.publish(image)
        assert probe.spin_until(lambda key=(sec, nsec): by_stamp(detections, key), 10.0), f"no detections for {sec}"
    truth_pub.publish(truth(make_header(5003, 4), (1.0, 2.0, 3.0, 4.0)))  # no image: never published
    probe.spin_for(0.5)

    assert not by_stamp(detections, (5003, 4))
    for key, (box, _) in cases.items():
        (det,) = by_stamp(detections, key)
        assert det.header.frame_id == FRAME_ID and det.backend == "ground_truth"
        assert (det.image_width, det.image_height) == (160, 120)
        if box[2] > box[0]:
            assert len(det.detections) == 1
            np.testing.assert_allclose(detection_to_box(det.detections[0]), [*box, 1.0], atol=1e-5)
        else:
            assert len(det.detections) == 0
    if namespace == TIMED_NS:  # the stand-in's network was loaded (and ran); its own boxes never went out
        log = read_log(graph["procs"][f"{TIMED_NS}/detector_node"])
        assert f"timing stand-in detector model '{graph['models']['detector']}' loaded" in log, log


# ----------------------------------------------------------------------------- parameters at runtime


def test_thresholds_and_crop_change_at_runtime_and_the_engine_settings_do_not(graph):
    probe, pub = graph["probe"], graph["image_pub"]
    detector, hmr = f"{NS}/detector_node", f"{NS}/hmr_node"
    # The contract detector scores the background ~0.2 as person (multi_label): below the default
    # threshold, above 0.1.
    results = set_parameters(probe, detector, score_threshold=0.1, max_detections=3)
    assert all(r.successful for r in results), [r.reason for r in results]
    crop, inline = set_parameters(probe, hmr, box_scale=1.5, inline_mesh_faces=True)
    assert crop.successful and inline.successful, (crop.reason, inline.reason)
    try:
        rgb, _ = person_blob_image(200, 80)
        good = numpy_to_image(rgb, "rgb8", make_header(6000))
        assert send_until(probe, lambda: pub.publish(good), lambda: by_stamp(graph["detections"], (6000, 0))
                          and by_stamp(graph["meshes"], (6000, 0)), 24.0)
        det = by_stamp(graph["detections"], (6000, 0))[0]
        assert len(det.detections) == 3 and det.detections[0].score > 0.9 > det.detections[2].score > 0.1
        mesh_msg = by_stamp(graph["meshes"], (6000, 0))[0]
        # inline_mesh_faces: the triangles in the mesh itself (still named), readable with nothing received.
        assert len(mesh_msg.faces) == graph["body"].faces.size and mesh_msg.faces_id
        mesh = human_mesh_to_arrays(mesh_msg)
        box = mesh.detection
        np.testing.assert_allclose(mesh.processed_box[3],
                                   1.5 * max(box[3] - box[1] - 1, (box[2] - box[0] - 1) * 4 / 3), rtol=1e-5)
    finally:
        results = set_parameters(probe, detector, score_threshold=0.25, max_detections=20)
        assert all(r.successful for r in results)
        assert all(r.successful for r in set_parameters(probe, hmr, box_scale=1.25, inline_mesh_faces=False))
    (out_of_range,) = set_parameters(probe, detector, iou_threshold=1.5)
    assert not out_of_range.successful and "iou_threshold" in out_of_range.reason
    (engine,) = set_parameters(probe, detector, backend="tensorrt")
    assert not engine.successful and "backend" in engine.reason
    (model,) = set_parameters(probe, hmr, body_model_path="/tmp/other.npz")
    assert not model.successful and "body_model_path" in model.reason
    for proc in graph["procs"].values():
        assert proc.poll() is None


def test_detector_carries_the_target_box_between_detections(graph):
    from geometry_msgs.msg import PoseStamped

    from leapnbv_common.conversions import input_stamps, stamp_to_ns

    probe = graph["probe"]
    image_pub = probe.node.create_publisher(Image, f"{CARRY_NS}/image", stage_output_qos(5))
    truth_pub = probe.node.create_publisher(SceneGroundTruth, f"{CARRY_NS}/ground_truth", stage_output_qos(10))
    pose_pub = probe.node.create_publisher(PoseStamped, f"{CARRY_NS}/camera_pose", stage_output_qos(10))
    mesh_pub = probe.node.create_publisher(HumanMesh, f"{CARRY_NS}/human_mesh_metric", stage_output_qos(1))
    detections = probe.collect(PersonDetections, f"{CARRY_NS}/detections")
    assert probe.spin_until(lambda: min(pub.get_subscription_count() for pub in
                                        (image_pub, truth_pub, pose_pub, mesh_pub)) >= 1, 10.0)
    probe.spin_for(0.3)
    fx, cx, cy = 500.0, 320.0, 240.0
    rng = np.random.default_rng(0)
    person = rng.uniform([-0.25, -0.8, -0.15], [0.25, 0.8, 0.15], size=(500, 3)) + [0.0, 0.0, 3.0]

    def projected_box(points: np.ndarray) -> list:
        u, v = fx * points[:, 0] / points[:, 2] + cx, fx * points[:, 1] / points[:, 2] + cy
        return [float(u.min()), float(v.min()), float(u.max()), float(v.max())]

    def send_frame(k: int, shift_m: float, truth_box) -> Header:
        header = make_header(6000, k * 33_000_000)  # a 30 FPS camera
        pose = PoseStamped(header=Header(stamp=header.stamp, frame_id="map"))
        pose.pose.position.x, pose.pose.position.z = shift_m, 1.2  # identity rotation: camera x = map x
        pose.pose.orientation.w = 1.0
        pose_pub.publish(pose)
        truth = SceneGroundTruth(header=header, body_model_id="stand_in_small")
        truth.person_box = PersonDetection(x_min=truth_box[0], y_min=truth_box[1], x_max=truth_box[2],
                                           y_max=truth_box[3], score=1.0)
        truth_pub.publish(truth)
        probe.spin_for(0.1)
        image_pub.publish(numpy_to_image(np.zeros((480, 640, 3), np.uint8), "rgb8", header))
        assert probe.spin_until(lambda: by_stamp(detections, stamp_key(header)), 10.0), f"frame {k}"
        return header

    box_1 = projected_box(person)
    first = send_frame(1, 0.0, box_1)  # detected (the truth's box)
    mesh = HumanMesh(header=first, fx=fx, fy=fx, cx=cx, cy=cy, image_width=640, image_height=480)
    mesh.detection = PersonDetection(x_min=box_1[0], y_min=box_1[1], x_max=box_1[2], y_max=box_1[3], score=0.9)
    mesh.vertices = person.astype(np.float32).ravel().tolist()
    mesh.faces = [0, 1, 2]
    mesh_pub.publish(mesh)
    probe.spin_for(0.3)
    decoy = (5.0, 5.0, 50.0, 50.0)  # a truth box the carried frames must not show
    frames = [send_frame(k, 0.1 * (k - 1), decoy) for k in (2, 3, 4)]
    (det_1,) = by_stamp(detections, stamp_key(first))
    np.testing.assert_allclose(detection_to_box(det_1.detections[0])[:4], box_1, atol=1e-3)
    assert not det_1.inputs
    for k, header in zip((2, 3), frames[:2]):  # carried: the camera moved 0.1 m right per frame
        (det,) = by_stamp(detections, stamp_key(header))
        expected = projected_box(person - [0.1 * (k - 1), 0.0, 0.0])
        # within 1.5 px: one scale and shift for the whole body, while its depth (0.3 m) gives some parallax
        np.testing.assert_allclose(detection_to_box(det.detections[0])[:4], expected, atol=1.5)
        assert input_stamps(det) == [("human_mesh_metric", stamp_to_ns(first.stamp), 1),
                                     ("camera_pose", stamp_to_ns(header.stamp), 0),
                                     ("camera_pose", stamp_to_ns(first.stamp), 1)]
    (det_4,) = by_stamp(detections, stamp_key(frames[2]))  # the third frame after a detection: detected
    np.testing.assert_allclose(detection_to_box(det_4.detections[0])[:4], decoy, atol=1e-3)
    assert not det_4.inputs
    assert probe.spin_until(lambda: probe.status_where(
        f"{CARRY_NS}/detector_node", lambda s: diag_value(s, "counted.boxes_carried") == "2") is not None, 5.0)
