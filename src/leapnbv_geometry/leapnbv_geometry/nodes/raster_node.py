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

A mesh that names its triangles by id takes them from mesh_faces (latched, once per model); one whose
triangles have not come is refused (``rejected.mesh_faces_unknown``). The metric mesh goes out in the
form its input came in: triangles named by the same id, or in the message.

Parameters: :class:`leapnbv_geometry.params.RasterParams`; all but the depth cache size change at
runtime (``ros2 param set``).
"""
from __future__ import annotations

import time
from typing import Set

import numpy as np
from sensor_msgs.msg import CameraInfo, Image

from leapnbv_common.contracts import check_same_frame, check_same_size, refused
from leapnbv_common.conversions import (
    TargetGeometryArrays,
    arrays_to_human_mesh,
    arrays_to_target_geometry,
    camera_info_to_k,
    depth_to_metres,
    ground_plane_to_arrays,
    image_size,
    numpy_to_image,
)
from leapnbv_common.managed_node import ManagedNode, managed_node_main
from leapnbv_common.mesh_faces_topic import MeshFacesInput
from leapnbv_common.qos import camera_input_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stage import NEAREST, REJECT, SAME_OR_LATEST, Companion, Frame, KeyInput, Stage
from leapnbv_common.stage_inputs import checked_camera_info, checked_depth_image, checked_human_mesh
from leapnbv_common.topics import GROUND_PLANE, HUMAN_MESH, HUMAN_MESH_METRIC, PERSON_MASK, TARGET_GEOMETRY
from leapnbv_geometry.mesh_registration import register_for_frame
from leapnbv_geometry.params import RasterParams
from leapnbv_geometry.raster import warm_up
from leapnbv_geometry.target_geometry import compute_target_geometry, place_mesh_metric
from leapnbv_msgs.msg import GroundPlane, HumanMesh, TargetGeometry


class RasterNode(ManagedNode):
    def __init__(self) -> None:
        super().__init__("raster_node", RasterParams)

    def configure_stage(self) -> None:
        p = self.params.value
        self.target_pub = self.create_lifecycle_publisher(TargetGeometry, TARGET_GEOMETRY, stage_output_qos())
        self.mask_pub = self.create_lifecycle_publisher(Image, PERSON_MASK, stage_output_qos())
        self.mesh_pub = self.create_lifecycle_publisher(HumanMesh, HUMAN_MESH_METRIC, stage_output_qos())
        self.mesh_faces = MeshFacesInput(self)
        warm_up()  # compile the rasterizer before subscribing: the graph is ready only after it
        # The mesh starts the work (the newest only). Depth frames and camera infos are pulled when a mesh
        # comes (they do not wake the node at 30 Hz) and depth frames stay serialized until one pairs; the
        # frame's plane (ground_node stamps it with the frame's, the mesh's, stamp) is waited for briefly.
        self.stage = Stage(self, KeyInput("human_mesh", HumanMesh, HUMAN_MESH,
                                          lambda msg: checked_human_mesh(msg, self.mesh_faces.known),
                                          stage_input_qos(1)), [
            Companion("depth", Image, "depth", checked_depth_image, camera_input_qos(p.depth_cache_size),
                      match=NEAREST, slop_s=lambda f: self.params.value.slop_s,
                      wait_s=lambda f: self.params.value.depth_wait_s, when_missing=REJECT,
                      missing_reason="no_matching_depth",
                      missing_detail=lambda f: f"no depth frame within the slop of stamp {f.stamp_ns} ns",
                      capacity=p.depth_cache_size, raw=True, pulled=True, consume=True, skip_older=True),
            # The depth frame's own camera_info, else the latest one (calibration: recorded as STATIC).
            Companion("depth/camera_info", CameraInfo, "depth/camera_info", checked_camera_info,
                      camera_input_qos(p.depth_cache_size), match=SAME_OR_LATEST, stamp_from="depth",
                      when_missing=REJECT, missing_reason="bad_frame",
                      missing_detail=lambda f: "no depth camera_info received yet", capacity=p.depth_cache_size,
                      pulled=True, bad_reason="bad_camera_info"),
            # No plane of this frame in time: served without one (background keeps the floor points), never
            # with another frame's.
            Companion("ground_plane", GroundPlane, GROUND_PLANE, ground_plane_to_arrays,
                      stage_input_qos(p.depth_cache_size), wait_s=lambda f: self.params.value.ground_wait_s,
                      missing_reason="ground_plane_late",
                      missing_detail=lambda f: "no ground plane of this depth frame in time: served without one"
                      " (background keeps the floor points), never with another frame's",
                      capacity=p.depth_cache_size),
        ], self.on_frame, capacity=p.depth_cache_size)

    def activate_stage(self) -> None:
        self.mesh_faces.subscribe()
        self.stage.start()
        self.diagnostics.await_publishers(HUMAN_MESH, GROUND_PLANE)  # ready once the stages before are connected

    def deactivate_stage(self) -> None:
        self.stage.stop()

    def on_params_change(self, params: RasterParams, changed: Set[str]) -> None:
        """Everything is read per frame (the waits too, for the frames already waiting)."""

    def on_frame(self, frame: Frame) -> None:
        started = time.perf_counter()
        mesh, depth_msg = frame["human_mesh"], frame["depth"]
        mesh_msg: HumanMesh = frame.key.message
        info: CameraInfo = frame["depth/camera_info"]
        ground = frame.received("ground_plane")
        p = self.params.value
        k = camera_info_to_k(info)
        # One frame: depth, its camera_info, the mesh (and the image it came from) and the floor agree.
        depth_frame = depth_msg.header.frame_id
        if refused(self.diagnostics, "bad_frame", check_same_size, "depth", image_size(depth_msg), "depth camera_info",
                   image_size(info)) or \
                refused(self.diagnostics, "bad_frame", check_same_frame, "depth", depth_frame, "depth camera_info",
                        info.header.frame_id) or \
                refused(self.diagnostics, "bad_frame", check_same_size, "the mesh's image",
                        (mesh_msg.image_width, mesh_msg.image_height), "depth", image_size(depth_msg)) or \
                refused(self.diagnostics, "bad_frame", check_same_frame, "human_mesh", mesh_msg.header.frame_id,
                        "depth", depth_frame) or \
                (ground is not None and refused(self.diagnostics, "bad_frame", check_same_frame, "ground_plane",
                                                ground.frame_id, "depth", depth_frame)):
            return
        depth = depth_to_metres(depth_msg)
        vertices = place_mesh_metric(mesh.vertices, mesh.virtual_intrinsics, k, mesh.cam_translation,
                                     mesh.image_size, (depth.shape[1], depth.shape[0]))
        # Registered to the depth inside the box (when on): the registered mesh makes the mask, target and mesh.
        registration = register_for_frame(vertices, mesh.faces, depth, k, mesh.detection[:4], p)
        floor = None if ground is None else ground.value
        result = compute_target_geometry(
            registration.vertices, mesh.faces, depth, k, mesh.detection[:4], box_dilation_px=p.box_dilation_px,
            depth_tolerance=p.depth_tolerance, min_depth=p.min_depth, max_depth=p.max_depth,
            background_stride=p.background_stride, target_stride=p.target_stride,
            ground_plane=(floor.normal, floor.offset) if floor is not None and floor.valid else None,
            ground_inlier_threshold=p.ground_inlier_threshold, depth_offset=registration.depth_offset,
            refused_reason=registration.refused_reason, mesh_raster=registration.raster)
        header = depth_msg.header
        header.stamp = mesh_msg.header.stamp  # outputs carry the stamp of the frame the mesh came from
        target = TargetGeometryArrays(
            target_points=result.target_points, background_points=result.background_points,
            centroid=result.centroid, bbox_min=result.bbox_min, bbox_max=result.bbox_max,  # zeros when not valid
            mask_pixel_count=result.mask_pixel_count, visible_fraction=result.visible_fraction,
            depth_offset=result.depth_offset + registration.depth_shift, valid=result.valid, k=k,
            width=depth.shape[1], height=depth.shape[0])
        compute_time_ms = (time.perf_counter() - started) * 1e3
        if not result.valid:
            self.diagnostics.reject("mesh_not_registered" if registration.refused_reason else "empty_target",
                                    result.invalid_reason)
        if p.registration_enabled:  # the last frame's fit: info.registration on /diagnostics
            self.diagnostics.set_info("registration", registration.summary)
        inputs = frame.inputs
        self.target_pub.publish(arrays_to_target_geometry(target, header, compute_time_ms, inputs=inputs))
        self.mask_pub.publish(numpy_to_image(result.mask.astype(np.uint8) * 255, "mono8", header))
        mesh.vertices = result.metric_vertices.astype(np.float32)
        mesh.virtual_intrinsics = (k[0, 0], k[1, 1], k[0, 2], k[1, 2])
        self.mesh_pub.publish(arrays_to_human_mesh(mesh, header, compute_time_ms, inputs=inputs,
                                                   inline_faces=len(mesh_msg.faces) > 0))
        self.diagnostics.frame_out(header.stamp, compute_time_ms)


main = managed_node_main(RasterNode)  # the console script (leapnbv_common.managed_node: the process tuned, then run)


if __name__ == "__main__":
    main()
