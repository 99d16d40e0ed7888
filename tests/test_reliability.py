"""Reliability of the running graph: bad inputs on every topic, startup faults, and stopping by signal.

The five nodes run as processes (ground-truth perception, stand-in body), fed the first frame of
bags/sample_a under fresh stamps. Bad inputs go in batches, each kind with its own stamp; for every
kind: no node dies, the rejection is counted on /diagnostics under its named reason (exactly once
per kind and node), no output carries its stamp (or, for a camera pose, the frame is still planned,
without the map), and the good frame sent after each batch gets the same goal as the clean run.
The contract each kind breaks is unit-tested in src/leapnbv_common/test/test_contracts.py and
test_conversion_contracts.py; bag faults are in tests/test_reliability_bags.py.
"""
from __future__ import annotations

import array
import collections
import math
import signal
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

import node_harness as harness  # noqa: E402
from diagnostic_msgs.msg import DiagnosticStatus  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from node_harness import NS, by_stamp, diag_value, read_log, send_until, set_parameters, stamp_key  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from leapnbv_bags.bag_io import read_bag  # noqa: E402
from leapnbv_common import topics  # noqa: E402
from leapnbv_common.conversions import (  # noqa: E402
    header_with_stamp,
    numpy_to_image,
    pose_msg,
    pose_to_numpy,
    xyz_to_pointcloud2,
)
from leapnbv_common.qos import latched_map_qos, stage_input_qos, stage_output_qos  # noqa: E402
from leapnbv_msgs.msg import (  # noqa: E402
    GroundPlane,
    HumanMesh,
    PersonDetections,
    SceneGroundTruth,
    TargetGeometry,
    ViewCandidates,
)
from leapnbv_stand_ins.files import ensure_stand_in_body_model  # noqa: E402

pytestmark = [pytest.mark.ros]

FRAME_ID = "camera_color_optical_frame"
OTHER_FRAME = "camera_depth_optical_frame"  # a real frame name, just not this frame's
MAP_FRAME = "map"
BASE_NS = 1_700_000_000 * 1_000_000_000  # in the clock's past, as recorded stamps: inputs ahead of it are refused
STEP_NS = 10_000_000  # 10 ms between stamps: every stamp is new, the person mask stays fresh
NAN = float("nan")

# Outputs by the node that publishes them, and what is downstream of each node for one frame.
OUTPUTS = {
    "detector_node": ["detections"],
    "hmr_node": ["human_mesh"],
    "raster_node": ["target_geometry", "person_mask", "human_mesh_metric"],
    "ground_node": ["ground_plane"],
    "nbv_node": ["view_candidates", "next_best_view", "base_goal"],
}
DOWNSTREAM = {
    "detector_node": ["detector_node", "hmr_node", "raster_node", "nbv_node"],
    "hmr_node": ["hmr_node", "raster_node", "nbv_node"],
    "raster_node": ["raster_node", "nbv_node"],
    "ground_node": ["ground_node"],
    "nbv_node": ["nbv_node"],
}
OUTPUT_TYPES = {"detections": PersonDetections, "human_mesh": HumanMesh, "target_geometry": TargetGeometry,
                "person_mask": Image, "human_mesh_metric": HumanMesh, "ground_plane": GroundPlane,
                "view_candidates": ViewCandidates, "next_best_view": PoseStamped, "base_goal": PoseStamped}
# Reasons that clean frames can add to as well (counted with >=, not ==).
SHARED_REASONS = {"duplicate_stamp", "no_camera_pose", "ground_plane_late", "no_matching_depth", "no_ground_plane"}


def copy(msg):
    return deserialize_message(serialize_message(msg), type(msg))


# ----------------------------------------------------------------------------- the graph


@pytest.fixture(scope="module")
def sample(repo_root):
    """The messages of the first frame of bags/sample_a, by topic (deserialized anew on each call)."""
    classes = {"sensor_msgs/msg/Image": Image, "sensor_msgs/msg/CameraInfo": CameraInfo,
               "leapnbv_msgs/msg/SceneGroundTruth": SceneGroundTruth, "geometry_msgs/msg/PoseStamped": PoseStamped}
    first: Dict[str, Tuple[type, bytes]] = {}
    for topic, msgtype, _, cdr in read_bag(repo_root / "bags/sample_a", raw=True):
        if topic not in first:
            first[topic] = (classes[msgtype], bytes(cdr))
    assert len(first) == 6  # images, camera infos, the simulator's truth, the camera pose
    return lambda topic: deserialize_message(first[topic][1], first[topic][0])


