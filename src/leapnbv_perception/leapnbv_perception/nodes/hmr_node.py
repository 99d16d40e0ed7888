"""hmr_node: image + PersonDetections (same stamp) -> HumanMesh of the target person.

Engine backends run the SMPLer-X-style encoder + heads and the FP32 SMPL-X tail; the
ground_truth backend poses the body model with the simulator's ground-truth parameters.

One frame, one set of inputs: the detections are paired with the image (or the ground truth) of
exactly their stamp, and the mesh lists what it used (``inputs``). Latest-frame scheduling: the
detections subscription keeps the newest message only, a frame older than one already published
is dropped, and cached images / ground truth older than a published frame are dropped; every drop
is counted on /diagnostics (``dropped.<reason>``). Once the engine is loaded, /diagnostics says whether
it estimates the hands (``info.hands``: ``estimated``, or ``not_estimated`` for a body-only export,
whose meshes all have the SMPL-X hand mean pose; that is also logged once).

The body model's triangles go out once per model on the latched mesh_faces topic and each mesh names
them by id (``faces_id``; leapnbv_common.mesh_faces), unless ``inline_mesh_faces`` puts them in every mesh.

Which detection is the target (:mod:`leapnbv_perception.nodes.target_inputs`, the rules in
:mod:`leapnbv_perception.target_tracking`): its place in the camera pose's fixed frame, from the frame's
depth and camera pose, within a gate around where the target's track predicts it; without a pose or depth,
by box overlap in the image. Every decided frame publishes a ``TargetTrack`` on ``target_track`` (TRACKED,
NOT_SEEN, LOST or NONE) before the mesh; a frame whose target is not among its detections gets no mesh
(``rejected.target_not_seen``).

Parameters: :class:`leapnbv_perception.params.HmrParams`. The crop scale, the hand un-mirroring,
the target tracking and inline_mesh_faces change at runtime; the engine, the models, the cache and the
camera-pose source are set at start-up.
"""
from __future__ import annotations

import os
import time
from typing import Set

import numpy as np
from sensor_msgs.msg import Image

from leapnbv_common.contracts import check_same_frame, check_same_size, refused
from leapnbv_common.conversions import (
    HumanMeshArrays,
    SerializedImage,
    arrays_to_human_mesh,
    detections_to_boxes,
    image_size,
    image_to_rgb,
)
from leapnbv_common.managed_node import ManagedNode, managed_node_main
from leapnbv_common.mesh_faces_topic import MeshFacesPublisher
from leapnbv_common.qos import camera_input_qos, stage_input_qos, stage_output_qos
from leapnbv_common.stage import REJECT, Companion, Frame, KeyInput, Stage
from leapnbv_common.topics import DETECTIONS, HUMAN_MESH
from leapnbv_msgs.msg import HumanMesh, PersonDetections
from leapnbv_perception.backends.ground_truth import GROUND_TRUTH_BACKEND, GroundTruthMeshBackend, people_published_on
from leapnbv_perception.nodes.engine_loading import create_engine_backend, load_in_configure
from leapnbv_perception.nodes.target_inputs import TargetInputs
from leapnbv_perception.params import HmrParams
from leapnbv_perception.target_tracking import STATE_NOT_SEEN

# How long detections wait for their colour image: DDS does not order topics, and a fast detector (the
# simulator's boxes, a carried box) can publish before this node has the image it was made from.
IMAGE_WAIT_S = 0.2


