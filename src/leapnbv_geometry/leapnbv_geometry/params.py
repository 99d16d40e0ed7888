"""The parameters of raster_node and ground_node: one source of each default, description and range.

The defaults are the deployed robot's (the ground priors describe its camera mounting).
Parameters the node builds its subscriptions or caches from are read-only: set at start-up.
"""
from __future__ import annotations

from dataclasses import dataclass

from leapnbv_common.params import StageParams, param

WAIT_MAX_S = 10.0
MAX_RANGE_M = 100.0
MIN_RANGE_M = 0.001  # depth 0 is "no return": the valid range starts above it


def check_depth_range(min_depth: float, max_depth: float) -> None:
    """Raises ValueError unless min_depth < max_depth."""
    if not min_depth < max_depth:
        raise ValueError(f"min_depth ({min_depth}) must be below max_depth ({max_depth})")


@dataclass
class RasterParams(StageParams):
    """raster_node: HumanMesh + depth (+ the frame's GroundPlane) -> TargetGeometry, person mask, metric mesh."""

    slop_s: float = param(0.005, "s: largest stamp difference between a mesh and the depth frame it is paired with",
                          min=0.0, max=1.0)
    depth_wait_s: float = param(1.0, "s: how long a mesh waits for its depth frame before it is dropped and counted",
                                min=0.0, max=WAIT_MAX_S)
    depth_cache_size: int = param(45, "depth frames kept while their meshes are computed (45: 1.5 s of a 30 FPS "
                                  "camera, what a CPU detector + HMR can take per frame)", min=1, max=1000,
                                  read_only=True)
    ground_wait_s: float = param(0.5, "s: how long a frame waits for the ground plane fitted on its depth frame; "
                                 "then it is served without a plane (never with another frame's)", min=0.0,
                                 max=WAIT_MAX_S)
    box_dilation_px: float = param(10.0, "px: the detection box is grown by this much before intersecting the "
                                   "silhouette", min=0.0, max=1000.0)
    depth_tolerance: float = param(0.15, "metres: mask pixels farther than this from the aligned mesh depth are "
                                   "dropped", min=MIN_RANGE_M, max=10.0)
    min_depth: float = param(0.1, "metres: nearer depth readings are invalid", min=MIN_RANGE_M, max=MAX_RANGE_M)
    max_depth: float = param(10.0, "metres: farther depth readings are invalid", min=MIN_RANGE_M, max=MAX_RANGE_M)
    background_stride: int = param(4, "px: pixel stride of the background point set", min=1, max=64)
    target_stride: int = param(1, "px: target points of every n-th row and column (1: every person pixel; 2 for a "
                                  "planner over a Wi-Fi link, docs/TWO_HOSTS.md)", min=1, max=8)
    ground_inlier_threshold: float = param(0.03, "metres: background points this close to the ground plane are "
                                           "dropped", min=0.0, max=1.0)
    # Mesh registration to the depth (mesh_registration): the registered mesh makes the mask and the target.
    registration_enabled: bool = param(False, "scale the mesh about the camera centre to the depth inside its box "
                                       "before the mask and the target; a mesh that cannot be registered gives no "
                                       "target (rejected.mesh_not_registered)")
    registration_inlier_band: float = param(0.15, "metres: |depth - registered mesh depth| within which a pixel is "
                                            "an inlier of the registration", min=MIN_RANGE_M, max=10.0)
    registration_min_inlier_share: float = param(0.1, "smallest share of the silhouette's valid-depth pixels that "
                                                 "must be inliers", min=0.0, max=1.0)
    registration_max_residual: float = param(0.1, "metres: largest RMS residual of the registration's inliers",
                                             min=MIN_RANGE_M, max=10.0)
    registration_max_spill: float = param(0.5, "largest share of the ring just outside the silhouette at a "
                                          "candidate's depth (more: an occluder or background, not the person)",
                                          min=0.0, max=1.0)

    def check(self) -> None:
        check_depth_range(self.min_depth, self.max_depth)


