"""Every topic name of the graph, in one place.

Stage outputs are published under relative names inside the graph's namespace; the camera and
robot inputs are absolute names that the runner and the launch file remap the nodes' relative
input names to. Nodes create their publishers and subscriptions with the relative names below.
"""
from __future__ import annotations

from typing import Dict

NAMESPACE = "/leapnbv"

# Camera driver topics (RealSense names), remappable on the command line of the runner/launch.
# Keys are the relative names the nodes subscribe to.
CAMERA_TOPICS: Dict[str, str] = {
    "image": "/camera/color/image_raw",
    "camera_info": "/camera/color/camera_info",
    "depth": "/camera/aligned_depth_to_color/image_raw",
    "depth/camera_info": "/camera/aligned_depth_to_color/camera_info",
}
COLOR_IMAGE_TOPIC = CAMERA_TOPICS["image"]
COLOR_INFO_TOPIC = CAMERA_TOPICS["camera_info"]
DEPTH_IMAGE_TOPIC = CAMERA_TOPICS["depth"]
DEPTH_INFO_TOPIC = CAMERA_TOPICS["depth/camera_info"]

# Optional robot inputs (remappable like the camera topics): the camera's optical frame in a
# fixed, floor-aligned frame (z up, floor z = 0; from the robot's localization / TF), stamped
# with each camera frame, and the robot's map of static obstacles as occupied voxel centres in
# that frame (latched).
CAMERA_POSE = "camera_pose"
OBSTACLE_MAP = "obstacle_map"
ROBOT_TOPICS: Dict[str, str] = {
    CAMERA_POSE: NAMESPACE + "/" + CAMERA_POSE,
    OBSTACLE_MAP: NAMESPACE + "/" + OBSTACLE_MAP,
}
CAMERA_POSE_TOPIC = ROBOT_TOPICS["camera_pose"]
OBSTACLE_MAP_TOPIC = ROBOT_TOPICS["obstacle_map"]

# The robot's TF tree (tf2_msgs/TFMessage; absolute names, as tf2_ros uses them): dynamic links on
# TF_TOPIC, static ones (transient-local) on TF_STATIC_TOPIC. The TF camera-pose source reads both.
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"

# Every remappable input of the graph.
INPUT_TOPICS: Dict[str, str] = {**CAMERA_TOPICS, **ROBOT_TOPICS}

# The simulator's ground truth (the ground-truth perception backends read it).
GROUND_TRUTH = "ground_truth"
GROUND_TRUTH_TOPIC = NAMESPACE + "/sim/ground_truth"
# leapnbv_msgs/ScenePeople: the other people of the same frame (bystanders, passers-by).
SCENE_PEOPLE = "scene_people"
SCENE_PEOPLE_TOPIC = NAMESPACE + "/sim/people"

# Stage outputs: relative names, published inside NAMESPACE.
DETECTIONS = "detections"
HUMAN_MESH = "human_mesh"
# leapnbv_msgs/TargetTrack, one per detections frame hmr_node decides on: which person is the target and where.
TARGET_TRACK = "target_track"
TARGET_GEOMETRY = "target_geometry"
PERSON_MASK = "person_mask"
HUMAN_MESH_METRIC = "human_mesh_metric"
GROUND_PLANE = "ground_plane"
VIEW_CANDIDATES = "view_candidates"
NEXT_BEST_VIEW = "next_best_view"
BASE_GOAL = "base_goal"
GOAL_STATUS = "goal_status"  # leapnbv_msgs/GoalStatus, latched: whether next_best_view / base_goal may be acted on
MARKERS = "markers"
# nav_msgs/Path to the base goal (latched), published with it when the planner's reachability is on; not in
# OUTPUT_TOPICS (not every frame has one).
BASE_PATH = "base_path"

# leapnbv_msgs/MeshFaces, latched, once per body model (not per frame: not in OUTPUT_TOPICS): the triangles that
# the HumanMesh messages on human_mesh and human_mesh_metric name by faces_id (leapnbv_common.mesh_faces).
MESH_FACES = "mesh_faces"
MESH_FACES_TOPIC = NAMESPACE + "/" + MESH_FACES
# Outputs sent once per model, latched (a recording of the outputs keeps them: its meshes need them).
MODEL_OUTPUT_TOPICS: Dict[str, str] = {MESH_FACES_TOPIC: "leapnbv_msgs/msg/MeshFaces"}

# Every output of the graph (absolute names), with its message type.
OUTPUT_TOPICS: Dict[str, str] = {
    NAMESPACE + "/" + DETECTIONS: "leapnbv_msgs/msg/PersonDetections",
    NAMESPACE + "/" + HUMAN_MESH: "leapnbv_msgs/msg/HumanMesh",
    NAMESPACE + "/" + TARGET_GEOMETRY: "leapnbv_msgs/msg/TargetGeometry",
    NAMESPACE + "/" + PERSON_MASK: "sensor_msgs/msg/Image",
    NAMESPACE + "/" + HUMAN_MESH_METRIC: "leapnbv_msgs/msg/HumanMesh",
    NAMESPACE + "/" + GROUND_PLANE: "leapnbv_msgs/msg/GroundPlane",
    NAMESPACE + "/" + VIEW_CANDIDATES: "leapnbv_msgs/msg/ViewCandidates",
    NAMESPACE + "/" + NEXT_BEST_VIEW: "geometry_msgs/msg/PoseStamped",
    NAMESPACE + "/" + BASE_GOAL: "geometry_msgs/msg/PoseStamped",
    NAMESPACE + "/" + MARKERS: "visualization_msgs/msg/MarkerArray",
}
# The last output of each frame: a frame is done once its view candidates are out.
FINAL_OUTPUT_TOPIC = NAMESPACE + "/" + VIEW_CANDIDATES
NEXT_BEST_VIEW_TOPIC = NAMESPACE + "/" + NEXT_BEST_VIEW


def output_topic(relative: str) -> str:
    """Absolute name of a stage output."""
    return NAMESPACE + "/" + relative


def short_topic(topic: str) -> str:
    """The relative name of an absolute graph topic (``/leapnbv/ground_plane`` -> ``ground_plane``)."""
    prefix = NAMESPACE + "/"
    return topic[len(prefix):] if topic.startswith(prefix) else topic.lstrip("/")
