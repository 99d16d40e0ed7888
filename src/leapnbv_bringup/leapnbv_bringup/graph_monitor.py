"""graph_monitor: reports on /diagnostics how often each node of the graph started and whether it is heard.

On the robot the launch file respawns a node that dies (launch_ros ``respawn``), which by itself
tells nobody. This node watches the graph from outside, with no change to the nodes:

* a node **start** is a new DDS writer of the node's /diagnostics (every start of a node process
  creates one; the graph API lists each writer with its node name and a unique GID), so
  ``starts`` counts the node's processes seen since the monitor started and ``restarts`` is
  ``starts - 1``;
* a node is **heard** while its /diagnostics status arrives (every node sends one a second);
  silent for ``silence_s`` means dead, stopped or hung.

It publishes one DiagnosticStatus, ``/leapnbv/graph_monitor``, once a second: OK when every node
is heard and none restarted within ``recent_s``; WARN when one restarted within ``recent_s``;
ERROR when one is silent or was never heard. Values per node: ``<node>.state`` (alive, silent,
never_seen), ``<node>.starts``, ``<node>.restarts``, ``<node>.last_start_s_ago``,
``<node>.last_heard_s_ago``. A restart of the monitor itself starts its counts again.

    ros2 run leapnbv_bringup graph_monitor   (the launch file starts it in /leapnbv)
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Dict, Iterable, List, Optional, Set, Tuple

OK, WARN, ERROR = 0, 1, 2
ALIVE, SILENT, NEVER_SEEN = "alive", "silent", "never_seen"


@dataclass
class WatchedNode:
    """What the monitor knows about one node."""

    writers: Set[bytes] = field(default_factory=set)
    last_start: Optional[float] = None
    last_heard: Optional[float] = None

    @property
    def starts(self) -> int:
        return len(self.writers)


class GraphHealth:
    """The ROS-free core: starts from writer GIDs, liveness from received statuses.

    Args:
        names: The nodes to watch (plain names, e.g. "nbv_node").
        silence_s: A node not heard for this long is silent.
        recent_s: A restart this recent makes the status WARN.
    """

    def __init__(self, names: Iterable[str], silence_s: float = 3.0, recent_s: float = 60.0) -> None:
        self.nodes: Dict[str, WatchedNode] = {name: WatchedNode() for name in names}
        self.silence_s = float(silence_s)
        self.recent_s = float(recent_s)

    def writers_seen(self, name: str, gids: Iterable[bytes], now: float) -> List[str]:
        """Record the /diagnostics writers the graph lists for `name`; returns a line per new start."""
        node = self.nodes.get(name)
        if node is None:
            return []
        lines = []
        for gid in gids:
            if gid not in node.writers:
                node.writers.add(gid)
                node.last_start = now
                if node.starts > 1:
                    lines.append(f"{name} started again: start {node.starts} ({node.starts - 1} restarts)")
        return lines

    def heard(self, name: str, now: float) -> None:
        node = self.nodes.get(name)
        if node is not None:
            node.last_heard = now
            if node.last_start is None:  # heard before the graph API listed its writer
                node.last_start = now

    def state(self, name: str, now: float) -> str:
        node = self.nodes[name]
        if node.last_heard is None:
            return NEVER_SEEN
        return ALIVE if now - node.last_heard <= self.silence_s else SILENT

    def summary(self, now: float) -> Tuple[int, str, List[Tuple[str, str]]]:
        """(level, message, key/value pairs) of the monitor's status."""
        level, problems, values = OK, [], []
        for name, node in self.nodes.items():
            state = self.state(name, now)
            restarts = max(0, node.starts - 1)
            if state != ALIVE:
                level = ERROR
                problems.append(f"{name} {state.replace('_', ' ')}")
            elif restarts and node.last_start is not None and now - node.last_start <= self.recent_s:
                level = max(level, WARN)
                problems.append(f"{name} restarted ({restarts}x)")
            values += [
                (f"{name}.state", state),
                (f"{name}.starts", str(node.starts)),
                (f"{name}.restarts", str(restarts)),
                (f"{name}.last_start_s_ago", f"{now - node.last_start:.1f}" if node.last_start is not None else ""),
                (f"{name}.last_heard_s_ago", f"{now - node.last_heard:.1f}" if node.last_heard is not None else ""),
            ]
        return level, "; ".join(problems) or "ok", values


def main(args=None) -> None:
    """The graph monitor node (``ros2 run leapnbv_bringup graph_monitor``)."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from rclpy.node import Node

    from leapnbv_bringup.graph import node_names
    from leapnbv_common.node_params import run_node

    class GraphMonitorNode(Node):
        def __init__(self) -> None:
            super().__init__("graph_monitor")
            self.declare_parameter("nodes", node_names())
            self.declare_parameter("silence_s", 3.0)
            self.declare_parameter("recent_s", 60.0)
            self.declare_parameter("period_s", 1.0)
            names = list(self.get_parameter("nodes").value)
            self.health = GraphHealth(names, self.get_parameter("silence_s").value,
                                      self.get_parameter("recent_s").value)
            namespace = self.get_namespace().rstrip("/")
            self.status_names = {f"{namespace}/{name}": name for name in names}
            self.own_name = f"{namespace}/graph_monitor"
            self.publisher = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
            self.create_subscription(DiagnosticArray, "/diagnostics", self.on_diagnostics, 50)
            self.create_timer(float(self.get_parameter("period_s").value), self.tick)

        def on_diagnostics(self, msg: DiagnosticArray) -> None:
            now = time.monotonic()
            for status in msg.status:
                name = self.status_names.get(status.name)
                if name is not None:
                    self.health.heard(name, now)

        def tick(self) -> None:
            now = time.monotonic()
            namespace = self.get_namespace()
            gids: Dict[str, List[bytes]] = {}
            for info in self.get_publishers_info_by_topic("/diagnostics"):
                if info.node_namespace == namespace:
                    gids.setdefault(info.node_name, []).append(bytes(info.endpoint_gid))
            for name, node_gids in gids.items():
                for line in self.health.writers_seen(name, node_gids, now):
                    self.get_logger().warning(line)
            level, message, values = self.health.summary(now)
            out = DiagnosticArray()
            out.header.stamp = self.get_clock().now().to_msg()
            out.status = [DiagnosticStatus(level=bytes([level]), name=self.own_name, message=message[:200],
                                           hardware_id="graph_monitor",
                                           values=[KeyValue(key=k, value=v) for k, v in values])]
            self.publisher.publish(out)

    run_node(GraphMonitorNode, args)


if __name__ == "__main__":
    main()
