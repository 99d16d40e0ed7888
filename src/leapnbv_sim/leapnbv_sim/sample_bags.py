"""The committed sample bags: two synthetic scenes, ten frames each, as a RealSense would record them.

    python -m leapnbv_sim.sample_bags [--out bags] [--force]

The robot drifts 2 cm sideways per frame (10 Hz), so consecutive frames differ by more than
noise and the HMR stage has a target to track. Each frame carries the camera's pose in a ``map`` frame
(``/leapnbv/camera_pose``, as a robot's localisation publishes it), so the planner keeps its committed goal
in a fixed frame across the frames. Deterministic: the same seeds and stand-in body
give byte-identical images.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Dict, List, NamedTuple, Optional, Sequence, Tuple, Union

import numpy as np

from leapnbv_bags.bag_io import RELIABLE_QOS, SENSOR_DATA_QOS, BagWriter, make_typestore
from leapnbv_common.topics import CAMERA_POSE_TOPIC, CAMERA_TOPICS, GROUND_TRUTH_TOPIC
from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_sim.generation import SceneConfig, generate_scene
from leapnbv_sim.poses import CameraPose
from leapnbv_sim.render import RenderedFrame
from leapnbv_sim.scene import Scene
from leapnbv_stand_ins.files import ensure_stand_in_body_model


class SampleBagSpec(NamedTuple):
    """The scene of one sample bag."""

    seed: int
    walls: bool


# name -> scene seed and options; two different scenes (with and without walls).
SAMPLE_BAGS: Dict[str, SampleBagSpec] = {
    "sample_a": SampleBagSpec(seed=3, walls=True),
    "sample_b": SampleBagSpec(seed=11, walls=False),
}
NUM_FRAMES = 10
DRIFT_M_PER_FRAME = 0.02
MAP_FRAME_ID = "map"  # the fixed frame of the sample bags' camera poses


def render_drifting_frames(
    scene: Scene, num_frames: int = NUM_FRAMES, drift_m: float = DRIFT_M_PER_FRAME
) -> List[RenderedFrame]:
    """Frames from the start view moved drift_m per frame along the camera's x axis (level)."""
    start = scene.start_camera
    frames = []
    for i in range(num_frames):
        position = start.position + start.rotation[:, 0] * (drift_m * i)
        frames.append(scene.render(CameraPose(start.rotation, position), frame_index=i))
    return frames


class SampleBagInfo(NamedTuple):
    """What :func:`make_sample_bag` wrote."""

    counts: Dict[str, int]  # messages per topic
    occluder_share: Tuple[float, float]  # smallest and largest over the frames


def make_sample_bag(
    path: Path, seed: int, walls: bool, body_model: SMPLXModel, body_model_id: str, overwrite: bool
) -> SampleBagInfo:
    """Generate a sample scene, render its drifting frames and record them (:func:`write_scene_bag`).

    Args:
        path: Bag directory to create.
        seed: Scene seed.
        walls: Whether the scene has walls.
        body_model: The body model the scene's person is posed with.
        body_model_id: Stored in each SceneGroundTruth.
        overwrite: Replace an existing bag.

    Returns:
        Message counts and the frames' occluder-share range.
    """
    scene = generate_scene(SceneConfig(seed=seed, walls=walls, body_resolution="small"), body_model)
    frames = render_drifting_frames(scene)
    counts = write_scene_bag(path, frames, body_model_id=body_model_id, overwrite=overwrite,
                             camera_pose_frame_id=MAP_FRAME_ID)
    shares = [f.ground_truth.occluder_share for f in frames]
    return SampleBagInfo(counts, (float(np.min(shares)), float(np.max(shares))))


