"""raster_node: HumanMesh + depth (+ the frame's GroundPlane) -> TargetGeometry, mask, metric mesh.

Parameters: :class:`leapnbv_geometry.params.RasterParams`; all but the depth cache size change at
runtime (``ros2 param set``).
"""
from __future__ import annotations

import time
from typing import Optional, Set

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from leapnbv_common.contracts import DuplicateStampGuard, check_same_frame, check_same_size, refused
from leapnbv_common.conversions import (
    DEPTH_ENCODINGS,
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
from leapnbv_common.qos import camera_input_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stamp_cache import CompanionWait, StampCache
from leapnbv_common.topics import GROUND_PLANE, HUMAN_MESH, HUMAN_MESH_METRIC, PERSON_MASK, TARGET_GEOMETRY
from leapnbv_geometry.params import RasterParams
from leapnbv_geometry.raster import warm_up
from leapnbv_geometry.target_geometry import compute_target_geometry, place_mesh_metric
from leapnbv_msgs.msg import GroundPlane, HumanMesh, TargetGeometry


class RasterNode(Node):
    def __init__(self) -> None:
        super().__init__("raster_node")
        self.params = NodeParams(self, RasterParams, self.on_params_change)
        p = self.params.value
        self.diagnostics = StageDiagnostics(self)
        self.depth_frames: StampCache = StampCache(p.depth_cache_size)
        self.pending_meshes: StampCache = StampCache(5)  # meshes that came before their depth
        self.ground = CompanionWait(int(p.ground_wait_s * 1e9))
        self.camera_info: Optional[CameraInfo] = None
        self.stamps = DuplicateStampGuard()  # one content per stamp and input (contracts)
        self.target_pub = self.create_publisher(TargetGeometry, TARGET_GEOMETRY, stage_output_qos())
        self.mask_pub = self.create_publisher(Image, PERSON_MASK, stage_output_qos())
        self.mesh_pub = self.create_publisher(HumanMesh, HUMAN_MESH_METRIC, stage_output_qos())
        warm_up()  # compile the rasterizer before subscribing: the graph is ready only after it
        self.create_subscription(Image, "depth", self.on_depth, camera_input_qos(p.depth_cache_size))
        self.create_subscription(CameraInfo, "depth/camera_info", self.on_camera_info, camera_input_qos(1))
        self.create_subscription(HumanMesh, HUMAN_MESH, self.on_mesh, stage_input_qos(5))
        self.create_subscription(GroundPlane, GROUND_PLANE, self.on_ground, stage_input_qos(5))
        self.create_timer(0.02, self.expire_waits)

    def on_params_change(self, params: RasterParams, changed: Set[str]) -> None:
        """A new ground wait applies to the frames already waiting too; the rest is read per frame."""
        self.ground.wait_ns = int(params.ground_wait_s * 1e9)

    def now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    @rejects_bad_input("bad_camera_info")
    def on_camera_info(self, msg: CameraInfo) -> None:
        camera_info_to_k(msg)  # validate before keeping it
        self.camera_info = msg

    @rejects_bad_input("bad_depth")
    def on_depth(self, msg: Image) -> None:
        # The depth contract (a view, no conversion)
        if refused(self.diagnostics, "bad_depth", check_image, msg, DEPTH_ENCODINGS, "depth") or \
                refused(self.diagnostics, "bad_depth", self.stamps.check, "depth", msg):
            return
        stamp = stamp_to_ns(msg.header.stamp)
        self.depth_frames.put(stamp, msg)
        # A mesh that came first pairs with this depth under the same slop as the other order.
        waiting = self.pending_meshes.find_nearest(stamp, int(self.params.value.slop_s * 1e9))
        if waiting is not None:
            self.pending_meshes.pop(waiting[0])
            self.pair_with_ground(waiting[1][0], msg)

    @rejects_bad_input("bad_ground_plane")
    def on_ground(self, msg: GroundPlane) -> None:
        # The contract: unit normal pointing up toward the camera, camera above it
        if refused(self.diagnostics, "bad_ground_plane", ground_plane_to_arrays, msg) or \
                refused(self.diagnostics, "bad_ground_plane", self.stamps.check, "ground_plane", msg):
            return
        ready = self.ground.add_companion(stamp_to_ns(msg.header.stamp), msg)
        if ready is not None:
            self.process(*ready[0], ready[1])

    @rejects_bad_input("bad_human_mesh")
    def on_mesh(self, msg: HumanMesh) -> None:
        self.diagnostics.frame_in()
        # The contract: a finite mesh with faces in range
        if refused(self.diagnostics, "bad_human_mesh", human_mesh_to_arrays, msg) or \
                refused(self.diagnostics, "bad_human_mesh", self.stamps.check, "human_mesh", msg):
            return
        stamp = stamp_to_ns(msg.header.stamp)
        match = self.depth_frames.find_nearest(stamp, int(self.params.value.slop_s * 1e9))
        if match is None:
            # The depth frame may still be on its way: wait for it a little (expire_waits).
            self.pending_meshes.put(stamp, (msg, self.now_ns()))
            return
        self.pair_with_ground(msg, match[1])

    def pair_with_ground(self, mesh: HumanMesh, depth: Image) -> None:
        ready = self.ground.add_frame(stamp_to_ns(mesh.header.stamp), (mesh, depth), self.now_ns())
        if ready is not None:
            self.process(*ready[0], ready[1])

    def expire_waits(self) -> None:
        for (mesh, depth), ground in self.ground.expire(self.now_ns()):
            self.diagnostics.reject("ground_plane_late", "used the latest ground plane instead of the frame's")
            self.process(mesh, depth, ground)
        # Meshes whose depth never came (dropped on the way) are counted, never mismatched.
        now = self.now_ns()
        for stamp, (_, since) in self.pending_meshes.items():
            if now - since > self.params.value.depth_wait_s * 1e9:
                self.pending_meshes.pop(stamp)
                self.diagnostics.reject("no_matching_depth", f"no depth frame within the slop of stamp {stamp} ns")

    @rejects_bad_input("bad_frame")
    def process(self, mesh_msg: HumanMesh, depth_msg: Image, ground: Optional[GroundPlane]) -> None:
        started = time.perf_counter()
        if self.camera_info is None:
            raise ValueError("no depth camera_info received yet")
        p = self.params.value
        k = camera_info_to_k(self.camera_info)
        # One frame: depth, its camera_info, the mesh (and the image it came from) and the floor agree.
        info, frame = self.camera_info, depth_msg.header.frame_id
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
        if ground is not None:
            floor = ground_plane_to_arrays(ground)
            plane = (floor.normal, floor.offset) if floor.valid else None
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
        self.target_pub.publish(arrays_to_target_geometry(target, header, compute_time_ms))
        self.mask_pub.publish(numpy_to_image(result.mask.astype(np.uint8) * 255, "mono8", header))
        mesh.vertices = result.metric_vertices.astype(np.float32)
        mesh.virtual_intrinsics = (k[0, 0], k[1, 1], k[0, 2], k[1, 2])
        self.mesh_pub.publish(arrays_to_human_mesh(mesh, header, compute_time_ms))
        self.diagnostics.frame_out(header.stamp, compute_time_ms)


def main(args=None) -> None:
    run_node(RasterNode, args)


if __name__ == "__main__":
    main()
