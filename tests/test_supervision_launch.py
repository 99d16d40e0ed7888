"""The robot's launch file: it compiles, and its nodes, remaps and respawn come from leapnbv_bringup.graph.

Each stage is a lifecycle node that the lifecycle manager brings up.

The `launch` / `launch_ros` packages are not on PyPI, so the launch file runs here against a
small fake of the few classes it uses, which records each Node(...)'s and LifecycleNode(...)'s
keyword arguments.
"""
from __future__ import annotations

import importlib.util
import py_compile
import sys
import types

import pytest

from leapnbv_bringup.graph import (
    MANAGER_NODE,
    MONITOR_NODE,
    NAMESPACE,
    default_params_file,
    fastdds_profile_file,
    graph_nodes,
    node_names,
)
from leapnbv_bringup.graph_runner import GraphRunner

LAUNCH_FILE = "src/leapnbv_bringup/launch/leapnbv.launch.py"


class _Recorded:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


class FakeLaunchConfiguration:
    def __init__(self, name):
        self.name = name

    def perform(self, context):
        return context.launch_configurations[self.name]


def fake_launch_modules():
    launch = types.ModuleType("launch")
    launch.LaunchDescription = type("LaunchDescription", (_Recorded,), {})
    actions = types.ModuleType("launch.actions")
    for name in ("DeclareLaunchArgument", "OpaqueFunction", "SetEnvironmentVariable"):
        setattr(actions, name, type(name, (_Recorded,), {}))
    substitutions = types.ModuleType("launch.substitutions")
    substitutions.LaunchConfiguration = FakeLaunchConfiguration
    launch_ros = types.ModuleType("launch_ros")
    ros_actions = types.ModuleType("launch_ros.actions")
    ros_actions.Node = type("Node", (_Recorded,), {})
    ros_actions.LifecycleNode = type("LifecycleNode", (_Recorded,), {})
    return {"launch": launch, "launch.actions": actions, "launch.substitutions": substitutions,
            "launch_ros": launch_ros, "launch_ros.actions": ros_actions}


