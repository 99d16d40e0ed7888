"""The LEAP-NBV node graph: which nodes run, in which namespace, with which topic remaps.

Both the graph runner (processes, used here and in tests) and the ROS 2 launch file (the
robot) build the graph from this one list, so they cannot drift apart.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

from leapnbv_common.power_monitor import power_node_wanted
from leapnbv_common.topics import (  # noqa: F401 - re-exported for the launch file and tools
    CAMERA_POSE,
    CAMERA_TOPICS,
    FINAL_OUTPUT_TOPIC,
    GROUND_TRUTH,
    GROUND_TRUTH_TOPIC,
    INPUT_TOPICS,
    NAMESPACE,
    OBSTACLE_MAP,
    OUTPUT_TOPICS,
    ROBOT_TOPICS,
    SCENE_PEOPLE,
    SCENE_PEOPLE_TOPIC,
)


@dataclass(frozen=True)
class NodeSpec:
    """One node of the graph: the package and executable, and the remaps of its inputs.

    ``warm_up`` names functions (``module.function``) that compile what the node compiles at
    start-up; the graph runner's standby process calls them ahead, so a restart does not pay
    for them (the node calls them again, which is then instant).
    """

    name: str
    package: str
    module: str
    remaps: Dict[str, str] = field(default_factory=dict)
    warm_up: Tuple[str, ...] = ()

    @property
    def executable(self) -> str:
        return self.name


def graph_nodes(camera_topics: Optional[Dict[str, str]] = None) -> List[NodeSpec]:
    """The five nodes, inputs remapped to the topics given (keys of INPUT_TOPICS; RealSense names by default)."""
    cam = dict(INPUT_TOPICS)
    cam.update(camera_topics or {})
    gt = {GROUND_TRUTH: GROUND_TRUTH_TOPIC, SCENE_PEOPLE: SCENE_PEOPLE_TOPIC}
    return [
        NodeSpec("detector_node", "leapnbv_perception", "leapnbv_perception.nodes.detector_node",
                 {"image": cam["image"], CAMERA_POSE: cam[CAMERA_POSE], **gt}),  # poses: detect_every_n_frames
        # depth and poses: which detection is the target (its place in the fixed frame)
        NodeSpec("hmr_node", "leapnbv_perception", "leapnbv_perception.nodes.hmr_node",
                 {"image": cam["image"], "camera_info": cam["camera_info"], "depth": cam["depth"],
                  "depth/camera_info": cam["depth/camera_info"], CAMERA_POSE: cam[CAMERA_POSE], **gt}),
        NodeSpec("raster_node", "leapnbv_geometry", "leapnbv_geometry.nodes.raster_node",
                 {"depth": cam["depth"], "depth/camera_info": cam["depth/camera_info"]},
                 warm_up=("leapnbv_geometry.raster.warm_up",)),
        NodeSpec("ground_node", "leapnbv_geometry", "leapnbv_geometry.nodes.ground_node",
                 {"depth": cam["depth"], "depth/camera_info": cam["depth/camera_info"],
                  CAMERA_POSE: cam[CAMERA_POSE]}),
        NodeSpec("nbv_node", "leapnbv_planner", "leapnbv_planner.nodes.nbv_node",
                 {CAMERA_POSE: cam[CAMERA_POSE], OBSTACLE_MAP: cam[OBSTACLE_MAP]},
                 warm_up=("leapnbv_planner.scoring.warm_up_scoring",
                          "leapnbv_planner.obstacle_map.warm_up_obstacle_map")),
        # energy per frame on /diagnostics, where the board has power rails ($LEAPNBV_POWER_NODE=1/0 forces)
        *([NodeSpec("power_node", "leapnbv_bringup", "leapnbv_bringup.nodes.power_node")]
          if power_node_wanted() else []),
    ]


def node_names() -> List[str]:
    """The names of the graph's nodes, in start order."""
    return [spec.name for spec in graph_nodes()]


# The graph monitor: not a stage; it watches the stages' /diagnostics and reports each node's
# starts (restarts) and silence on /diagnostics. The launch file runs it next to the five nodes
# (the graph runner reports its own restarts, so it does not need it).
MONITOR_NODE = NodeSpec("graph_monitor", "leapnbv_bringup", "leapnbv_bringup.graph_monitor")
# The lifecycle manager: takes the graph's managed nodes through configure and activate (the launch file
# starts them with autostart:=false), retries a failed configure and brings a respawned node up again
# (leapnbv_bringup.lifecycle_manager; the graph runner runs the same manager in its own process).
MANAGER_NODE = NodeSpec("lifecycle_manager", "leapnbv_bringup", "leapnbv_bringup.lifecycle_manager")


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


def fastdds_environment(profile_file: str) -> Dict[str, str]:
    """The environment a Fast DDS profile needs: the file, and asynchronous publication if it paces writers.

    A flow controller (fastdds_two_hosts_wifi.xml paces the large stage outputs under a Wi-Fi link's rate) works
    only on writers that publish asynchronously; with rmw_fastrtps's default synchronous mode the writer that
    names one fails to be created (raster_node does not configure). Other profiles keep the default mode.
    """
    env = {"FASTRTPS_DEFAULT_PROFILES_FILE": profile_file}
    try:
        with open(profile_file, encoding="utf-8") as handle:
            paces = "<flow_controller_descriptor_list" in handle.read()
    except OSError:
        paces = False  # Fast DDS itself reports the missing profile
    if paces:
        env["RMW_FASTRTPS_PUBLICATION_MODE"] = "ASYNCHRONOUS"
    return env

