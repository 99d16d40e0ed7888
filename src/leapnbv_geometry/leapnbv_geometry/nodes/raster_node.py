"""raster_node: HumanMesh + depth (+ the frame's GroundPlane) -> TargetGeometry, mask, metric mesh.

One frame, one set of inputs: a mesh is paired with the depth frame of its stamp (within
``slop_s``), the camera_info of that depth frame, and the ground plane fitted on that depth frame
(waited for at most ``ground_wait_s``). A frame whose plane did not come in time is served without
one (its background keeps the floor points; counted as ``rejected.ground_plane_late``), never with
another frame's plane. Every output lists the stamps it used (``inputs``).

Latest-frame scheduling: the mesh subscription keeps the newest message only; a mesh waiting for
its depth frame or its plane is superseded by a newer one; a mesh older than a frame already
published is dropped; depth frames older than a published frame are dropped from the cache.
Every drop is counted on /diagnostics (``dropped.<reason>``).

Parameters: :class:`leapnbv_geometry.params.RasterParams`; all but the depth cache size change at
runtime (``ros2 param set``).
"""
from __future__ import annotations

import time
from typing import Optional, Set, Tuple

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from leapnbv_common.contracts import DuplicateStampGuard, check_same_frame, check_same_size, refused
from leapnbv_common.conversions import (
    DEPTH_ENCODINGS,
    SerializedImage,
    TargetGeometryArrays,
    arrays_to_human_mesh,
    arrays_to_target_geometry,
    camera_info_to_k,
    check_image,
    depth_to_metres,
    ground_plane_to_arrays,
    human_mesh_to_arrays,
    image_size,
    numpy_to_image,
    stamp_to_ns,
)
from leapnbv_common.diagnostics import StageDiagnostics, rejects_bad_input
from leapnbv_common.node_params import NodeParams, run_node
from leapnbv_common.process_tuning import tune_node_process
from leapnbv_common.pulled_input import HOUSEKEEPING_PERIOD_S, PulledInput
from leapnbv_common.qos import camera_input_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stamp_cache import STAMP_RESTART_NS, CompanionWait, StampCache
from leapnbv_common.topics import GROUND_PLANE, HUMAN_MESH, HUMAN_MESH_METRIC, PERSON_MASK, TARGET_GEOMETRY
from leapnbv_geometry.params import RasterParams
from leapnbv_geometry.raster import warm_up
from leapnbv_geometry.target_geometry import compute_target_geometry, place_mesh_metric
from leapnbv_msgs.msg import GroundPlane, HumanMesh, InputStamp, TargetGeometry

WAIT_CHECK_PERIOD_S = 0.02  # how often waiting frames are checked (the timer runs only while one waits)


