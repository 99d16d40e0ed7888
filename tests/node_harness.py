"""Shared harness for the node integration tests: node processes, a probe node, diagnostics and stamps."""
from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from typing import Callable, Dict, Iterator, List, Optional

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from std_msgs.msg import Header

from leapnbv_bringup.graph import default_params_file
from leapnbv_common.qos import stage_input_qos

NS = "/leapnbv"


# ----------------------------------------------------------------------------- node processes


def start_node(module: str, log_path: str, namespace: str = NS, params: Optional[Dict[str, str]] = None,
               remaps: Optional[Dict[str, str]] = None, env: Optional[Dict[str, str]] = None) -> subprocess.Popen:
    """Start one node process the way leapnbv_bringup.graph_runner does (params file + overrides).

    ``module`` is a module name, or the path of a script (a test's own node); ``env`` adds to the environment.
    """
    program = [module] if module.endswith(".py") else ["-m", module]
    cmd = [sys.executable, *program, "--ros-args", "-r", f"__ns:={namespace}",
           "--params-file", default_params_file()]
    for name, value in (params or {}).items():
        cmd += ["-p", f"{name}:={value}"]
    for source, target in (remaps or {}).items():
        cmd += ["-r", f"{source}:={target}"]
    log = open(log_path, "w")  # noqa: SIM115 - the process owns it until stop_node
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                            env=dict(os.environ, PYTHONUNBUFFERED="1", **(env or {})), start_new_session=True)
    proc.log_path = log_path
    proc.log_handle = log
    return proc


