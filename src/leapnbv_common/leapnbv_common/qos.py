"""The QoS profiles of the graph, in one place (docs/ARCHITECTURE.md, "Topics and QoS")."""
from __future__ import annotations

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
)

from leapnbv_common.mesh_faces import KNOWN_FACES_CAPACITY


def _keep_last(depth: int, reliability: ReliabilityPolicy, durability: DurabilityPolicy) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=reliability, durability=durability)


def camera_input_qos(depth: int = 1) -> QoSProfile:
    """Sensor-data QoS for camera topics: best effort, volatile, keep the latest `depth` frames.

    Depth 1 on inference inputs means the latest frame wins and no backlog builds up.
    """
    return _keep_last(depth, ReliabilityPolicy.BEST_EFFORT, DurabilityPolicy.VOLATILE)


def stage_input_qos(depth: int = 1) -> QoSProfile:
    """Reliable input from another stage of the graph (matches stage_output_qos)."""
    return _keep_last(depth, ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE)


def stage_output_qos(depth: int = 5) -> QoSProfile:
    """Outputs of a stage: reliable, volatile."""
    return _keep_last(depth, ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE)


def latched_goal_qos() -> QoSProfile:
    """The next-best-view goal: reliable and transient-local, so a late subscriber gets the last goal."""
    return _keep_last(1, ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL)


def latched_map_qos() -> QoSProfile:
    """Maps (e.g. the obstacle map): reliable and transient-local with depth 1, so a node that
    starts late still gets the current map, and only the latest map is kept."""
    return _keep_last(1, ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL)


def latched_mesh_faces_qos() -> QoSProfile:
    """A body model's triangles (mesh_faces): reliable and transient-local, one sample per model kept, so a
    reader that starts late (or on another host) still gets the triangles its meshes name."""
    return _keep_last(KNOWN_FACES_CAPACITY, ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL)


def tf_qos(depth: int = 100) -> QoSProfile:
    """/tf as tf2_ros publishes and reads it: reliable, volatile, a deep history (many links at a high rate)."""
    return _keep_last(depth, ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE)


def tf_static_qos(depth: int = 100) -> QoSProfile:
    """/tf_static as tf2_ros reads it: reliable, transient-local (each broadcaster keeps its one latest
    message, depth 1, for subscribers that come later; a listener keeps up to ``depth`` broadcasters')."""
    return _keep_last(depth, ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL)