class RasterNode(Node):
    def __init__(self) -> None:
        super().__init__("raster_node")
        self.params = NodeParams(self, RasterParams, self.on_params_change)
        p = self.params.value
        self.diagnostics = StageDiagnostics(self)
        drop = self.diagnostics.drop_callback()
        self.depth_frames: StampCache = StampCache(p.depth_cache_size, "depth_evicted", drop)
        self.camera_infos: StampCache = StampCache(p.depth_cache_size, "camera_info_evicted")
        self.latest_camera_info: Optional[CameraInfo] = None
        self.pending_mesh: Optional[Tuple[int, HumanMesh, int]] = None  # (stamp, mesh, since ns): waits for depth
        self.last_published: Optional[int] = None
        self.stamps = DuplicateStampGuard()  # one content per stamp and input (contracts)
        # Frames (mesh, depth, camera_info) wait here for the plane of their stamp.
        self.ground = CompanionWait(int(p.ground_wait_s * 1e9), capacity=p.depth_cache_size, frame_name="frame",
                                    companion_name="ground_plane", on_drop=drop)
        self.target_pub = self.create_publisher(TargetGeometry, TARGET_GEOMETRY, stage_output_qos())
        self.mask_pub = self.create_publisher(Image, PERSON_MASK, stage_output_qos())
        self.mesh_pub = self.create_publisher(HumanMesh, HUMAN_MESH_METRIC, stage_output_qos())
        warm_up()  # compile the rasterizer before subscribing: the graph is ready only after it
        # Depth frames and planes are companions: they arrive before their mesh, and their queues hold
        # what comes while this node is busy. The mesh starts the work: the newest one only.
        # Depth frames and camera infos are pulled when a mesh comes (they do not wake the node at 30 Hz:
        # leapnbv_common.pulled_input), and depth frames stay serialized until a mesh pairs with one.
        self.depth_input = PulledInput.create(self, Image, "depth", self.on_depth,
                                              camera_input_qos(p.depth_cache_size), raw=True)
        self.info_input = PulledInput.create(self, CameraInfo, "depth/camera_info", self.on_camera_info,
                                             camera_input_qos(p.depth_cache_size))
        self.create_subscription(HumanMesh, HUMAN_MESH, self.on_mesh, stage_input_qos(1))
        self.create_subscription(GroundPlane, GROUND_PLANE, self.on_ground, stage_input_qos(p.depth_cache_size))
        self.diagnostics.await_publishers(HUMAN_MESH, GROUND_PLANE)  # ready once the stages before are connected
        # A bad depth frame or camera_info is counted within HOUSEKEEPING_PERIOD_S even while no mesh comes.
        self.create_timer(HOUSEKEEPING_PERIOD_S, self.pull_companions)
        self.wait_timer = self.create_timer(WAIT_CHECK_PERIOD_S, self.expire_waits)
        self.wait_timer.cancel()  # runs only while a frame waits: an idle node does not wake up

    def on_params_change(self, params: RasterParams, changed: Set[str]) -> None:
        """A new ground wait applies to the frames already waiting too; the rest is read per frame."""
        self.ground.wait_ns = int(params.ground_wait_s * 1e9)

    def now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def start_wait_timer(self) -> None:
        if self.wait_timer.is_canceled():
            self.wait_timer.reset()

    def pull_companions(self) -> None:
        """Take the camera infos and depth frames that arrived since the last pull."""
        self.info_input.drain()
        self.depth_input.drain()

    @rejects_bad_input("bad_camera_info")
    def on_camera_info(self, msg: CameraInfo) -> None:
        camera_info_to_k(msg)  # validate before keeping it
        self.camera_infos.put(stamp_to_ns(msg.header.stamp), msg)
        self.latest_camera_info = msg

    @rejects_bad_input("bad_depth")
    def on_depth(self, msg: bytes, info) -> None:
        """A depth frame, read in place from its serialized bytes: cached by stamp until a mesh pairs with it."""
        self.diagnostics.input_seen("depth", info)
        msg = SerializedImage(msg)  # a ConversionError counts as bad_depth
        # The depth contract (a view, no conversion)
        if refused(self.diagnostics, "bad_depth", check_image, msg, DEPTH_ENCODINGS, "depth") or \
                refused(self.diagnostics, "bad_depth", self.stamps.check, "depth", msg):
            return
        stamp = stamp_to_ns(msg.header.stamp)
        if self.last_published is not None and 0 < self.last_published - stamp < STAMP_RESTART_NS:
            self.diagnostics.drop("depth_older_than_published")
            return
        self.depth_frames.put(stamp, msg)
        # A mesh that came first pairs with this depth under the same slop as the other order.
        if self.pending_mesh is not None and abs(self.pending_mesh[0] - stamp) <= self.slop_ns():
            _, mesh, _ = self.pending_mesh
            self.pending_mesh = None
            self.pair_with_ground(mesh, stamp, msg)

    @rejects_bad_input("bad_ground_plane")
    def on_ground(self, msg: GroundPlane) -> None:
        # The contract: unit normal pointing up toward the camera, camera above it
        if refused(self.diagnostics, "bad_ground_plane", ground_plane_to_arrays, msg) or \
                refused(self.diagnostics, "bad_ground_plane", self.stamps.check, "ground_plane", msg):
            return
        ready = self.ground.add_companion(stamp_to_ns(msg.header.stamp), msg)
        if ready is not None:
            self.process(*ready[0], ready[1])

    def slop_ns(self) -> int:
        return int(self.params.value.slop_s * 1e9)

    @rejects_bad_input("bad_human_mesh")
    def on_mesh(self, msg: HumanMesh, info) -> None:
        self.diagnostics.frame_in()
        self.diagnostics.input_seen("human_mesh", info)
        # The contract: a finite mesh with faces in range
        if refused(self.diagnostics, "bad_human_mesh", human_mesh_to_arrays, msg) or \
                refused(self.diagnostics, "bad_human_mesh", self.stamps.check, "human_mesh", msg):
            return
        stamp = stamp_to_ns(msg.header.stamp)
        if self.last_published is not None and stamp <= self.last_published:
            if self.last_published - stamp < STAMP_RESTART_NS:
                self.diagnostics.drop("duplicate_stamp" if stamp == self.last_published else "older_than_published")
                return
            self.last_published = None  # the stamps started over (a replay from its start)
        self.pull_companions()
        if self.pending_mesh is not None:
            if self.pending_mesh[0] >= stamp:
                self.diagnostics.drop("human_mesh_superseded")
                return
            self.pending_mesh = None
            self.diagnostics.drop("human_mesh_superseded")  # the older mesh still had no depth: this one wins
        match = self.depth_frames.find_nearest(stamp, self.slop_ns())
        if match is None:
            # The depth frame may still be on its way: wait for it a little (expire_waits).
            self.pending_mesh = (stamp, msg, self.now_ns())
            self.start_wait_timer()
            return
        self.pair_with_ground(msg, *match)

    def pair_with_ground(self, mesh: HumanMesh, depth_stamp: int, depth: SerializedImage) -> None:
        """Wait for the plane of this frame (ground_node stamps it with the frame's stamp, the mesh's)."""
        self.depth_frames.pop(depth_stamp)
        camera_info = self.camera_infos.get_exact(depth_stamp)
        ready = self.ground.add_frame(stamp_to_ns(mesh.header.stamp), (mesh, depth, camera_info), self.now_ns())
        if ready is not None:
            self.process(*ready[0], ready[1])
        elif self.ground.waiting():
            self.start_wait_timer()

    def expire_waits(self) -> None:
        for _, (mesh, depth, camera_info) in self.ground.expire(self.now_ns()):
            self.diagnostics.reject("ground_plane_late", "no ground plane of this depth frame in time: served without"
                                    " one (background keeps the floor points), never with another frame's")
            self.process(mesh, depth, camera_info, None)
        # A mesh whose depth never came (dropped on the way) is counted, never mismatched.
        if self.pending_mesh is not None:
            self.pull_companions()
        if self.pending_mesh is not None:
            stamp, _, since = self.pending_mesh
            if self.now_ns() - since > self.params.value.depth_wait_s * 1e9:
                self.pending_mesh = None
                self.diagnostics.reject("no_matching_depth", f"no depth frame within the slop of stamp {stamp} ns")
        if self.pending_mesh is None and not self.ground.waiting():
            self.wait_timer.cancel()

    def frame_camera_info(self, camera_info: Optional[CameraInfo]) -> Tuple[CameraInfo, tuple]:
        """The depth frame's own camera_info, else the latest one (calibration: recorded as STATIC)."""
        if camera_info is not None:
            return camera_info, ("depth/camera_info", stamp_to_ns(camera_info.header.stamp), InputStamp.SAME_FRAME)
        if self.latest_camera_info is None:
            raise ValueError("no depth camera_info received yet")
        info = self.latest_camera_info
        return info, ("depth/camera_info", stamp_to_ns(info.header.stamp), InputStamp.STATIC)

    @rejects_bad_input("bad_frame")
    def process(self, mesh_msg: HumanMesh, depth_msg: SerializedImage, camera_info: Optional[CameraInfo],
                ground: Optional[GroundPlane]) -> None:
        started = time.perf_counter()
        mesh_stamp, depth_stamp = stamp_to_ns(mesh_msg.header.stamp), stamp_to_ns(depth_msg.header.stamp)
        if self.last_published is not None and mesh_stamp <= self.last_published:
            self.diagnostics.drop("older_than_published")
            return
        self.last_published = mesh_stamp
        self.depth_frames.drop_older_than(depth_stamp, "depth_skipped")  # frames the graph did not work on
        camera_info, info_input = self.frame_camera_info(camera_info)
        p = self.params.value
        k = camera_info_to_k(camera_info)
        # One frame: depth, its camera_info, the mesh (and the image it came from) and the floor agree.
        info, frame = camera_info, depth_msg.header.frame_id
        if refused(self.diagnostics, "bad_frame", check_same_size, "depth", image_size(depth_msg), "depth camera_info",
                   image_size(info)) or \
                refused(self.diagnostics, "bad_frame", check_same_frame, "depth", frame, "depth camera_info",
                        info.header.frame_id) or \
                refused(self.diagnostics, "bad_frame", check_same_size, "the mesh's image",
                        (mesh_msg.image_width, mesh_msg.image_height), "depth", image_size(depth_msg)) or \
                refused(self.diagnostics, "bad_frame", check_same_frame, "human_mesh", mesh_msg.header.frame_id,
                        "depth", frame) or \
                (ground is not None and refused(self.diagnostics, "bad_frame", check_same_frame, "ground_plane",
                                                ground.header.frame_id, "depth", frame)):
            return
        depth = depth_to_metres(depth_msg)
        mesh = human_mesh_to_arrays(mesh_msg)
        vertices = place_mesh_metric(mesh.vertices, mesh.virtual_intrinsics, k, mesh.cam_translation,
                                     mesh.image_size, (depth.shape[1], depth.shape[0]))
        plane = None
        inputs = [("human_mesh", mesh_stamp), ("depth", depth_stamp), info_input]
        if ground is not None:
            floor = ground_plane_to_arrays(ground)
            plane = (floor.normal, floor.offset) if floor.valid else None
            inputs.append(("ground_plane", stamp_to_ns(ground.header.stamp)))
        result = compute_target_geometry(
            vertices, mesh.faces, depth, k, mesh.detection[:4], box_dilation_px=p.box_dilation_px,
            depth_tolerance=p.depth_tolerance, min_depth=p.min_depth, max_depth=p.max_depth,
            background_stride=p.background_stride, ground_plane=plane,
            ground_inlier_threshold=p.ground_inlier_threshold)
        header = depth_msg.header
        header.stamp = mesh_msg.header.stamp  # outputs carry the stamp of the frame the mesh came from
        target = TargetGeometryArrays(
            target_points=result.target_points, background_points=result.background_points,
            centroid=result.centroid, bbox_min=result.bbox_min, bbox_max=result.bbox_max,  # zeros when not valid
            mask_pixel_count=result.mask_pixel_count, visible_fraction=result.visible_fraction,
            depth_offset=result.depth_offset, valid=result.valid, k=k, width=depth.shape[1], height=depth.shape[0])
        compute_time_ms = (time.perf_counter() - started) * 1e3
        if not result.valid:
            self.diagnostics.reject("empty_target", result.invalid_reason)
        self.target_pub.publish(arrays_to_target_geometry(target, header, compute_time_ms, inputs=inputs))
        self.mask_pub.publish(numpy_to_image(result.mask.astype(np.uint8) * 255, "mono8", header))
        mesh.vertices = result.metric_vertices.astype(np.float32)
        mesh.virtual_intrinsics = (k[0, 0], k[1, 1], k[0, 2], k[1, 2])
        self.mesh_pub.publish(arrays_to_human_mesh(mesh, header, compute_time_ms, inputs=inputs))
        self.diagnostics.frame_out(header.stamp, compute_time_ms)


def main(args=None) -> None:
    tune_node_process()  # one BLAS thread, image buffers reused (leapnbv_common.process_tuning)
    run_node(RasterNode, args)


if __name__ == "__main__":
    main()