@pytest.fixture(scope="module")
def graph(tmp_path_factory, sample):
    logs = tmp_path_factory.mktemp("reliability_logs")
    body = ensure_stand_in_body_model("small")
    truncated = logs / "truncated_body.npz"
    data = open(body, "rb").read()
    truncated.write_bytes(data[: len(data) // 2])
    # Stamps of 2023 (BASE_NS), not the clock's: no goal age limit, as in a replay (tests/test_frame_timing.py and
    # tests/test_input_limits.py test it on the clock's stamps).
    overrides = {"detector_node": {"backend": "ground_truth"},
                 "hmr_node": {"backend": "ground_truth", "body_model_path": body},
                 "nbv_node": {"max_goal_age_s": "0.0"}}
    procs = harness.start_graph(str(logs), overrides)
    # Startup faults, each in its own namespace: they must start, say what is wrong, and keep serving.
    faults = {
        "/fault_model/detector_node": harness.start_node(
            "leapnbv_perception.nodes.detector_node", str(logs / "fault_model.log"), "/fault_model",
            {"backend": "onnxruntime", "model_file_path": "/nonexistent/yolov8s.onnx",
             "configure_retry_period_s": "1.0"}),
        "/fault_body/hmr_node": harness.start_node(
            "leapnbv_perception.nodes.hmr_node", str(logs / "fault_body.log"), "/fault_body",
            {"backend": "ground_truth", "body_model_path": "/nonexistent/SMPLX_NEUTRAL.npz"}),
        "/fault_corrupt/hmr_node": harness.start_node(
            "leapnbv_perception.nodes.hmr_node", str(logs / "fault_corrupt.log"), "/fault_corrupt",
            {"backend": "ground_truth", "body_model_path": str(truncated)}),
    }
    refused_start = harness.start_node("leapnbv_planner.nodes.nbv_node", str(logs / "fault_param.log"),
                                       "/fault_param", {"radius": "-3.0"})
    with harness.running_graph("reliability_test", {**procs, **faults}) as probe:
        node = probe.node
        camera = {name: node.create_publisher(type_, topic, stage_output_qos(10)) for name, (type_, topic) in {
            "colour": (Image, topics.COLOR_IMAGE_TOPIC), "colour_info": (CameraInfo, topics.COLOR_INFO_TOPIC),
            "depth": (Image, topics.DEPTH_IMAGE_TOPIC), "depth_info": (CameraInfo, topics.DEPTH_INFO_TOPIC),
            "truth": (SceneGroundTruth, topics.GROUND_TRUTH_TOPIC)}.items()}
        stage = {name: node.create_publisher(type_, f"{NS}/{name}", stage_output_qos(10)) for name, type_ in {
            "detections": PersonDetections, "human_mesh": HumanMesh, "ground_plane": GroundPlane,
            "target_geometry": TargetGeometry, "person_mask": Image, "camera_pose": PoseStamped}.items()}
        map_pub = node.create_publisher(PointCloud2, topics.OBSTACLE_MAP_TOPIC, latched_map_qos())
        outputs = {name: collect_graph_outputs(probe, type_, f"{NS}/{name}") for name, type_ in OUTPUT_TYPES.items()}
        harness.wait_ready(probe, {**procs, **faults}, timeout_s=120.0)
        assert probe.spin_until(lambda: all(p.get_subscription_count() >= 1 for p in camera.values())
                                and all(p.get_subscription_count() >= 1 for p in stage.values()), 20.0)
        probe.spin_for(0.5)
        g = {"probe": probe, "procs": procs, "faults": faults, "refused_start": refused_start, "camera": camera,
             "stage": stage, "map_pub": map_pub, "out": outputs, "sample": sample, "next": [0], "logs": logs,
             "body": body, "truncated": truncated, "reference": None, "kinds": [], "good": []}
        yield g
        harness.stop_node(refused_start)


def collect_graph_outputs(probe, msg_type, topic: str) -> list:
    """What the graph publishes on a topic; the test's own injected stage messages (compute_time_ms = -1) are
    left out."""
    received: list = []

    def keep(msg) -> None:
        if getattr(msg, "compute_time_ms", 0.0) >= 0.0:
            received.append(msg)

    probe.node.create_subscription(msg_type, topic, keep, stage_input_qos(200))
    return received


def next_header(g, frame_id: str = FRAME_ID) -> Header:
    g["next"][0] += 1
    return header_with_stamp(BASE_NS + g["next"][0] * STEP_NS, frame_id)


def frame_messages(g, header: Header) -> Dict[str, object]:
    """The sample frame under this header: both camera infos, the ground truth, colour and depth."""
    msgs = {"colour_info": g["sample"](topics.COLOR_INFO_TOPIC), "depth_info": g["sample"](topics.DEPTH_INFO_TOPIC),
            "truth": g["sample"](topics.GROUND_TRUTH_TOPIC), "colour": g["sample"](topics.COLOR_IMAGE_TOPIC),
            "depth": g["sample"](topics.DEPTH_IMAGE_TOPIC)}
    for msg in msgs.values():
        msg.header = copy(header)
    return msgs


def publish(g, name: str, msg, pause: float = 0.05) -> None:
    (g["camera"].get(name) or g["stage"][name]).publish(msg)
    g["probe"].spin_for(pause)


def publish_frame(g, msgs: Dict[str, object], order=("colour_info", "depth_info", "truth", "colour", "depth")) -> None:
    for name in order:
        if name in msgs:
            publish(g, name, msgs[name], 0.02)


def goal_pose(msg: PoseStamped):
    return pose_to_numpy(msg.pose)


def assert_same_goal(got: PoseStamped, want: PoseStamped, what: str) -> None:
    (r_got, p_got), (r_want, p_want) = goal_pose(got), goal_pose(want)
    assert np.linalg.norm(p_got - p_want) < 0.01, f"{what}: goal at {p_got}, the clean run's at {p_want}"
    angle = math.degrees(math.acos(float(np.clip((np.trace(r_got.T @ r_want) - 1) / 2, -1, 1))))
    assert angle < 1.0, f"{what}: goal turned {angle:.2f} deg from the clean run's"


def send_good_frame(g, what: str, extra: Optional[Callable[[Header], None]] = None) -> PoseStamped:
    """The sample frame under a new stamp, sent until its goal came; its goal equals the clean run's."""
    header = next_header(g)
    key = stamp_key(header)
    msgs = frame_messages(g, header)

    def send() -> None:
        if extra is not None:
            extra(header)
        publish_frame(g, msgs)

    assert send_until(g["probe"], send, lambda: by_stamp(g["out"]["next_best_view"], key), 30.0), \
        f"{what}: no goal for the good frame {key}"
    goal = by_stamp(g["out"]["next_best_view"], key)[0]
    g["good"].append(key)
    if g["reference"] is not None:
        assert_same_goal(goal, g["reference"], what)
    return goal


def counter(g, node: str, reason: str) -> int:
    status = g["probe"].status_where(f"{NS}/{node}", lambda s: True)
    return int(diag_value(status, f"rejected.{reason}")) if status else 0


# ----------------------------------------------------------------------------- bad-input kinds


@dataclass
class Kind:
    """One kind of bad input: how to send it under a stamp, where it must be counted, what stays silent."""

    name: str
    send: Callable[[dict, Header], None]
    expect: Tuple[Tuple[str, str], ...]  # (node, reason), each counted once for this kind
    planned: bool = False  # the frame is still planned (without the bad companion): goal == clean run's
    duplicate: bool = False  # sent under the stamp of the last good frame
    key: tuple = ()

    @property
    def silent(self) -> List[str]:
        """Outputs that must not carry this kind's stamp: those of the refusing nodes and downstream."""
        names = {n for node, _ in self.expect for down in DOWNSTREAM[node] for n in OUTPUTS[down]}
        return sorted(names)


def run_batch(g, kinds: List[Kind], what: str) -> None:
    """Send every kind of the batch, wait for each rejection to be counted, then check the next good frame."""
    probe = g["probe"]
    expected = collections.Counter(pair for kind in kinds for pair in kind.expect)
    before = {pair: counter(g, *pair) for pair in expected}
    duplicates_before: Dict[tuple, Dict[str, int]] = {}
    for kind in kinds:
        if kind.duplicate:
            header = copy(g["last_good_header"])
            duplicates_before[kind.name] = {name: len(by_stamp(msgs, stamp_key(header)))
                                            for name, msgs in g["out"].items()}
        else:
            header = next_header(g)
        kind.key = stamp_key(header)
        kind.send(g, header)
        probe.spin_for(0.15)
        g["kinds"].append(kind)

    def counted() -> bool:
        return all(counter(g, *pair) >= before[pair] + n for pair, n in expected.items())

    if not probe.spin_until(counted, 20.0):
        missing = {f"{n}/{r}": (counter(g, n, r), before[(n, r)] + k) for (n, r), k in expected.items()
                   if counter(g, n, r) < before[(n, r)] + k}
        raise AssertionError(f"{what}: rejections not counted (now, wanted): {missing}")
    for kind in kinds:
        if kind.planned:
            assert send_until(probe, lambda: None, lambda k=kind.key: by_stamp(g["out"]["next_best_view"], k), 30.0), \
                f"{kind.name}: the frame was dropped instead of planned without the bad input"
            assert_same_goal(by_stamp(g["out"]["next_best_view"], kind.key)[0], g["reference"], kind.name)
    good = send_good_frame(g, f"the good frame after {what}")
    g["last_good_header"] = good.header
    probe.spin_for(1.2)  # one more diagnostics period: nothing else may add to these counters
    for (node, reason), n in expected.items():
        added = counter(g, node, reason) - before[(node, reason)]
        if reason not in SHARED_REASONS:
            assert added == n, f"{what}: {node} counted {reason} {added} times for {n} kind(s)"
    for kind in kinds:
        if kind.duplicate:
            after = {name: len(by_stamp(msgs, kind.key)) for name, msgs in g["out"].items()}
            for name in kind.silent:
                assert after[name] == duplicates_before[kind.name][name], \
                    f"{kind.name}: a second {name} for stamp {kind.key}"
    for name, proc in {**g["procs"], **g["faults"]}.items():
        assert proc.poll() is None, f"{name} died during {what}:\n{read_log(proc)[-3000:]}"


def captured(g, name: str):
    """A copy of the graph's own output ``name`` for the reference frame (a valid stage message to break)."""
    return copy(by_stamp(g["out"][name], stamp_key(g["reference"].header))[0])


def with_header(msg, header: Header):
    """A captured stage message under another header, marked as the test's own (compute_time_ms = -1)."""
    msg.header = copy(header)
    msg.compute_time_ms = -1.0
    if isinstance(msg, TargetGeometry):
        msg.camera_info.header = copy(header)
        msg.target_points.header = copy(header)
        msg.background_points.header = copy(header)
    return msg


def small_image(encoding: str, header: Header, width: int = 64, height: int = 48) -> Image:
    shape = {"rgb8": (height, width, 3), "16UC1": (height, width), "mono8": (height, width)}[encoding]
    dtype = np.uint16 if encoding == "16UC1" else np.uint8
    return numpy_to_image(np.ones(shape, dtype), encoding, header)


def broken_image(encoding: str, header: Header, how: str) -> Image:
    image = small_image(encoding, header)
    if how == "unknown_encoding":
        image.encoding = "yuv422"
    elif how == "truncated":
        image.data = bytes(image.data[: len(image.data) // 2])
    elif how == "step":
        image.step = image.step - 3
    elif how == "empty":
        image.width = image.height = image.step = 0
        image.data = b""
    return image


def camera_pose(header: Header, z: float = 1.2, quaternion=None, position=None) -> PoseStamped:
    msg = PoseStamped(header=Header(stamp=header.stamp, frame_id=MAP_FRAME))
    rotation = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # optical z forward, y down
    msg.pose = pose_msg(rotation, np.array(position if position is not None else [0.0, 0.0, z]))
    if quaternion is not None:
        q = msg.pose.orientation
        q.x, q.y, q.z, q.w = quaternion
    return msg


def kinds_of_camera_inputs() -> List[Kind]:
    det, ras, gnd = "detector_node", "raster_node", "ground_node"

    def colour(how):
        return lambda g, h: publish(g, "colour", broken_image("rgb8", h, how))

    def depth(how):
        return lambda g, h: publish(g, "depth", broken_image("16UC1", h, how))

    def depth_on_colour(g, h):
        publish(g, "colour", small_image("16UC1", h))

    def colour_on_depth(g, h):
        publish(g, "depth", small_image("rgb8", h))

    return [
        Kind("colour: unknown encoding (yuv422)", colour("unknown_encoding"), ((det, "bad_image"),)),
        Kind("colour: payload cut in half", colour("truncated"), ((det, "bad_image"),)),
        Kind("colour: step shorter than a row", colour("step"), ((det, "bad_image"),)),
        Kind("colour: empty 0x0 image", colour("empty"), ((det, "bad_image"),)),
        Kind("colour: a depth encoding (16UC1)", depth_on_colour, ((det, "bad_image"),)),
        Kind("depth: payload cut in half", depth("truncated"), ((ras, "bad_depth"), (gnd, "bad_depth"))),
        Kind("depth: unknown encoding", depth("unknown_encoding"), ((ras, "bad_depth"), (gnd, "bad_depth"))),
        Kind("depth: empty 0x0 image", depth("empty"), ((ras, "bad_depth"), (gnd, "bad_depth"))),
        Kind("depth: a colour encoding (rgb8)", colour_on_depth, ((ras, "bad_depth"), (gnd, "bad_depth"))),
        Kind("depth: step shorter than a row", depth("step"), ((ras, "bad_depth"), (gnd, "bad_depth"))),
    ]


def kinds_of_camera_infos() -> List[Kind]:
    ras, gnd, hmr = "raster_node", "ground_node", "hmr_node"

    def info(topic: str, change: Callable[[CameraInfo], None]):
        def send(g, h):
            msg = g["sample"](topics.DEPTH_INFO_TOPIC if topic == "depth_info" else topics.COLOR_INFO_TOPIC)
            msg.header = copy(h)
            change(msg)
            publish(g, topic, msg, 0.3)  # camera infos are kept one deep: one at a time
        return send

    def k(index, value):
        def change(msg):
            values = list(msg.k)
            values[index] = value
            msg.k = values
        return change

    def size(msg):
        msg.width = 0

    def centre(msg):
        msg.width, msg.height = 100, 80  # K's principal point (320, 240) lies outside a 100x80 image

    # hmr_node reads the depth camera_info too (its target's place in the fixed frame).
    both = ((ras, "bad_camera_info"), (gnd, "bad_camera_info"), (hmr, "bad_camera_info"))
    return [
        Kind("depth camera_info: zero focal length", info("depth_info", k(0, 0.0)), both),
        Kind("depth camera_info: NaN in K", info("depth_info", k(4, NAN)), both),
        Kind("depth camera_info: empty size", info("depth_info", size), both),
        Kind("depth camera_info: principal point outside the image", info("depth_info", centre), both),
        Kind("colour camera_info: inf in K", info("colour_info", k(2, float("inf"))), ((hmr, "bad_camera_info"),)),
    ]


def kinds_of_ground_truth() -> List[Kind]:
    det, hmr = "detector_node", "hmr_node"

    def truth(change: Callable[[SceneGroundTruth], None], with_image: bool = False):
        def send(g, h):
            msgs = frame_messages(g, h)
            change(msgs["truth"])
            if with_image:
                publish_frame(g, {"colour": msgs["colour"]})
            publish(g, "truth", msgs["truth"])
        return send

    def nan_translation(m):
        m.translation[1] = NAN

    def nan_pose(m):
        m.body_pose[7] = NAN

    def nan_box(m):
        m.person_box.x_min = NAN

    def inverted(m):
        m.person_box.x_min, m.person_box.x_max = m.person_box.x_max, m.person_box.x_min

    def score(m):
        m.person_box.score = 2.0

    def occlusion(m):
        m.occlusion_share = 1.5

    def outside(m):
        m.person_box.x_min, m.person_box.x_max = 5000.0, 5100.0

    both = ((det, "bad_ground_truth"), (hmr, "bad_ground_truth"))
    return [
        Kind("ground truth: NaN translation", truth(nan_translation), both),
        Kind("ground truth: NaN body pose", truth(nan_pose), both),
        Kind("ground truth: NaN person box", truth(nan_box), both),
        Kind("ground truth: inverted person box", truth(inverted), both),
        Kind("ground truth: box score 2", truth(score), both),
        Kind("ground truth: occlusion share 1.5", truth(occlusion), both),
        Kind("ground truth: person box outside the image", truth(outside, with_image=True),
             ((det, "bad_ground_truth"),)),
    ]


def kinds_of_detections() -> List[Kind]:
    hmr = "hmr_node"

    def detections(change: Callable[[PersonDetections], None]):
        def send(g, h):
            msg = with_header(captured(g, "detections"), h)
            msg.detections = [msg.detections[0], copy(msg.detections[0])]
            msg.detections[0].score = 0.9
            change(msg)
            publish(g, "detections", msg)
        return send

    def field(name, value):
        return detections(lambda m: setattr(m.detections[1], name, value))

    def no_size(m):
        m.image_width = 0

    def inverted(m):
        d = m.detections[1]
        d.x_min, d.x_max = d.x_max, d.x_min

    def outside(m):
        m.detections[1].x_min, m.detections[1].x_max = 900.0, 990.0

    bad = ((hmr, "bad_detections"),)
    return [
        Kind("detections: NaN score next to 0.9", field("score", NAN), bad),
        Kind("detections: score 1.5", field("score", 1.5), bad),
        Kind("detections: score -0.2", field("score", -0.2), bad),
        Kind("detections: inf box corner", field("y_max", float("inf")), bad),
        Kind("detections: inverted box", detections(inverted), bad),
        Kind("detections: box outside the image", detections(outside), bad),
        Kind("detections: empty image size", detections(no_size), bad),
    ]


def kinds_of_meshes() -> List[Kind]:
    ras = "raster_node"

    def mesh(change: Callable[[HumanMesh], None]):
        def send(g, h):
            msg = with_header(captured(g, "human_mesh"), h)
            change(msg)
            publish(g, "human_mesh", msg)
        return send

    def nan_vertex(m):
        v = np.frombuffer(m.vertices, np.float32).copy()
        v[10] = NAN
        m.vertices = array.array("f", v.tobytes())

    def face_out_of_range(m):
        m.faces = array.array("I", [0, 1, 2, 3, 10_000_000, 4])  # carried in the message (which wins over an id)

    def unknown_faces(m):
        m.faces_id = "20908:0123456789abcdef"  # named, never sent on mesh_faces

    def malformed_faces_id(m):
        m.faces_id = "triangles"

    def ragged(m):
        m.vertices = array.array("f", np.frombuffer(m.vertices, np.float32)[:-1].tobytes())

    def focal(m):
        m.fx = 0.0

    def translation(m):
        m.cam_translation[2] = NAN

    def size(m):
        m.image_height = 0

    bad = ((ras, "bad_human_mesh"),)
    return [
        Kind("mesh: NaN vertex", mesh(nan_vertex), bad),
        Kind("mesh: face index out of range", mesh(face_out_of_range), bad),
        Kind("mesh: triangles named by an id never sent", mesh(unknown_faces), ((ras, "mesh_faces_unknown"),)),
        Kind("mesh: faces_id that is no id", mesh(malformed_faces_id), ((ras, "bad_mesh_faces"),)),
        Kind("mesh: vertex floats not a multiple of 3", mesh(ragged), bad),
        Kind("mesh: zero virtual focal length", mesh(focal), bad),
        Kind("mesh: NaN camera translation", mesh(translation), bad),
        Kind("mesh: empty image size", mesh(size), bad),
    ]


def kinds_of_planes_and_targets() -> List[Kind]:
    ras, nbv = "raster_node", "nbv_node"

    def plane(change: Callable[[GroundPlane], None]):
        def send(g, h):
            msg = with_header(captured(g, "ground_plane"), h)
            change(msg)
            publish(g, "ground_plane", msg)
        return send

    def down(m):
        m.normal.x, m.normal.y, m.normal.z = -m.normal.x, -m.normal.y, -m.normal.z

    def long_normal(m):
        m.normal.x, m.normal.y, m.normal.z = 2 * m.normal.x, 2 * m.normal.y, 2 * m.normal.z

    def below(m):
        m.offset = -abs(m.offset)

    def nan_normal(m):
        m.normal.y = NAN

    def source(m):
        m.source = 7

    def target(change: Callable[[TargetGeometry], None]):
        def send(g, h):
            msg = with_header(captured(g, "target_geometry"), h)
            change(msg)
            publish(g, "target_geometry", msg)
        return send

    def nan_centroid(m):
        m.centroid.z = NAN

    def nan_point(m):
        points = np.frombuffer(m.target_points.data, np.float32).copy()
        points[4] = NAN
        m.target_points.data = points.tobytes()

    def short_cloud(m):
        m.target_points.data = bytes(m.target_points.data[:-12])

    def focal(m):
        values = list(m.camera_info.k)
        values[0] = -615.0
        m.camera_info.k = values

    def info_frame(m):
        m.camera_info.header = Header(stamp=m.header.stamp, frame_id=OTHER_FRAME)

    def empty_valid(m):
        m.target_points = xyz_to_pointcloud2(np.zeros((0, 3), np.float32), m.header)

    def inverted(m):
        m.bbox_min, m.bbox_max = m.bbox_max, m.bbox_min

    def fraction(m):
        m.visible_fraction = 3.0

    planes = ((ras, "bad_ground_plane"), (nbv, "bad_ground_plane"))
    bad = ((nbv, "bad_target"),)
    return [
        Kind("ground plane: normal pointing down", plane(down), planes),
        Kind("ground plane: normal of length 2", plane(long_normal), planes),
        Kind("ground plane: camera below the floor (d < 0)", plane(below), planes),
        Kind("ground plane: NaN normal", plane(nan_normal), planes),
        Kind("ground plane: unknown source", plane(source), planes),
        Kind("target: NaN centroid", target(nan_centroid), bad),
        Kind("target: NaN point", target(nan_point), bad),
        Kind("target: point cloud shorter than its size", target(short_cloud), bad),
        Kind("target: negative focal length in its camera_info", target(focal), bad),
        Kind("target: camera_info in another frame", target(info_frame), ((nbv, "frame_id_mismatch"),)),
        Kind("target: valid without points", target(empty_valid), bad),
        Kind("target: inverted box", target(inverted), bad),
        Kind("target: visible fraction 3", target(fraction), bad),
    ]


def kinds_of_robot_inputs() -> List[Kind]:
    gnd, nbv = "ground_node", "nbv_node"

    def pose(**kwargs):
        return lambda g, h: publish(g, "camera_pose", camera_pose(h, **kwargs))

    def obstacle_map(make: Callable[[Header], PointCloud2]):
        return lambda g, h: g["map_pub"].publish(make(Header(stamp=h.stamp, frame_id=MAP_FRAME)))

    def nan_map(h):
        return xyz_to_pointcloud2(np.array([[5.0, 5.0, 0.5], [NAN, 5.0, 0.5]], np.float32), h)

    def short_map(h):
        msg = xyz_to_pointcloud2(np.array([[5.0, 5.0, 0.5], [5.1, 5.0, 0.5]], np.float32), h)
        msg.data = bytes(msg.data[:-4])
        return msg

    def double_map(h):
        msg = xyz_to_pointcloud2(np.array([[5.0, 5.0, 0.5]], np.float32), h)
        msg.fields = [PointField(name=n, offset=o, datatype=PointField.FLOAT64, count=1)
                      for n, o in (("x", 0), ("y", 4), ("z", 8))]
        return msg

    def huge_map(h):
        return xyz_to_pointcloud2(np.array([[0.0, 0.0, 0.5], [3000.0, 3000.0, 200.0]], np.float32), h)

    def mask(encoding: str, frame_id: str = FRAME_ID):
        return lambda g, h: publish(g, "person_mask", small_image(encoding, Header(stamp=h.stamp, frame_id=frame_id)),
                                    0.3)  # the mask is kept one deep: one at a time

    poses = ((gnd, "bad_camera_pose"), (nbv, "bad_camera_pose"))
    return [
        Kind("camera pose: |q| = 2", pose(quaternion=(0.0, 0.0, 0.0, 2.0)), poses),
        Kind("camera pose: zero quaternion", pose(quaternion=(0.0, 0.0, 0.0, 0.0)), poses),
        Kind("camera pose: NaN position", pose(position=[0.0, NAN, 1.2]), poses),
        Kind("obstacle map: a NaN point", obstacle_map(nan_map), ((nbv, "bad_obstacle_map"),)),
        Kind("obstacle map: payload shorter than its points", obstacle_map(short_map), ((nbv, "bad_obstacle_map"),)),
        Kind("obstacle map: float64 fields", obstacle_map(double_map), ((nbv, "bad_obstacle_map"),)),
        Kind("obstacle map: 3 km across", obstacle_map(huge_map), ((nbv, "bad_obstacle_map"),)),
        Kind("person mask: 16UC1", mask("16UC1"), ((gnd, "bad_person_mask"),)),
        Kind("person mask: another frame", mask("mono8", OTHER_FRAME), ((gnd, "frame_id_mismatch"),)),
    ]


def kinds_planned_without_the_pose() -> List[Kind]:
    """A frame whose camera pose is refused is planned without the map, not dropped."""
    gnd, nbv = "ground_node", "nbv_node"

    def frame_with_pose(**kwargs):
        def send(g, h):
            publish(g, "camera_pose", camera_pose(h, **kwargs))
            publish_frame(g, frame_messages(g, h))
        return send

    counted = ((gnd, "bad_camera_pose"), (nbv, "bad_camera_pose"), (nbv, "no_camera_pose"))
    return [
        Kind("camera pose: NaN quaternion (frame planned without the map)",
             frame_with_pose(quaternion=(NAN, NAN, NAN, NAN)), counted, planned=True),
        Kind("camera pose: below the floor (frame planned without the map)",
             frame_with_pose(z=-0.4), counted, planned=True),
    ]


def kinds_across_messages() -> List[Kind]:
    """Sizes and frame_ids that disagree between the messages of one frame."""
    hmr, ras, gnd, det, nbv = "hmr_node", "raster_node", "ground_node", "detector_node", "nbv_node"

    def half_depth(g, h):
        """Colour 640x480 with its camera_info, depth 320x240 with a matching camera_info (the issue's case)."""
        msgs = frame_messages(g, h)
        depth = np.frombuffer(msgs["depth"].data, np.uint16).reshape(480, 640)[::2, ::2]
        msgs["depth"] = numpy_to_image(np.ascontiguousarray(depth), "16UC1", copy(h))
        info = msgs["depth_info"]
        info.width, info.height = 320, 240
        info.k = [v / 2 if i in (0, 2, 4, 5) else v for i, v in enumerate(info.k)]
        publish_frame(g, msgs)
        publish(g, "depth_info", g["sample"](topics.DEPTH_INFO_TOPIC), 0.3)  # the good size again

    def small_colour(g, h):
        msgs = frame_messages(g, h)
        colour = np.frombuffer(msgs["colour"].data, np.uint8).reshape(480, 640, 3)[::2, ::2]
        msgs["colour"] = numpy_to_image(np.ascontiguousarray(colour), "rgb8", copy(h))
        msgs.pop("depth")
        publish_frame(g, msgs)

    def depth_against_info(g, h):
        msgs = frame_messages(g, h)
        publish_frame(g, {"depth_info": msgs["depth_info"]})
        depth = np.frombuffer(msgs["depth"].data, np.uint16).reshape(480, 640)[:240, :320]
        publish(g, "depth", numpy_to_image(np.ascontiguousarray(depth), "16UC1", copy(h)))

    def depth_frame(g, h):
        msgs = frame_messages(g, h)
        msgs["depth"].header.frame_id = OTHER_FRAME
        publish_frame(g, {"depth_info": msgs["depth_info"], "depth": msgs["depth"]})

    def mesh_frame(g, h):
        msgs = frame_messages(g, h)
        publish_frame(g, {"depth_info": msgs["depth_info"], "depth": msgs["depth"]})
        publish(g, "human_mesh", with_header(captured(g, "human_mesh"), Header(stamp=h.stamp, frame_id=OTHER_FRAME)))

    def mesh_size(g, h):
        msgs = frame_messages(g, h)
        publish_frame(g, {"depth_info": msgs["depth_info"], "depth": msgs["depth"]})
        mesh = with_header(captured(g, "human_mesh"), h)
        mesh.image_width, mesh.image_height = 320, 240
        publish(g, "human_mesh", mesh)

    def truth_frame(g, h):
        msgs = frame_messages(g, h)
        msgs["truth"].header.frame_id = OTHER_FRAME
        publish_frame(g, {"truth": msgs["truth"], "colour": msgs["colour"]})

    def detections_frame(g, h):
        msgs = frame_messages(g, h)
        publish(g, "truth", msgs["truth"])
        publish(g, "detections", with_header(captured(g, "detections"), Header(stamp=h.stamp, frame_id=OTHER_FRAME)))

    def plane_frame(g, h):
        publish(g, "target_geometry", with_header(captured(g, "target_geometry"), h))
        publish(g, "ground_plane", with_header(captured(g, "ground_plane"), Header(stamp=h.stamp,
                                                                                  frame_id=OTHER_FRAME)))

    return [
        Kind("colour 640x480 and depth 320x240, each with its own camera_info", half_depth,
             ((ras, "image_size_mismatch"),)),
        Kind("colour 320x240 with a 640x480 camera_info", small_colour, ((hmr, "image_size_mismatch"),)),
        Kind("depth 320x240 with a 640x480 camera_info", depth_against_info, ((gnd, "image_size_mismatch"),)),
        Kind("depth and its camera_info in different frames", depth_frame, ((gnd, "frame_id_mismatch"),)),
        Kind("mesh and depth in different frames", mesh_frame, ((ras, "frame_id_mismatch"),)),
        Kind("mesh of a 320x240 image on a 640x480 depth", mesh_size, ((ras, "image_size_mismatch"),)),
        Kind("colour image and ground truth in different frames", truth_frame, ((det, "frame_id_mismatch"),)),
        Kind("detections and camera_info in different frames", detections_frame, ((hmr, "frame_id_mismatch"),)),
        Kind("target and ground plane in different frames", plane_frame, ((nbv, "frame_id_mismatch"),)),
    ]


def kinds_of_duplicate_stamps() -> List[Kind]:
    """A second, different message under the stamp of a frame already served."""
    det, hmr, ras, gnd, nbv = "detector_node", "hmr_node", "raster_node", "ground_node", "nbv_node"

    def colour(g, h):
        image = frame_messages(g, h)["colour"]
        image.data = bytes(len(image.data))  # a black image
        publish(g, "colour", image)

    def depth(g, h):
        image = frame_messages(g, h)["depth"]
        image.data = bytes(len(image.data))
        publish(g, "depth", image)

    def truth(g, h):
        msg = frame_messages(g, h)["truth"]
        msg.translation[0] += 0.5
        publish(g, "truth", msg)

    def stage(name, change):
        def send(g, h):
            msg = with_header(captured(g, name), h)
            change(msg)
            publish(g, name, msg)
        return send

    def shift_detection(m):
        m.detections[0].x_min += 7.0

    def shift_mesh(m):
        m.cam_translation[0] += 0.3

    def lower_plane(m):
        m.offset += 0.25

    def move_target(m):
        m.centroid.x += 0.4

    def poses(g, h):
        publish(g, "camera_pose", camera_pose(h, z=1.2))
        publish(g, "camera_pose", camera_pose(h, z=1.5))

    dup = "duplicate_stamp"
    return [
        Kind("duplicate stamp: colour image", colour, ((det, dup),), duplicate=True),
        Kind("duplicate stamp: depth image", depth, ((ras, dup), (gnd, dup)), duplicate=True),
        Kind("duplicate stamp: ground truth", truth, ((det, dup), (hmr, dup)), duplicate=True),
        Kind("duplicate stamp: detections", stage("detections", shift_detection), ((hmr, dup),), duplicate=True),
        Kind("duplicate stamp: mesh", stage("human_mesh", shift_mesh), ((ras, dup),), duplicate=True),
        Kind("duplicate stamp: ground plane", stage("ground_plane", lower_plane), ((ras, dup), (nbv, dup)),
             duplicate=True),
        Kind("duplicate stamp: target", stage("target_geometry", move_target), ((nbv, dup),), duplicate=True),
        Kind("duplicate stamp: camera pose", poses, ((gnd, dup), (nbv, dup)), duplicate=True),
    ]


BATCHES = [
    ("camera images", kinds_of_camera_inputs),
    ("camera infos", kinds_of_camera_infos),
    ("ground truth", kinds_of_ground_truth),
    ("detections", kinds_of_detections),
    ("meshes", kinds_of_meshes),
    ("ground planes and targets", kinds_of_planes_and_targets),
    ("camera poses, obstacle maps, masks", kinds_of_robot_inputs),
    ("frames planned without their camera pose", kinds_planned_without_the_pose),
    ("sizes and frames across messages", kinds_across_messages),
    ("duplicate stamps", kinds_of_duplicate_stamps),
]


# ----------------------------------------------------------------------------- the tests


def test_clean_run_gives_the_reference_goal(graph):
    g = graph
    send_good_frame(g, "warm-up frame 1")
    send_good_frame(g, "warm-up frame 2")  # from here on, the previous frame's mask is the same person
    g["reference"] = send_good_frame(g, "reference frame")
    g["last_good_header"] = g["reference"].header
    again = send_good_frame(g, "a second clean frame")
    assert_same_goal(again, g["reference"], "a second clean frame")
    g["map_pub"].publish(xyz_to_pointcloud2(np.array([[40.0, 40.0, 0.5]], np.float32),
                                            Header(frame_id=MAP_FRAME)))  # a map: frames without a pose say so


@pytest.mark.parametrize("batch", [name for name, _ in BATCHES])
def test_bad_inputs_are_refused_counted_and_the_next_frame_planned_as_before(graph, batch):
    assert graph["reference"] is not None, "the clean run did not complete"
    run_batch(graph, dict(BATCHES)[batch](), batch)


def test_no_output_carries_a_bad_stamp_and_there_are_forty_kinds(graph):
    g = graph
    kinds = g["kinds"]
    assert len({k.name for k in kinds}) == len(kinds) >= 40, len(kinds)
    g["probe"].spin_for(1.0)
    for kind in kinds:
        if kind.planned or kind.duplicate:
            continue
        for name in kind.silent:
            assert not by_stamp(g["out"][name], kind.key), f"{kind.name}: {name} published for its stamp"
    # Goals only ever for good frames and the frames planned without their pose; each equals the clean run's.
    allowed = set(g["good"]) | {k.key for k in kinds if k.planned}
    warm_up = set(g["good"][:2])  # planned before a previous frame's person mask existed
    for goal in g["out"]["next_best_view"]:
        key = stamp_key(goal.header)
        assert key in allowed, f"a goal for stamp {key}, which is no good frame's"
        if key not in warm_up:
            assert_same_goal(goal, g["reference"], f"goal {key}")


def test_startup_faults_are_reported_and_the_nodes_keep_serving(graph):
    g = graph
    probe = g["probe"]
    for name, needle in [("/fault_model/detector_node", "/nonexistent/yolov8s.onnx"),
                         ("/fault_body/hmr_node", "/nonexistent/SMPLX_NEUTRAL.npz"),
                         ("/fault_corrupt/hmr_node", f"'{g['truncated']}' is truncated or corrupt")]:
        status = probe.status_where(name, lambda s: s.level == DiagnosticStatus.ERROR)
        assert status is not None, f"{name}: no ERROR on /diagnostics"
        assert needle in diag_value(status, "engine_state"), diag_value(status, "engine_state")
        assert g["faults"][name].poll() is None, f"{name} died:\n{read_log(g['faults'][name])[-2000:]}"
        assert "Traceback" not in read_log(g["faults"][name])
        # A managed node without its engine stays unconfigured, says why, and takes no frames.
        assert diag_value(status, "lifecycle_state") == "unconfigured", diag_value(status, "lifecycle_state")
    image_pub = probe.node.create_publisher(Image, "/fault_model/image", stage_output_qos(5))
    probe.spin_for(3.0)  # longer than a configure retry
    assert image_pub.get_subscription_count() == 0
    # A parameter out of range at start: one line naming it, exit code 2, no traceback.
    refused = g["refused_start"]
    assert refused.wait(timeout=60) == 2
    log = read_log(refused)
    assert "Traceback" not in log and "[nbv_node] cannot start:" in log and "radius" in log, log
    # ... and at runtime: refused with the reason, the node keeps planning as before.
    (result,) = set_parameters(probe, f"{NS}/nbv_node", radius=-3.0)
    assert not result.successful and "radius" in result.reason
    send_good_frame(g, "the good frame after a refused parameter")


def test_sigint_and_sigterm_end_every_node_with_exit_0_and_no_traceback(graph):
    g = graph
    # Work queued in every node when the signals come, so that callbacks are running when they arrive:
    # frames, and planes + targets for the planner (each plan takes tens of milliseconds).
    for _ in range(4):
        publish_frame(g, frame_messages(g, next_header(g)))
    for _ in range(12):
        header = next_header(g)
        publish(g, "ground_plane", with_header(captured(g, "ground_plane"), header), 0.0)
        publish(g, "target_geometry", with_header(captured(g, "target_geometry"), header), 0.0)
    g["probe"].spin_for(0.3)
    signals = {"detector_node": signal.SIGTERM, "hmr_node": signal.SIGINT, "raster_node": signal.SIGTERM,
               "ground_node": signal.SIGINT, "nbv_node": signal.SIGTERM}
    codes = {name: harness.stop_with_signal(g["procs"][f"{NS}/{name}"], sig) for name, sig in signals.items()}
    codes.update({name: harness.stop_with_signal(proc, signal.SIGTERM) for name, proc in g["faults"].items()})
    assert all(code == 0 for code in codes.values()), codes
    for name, proc in {**g["procs"], **g["faults"]}.items():
        log = read_log(proc)
        assert "Traceback" not in log and "internal_error" not in log, f"{name}:\n{log[-3000:]}"