def write_scene_bag(
    path: Union[str, Path],
    frames: Sequence[RenderedFrame],
    *,
    frame_id: str = "camera_color_optical_frame",
    start_stamp_ns: int = 1_700_000_000_000_000_000,
    period_ns: int = 100_000_000,
    body_model_id: str = "stand_in_small",
    overwrite: bool = False,
    camera_pose_frame_id: Optional[str] = None,
) -> Dict[str, int]:
    """Record rendered frames under RealSense topic names plus the simulator's ground truth (and camera pose).

    Each frame i gets stamp ``start_stamp_ns + i * period_ns`` on all its topics (header stamp
    and bag log time alike); the messages are the simulator node's own
    (:func:`leapnbv_sim.frame_messages.camera_frame_messages`, the ROS glue that this ROS-free
    module imports only when it writes). rclpy's CDR leaves alignment padding uninitialised, so
    each message is read back into the bag's typestore and written by rosbags, which zeroes it:
    the same frames give a byte-identical bag on every run.

    Args:
        path: Bag directory to create.
        frames: Rendered frames (all the same size).
        frame_id: Optical frame of the colour camera.
        start_stamp_ns: Stamp of the first frame, nanoseconds since the epoch.
        period_ns: Time between frames, nanoseconds.
        body_model_id: Stored in each SceneGroundTruth.
        overwrite: Replace an existing bag atomically once the new one is complete.
        camera_pose_frame_id: Also record each frame's camera pose (its ``camera_pose``: the optical frame in the
            world) on the camera pose topic, in this frame id; None: no camera pose.

    Returns:
        Message count per topic.

    Raises:
        BagError: ``path`` exists (without overwrite) or writing fails.
    """
    from leapnbv_sim.frame_messages import serialized_camera_frames  # the ROS glue: rclpy and messages

    msgtypes = {CAMERA_TOPICS["image"]: "sensor_msgs/msg/Image",
                CAMERA_TOPICS["camera_info"]: "sensor_msgs/msg/CameraInfo",
                CAMERA_TOPICS["depth"]: "sensor_msgs/msg/Image",
                CAMERA_TOPICS["depth/camera_info"]: "sensor_msgs/msg/CameraInfo",
                GROUND_TRUTH_TOPIC: "leapnbv_msgs/msg/SceneGroundTruth"}
    frame_topics = list(msgtypes)
    pose = None if camera_pose_frame_id is None else (CAMERA_POSE_TOPIC, camera_pose_frame_id)
    if pose is not None:
        msgtypes[CAMERA_POSE_TOPIC] = "geometry_msgs/msg/PoseStamped"
    with BagWriter(path, overwrite=overwrite, typestore=make_typestore()) as bag:
        for topic, msgtype in msgtypes.items():
            bag.add_topic(topic, msgtype, qos=RELIABLE_QOS if topic in (GROUND_TRUTH_TOPIC, CAMERA_POSE_TOPIC)
                          else SENSOR_DATA_QOS)
        stamped = ((int(start_stamp_ns) + index * int(period_ns), frame) for index, frame in enumerate(frames))
        for topic, stamp, cdr in serialized_camera_frames(stamped, frame_id, body_model_id, frame_topics, pose):
            bag.write(topic, stamp, bag.typestore.deserialize_cdr(cdr, msgtypes[topic]))
        counts = dict(bag.message_counts)
    return counts


def main(argv: Optional[List[str]] = None) -> int:
    """Write the sample bags (the command line above); returns the exit status."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="bags", help="folder for the bags")
    parser.add_argument("--force", action="store_true", help="replace existing bags (atomically)")
    args = parser.parse_args(argv)

    body_model = SMPLXModel.load(ensure_stand_in_body_model("small"))
    for name, spec in SAMPLE_BAGS.items():
        path = Path(args.out) / name
        if path.exists() and not args.force:
            print(f"[bags] {path} exists (use --force to replace)")
            continue
        info = make_sample_bag(path, spec.seed, spec.walls, body_model, "stand_in_small", args.force)
        print(f"[bags] wrote {path}: {info.counts}; occluder share {info.occluder_share}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