@dataclass
class GroundParams(StageParams):
    """Parameters of ground_node.

    ground_node: depth + camera_info (minus the latest person mask) -> GroundPlane (RANSAC, or the
    camera pose's floor).
    """

    # The priors describe the robot's camera mounting (its height above the floor and its pitch), not any
    # simulator: a robot with another mounting sets them (the evaluation sets them from its robot model).
    # These priors keep box tops and walls out.
    max_tilt_deg: float = param(25.0, "deg: largest angle between the plane normal and the up expected from the "
                                "mounting pitch (camera_pitch_deg): walls are refused", min=0.0, max=90.0)
    camera_pitch_deg: float = param(0.0, "deg: the camera's mounting pitch below the horizon; the tilt prior is "
                                    "centred on the up it implies", min=-90.0, max=90.0)
    min_camera_height: float = param(0.8, "metres: the camera is at least this high above the floor (mounting prior)",
                                     min=0.0, max=MAX_RANGE_M)
    max_camera_height: float = param(1.6, "metres: the camera is at most this high above the floor (box tops are "
                                     "refused)", min=0.0, max=MAX_RANGE_M)
    inlier_threshold: float = param(0.03, "metres from the plane for a point to count as an inlier (at z = 0)",
                                    min=MIN_RANGE_M, max=1.0)
    depth_noise_coeff: float = param(0.0, "metres per m^2 added to the inlier threshold at depth z (depth noise ~ "
                                     "z^2)", min=0.0, max=1.0)
    iterations: int = param(256, "RANSAC hypotheses per frame (half drawn from neighbouring points)", min=1,
                            max=100000)
    min_inliers: int = param(200, "fewer inliers than this: valid=false", min=0, max=10000000)
    min_inlier_ratio: float = param(0.02, "smaller inlier share than this: valid=false", min=0.0, max=1.0)
    max_points: int = param(2048, "points subsampled to score the hypotheses (all points refine the winner)", min=3,
                            max=1000000)
    stride: int = param(4, "px: pixel stride when back-projecting the depth frame", min=1, max=64)
    min_depth: float = param(0.1, "metres: nearer depth readings are invalid", min=MIN_RANGE_M, max=MAX_RANGE_M)
    max_depth: float = param(10.0, "metres: farther depth readings are invalid", min=MIN_RANGE_M, max=MAX_RANGE_M)
    seed: int = param(0, "RANSAC random seed (deterministic results for replay)", min=0, max=2**31 - 1)
    # The previous frame's person mask is an exclusion hint of bounded age: it only removes floor candidates.
    mask_max_age_s: float = param(0.5, "s: the person mask is excluded only when it is at most this much older than "
                                  "the depth", min=0.0, max=60.0)
    mask_wait_s: float = param(0.0, "s: wait this long for the previous frame's person mask before fitting (0 = never, "
                               "the default: fit at once with the newest mask; a replay one frame at a time has it "
                               "anyway)", min=0.0, max=WAIT_MAX_S)
    # Latest-frame scheduling: fit the frames the rest of the graph works on (the detector admits them).
    fit_detected_frames_only: bool = param(True, "fit only the depth frames of camera frames the detector published "
                                           "a person for (detections of the same stamp within slop_s): the frames "
                                           "the graph works on; false: every depth frame", read_only=True)
    slop_s: float = param(0.005, "s: largest stamp difference between detections and the depth frame fitted for "
                          "them, and between a person mask and the frame it belongs to", min=0.0, max=1.0)
    depth_wait_s: float = param(0.5, "s: how long detections wait for their depth frame before they are dropped "
                                "and counted", min=0.0, max=WAIT_MAX_S)
    depth_cache_size: int = param(45, "depth frames kept until their detections come (45: 1.5 s of a 30 FPS "
                                  "camera, what a CPU detector can take per frame)", min=1, max=1000,
                                  read_only=True)
    # With a camera pose of the frame's stamp, RANSAC's plane is checked against the pose's floor z = 0 and
    # refused when they disagree; when RANSAC finds none, the pose's floor is used (occluders can hide all of it).
    use_camera_pose_fallback: bool = param(True, "use the camera pose (in a floor-aligned fixed frame) of the same "
                                           "stamp: it checks RANSAC's plane and replaces a refused or missing one",
                                           read_only=True)
    pose_max_angle_deg: float = param(2.0, "deg: a RANSAC plane whose normal is farther than this from the camera "
                                      "pose's floor is refused", min=0.0, max=90.0)
    pose_max_height_m: float = param(0.05, "metres: a RANSAC plane whose camera height differs more than this from "
                                     "the camera pose's is refused", min=0.0, max=MAX_RANGE_M)
    quality_full_support: float = param(0.2, "inlier ratio at which the plane's quality figure counts full support",
                                        min=0.001, max=1.0)
    # The frame's detections are what starts its fit (fit_detected_frames_only), so its boxes are at hand.
    exclude_detections: bool = param(True, "a frame with no recent person mask (the first of a scene) leaves out "
                                     "its own person boxes (its detections; with fit_detected_frames_only)")
    detection_grow_px: float = param(10.0, "px: person boxes are grown by this much when left out", min=0.0,
                                     max=1000.0)
    # The floor round the feet is often the only floor an occluder leaves in view. Measured on 50 start views per
    # family (scripts/experiments/floor_check.py, RANSAC alone): leaving the person out did not lower the wrong
    # floors there (3 -> 2-6 on the committed views, within RANSAC's own variation); the pose check (fuse_floor)
    # removes them.
    detection_top_share: float = param(0.6, "share of each person box's height, from its top, left out (the rest "
                                       "keeps the floor round the feet)", min=0.05, max=1.0)
    camera_pose_source: str = param("topic", "where the camera pose comes from: a key of "
                                    "leapnbv_common.camera_pose.CAMERA_POSE_SOURCES (topic: PoseStamped on "
                                    "camera_pose)", read_only=True)
    # The pose is published before the frame's images, but DDS does not order topics: wait this long for it.
    camera_pose_wait_s: float = param(0.2, "s: a frame without a RANSAC floor waits this long for its camera pose "
                                      "before the invalid plane is published (0 = only a pose already received)",
                                      min=0.0, max=WAIT_MAX_S)

    def check(self) -> None:
        check_depth_range(self.min_depth, self.max_depth)
        if not self.min_camera_height <= self.max_camera_height:
            raise ValueError(f"min_camera_height ({self.min_camera_height}) must not exceed max_camera_height "
                             f"({self.max_camera_height})")