def stop_node(proc: subprocess.Popen) -> None:
    """SIGINT (the node's clean shutdown path), kill if it hangs, then close its log."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)
    proc.log_handle.close()


def read_log(proc: subprocess.Popen) -> str:
    """Everything the node process has written to its log so far."""
    with open(proc.log_path, errors="replace") as handle:
        return handle.read()


# ----------------------------------------------------------------------------- probe node


class Probe:
    """The test's own ROS node (own context): publishers, collecting subscriptions, /diagnostics."""

    def __init__(self, name: str) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.statuses: Dict[str, List[DiagnosticStatus]] = {}
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, stage_input_qos(100))

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            self.statuses.setdefault(status.name, []).append(status)

    def collect(self, msg_type, topic: str, qos=None) -> list:
        received: list = []
        self.node.create_subscription(msg_type, topic, received.append, qos or stage_input_qos(50))
        return received

    def spin_until(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if predicate():
                return True
            self.executor.spin_once(timeout_sec=0.05)
        return predicate()

    def spin_for(self, seconds: float) -> None:
        self.spin_until(lambda: False, seconds)

    def status_where(self, name: str, predicate: Callable[[DiagnosticStatus], bool]) -> Optional[DiagnosticStatus]:
        for status in reversed(self.statuses.get(name, [])):
            if predicate(status):
                return status
        return None

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


def diag_value(status: DiagnosticStatus, key: str, default: str = "0") -> str:
    """The value of one key of a diagnostic status (counters read as "0" until first set)."""
    return next((kv.value for kv in status.values if kv.key == key), default)


def send_until(probe: Probe, send: Callable[[], None], arrived: Callable[[], bool], timeout_s: float,
               attempts: int = 3) -> bool:
    """Send, and send the same frame again while nothing came of it.

    Camera inputs are best effort, and a large frame can be lost on a loaded machine like on a real
    camera link.
    """
    for _ in range(attempts):
        send()
        if probe.spin_until(arrived, timeout_s / attempts):
            return True
    return False


def wait_ready(probe: Probe, procs: Dict[str, subprocess.Popen], timeout_s: float = 30.0) -> None:
    """Until every node published diagnostics (it spins, so its subscriptions are live)."""
    ok = probe.spin_until(lambda: all(name in probe.statuses for name in procs)
                          or any(p.poll() is not None for p in procs.values()), timeout_s)
    for name, proc in procs.items():
        assert proc.poll() is None, f"{name} exited with {proc.returncode}:\n{read_log(proc)[-3000:]}"
    assert ok, f"nodes not ready: {sorted(set(procs) - set(probe.statuses))}"


@contextlib.contextmanager
def running_graph(probe_name: str, procs: Dict[str, subprocess.Popen]) -> Iterator[Probe]:
    """A probe node next to node processes already started.

    On leaving, the probe closes and every process stops (also when the probe itself fails to start).
    """
    try:
        probe = Probe(probe_name)
        try:
            yield probe
        finally:
            probe.close()
    finally:
        for proc in procs.values():
            stop_node(proc)


# ----------------------------------------------------------------------------- stamps


def stamp_key(header: Header) -> tuple:
    """(sec, nanosec) of a header: what pairs a node's output with the frame it came from."""
    return (header.stamp.sec, header.stamp.nanosec)


def header_factory(frame_id: str) -> Callable[..., Header]:
    """make_header(sec, nanosec=0) for one test file's camera frame (colour or depth optical frame)."""

    def make_header(sec: int, nanosec: int = 0) -> Header:
        header = Header(frame_id=frame_id)
        header.stamp.sec, header.stamp.nanosec = sec, nanosec
        return header

    return make_header


def by_stamp(messages: list, key: tuple) -> list:
    """The messages whose header has the stamp key."""
    return [m for m in messages if stamp_key(m.header) == key]


def set_parameters(probe: Probe, node: str, **values) -> list:
    """``ros2 param set`` over DDS on the node ``node`` (full name): the SetParametersResult of each value."""
    client = AsyncParameterClient(probe.node, node)
    assert client.wait_for_services(10.0), f"{node} parameter services"
    future = client.set_parameters([Parameter(name, value=value) for name, value in values.items()])
    assert probe.spin_until(future.done, 10.0), f"setting parameters of {node} timed out"
    return list(future.result().results)


# ----------------------------------------------------------------------------- whole graph, signals


def start_graph(log_dir: str, overrides: Optional[Dict[str, Dict[str, str]]] = None,
                namespace: str = NS) -> Dict[str, subprocess.Popen]:
    """The five nodes of leapnbv_bringup.graph as processes, remapped and configured as the runner does.

    Keyed by full node name; ``overrides`` maps a node's short name to parameter values.
    """
    from leapnbv_bringup.graph import graph_nodes

    procs = {}
    for spec in graph_nodes():
        procs[f"{namespace}/{spec.name}"] = start_node(
            spec.module, os.path.join(log_dir, f"{spec.name}.log"), namespace=namespace,
            params=(overrides or {}).get(spec.name), remaps=spec.remaps)
    return procs


def stop_with_signal(proc: subprocess.Popen, sig: int = signal.SIGINT, timeout_s: float = 20.0) -> Optional[int]:
    """Send one signal and wait: the exit code, or None when the process had to be killed."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)
            return None
    return proc.returncode


# ----------------------------------------------------------------------------- lifecycle (ros2 lifecycle get/set)


def lifecycle_get(probe: Probe, node: str, timeout_s: float = 10.0) -> str:
    """``ros2 lifecycle get <node>`` over DDS: the label of its state (e.g. "unconfigured")."""
    from lifecycle_msgs.srv import GetState

    return _lifecycle_call(probe, GetState, f"{node}/get_state", GetState.Request(), timeout_s,
                           query=True).current_state.label


def lifecycle_transitions(probe: Probe, node: str, timeout_s: float = 10.0) -> List[str]:
    """``ros2 lifecycle list <node>``: the labels of the transitions available in its state."""
    from lifecycle_msgs.srv import GetAvailableTransitions

    response = _lifecycle_call(probe, GetAvailableTransitions, f"{node}/get_available_transitions",
                               GetAvailableTransitions.Request(), timeout_s, query=True)
    return [t.transition.label for t in response.available_transitions]


def lifecycle_set(probe: Probe, node: str, transition: str, timeout_s: float = 60.0) -> bool:
    """``ros2 lifecycle set <node> <transition>`` (by label: configure, activate, ...): whether it succeeded."""
    from lifecycle_msgs.srv import ChangeState

    request = ChangeState.Request()
    request.transition.label = transition
    return bool(_lifecycle_call(probe, ChangeState, f"{node}/change_state", request, timeout_s).success)


def _lifecycle_call(probe: Probe, srv_type, service: str, request, timeout_s: float, query: bool = False):
    """One service call; ``query`` (a read-only service): asked again once when no answer came.

    A client whose request reader matched may still lack the server's response writer (DDS matches the two
    topics of a service one by one), and on a loaded machine the one answer is then lost; asking a state
    twice changes nothing.
    """
    client = probe.node.create_client(srv_type, service)
    try:
        assert probe.spin_until(client.service_is_ready, 10.0), f"no {service} service"
        for _ in range(2 if query else 1):
            future = client.call_async(request)
            if probe.spin_until(future.done, timeout_s):
                return future.result()
        raise AssertionError(f"{service}: no answer within {timeout_s} s"
                             + (" (asked twice)" if query else ""))
    finally:
        probe.node.destroy_client(client)


def read_log_path(path) -> str:
    """A log file's text ("" while it does not exist)."""
    try:
        with open(path, errors="replace") as handle:
            return handle.read()
    except FileNotFoundError:
        return ""