class HmrNode(ManagedNode):
    def __init__(self) -> None:
        super().__init__("hmr_node", HmrParams)

    def configure_stage(self) -> None:
        """The engine (or the body model, for the ground-truth backend) is loaded here: a missing or broken file
        fails the configure with its path and the node stays unconfigured (retried: leapnbv_common.managed_node)."""
        p = self.params.value
        self.diagnostics.hardware_id = p.backend
        self.ground_truth = p.backend == GROUND_TRUTH_BACKEND
        if self.ground_truth:  # the error budget's corrupted truth says so in every status
            self.diagnostics.set_info("truth_corruption", p.mesh_corruption().describe())
        self.engine = load_in_configure(self, f"HMR engine {p.model_file_path!r} with body model "
                                                       f"{p.body_model_path!r}", self.load_engine)
        self.publisher = self.create_lifecycle_publisher(HumanMesh, HUMAN_MESH, stage_output_qos())
        self.mesh_faces = MeshFacesPublisher(self)
        self.target = TargetInputs(self)
        if self.ground_truth:
            companions = GroundTruthMeshBackend.companions(p.cache_size, people_published_on(self))
        else:
            # Images wait for their detections (the detector takes a while) in the reader and the stage's cache,
            # serialized: pulled when detections come, deserialized only for the frame worked on.
            companions = [Companion("image", Image, "image", SerializedImage, camera_input_qos(p.cache_size),
                                    wait_s=lambda f: IMAGE_WAIT_S, when_missing=REJECT,
                                    missing_reason="no_matching_image",
                                    missing_detail=lambda f: f"no image with stamp {f.stamp_ns} ns within"
                                    f" {IMAGE_WAIT_S} s", capacity=p.cache_size, raw=True, pulled=True, consume=True,
                                    skip_older=True)]
        # The detections start the work (the newest only); the truth or the image, the camera infos, the depth
        # frames and the camera poses come at camera rate and are pulled when detections come
        # (leapnbv_common.pulled_input).
        self.stage = Stage(self, KeyInput("detections", PersonDetections, DETECTIONS, detections_to_boxes,
                                          stage_input_qos(1)), companions + self.target.companions(), self.estimate,
                           capacity=p.cache_size, on_restart=self.target.reset)
        self.target.attach()

    def activate_stage(self) -> None:
        self.stage.start()
        self.diagnostics.await_publishers(DETECTIONS)  # ready once the detector is connected

    def deactivate_stage(self) -> None:
        self.stage.stop()

    def cleanup_stage(self) -> None:
        self.engine = None  # the engine's memory goes with it

    def load_engine(self):
        from leapnbv_perception.smplx_layer import SMPLXModel

        p = self.params.value
        if not p.body_model_path:
            raise FileNotFoundError("parameter body_model_path is empty: set it to SMPLX_NEUTRAL.npz")
        body_model = SMPLXModel.load(os.path.expanduser(p.body_model_path))
        if self.ground_truth:
            return body_model
        from leapnbv_perception.hmr import HANDS_ESTIMATED, HANDS_NOT_ESTIMATED, HumanMeshEstimator

        estimator = HumanMeshEstimator(create_engine_backend(p), body_model, box_scale=p.box_scale,
                                       unmirror_left_hand=p.unmirror_left_hand)
        # Said once, when the engine loads: a body-only engine's meshes all have the hand mean pose.
        self.diagnostics.set_info("hands", HANDS_ESTIMATED if estimator.hands_estimated else HANDS_NOT_ESTIMATED)
        if not estimator.hands_estimated:
            self.get_logger().info(
                f"HMR engine {p.model_file_path!r} is body-only (export metadata leapnbv.hands=not_estimated): "
                "the hand poses are not estimated, every mesh has the SMPL-X hand mean pose")
        return estimator

    def on_params_change(self, params: HmrParams, changed: Set[str]) -> None:
        """The crop scale and the hand un-mirroring apply from the next frame; the tracking settings
        are read per frame, and switching the tracking off or on forgets the target and the people followed
        (the next frame takes a target by the acquisition rule)."""
        if changed & {"track_previous_target", "track_in_fixed_frame"}:
            self.target.reset()
        if self.engine is not None and not self.ground_truth:
            self.engine.box_scale = params.box_scale
            self.engine.unmirror_left_hand = params.unmirror_left_hand

    def estimate(self, frame: Frame) -> None:
        started = time.perf_counter()
        detections: PersonDetections = frame.key.message
        # The frame's other input (its colour image, or the camera_info the ground truth is placed with)
        # names the same frame and has the size the detections were found in.
        other_name, other = GroundTruthMeshBackend.reference(frame) if self.ground_truth else ("image", frame["image"])
        if refused(self.diagnostics, "bad_frame", check_same_frame, "detections", detections.header.frame_id,
                   other_name, other.header.frame_id) or \
                refused(self.diagnostics, "bad_frame", check_same_size, "the detections' image",
                        (detections.image_width, detections.image_height), other_name, image_size(other)):
            return
        boxes = frame["detections"]
        p = self.params.value
        decision = self.target.decide(frame, boxes, (int(detections.image_width), int(detections.image_height)))
        if decision.detection_index < 0:
            if decision.state == STATE_NOT_SEEN:
                self.diagnostics.reject("target_not_seen", decision.reason)
            else:
                self.diagnostics.reject("no_person", decision.reason)
            return
        box = boxes[decision.detection_index]
        if self.ground_truth:
            mesh = GroundTruthMeshBackend.mesh(self.engine, frame, box, p.box_scale, p.mesh_corruption())
        else:
            mesh = self.engine_mesh(box, frame["image"])
        self.mesh_faces.name(mesh)  # its triangles on mesh_faces before the first mesh that names them
        out = arrays_to_human_mesh(mesh, header=detections.header,
                                   compute_time_ms=(time.perf_counter() - started) * 1e3, inputs=frame.inputs,
                                   inline_faces=p.inline_mesh_faces)
        self.publisher.publish(out)
        self.diagnostics.frame_out(detections.header.stamp, out.compute_time_ms)

    def engine_mesh(self, box: np.ndarray, image: SerializedImage) -> HumanMeshArrays:
        rgb = image_to_rgb(image)
        est = self.engine.estimate(rgb, box[:4])
        return HumanMeshArrays(
            vertices=est.vertices, faces=est.faces, virtual_intrinsics=(est.fx, est.fy, est.cx, est.cy),
            image_size=(rgb.shape[1], rgb.shape[0]), detection=box, processed_box=est.processed_box,
            root_pose=est.root, body_pose=est.body, left_hand_pose=est.left_hand,
            right_hand_pose=est.right_hand, jaw_pose=est.jaw, betas=est.betas,
            expression=est.expression, cam_translation=est.cam_translation,
            model_id=os.path.basename(self.params.value.model_file_path))


main = managed_node_main(HmrNode)  # the console script (leapnbv_common.managed_node: the process tuned, then run)


if __name__ == "__main__":
    main()
