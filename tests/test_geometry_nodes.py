"""raster_node and ground_node as processes over DDS, fed a rendered scene: stamps, pairing, bad depth,
ground_node's fallback on the camera pose's floor, parameters changed at runtime, and the depth conversion."""
from __future__ import annotations

import time
from typing import Callable

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

import node_harness as harness  # noqa: E402
from diagnostic_msgs.msg import DiagnosticStatus  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from node_harness import NS, by_stamp, diag_value, send_until, set_parameters, stamp_key  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from leapnbv_common.conversions import (  # noqa: E402
    HumanMeshArrays,
    arrays_to_human_mesh,
    depth_to_metres,
    make_camera_info,
    numpy_to_image,
    point_to_numpy,
    pointcloud2_to_xyz,
    pose_msg,
    pose_to_numpy,
)
from leapnbv_common.mesh_faces import mesh_faces_id  # noqa: E402
from leapnbv_common.qos import latched_mesh_faces_qos, stage_output_qos  # noqa: E402
from leapnbv_geometry.ground import floor_plane_from_camera_pose  # noqa: E402
from leapnbv_geometry.params import MIN_RANGE_M  # noqa: E402
from leapnbv_msgs.msg import GroundPlane, HumanMesh, MeshFaces, TargetGeometry  # noqa: E402
from leapnbv_perception.smplx_layer import SMPLXModel  # noqa: E402
from leapnbv_sim.generation import SceneConfig, generate_scene  # noqa: E402
from leapnbv_stand_ins.files import ensure_stand_in_body_model  # noqa: E402

pytestmark = [pytest.mark.ros]

FRAME_ID = "camera_depth_optical_frame"
SCENE_SEED = 6

make_header = harness.header_factory(FRAME_ID)  # headers stamped in this file's camera frame


# ----------------------------------------------------------------------------- scene + graph


@pytest.fixture(scope="module")
def scene():
    body = SMPLXModel.load(ensure_stand_in_body_model("small"))
    scene = generate_scene(SceneConfig(seed=SCENE_SEED), body)
    frames = [scene.render(frame_index=i) for i in range(3)]
    assert frames[0].ground_truth.person_pixel_count > 2000  # the person is well in view
    return {"scene": scene, "frames": frames, "faces": body.faces.reshape(-1, 3)}


def mesh_message(frame, faces: np.ndarray, header: Header) -> HumanMesh:
    """A HumanMesh as a perfect HMR would give it: GT camera-frame vertices, the real K as virtual K."""
    truth = frame.ground_truth
    params = truth.body_params_camera
    k = frame.K
    box = np.array([*truth.person_box_xyxy, 1.0], np.float32)
    arrays = HumanMeshArrays(
        vertices=truth.vertices_camera.astype(np.float32), faces=faces,
        virtual_intrinsics=(k[0, 0], k[1, 1], k[0, 2], k[1, 2]), image_size=(640, 480), detection=box,
        processed_box=np.zeros(4, np.float32), root_pose=params.root_pose, body_pose=params.body_pose,
        left_hand_pose=params.left_hand_pose, right_hand_pose=params.right_hand_pose, jaw_pose=params.jaw_pose,
        betas=params.betas, expression=params.expression, cam_translation=truth.translation_camera,
        model_id="ground_truth")
    return arrays_to_human_mesh(arrays, header)


@pytest.fixture(scope="module")
def graph(scene, tmp_path_factory):
    logs = tmp_path_factory.mktemp("geometry_logs")
    procs = {
        f"{NS}/raster_node": harness.start_node("leapnbv_geometry.nodes.raster_node", str(logs / "raster.log")),
        # Fed depth frames alone (no detector): every depth frame is fitted.
        f"{NS}/ground_node": harness.start_node("leapnbv_geometry.nodes.ground_node", str(logs / "ground.log"),
                                                params={"fit_detected_frames_only": "false"}),
    }
    with harness.running_graph("geometry_nodes_test", procs) as probe:
        g = {
            "probe": probe, "procs": procs,
            "depth_pub": probe.node.create_publisher(Image, f"{NS}/depth", stage_output_qos(5)),
            "info_pub": probe.node.create_publisher(CameraInfo, f"{NS}/depth/camera_info", stage_output_qos(1)),
            "mesh_pub": probe.node.create_publisher(HumanMesh, f"{NS}/human_mesh", stage_output_qos(5)),
            "pose_pub": probe.node.create_publisher(PoseStamped, f"{NS}/camera_pose", stage_output_qos(10)),
            "targets": probe.collect(TargetGeometry, f"{NS}/target_geometry"),
            "planes": probe.collect(GroundPlane, f"{NS}/ground_plane"),
            "masks": probe.collect(Image, f"{NS}/person_mask"),
            "metric_meshes": probe.collect(HumanMesh, f"{NS}/human_mesh_metric"),
            "faces_pub": probe.node.create_publisher(MeshFaces, f"{NS}/mesh_faces", latched_mesh_faces_qos()),
        }
        harness.wait_ready(probe, procs)
        assert probe.spin_until(lambda: g["depth_pub"].get_subscription_count() >= 2
                                and g["mesh_pub"].get_subscription_count() >= 1
                                and g["info_pub"].get_subscription_count() >= 2
                                and g["pose_pub"].get_subscription_count() >= 1, 10.0)
        yield g