@pytest.fixture
def launch_description(repo_root, monkeypatch):
    for name, module in fake_launch_modules().items():
        monkeypatch.setitem(sys.modules, name, module)
    spec = importlib.util.spec_from_file_location("leapnbv_launch_under_test", repo_root / LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.generate_launch_description()


def run_launch(description, function="_nodes", **arguments):
    """Declared defaults + `arguments`, then the OpaqueFunction `function`: the actions it returns."""
    entities = description.args[0]
    declared = {e.args[0]: e.kwargs["default_value"] for e in entities if type(e).__name__ == "DeclareLaunchArgument"}
    unknown = set(arguments) - set(declared)
    assert not unknown, f"not launch arguments: {unknown}"
    context = types.SimpleNamespace(launch_configurations={**declared, **arguments})
    opaque = [e.kwargs["function"] for e in entities if type(e).__name__ == "OpaqueFunction"]
    assert [f.__name__ for f in opaque] == ["_environment", "_nodes"]  # the environment before the nodes
    return next(f for f in opaque if f.__name__ == function)(context)


def launch_environment(description, **arguments):
    return {e.args[0]: e.args[1] for e in run_launch(description, "_environment", **arguments)}


def test_launch_file_compiles(repo_root, tmp_path):
    # cfile outside the source tree: a __pycache__ in launch/ would break setup.py's glob("launch/*").
    py_compile.compile(str(repo_root / LAUNCH_FILE), cfile=str(tmp_path / "launch.pyc"), doraise=True)


def test_launch_nodes_remaps_and_respawn_come_from_the_graph(launch_description):
    nodes = run_launch(launch_description)
    by_name = {n.kwargs["name"]: n.kwargs for n in nodes}
    kinds = {n.kwargs["name"]: type(n).__name__ for n in nodes}
    assert list(by_name) == node_names() + [MANAGER_NODE.name, MONITOR_NODE.name]
    for spec in graph_nodes():
        kwargs = by_name[spec.name]
        assert kinds[spec.name] == "LifecycleNode"
        assert (kwargs["package"], kwargs["executable"], kwargs["namespace"]) == (spec.package, spec.executable,
                                                                                  NAMESPACE)
        assert dict(kwargs["remappings"]) == spec.remaps
        # The YAML, then autostart off: the lifecycle manager takes the node through its transitions.
        assert kwargs["parameters"] == [default_params_file(), {"autostart": False}]
        assert (kwargs["respawn"], kwargs["respawn_delay"], kwargs["respawn_max_retries"]) == (True, 1.0, 5)
    manager = by_name[MANAGER_NODE.name]
    assert kinds[MANAGER_NODE.name] == "Node"
    assert (manager["package"], manager["executable"], manager["namespace"]) == ("leapnbv_bringup",
                                                                                 "lifecycle_manager", NAMESPACE)
    assert manager["parameters"] == [{"node_names": node_names(), "autostart": True}]
    monitor = by_name[MONITOR_NODE.name]
    assert (monitor["package"], monitor["executable"]) == ("leapnbv_bringup", "graph_monitor")
    assert monitor["parameters"] == [{"nodes": node_names()}]
    assert launch_environment(launch_description) == {"FASTRTPS_DEFAULT_PROFILES_FILE": fastdds_profile_file()}


def test_a_profile_that_paces_writers_publishes_asynchronously(launch_description, repo_root):
    # Fast DDS's flow controllers work only on asynchronous writers: without the mode, raster_node's
    # paced writer is not created. Other profiles keep rmw_fastrtps's default (synchronous).
    config = repo_root / "src" / "leapnbv_bringup" / "config"
    wifi = str(config / "fastdds_two_hosts_wifi.xml")
    assert launch_environment(launch_description, fastdds_profile=wifi) == {
        "FASTRTPS_DEFAULT_PROFILES_FILE": wifi, "RMW_FASTRTPS_PUBLICATION_MODE": "ASYNCHRONOUS"}
    wired = str(config / "fastdds_two_hosts.xml")
    assert launch_environment(launch_description, fastdds_profile=wired) == {"FASTRTPS_DEFAULT_PROFILES_FILE": wired}
    runner = GraphRunner(env={"FASTRTPS_DEFAULT_PROFILES_FILE": wifi})
    assert runner.env["RMW_FASTRTPS_PUBLICATION_MODE"] == "ASYNCHRONOUS"
    assert "RMW_FASTRTPS_PUBLICATION_MODE" not in GraphRunner(env={}).env


def test_launch_arguments_choose_respawn_topics_and_one_hosts_nodes(launch_description):
    nodes = run_launch(launch_description, respawn="false", respawn_delay="2.5", respawn_max_retries="-1",
                       nodes="raster_node,ground_node,nbv_node", depth_topic="/cam2/depth")
    by_name = {n.kwargs["name"]: n.kwargs for n in nodes}
    assert list(by_name) == ["raster_node", "ground_node", "nbv_node", "lifecycle_manager", "graph_monitor"]
    assert dict(by_name["raster_node"]["remappings"])["depth"] == "/cam2/depth"
    assert dict(by_name["ground_node"]["remappings"])["depth"] == "/cam2/depth"
    assert all((k["respawn"], k["respawn_delay"], k["respawn_max_retries"]) == (False, 2.5, -1)
               for k in by_name.values())
    assert by_name["graph_monitor"]["parameters"] == [{"nodes": ["raster_node", "ground_node", "nbv_node"]}]
    assert by_name["lifecycle_manager"]["parameters"] == [{"node_names": ["raster_node", "ground_node", "nbv_node"],
                                                           "autostart": True}]
    with pytest.raises(RuntimeError, match="unknown nodes"):
        run_launch(launch_description, nodes="detector_node,nbv_nod")


def test_autostart_false_leaves_the_nodes_for_ros2_lifecycle_set(launch_description):
    nodes = run_launch(launch_description, autostart="false")
    by_name = {n.kwargs["name"]: n.kwargs for n in nodes}
    assert by_name["lifecycle_manager"]["parameters"] == [{"node_names": node_names(), "autostart": False}]
    assert all(by_name[name]["parameters"][1] == {"autostart": False} for name in node_names())
