"""raster_node: HumanMesh + depth (+ the frame's GroundPlane) -> TargetGeometry, mask, metric mesh."""
from __future__ import annotations

import time
from typing import Optional

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from leapnbv_common.conversions import (
    arrays_to_human_mesh,
    camera_info_to_k,
    depth_to_metres,
    human_mesh_to_arrays,
    numpy_to_image,
    point_msg,
    stamp_to_ns,
    xyz_to_pointcloud2,
)
from leapnbv_common.diagnostics import StageDiagnostics, rejects_bad_input
from leapnbv_common.node_params import declare_parameters, run_node
from leapnbv_common.qos import camera_input_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stamp_cache import CompanionWait, StampCache
from leapnbv_geometry.raster import warm_up
from leapnbv_geometry.target_geometry import compute_target_geometry, place_mesh_metric
from leapnbv_msgs.msg import GroundPlane, HumanMesh, TargetGeometry

PARAMETERS = {
    "slop_s": (0.005, "largest stamp difference between a mesh and the depth frame it is paired with"),
    "depth_wait_s": (1.0, "how long a mesh waits for its depth frame before it is dropped and counted"),
    "depth_cache_size": (15, "depth frames kept while their meshes are computed"),
    "ground_wait_s": (1.0, "how long a frame waits for the ground plane of the same stamp, then uses the latest"),
    "box_dilation_px": (10.0, "the detection box is grown by this much before intersecting the silhouette"),
    "depth_tolerance": (0.15, "metres: mask pixels farther than this from the aligned mesh depth are dropped"),
    "min_depth": (0.1, "metres: nearer depth readings are invalid"),
    "max_depth": (10.0, "metres: farther depth readings are invalid"),
    "background_stride": (4, "pixel stride of the background point set"),
    "ground_inlier_threshold": (0.03, "metres: background points this close to the ground plane are dropped"),
}


class RasterNode(Node):
    def __init__(self) -> None:
        super().__init__("raster_node")
        p = self.params = declare_parameters(self, PARAMETERS)
        self.diagnostics = StageDiagnostics(self)
        self.depth_frames: StampCache = StampCache(p["depth_cache_size"])
        self.pending_meshes: StampCache = StampCache(5)  # meshes that came before their depth
        self.ground = CompanionWait(int(p["ground_wait_s"] * 1e9))
        self.camera_info: Optional[CameraInfo] = None
        self.target_pub = self.create_publisher(TargetGeometry, "target_geometry", stage_output_qos())
        self.mask_pub = self.create_publisher(Image, "person_mask", stage_output_qos())
        self.mesh_pub = self.create_publisher(HumanMesh, "human_mesh_metric", stage_output_qos())
        warm_up()  # compile the rasterizer before subscribing: the graph is ready only after it
        self.create_subscription(Image, "depth", self.on_depth, camera_input_qos(p["depth_cache_size"]))
        self.create_subscription(CameraInfo, "depth/camera_info", self.on_camera_info, camera_input_qos(1))
        self.create_subscription(HumanMesh, "human_mesh", self.on_mesh, stage_input_qos(5))
        self.create_subscription(GroundPlane, "ground_plane", self.on_ground, stage_input_qos(5))
        self.create_timer(0.02, self.expire_waits)

    def now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    @rejects_bad_input("bad_camera_info")
    def on_camera_info(self, msg: CameraInfo) -> None:
        camera_info_to_k(msg)  # validate before keeping it
        self.camera_info = msg

    def on_depth(self, msg: Image) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        self.depth_frames.put(stamp, msg)
        # A mesh that came first pairs with this depth under the same slop as the other order.
        waiting = self.pending_meshes.find_nearest(stamp, int(self.params["slop_s"] * 1e9))
        if waiting is not None:
            self.pending_meshes.pop(waiting[0])
            self.pair_with_ground(waiting[1][0], msg)

    @rejects_bad_input("bad_ground_plane")
    def on_ground(self, msg: GroundPlane) -> None:
        ready = self.ground.add_companion(stamp_to_ns(msg.header.stamp), msg)
        if ready is not None:
            self.process(*ready[0], ready[1])

    def on_mesh(self, msg: HumanMesh) -> None:
        self.diagnostics.frame_in()
        stamp = stamp_to_ns(msg.header.stamp)
        match = self.depth_frames.find_nearest(stamp, int(self.params["slop_s"] * 1e9))
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
            if now - since > self.params["depth_wait_s"] * 1e9:
                self.pending_meshes.pop(stamp)
                self.diagnostics.reject("no_matching_depth", f"no depth frame within the slop of stamp {stamp} ns")

    @rejects_bad_input("bad_frame")
    def process(self, mesh_msg: HumanMesh, depth_msg: Image, ground: Optional[GroundPlane]) -> None:
        started = time.perf_counter()
        if self.camera_info is None:
            raise ValueError("no depth camera_info received yet")
        p = self.params
        k = camera_info_to_k(self.camera_info)
        depth = depth_to_metres(depth_msg)
        if depth.shape != (self.camera_info.height, self.camera_info.width):
            raise ValueError(f"depth {depth.shape[1]}x{depth.shape[0]} does not match camera_info "
                             f"{self.camera_info.width}x{self.camera_info.height}")
        mesh = human_mesh_to_arrays(mesh_msg)
        vertices = place_mesh_metric(mesh.vertices, mesh.virtual_intrinsics, k, mesh.cam_translation)
        plane = None
        if ground is not None and ground.valid:
            plane = (np.array([ground.normal.x, ground.normal.y, ground.normal.z]), float(ground.offset))
        result = compute_target_geometry(
            vertices, mesh.faces, depth, k, mesh.detection[:4], box_dilation_px=p["box_dilation_px"],
            depth_tolerance=p["depth_tolerance"], min_depth=p["min_depth"], max_depth=p["max_depth"],
            background_stride=p["background_stride"], ground_plane=plane,
            ground_inlier_threshold=p["ground_inlier_threshold"])
        header = depth_msg.header
        header.stamp = mesh_msg.header.stamp  # outputs carry the stamp of the frame the mesh came from
        out = TargetGeometry(header=header)
        out.target_points = xyz_to_pointcloud2(result.target_points, header)
        out.background_points = xyz_to_pointcloud2(result.background_points, header)
        out.centroid = point_msg(result.centroid if result.valid else np.zeros(3))
        out.bbox_min = point_msg(result.bbox_min if result.valid else np.zeros(3))
        out.bbox_max = point_msg(result.bbox_max if result.valid else np.zeros(3))
        out.mask_pixel_count = int(result.mask_pixel_count)
        out.visible_fraction = float(result.visible_fraction)
        out.depth_offset = float(result.depth_offset)
        out.valid = bool(result.valid)
        out.camera_info = self.camera_info
        out.compute_time_ms = (time.perf_counter() - started) * 1e3
        if not result.valid:
            self.diagnostics.reject("empty_target", result.invalid_reason)
        self.target_pub.publish(out)
        self.mask_pub.publish(numpy_to_image(result.mask.astype(np.uint8) * 255, "mono8", header))
        mesh.vertices = result.metric_vertices.astype(np.float32)
        mesh.virtual_intrinsics = (k[0, 0], k[1, 1], k[0, 2], k[1, 2])
        self.mesh_pub.publish(arrays_to_human_mesh(mesh, header, out.compute_time_ms))
        self.diagnostics.frame_out(header.stamp, out.compute_time_ms)


def main(args=None) -> None:
    run_node(RasterNode, args)


if __name__ == "__main__":
    main()
