"""The LEAP-NBV node graph: which nodes run, in which namespace, with which topic remaps.

Both the graph runner (processes, used here and in tests) and the ROS 2 launch file (the
robot) build the graph from this one list, so they cannot drift apart.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Dict, List

NAMESPACE = "/leapnbv"

# Camera driver topics (RealSense names), remappable on the command line of the runner/launch.
CAMERA_TOPICS = {
    "image": "/camera/color/image_raw",
    "camera_info": "/camera/color/camera_info",
    "depth": "/camera/aligned_depth_to_color/image_raw",
    "depth/camera_info": "/camera/aligned_depth_to_color/camera_info",
}
# Optional robot inputs (remappable like the camera topics): the camera's optical frame in a
# fixed, floor-aligned frame (z up, floor z = 0; from the robot's localization / TF), stamped
# with each camera frame, and the robot's map of static obstacles as occupied voxel centres in
# that frame (latched). ground_node falls back on the pose's floor when RANSAC finds none;
# nbv_node adds the map's obstacles to its footprint and line-of-sight tests.
ROBOT_TOPICS = {
    "camera_pose": "/leapnbv/camera_pose",
    "obstacle_map": "/leapnbv/obstacle_map",
}
# Every remappable input of the graph.
INPUT_TOPICS = {**CAMERA_TOPICS, **ROBOT_TOPICS}
GROUND_TRUTH_TOPIC = "/leapnbv/sim/ground_truth"


@dataclass(frozen=True)
class NodeSpec:
    """One node of the graph: the package and executable, and the remaps of its inputs."""

    name: str
    package: str
    module: str
    remaps: Dict[str, str] = field(default_factory=dict)

    @property
    def executable(self) -> str:
        return self.name


def graph_nodes(camera_topics: Dict[str, str] = None) -> List[NodeSpec]:
    """The five nodes, inputs remapped to the topics given (keys of INPUT_TOPICS; RealSense names by default)."""
    cam = dict(INPUT_TOPICS)
    cam.update(camera_topics or {})
    gt = {"ground_truth": GROUND_TRUTH_TOPIC}
    return [
        NodeSpec("detector_node", "leapnbv_perception", "leapnbv_perception.nodes.detector_node",
                 {"image": cam["image"], **gt}),
        NodeSpec("hmr_node", "leapnbv_perception", "leapnbv_perception.nodes.hmr_node",
                 {"image": cam["image"], "camera_info": cam["camera_info"], **gt}),
        NodeSpec("raster_node", "leapnbv_geometry", "leapnbv_geometry.nodes.raster_node",
                 {"depth": cam["depth"], "depth/camera_info": cam["depth/camera_info"]}),
        NodeSpec("ground_node", "leapnbv_geometry", "leapnbv_geometry.nodes.ground_node",
                 {"depth": cam["depth"], "depth/camera_info": cam["depth/camera_info"],
                  "camera_pose": cam["camera_pose"]}),
        NodeSpec("nbv_node", "leapnbv_planner", "leapnbv_planner.nodes.nbv_node",
                 {"camera_pose": cam["camera_pose"], "obstacle_map": cam["obstacle_map"]}),
    ]


# Every output of the graph (absolute names), with its message type.
OUTPUT_TOPICS = {
    NAMESPACE + "/detections": "leapnbv_msgs/msg/PersonDetections",
    NAMESPACE + "/human_mesh": "leapnbv_msgs/msg/HumanMesh",
    NAMESPACE + "/target_geometry": "leapnbv_msgs/msg/TargetGeometry",
    NAMESPACE + "/person_mask": "sensor_msgs/msg/Image",
    NAMESPACE + "/human_mesh_metric": "leapnbv_msgs/msg/HumanMesh",
    NAMESPACE + "/ground_plane": "leapnbv_msgs/msg/GroundPlane",
    NAMESPACE + "/view_candidates": "leapnbv_msgs/msg/ViewCandidates",
    NAMESPACE + "/next_best_view": "geometry_msgs/msg/PoseStamped",
    NAMESPACE + "/base_goal": "geometry_msgs/msg/PoseStamped",
    NAMESPACE + "/markers": "visualization_msgs/msg/MarkerArray",
}
FINAL_OUTPUT_TOPIC = NAMESPACE + "/view_candidates"


def default_params_file() -> str:
    """config/leapnbv.yaml from the installed share folder, else from the source tree."""
    here = os.path.dirname(os.path.abspath(__file__))
    candidates = [os.path.join(here, "..", "config", "leapnbv.yaml")]
    try:
        from ament_index_python.packages import get_package_share_directory

        candidates.insert(0, os.path.join(get_package_share_directory("leapnbv_bringup"), "config", "leapnbv.yaml"))
    except Exception:  # noqa: BLE001 - not installed: use the source tree
        pass
    for path in candidates:
        if os.path.exists(path):
            return os.path.normpath(path)
    raise FileNotFoundError(f"leapnbv.yaml not found in {candidates}")


def fastdds_profile_file() -> str:
    """The Fast DDS large-message profile shipped beside the parameter file."""
    return os.path.join(os.path.dirname(default_params_file()), "fastdds_large_messages.xml")
