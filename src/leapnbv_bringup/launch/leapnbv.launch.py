"""ROS 2 launch file for the robot: the same five nodes, namespace, remaps and YAML as the graph runner.

    ros2 launch leapnbv_bringup leapnbv.launch.py [image_topic:=...] [depth_topic:=...]
        [camera_pose_topic:=...] [obstacle_map_topic:=...]
        [params_file:=/path/to/leapnbv.yaml]   (backends and model paths are set in the YAML)
        [autostart:=true]   (false: the nodes wait unconfigured for `ros2 lifecycle set`)
        [respawn:=true] [respawn_delay:=1.0] [respawn_max_retries:=5]
        [nodes:=detector_node,hmr_node]   (one host's share of the graph, docs/TWO_HOSTS.md)
        [monitor:=true] [fastdds_profile:=/path/to/profile.xml]

The node list comes from leapnbv_bringup.graph (shared with leapnbv_bringup.graph_runner),
so the launch file is only the launch-system wrapper around it.

Lifecycle: each stage node is a managed (lifecycle) node, started with ``autostart:=false``; the
lifecycle manager (``lifecycle_manager``, in the same namespace, parameters ``node_names`` and
``autostart`` as nav2's) takes them through configure and activate, tries a failed configure
again (a model file that appears later is loaded then; the reason is on /diagnostics,
``/leapnbv/lifecycle_manager``), and brings a respawned node up again. ``ros2 lifecycle get/set
/leapnbv/<node>`` works on every node.

Respawn: a node that dies is started again after respawn_delay seconds (launch_ros
``respawn``), at most respawn_max_retries times over the whole launch (launch counts in total
and has no back-off; -1 = without limit); after that the node stays down and the graph monitor
reports it as silent (ERROR). The graph monitor (``graph_monitor``, in the same namespace)
publishes each node's start count and whether it is heard on /diagnostics
(``/leapnbv/graph_monitor``, see leapnbv_bringup/graph_monitor.py).
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, SetEnvironmentVariable
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import LifecycleNode, Node

from leapnbv_bringup.graph import (
    INPUT_TOPICS,
    MANAGER_NODE,
    MONITOR_NODE,
    NAMESPACE,
    default_params_file,
    fastdds_environment,
    fastdds_profile_file,
    graph_nodes,
    node_names,
)

RESPAWN_DELAY_S = "1.0"
RESPAWN_MAX_RETRIES = "5"


def _arg_name(key):
    return key.replace("/", "_") + "_topic"


def _true(text):
    return text.strip().lower() in ("1", "true", "yes", "on")


def _environment(context):
    """The Fast DDS profile's environment (asynchronous publication for a profile that paces writers)."""
    profile = LaunchConfiguration("fastdds_profile").perform(context)
    return [SetEnvironmentVariable(key, value) for key, value in fastdds_environment(profile).items()]


def _nodes(context):
    """The Node actions, built once the launch arguments are known."""
    value = {name: LaunchConfiguration(name).perform(context) for name in
             ("params_file", "respawn", "respawn_delay", "respawn_max_retries", "nodes", "monitor", "autostart",
              "use_sim_time")}
    camera_topics = {k: LaunchConfiguration(_arg_name(k)).perform(context) for k in INPUT_TOPICS}
    wanted = [n.strip() for n in value["nodes"].split(",") if n.strip()]
    unknown = sorted(set(wanted) - set(node_names()))
    if unknown:
        raise RuntimeError(f"nodes:= names unknown nodes {unknown}; the graph has {node_names()}")
    respawn = dict(respawn=_true(value["respawn"]), respawn_delay=float(value["respawn_delay"]),
                   respawn_max_retries=int(value["respawn_max_retries"]))
    actions = []
    # On sim time (use_sim_time:=true) only the graph's nodes: the manager's retries and the monitor keep the wall.
    node_overrides = {"autostart": False, **({"use_sim_time": True} if _true(value["use_sim_time"]) else {})}
    for spec in graph_nodes(camera_topics):
        if spec.name not in wanted:
            continue
        # The lifecycle manager below drives the transitions: the node itself does not autostart.
        actions.append(LifecycleNode(package=spec.package, executable=spec.executable, name=spec.name,
                                     namespace=NAMESPACE, parameters=[value["params_file"], node_overrides],
                                     remappings=list(spec.remaps.items()), output="screen", **respawn))
    manager = {"node_names": wanted, "autostart": _true(value["autostart"])}
    actions.append(Node(package=MANAGER_NODE.package, executable=MANAGER_NODE.executable, name=MANAGER_NODE.name,
                        namespace=NAMESPACE, parameters=[manager], output="screen", **respawn))
    if _true(value["monitor"]):
        actions.append(Node(package=MONITOR_NODE.package, executable=MONITOR_NODE.executable, name=MONITOR_NODE.name,
                            namespace=NAMESPACE, parameters=[{"nodes": wanted}], output="screen", **respawn))
    return actions


def generate_launch_description():
    """The launch arguments, the Fast DDS profile and the nodes (built when the arguments are known)."""
    args = [
        DeclareLaunchArgument("params_file", default_value=default_params_file(), description="parameter YAML"),
        DeclareLaunchArgument("autostart", default_value="true",
                              description="configure and activate every node (false: they wait unconfigured)"),
        DeclareLaunchArgument("respawn", default_value="true", description="start a node that dies again"),
        DeclareLaunchArgument("respawn_delay", default_value=RESPAWN_DELAY_S,
                              description="seconds before a dead node is started again"),
        DeclareLaunchArgument("respawn_max_retries", default_value=RESPAWN_MAX_RETRIES,
                              description="restarts of one node over the whole launch (-1: no limit)"),
        DeclareLaunchArgument("nodes", default_value=",".join(node_names()),
                              description="the nodes this host runs (comma separated)"),
        DeclareLaunchArgument("monitor", default_value="true",
                              description="run graph_monitor: node starts and silence on /diagnostics"),
        DeclareLaunchArgument("use_sim_time", default_value="false",
                              description="the graph's nodes on simulated time (their clocks follow /clock: the "
                                          "simulator with publish_clock); the lifecycle manager and the monitor "
                                          "stay on the wall clock"),
        DeclareLaunchArgument("fastdds_profile", default_value=fastdds_profile_file(),
                              description="Fast DDS XML profile (two hosts: fastdds_two_hosts.xml; "
                                          "over Wi-Fi: fastdds_two_hosts_wifi.xml)"),
    ]
    args += [DeclareLaunchArgument(_arg_name(k), default_value=v, description=f"input topic for '{k}'")
             for k, v in INPUT_TOPICS.items()]
    return LaunchDescription(args + [OpaqueFunction(function=_environment), OpaqueFunction(function=_nodes)])