def send_depth(graph, depth_msg: Image) -> None:
    """camera_info (best effort, depth 1) just before its depth frame, as a driver publishes them."""
    k = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])  # SceneConfig defaults
    graph["info_pub"].publish(make_camera_info(k, depth_msg.width, depth_msg.height, depth_msg.header))
    graph["probe"].spin_for(0.05)
    graph["depth_pub"].publish(depth_msg)


def send_frame(graph, depth_msg: Image, mesh_msg: HumanMesh, arrived: Callable[[], bool]) -> bool:
    """Depth (best effort) then its mesh, sent again while no output came (see send_until)."""
    def send() -> None:
        send_depth(graph, depth_msg)
        graph["probe"].spin_for(0.05)
        graph["mesh_pub"].publish(mesh_msg)

    return send_until(graph["probe"], send, arrived, 15.0)


def diag(graph, node: str, key: str) -> int:
    status = graph["probe"].status_where(f"{NS}/{node}", lambda s: True)
    return int(diag_value(status, key)) if status else 0


def assert_target_on_body(target: TargetGeometry, frame) -> np.ndarray:
    """The target points are observed body surface: near GT vertices, finite, in the depth range."""
    points = pointcloud2_to_xyz(target.target_points)
    assert points.shape[0] == target.mask_pixel_count > 500
    assert np.all(np.isfinite(points)) and np.all((points[:, 2] >= 0.1) & (points[:, 2] <= 10.0))
    vertices = frame.ground_truth.vertices_camera
    sample = points[:: max(1, len(points) // 1500)]
    nearest = np.sqrt(((sample[:, None, :] - vertices[None, :, :]) ** 2).sum(-1)).min(axis=1)
    assert np.percentile(nearest, 90) < 0.06, np.percentile(nearest, [50, 90, 99])
    visible = vertices[frame.ground_truth.visible_vertices]
    assert np.linalg.norm(point_to_numpy(target.centroid) - np.median(visible, axis=0)) < 0.15
    np.testing.assert_allclose(point_to_numpy(target.centroid), np.median(points, axis=0), atol=1e-4)
    np.testing.assert_allclose(point_to_numpy(target.bbox_min), points.min(axis=0), atol=1e-5)
    return points


# ----------------------------------------------------------------------------- raster_node


def test_raster_every_mesh_with_its_depth_gives_a_target_with_its_stamp(graph, scene):
    probe = graph["probe"]
    for i, frame in enumerate(scene["frames"]):
        header = make_header(100 + i, 1000 * i)
        key = stamp_key(header)
        assert send_frame(graph, numpy_to_image(frame.depth_mm, "16UC1", header),
                          mesh_message(frame, scene["faces"], header),
                          lambda key=key: by_stamp(graph["targets"], key) and by_stamp(graph["masks"], key)), \
            f"frame {i}: no TargetGeometry; raster: {probe.statuses.get(NS + '/raster_node', ['-'])[-1]}"
    for i, frame in enumerate(scene["frames"]):
        key = (100 + i, 1000 * i)
        target = by_stamp(graph["targets"], key)[0]
        assert target.header.frame_id == FRAME_ID and target.valid
        assert stamp_key(target.target_points.header) == key
        assert (target.camera_info.width, target.camera_info.height) == (640, 480)
        assert 0.3 < target.visible_fraction <= 1.0
        # A perfect mesh needs (almost) no depth alignment; depth noise only.
        assert abs(target.depth_offset) < 0.05
        assert_target_on_body(target, frame)
        mask = by_stamp(graph["masks"], key)[0]
        assert int(np.count_nonzero(np.frombuffer(mask.data, np.uint8))) == target.mask_pixel_count


def test_raster_survives_nan_zero_and_out_of_range_depth(graph, scene):
    probe = graph["probe"]
    frame = scene["frames"][0]
    clean = by_stamp(graph["targets"], (100, 0))
    depth = frame.depth_m.astype(np.float32).copy()
    x0, y0, x1, y1 = frame.ground_truth.person_box_xyxy
    depth[y0:y1, x0: x0 + (x1 - x0) // 4] = np.nan            # a quarter of the person unmeasured
    depth[y0 + (y1 - y0) // 2: y0 + (y1 - y0) // 2 + 15] = 0.0  # a band of no-return pixels
    depth[:40] = 50.0                                          # beyond max_depth
    depth[40:50] = np.inf
    depth[50:55] = -2.0
    header = make_header(200, 0)
    assert send_frame(graph, numpy_to_image(depth, "32FC1", header), mesh_message(frame, scene["faces"], header),
                      lambda: by_stamp(graph["targets"], (200, 0)))
    all_nan = np.full_like(depth, np.nan)
    header_nan = make_header(201, 0)
    assert send_frame(graph, numpy_to_image(all_nan, "32FC1", header_nan),
                      mesh_message(frame, scene["faces"], header_nan), lambda: by_stamp(graph["targets"], (201, 0)))

    target = by_stamp(graph["targets"], (200, 0))[0]
    assert target.valid
    points = assert_target_on_body(target, frame)
    assert np.all(points[:, 0] * 615.0 / points[:, 2] + 320.0 >= x0 + (x1 - x0) // 4 - 1)  # none from NaN pixels
    if clean:
        assert target.mask_pixel_count < clean[0].mask_pixel_count
    background = pointcloud2_to_xyz(target.background_points)
    assert np.all(np.isfinite(background)) and np.all((background[:, 2] >= 0.1) & (background[:, 2] <= 10.0))

    empty = by_stamp(graph["targets"], (201, 0))[0]
    assert not empty.valid and empty.mask_pixel_count == 0
    assert pointcloud2_to_xyz(empty.target_points).shape == (0, 3)
    assert probe.spin_until(lambda: diag(graph, "raster_node", "rejected.empty_target") >= 1, 5.0)
    # ground_node got the same frames: it answers each (the all-NaN one with valid=false).
    assert probe.spin_until(lambda: by_stamp(graph["planes"], (200, 0)) and by_stamp(graph["planes"], (201, 0)),
                            5.0)
    assert not by_stamp(graph["planes"], (201, 0))[0].valid
    for proc in graph["procs"].values():
        assert proc.poll() is None


def test_raster_takes_the_triangles_a_mesh_names_from_mesh_faces(graph, scene):
    probe, frame = graph["probe"], scene["frames"][0]
    faces_id = mesh_faces_id(scene["faces"])

    def named_mesh(header: Header) -> HumanMesh:
        msg = mesh_message(frame, scene["faces"], header)
        msg.faces, msg.faces_id = [], faces_id  # as hmr_node sends them: named, not carried
        return msg

    def frame_of(stamp_s: int) -> Callable[[], None]:
        header = make_header(stamp_s, 0)
        return lambda: (send_depth(graph, numpy_to_image(frame.depth_mm, "16UC1", header)), probe.spin_for(0.05),
                        graph["mesh_pub"].publish(named_mesh(header)))

    # Before its triangles came: refused with the reason, no output from it.
    before = diag(graph, "raster_node", "rejected.mesh_faces_unknown")
    frame_of(250)()
    assert probe.spin_until(lambda: diag(graph, "raster_node", "rejected.mesh_faces_unknown") >= before + 1, 6.0)
    assert not by_stamp(graph["targets"], (250, 0))
    # Triangles that are not those their id names are refused; the mesh stays unknown.
    bad_before = diag(graph, "raster_node", "rejected.bad_mesh_faces")
    graph["faces_pub"].publish(MeshFaces(faces_id=faces_id, faces=(scene["faces"][:, ::-1]).ravel().tolist()))
    assert probe.spin_until(lambda: diag(graph, "raster_node", "rejected.bad_mesh_faces") >= bad_before + 1, 6.0)
    # Once sent (latched), the meshes that name them are served, and the metric mesh names them too.
    graph["faces_pub"].publish(MeshFaces(faces_id=faces_id, faces=scene["faces"].ravel().tolist(), model_id="gt"))
    assert send_until(probe, frame_of(251), lambda: by_stamp(graph["targets"], (251, 0)), 15.0)
    assert_target_on_body(by_stamp(graph["targets"], (251, 0))[0], frame)
    assert probe.spin_until(lambda: by_stamp(graph["metric_meshes"], (251, 0)), 5.0)
    metric = by_stamp(graph["metric_meshes"], (251, 0))[0]
    assert len(metric.faces) == 0 and metric.faces_id == faces_id
    # A mesh that carries its triangles gets a metric mesh that carries them.
    header = make_header(252, 0)
    assert send_frame(graph, numpy_to_image(frame.depth_mm, "16UC1", header),
                      mesh_message(frame, scene["faces"], header), lambda: by_stamp(graph["metric_meshes"], (252, 0)))
    assert len(by_stamp(graph["metric_meshes"], (252, 0))[0].faces) == scene["faces"].size


def test_raster_drops_a_mesh_without_depth_and_never_mismatches_it(graph, scene):
    probe = graph["probe"]
    frame = scene["frames"][1]
    before = diag(graph, "raster_node", "rejected.no_matching_depth")
    # Depth at 300.000 s is cached; the mesh at 300.050 s is 50 ms away (slop 5 ms): no partner.
    send_depth(graph, numpy_to_image(frame.depth_mm, "16UC1", make_header(300, 0)))
    probe.spin_for(0.1)
    graph["mesh_pub"].publish(mesh_message(frame, scene["faces"], make_header(300, 50_000_000)))
    assert probe.spin_until(lambda: diag(graph, "raster_node", "rejected.no_matching_depth") >= before + 1, 6.0)
    probe.spin_for(0.3)
    assert not by_stamp(graph["targets"], (300, 50_000_000))
    assert not by_stamp(graph["targets"], (300, 0))
    status = probe.status_where(f"{NS}/raster_node",
                                lambda s: int(diag_value(s, "rejected.no_matching_depth")) >= before + 1)
    assert status.level == DiagnosticStatus.WARN


def test_raster_pairs_within_the_slop_whichever_arrives_first(graph, scene):
    probe = graph["probe"]
    frame = scene["frames"][2]
    # depth first, mesh 3 ms later
    send_depth(graph, numpy_to_image(frame.depth_mm, "16UC1", make_header(400, 0)))
    probe.spin_for(0.1)
    graph["mesh_pub"].publish(mesh_message(frame, scene["faces"], make_header(400, 3_000_000)))
    # (the mesh input keeps the newest message only: a second mesh sent at once would replace this one)
    assert probe.spin_until(lambda: by_stamp(graph["targets"], (400, 3_000_000)), 5.0)
    # mesh first, depth 3 ms later
    graph["mesh_pub"].publish(mesh_message(frame, scene["faces"], make_header(401, 0)))
    probe.spin_for(0.1)
    send_depth(graph, numpy_to_image(frame.depth_mm, "16UC1", make_header(401, 3_000_000)))
    assert probe.spin_until(lambda: by_stamp(graph["targets"], (400, 3_000_000))
                            and by_stamp(graph["targets"], (401, 0)), 5.0), \
        [stamp_key(t.header) for t in graph["targets"]]
    for key in ((400, 3_000_000), (401, 0)):
        (target,) = by_stamp(graph["targets"], key)  # the mesh's stamp, not the depth's
        assert target.valid
        assert_target_on_body(target, frame)


# ----------------------------------------------------------------------------- ground_node


def test_ground_plane_of_the_rendered_floor(graph, scene):
    probe = graph["probe"]
    keys = [(600 + i, 1000 * i) for i in range(len(scene["frames"]))]
    for key, frame in zip(keys, scene["frames"]):
        depth = numpy_to_image(frame.depth_mm, "16UC1", make_header(*key))
        assert send_until(probe, lambda depth=depth: send_depth(graph, depth),
                          lambda key=key: by_stamp(graph["planes"], key), 15.0)
    for key, frame in zip(keys, scene["frames"]):
        plane = by_stamp(graph["planes"], key)[0]
        assert plane.header.frame_id == FRAME_ID and plane.valid
        rotation = frame.camera_pose.rotation  # columns: optical axes in the world (z up)
        up_in_camera = rotation.T @ np.array([0.0, 0.0, 1.0])
        normal = np.array([plane.normal.x, plane.normal.y, plane.normal.z])
        assert abs(np.linalg.norm(normal) - 1.0) < 1e-6
        angle = np.degrees(np.arccos(np.clip(normal @ up_in_camera, -1.0, 1.0)))
        assert angle < 2.0, angle
        assert abs(plane.offset - frame.camera_pose.position[2]) < 0.03, (plane.offset, frame.camera_pose.position)
        assert plane.inlier_count >= 200 and 0.05 <= plane.inlier_ratio <= 1.0


def wall_depth(header: Header) -> Image:
    """A wall 2 m ahead filling the view, turning away on the right: no floor for RANSAC."""
    wall = np.full((480, 640), 2000, np.uint16)
    wall[:, 320:] = np.linspace(2000, 3000, 320).astype(np.uint16)
    return numpy_to_image(wall, "16UC1", header)


def test_ground_plane_of_a_wall_only_is_invalid(graph):
    probe = graph["probe"]
    before = diag(graph, "ground_node", "rejected.no_ground_plane")
    wall_msg = wall_depth(make_header(500, 0))  # and no camera pose: nothing to fall back on
    assert send_until(probe, lambda: send_depth(graph, wall_msg), lambda: by_stamp(graph["planes"], (500, 0)), 15.0)
    plane = by_stamp(graph["planes"], (500, 0))[0]
    assert not plane.valid
    assert probe.spin_until(lambda: diag(graph, "ground_node", "rejected.no_ground_plane") >= before + 1, 5.0)
    assert graph["procs"][f"{NS}/ground_node"].poll() is None


# ----------------------------------------------------------------------------- ground_node: camera-pose floor


def camera_pose(key: tuple, height: float = 1.2, pitch_down_deg: float = 10.0, yaw_deg: float = 30.0) -> PoseStamped:
    """T_map_cameraOptical of a camera ``height`` m above the floor, pitched down, as localization gives it."""
    yaw, pitch = np.radians(yaw_deg), np.radians(pitch_down_deg)
    heading, up = np.array([np.cos(yaw), np.sin(yaw), 0.0]), np.array([0.0, 0.0, 1.0])
    right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    forward = np.cos(pitch) * heading - np.sin(pitch) * up
    down = -np.sin(pitch) * heading - np.cos(pitch) * up
    header = Header(frame_id="map")
    header.stamp.sec, header.stamp.nanosec = key
    return PoseStamped(header=header, pose=pose_msg(np.column_stack([right, down, forward]),
                                                    np.array([2.0, -1.0, height])))


def plane_arrays(plane: GroundPlane):
    return np.array([plane.normal.x, plane.normal.y, plane.normal.z]), plane.offset


def test_ground_falls_back_on_the_camera_pose_when_no_floor_is_in_view(graph):
    probe = graph["probe"]
    pose_pub = graph["pose_pub"]
    fallbacks_before = diag(graph, "ground_node", "planes.camera_pose")
    rejects_before = diag(graph, "ground_node", "rejected.no_ground_plane")

    # No pose of the frame's stamp (one 5 ms later only): the invalid plane, after the wait.
    key_none = (520, 0)
    started = time.monotonic()
    assert send_until(probe, lambda: (pose_pub.publish(camera_pose((520, 5_000_000))),
                                      send_depth(graph, wall_depth(make_header(*key_none)))),
                      lambda: by_stamp(graph["planes"], key_none), 15.0)
    waited = time.monotonic() - started
    invalid = by_stamp(graph["planes"], key_none)[0]
    assert not invalid.valid and invalid.source == GroundPlane.SOURCE_RANSAC
    assert waited >= 0.18, waited  # camera_pose_wait_s = 0.2 (the node's clock, ours monotonic)
    assert probe.spin_until(lambda: diag(graph, "ground_node", "rejected.no_ground_plane") >= rejects_before + 1, 5.0)

    # The pose before its depth frame (the simulator's order), and after it (DDS does not order topics).
    key_before, key_after = (521, 0), (522, 0)
    pose_before, pose_after = camera_pose(key_before), camera_pose(key_after, height=1.45, pitch_down_deg=20.0)

    def before() -> None:
        pose_pub.publish(pose_before)
        probe.spin_for(0.05)
        send_depth(graph, wall_depth(make_header(*key_before)))

    def after() -> None:
        send_depth(graph, wall_depth(make_header(*key_after)))
        probe.spin_for(0.1)
        pose_pub.publish(pose_after)

    assert send_until(probe, before, lambda: by_stamp(graph["planes"], key_before), 15.0)
    assert send_until(probe, after, lambda: by_stamp(graph["planes"], key_after), 15.0)
    for key, pose, height, pitch in ((key_before, pose_before, 1.2, 10.0), (key_after, pose_after, 1.45, 20.0)):
        plane = by_stamp(graph["planes"], key)[0]
        assert plane.valid and plane.source == GroundPlane.SOURCE_CAMERA_POSE
        assert plane.header.frame_id == FRAME_ID  # the depth frame's header, not the pose's
        normal, offset = plane_arrays(plane)
        expected_normal, expected_offset = floor_plane_from_camera_pose(*pose_to_numpy(pose.pose))
        np.testing.assert_allclose(normal, expected_normal, atol=1e-9)
        assert offset == pytest.approx(expected_offset, abs=1e-9)
        # and the floor itself: up leans back by the pitch, d is the height
        angle = np.radians(pitch)
        np.testing.assert_allclose(normal, [0.0, -np.cos(angle), -np.sin(angle)], atol=1e-6)
        assert offset == pytest.approx(height, abs=1e-6)
        # RANSAC's own numbers on the same wall, as the invalid plane reported them
        assert (plane.inlier_count, plane.inlier_ratio) == (invalid.inlier_count, invalid.inlier_ratio)
    assert probe.spin_until(lambda: diag(graph, "ground_node", "planes.camera_pose") >= fallbacks_before + 2, 5.0)
    assert diag(graph, "ground_node", "rejected.no_ground_plane") == rejects_before + 1  # served, not rejected
    assert graph["procs"][f"{NS}/ground_node"].poll() is None


def test_ground_checks_ransac_against_the_pose_refusing_a_disagreeing_plane(graph, scene):
    probe = graph["probe"]
    frame = scene["frames"][0]
    refused_before = diag(graph, "ground_node", "floor.camera_pose_refused_ransac")
    confirmed_before = diag(graph, "ground_node", "floor.ransac_confirmed")

    def send(pose, key) -> None:
        graph["pose_pub"].publish(pose)
        probe.spin_for(0.05)
        send_depth(graph, numpy_to_image(frame.depth_mm, "16UC1", make_header(*key)))

    # The rendered camera's own pose: RANSAC agrees with it and is kept (its quality above one half).
    key = (530, 0)
    true_pose = PoseStamped(header=make_header(*key), pose=pose_msg(frame.camera_pose.rotation,
                                                                    frame.camera_pose.position))
    true_pose.header.frame_id = "map"
    assert send_until(probe, lambda: send(true_pose, key), lambda: by_stamp(graph["planes"], key), 15.0)
    plane = by_stamp(graph["planes"], key)[0]
    assert plane.valid and plane.source == GroundPlane.SOURCE_RANSAC
    normal, offset = plane_arrays(plane)
    assert abs(offset - frame.camera_pose.position[2]) < 0.03
    up_in_camera = frame.camera_pose.rotation.T @ np.array([0.0, 0.0, 1.0])
    assert np.degrees(np.arccos(np.clip(normal @ up_in_camera, -1.0, 1.0))) < 2.0
    assert plane.inlier_count >= 200
    assert 0.5 < plane.quality <= 1.0

    # A pose that disagrees with the plane in view (0.5 m higher, pitched 25 deg): RANSAC's plane is
    # refused and the pose's floor is published (the pose is the robot's localization: it wins).
    key = (531, 0)
    pose = camera_pose(key, height=frame.camera_pose.position[2] + 0.5, pitch_down_deg=25.0)
    assert send_until(probe, lambda: send(pose, key), lambda: by_stamp(graph["planes"], key), 15.0)
    plane = by_stamp(graph["planes"], key)[0]
    assert plane.valid and plane.source == GroundPlane.SOURCE_CAMERA_POSE
    normal, offset = plane_arrays(plane)
    expected_normal, expected_offset = floor_plane_from_camera_pose(*pose_to_numpy(pose.pose))
    np.testing.assert_allclose(normal, expected_normal, atol=1e-9)
    assert offset == pytest.approx(expected_offset, abs=1e-9)
    assert plane.quality == pytest.approx(0.5)
    assert plane.inlier_count >= 200  # RANSAC's own numbers, as it found them
    assert probe.spin_until(lambda: diag(graph, "ground_node", "floor.camera_pose_refused_ransac")
                            >= refused_before + 1, 5.0)
    assert diag(graph, "ground_node", "floor.ransac_confirmed") >= confirmed_before + 1


def test_ground_leaves_out_the_person_boxes_of_a_frame_without_a_mask(graph, scene):
    from leapnbv_common.conversions import box_to_detection
    from leapnbv_msgs.msg import PersonDetections

    probe = graph["probe"]
    frame = scene["frames"][0]
    detections_pub = probe.node.create_publisher(PersonDetections, f"{NS}/detections", stage_output_qos(5))
    assert probe.spin_until(lambda: detections_pub.get_subscription_count() >= 1, 10.0)

    def fitted_points(plane) -> float:
        return plane.inlier_count / plane.inlier_ratio  # the points RANSAC was fitted on

    key_plain, key_boxed = (550, 0), (552, 0)
    depth = lambda key: numpy_to_image(frame.depth_mm, "16UC1", make_header(*key))  # noqa: E731
    assert send_until(probe, lambda: send_depth(graph, depth(key_plain)),
                      lambda: by_stamp(graph["planes"], key_plain), 15.0)
    box = np.array([*frame.ground_truth.person_box_xyxy, 0.9], np.float32)

    def send_boxed() -> None:
        detections_pub.publish(PersonDetections(header=make_header(*key_boxed), image_width=640, image_height=480,
                                                detections=[box_to_detection(box)], backend="ground_truth"))
        probe.spin_for(0.05)
        send_depth(graph, depth(key_boxed))

    assert send_until(probe, send_boxed, lambda: by_stamp(graph["planes"], key_boxed), 15.0)
    plain, boxed = by_stamp(graph["planes"], key_plain)[0], by_stamp(graph["planes"], key_boxed)[0]
    # The upper 60 % of the grown box is left out: fewer points, the floor still found.
    x1, y1, x2, y2 = frame.ground_truth.person_box_xyxy
    dropped = fitted_points(plain) - fitted_points(boxed)
    assert dropped > 0.3 * ((x2 - x1) * 0.6 * (y2 - y1)) / 16  # stride 4: one point per 16 pixels
    assert boxed.valid and abs(boxed.offset - frame.camera_pose.position[2]) < 0.05


def test_ground_rejects_a_bad_camera_pose_and_keeps_serving(graph):
    probe = graph["probe"]
    before = diag(graph, "ground_node", "rejected.bad_camera_pose")
    below = camera_pose((540, 0), height=-0.3)  # the camera under the floor
    not_finite = camera_pose((541, 0))
    not_finite.pose.position.x = float("nan")
    not_unit = camera_pose((542, 0))  # a quaternion of norm 2 is no rotation
    q = not_unit.pose.orientation
    q.x, q.y, q.z, q.w = 2 * q.x, 2 * q.y, 2 * q.z, 2 * q.w
    zero = camera_pose((543, 0))
    zero.pose.orientation.x = zero.pose.orientation.y = zero.pose.orientation.z = zero.pose.orientation.w = 0.0
    bad = [below, not_finite, not_unit, zero]
    for pose in bad:
        key = (pose.header.stamp.sec, pose.header.stamp.nanosec)

        def send(pose=pose, key=key) -> None:
            graph["pose_pub"].publish(pose)
            probe.spin_for(0.05)
            send_depth(graph, wall_depth(make_header(*key)))

        assert send_until(probe, send, lambda key=key: by_stamp(graph["planes"], key), 15.0)
        plane = by_stamp(graph["planes"], key)[0]
        assert not plane.valid and plane.source == GroundPlane.SOURCE_RANSAC
    assert probe.spin_until(lambda: diag(graph, "ground_node", "rejected.bad_camera_pose") >= before + len(bad), 5.0)
    status = probe.status_where(f"{NS}/ground_node", lambda s: int(diag_value(s, "rejected.bad_camera_pose")) > before)
    assert status.level == DiagnosticStatus.WARN
    # and a good pose still works afterwards
    key = (544, 0)
    assert send_until(probe, lambda: (graph["pose_pub"].publish(camera_pose(key)), probe.spin_for(0.05),
                                      send_depth(graph, wall_depth(make_header(*key)))),
                      lambda: by_stamp(graph["planes"], key), 15.0)
    assert by_stamp(graph["planes"], key)[0].valid
    assert graph["procs"][f"{NS}/ground_node"].poll() is None



# ----------------------------------------------------------------------------- parameters at runtime


def test_raster_applies_a_wider_slop_at_runtime_and_refuses_an_empty_depth_range(graph, scene):
    probe = graph["probe"]
    frame = scene["frames"][1]
    (result,) = set_parameters(probe, f"{NS}/raster_node", slop_s=0.1)
    assert result.successful, result.reason
    try:
        # 50 ms apart: dropped under the default 5 ms slop (see above), paired under 100 ms.
        key = (700, 50_000_000)
        assert send_until(probe, lambda: (send_depth(graph, numpy_to_image(frame.depth_mm, "16UC1", make_header(700))),
                                          probe.spin_for(0.1),
                                          graph["mesh_pub"].publish(mesh_message(frame, scene["faces"],
                                                                                 make_header(*key)))),
                          lambda: by_stamp(graph["targets"], key), 15.0)
        assert by_stamp(graph["targets"], key)[0].valid
    finally:
        assert set_parameters(probe, f"{NS}/raster_node", slop_s=0.005)[0].successful
    (empty,) = set_parameters(probe, f"{NS}/raster_node", min_depth=20.0)
    assert not empty.successful and "min_depth (20.0) must be below max_depth (10.0)" in empty.reason
    (fixed,) = set_parameters(probe, f"{NS}/raster_node", depth_cache_size=3)
    assert not fixed.successful and "depth_cache_size" in fixed.reason
    assert graph["procs"][f"{NS}/raster_node"].poll() is None


def test_ground_refuses_invalid_settings_and_applies_ransac_settings_at_runtime(graph, scene):
    probe = graph["probe"]
    (heights,) = set_parameters(probe, f"{NS}/ground_node", min_camera_height=2.0)
    assert not heights.successful and "must not exceed max_camera_height" in heights.reason
    (source,) = set_parameters(probe, f"{NS}/ground_node", camera_pose_source="tf")
    assert not source.successful and "camera_pose_source" in source.reason
    depths = {key: numpy_to_image(scene["frames"][0].depth_mm, "16UC1", make_header(*key))
              for key in ((710, 0), (711, 0))}
    # The floor is in view, but no plane can have that many inliers: invalid until the setting is back.
    assert set_parameters(probe, f"{NS}/ground_node", min_inliers=10_000_000)[0].successful
    try:
        assert send_until(probe, lambda: send_depth(graph, depths[(710, 0)]),
                          lambda: by_stamp(graph["planes"], (710, 0)), 15.0)
    finally:
        assert set_parameters(probe, f"{NS}/ground_node", min_inliers=200)[0].successful
    assert send_until(probe, lambda: send_depth(graph, depths[(711, 0)]),
                      lambda: by_stamp(graph["planes"], (711, 0)), 15.0)
    assert not by_stamp(graph["planes"], (710, 0))[0].valid and by_stamp(graph["planes"], (711, 0))[0].valid
    assert graph["procs"][f"{NS}/ground_node"].poll() is None


# ----------------------------------------------------------------------------- depth conversion


def test_depth_to_metres_as_the_nodes_read_it():
    """16UC1 millimetres and 32FC1 metres become float32 metres; 0, NaN and inf become 0 ("no return").
    A negative 32FC1 reading is never valid: every stage's depth range starts above 0."""
    millimetres = np.array([[0, 1500], [65535, 20]], dtype=np.uint16)
    metres = depth_to_metres(numpy_to_image(millimetres, "16UC1"))
    np.testing.assert_allclose(metres, [[0.0, 1.5], [65.535, 0.02]], rtol=1e-6)
    assert metres.dtype == np.float32
    floats = depth_to_metres(numpy_to_image(np.array([[np.nan, 1.0], [np.inf, -2.0]], np.float32), "32FC1"))
    assert floats.dtype == np.float32 and np.all(np.isfinite(floats))
    np.testing.assert_array_equal(floats[0], [0.0, 1.0])
    assert floats[1, 0] == 0.0 and not floats[1, 1] >= MIN_RANGE_M
