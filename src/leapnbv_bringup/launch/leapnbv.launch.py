"""ROS 2 launch file for the robot: the same five nodes, namespace, remaps and YAML as the graph runner.

    ros2 launch leapnbv_bringup leapnbv.launch.py [image_topic:=...] [depth_topic:=...]
        [camera_pose_topic:=...] [obstacle_map_topic:=...]
        [params_file:=/path/to/leapnbv.yaml]   (backends and model paths are set in the YAML)

The node list comes from leapnbv_bringup.graph (shared with leapnbv_bringup.graph_runner),
so the launch file is only the launch-system wrapper around it.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, SetEnvironmentVariable
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from leapnbv_bringup.graph import INPUT_TOPICS, NAMESPACE, default_params_file, fastdds_profile_file, graph_nodes


def _arg_name(key):
    return key.replace("/", "_") + "_topic"


def generate_launch_description():
    args = [
        DeclareLaunchArgument("params_file", default_value=default_params_file(), description="parameter YAML"),
    ]
    args += [DeclareLaunchArgument(_arg_name(k), default_value=v, description=f"input topic for '{k}'")
             for k, v in INPUT_TOPICS.items()]
    camera_topics = {k: LaunchConfiguration(_arg_name(k)) for k in INPUT_TOPICS}
    nodes = []
    for spec in graph_nodes():
        remaps = [(src, camera_topics.get(src, dst)) for src, dst in spec.remaps.items()]
        nodes.append(Node(package=spec.package, executable=spec.executable, name=spec.name, namespace=NAMESPACE,
                          parameters=[LaunchConfiguration("params_file")], remappings=remaps, output="screen"))
    env = SetEnvironmentVariable("FASTRTPS_DEFAULT_PROFILES_FILE", fastdds_profile_file())
    return LaunchDescription(args + [env] + nodes)
