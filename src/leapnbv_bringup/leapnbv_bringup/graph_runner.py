"""Start the five LEAP-NBV nodes as separate processes from the one parameter file.

Used where `ros2 launch` is not available (the CPU machines, tests, the demo, replay): each
node runs as `python -m <module> --ros-args ...` with the namespace, the params file, the
command-line overrides and the topic remaps of `leapnbv_bringup.graph`. A readiness check
waits until every node is discovered; shutdown sends SIGINT, then escalates.

    python -m leapnbv_bringup.graph_runner --perception ground_truth --body-model models/x.npz
"""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from typing import Dict, List, Optional

from leapnbv_bringup.graph import (
    INPUT_TOPICS,
    NAMESPACE,
    NodeSpec,
    default_params_file,
    fastdds_profile_file,
    graph_nodes,
)

Overrides = Dict[str, Dict[str, str]]


def _die_with_parent() -> None:
    """In the child before exec: Linux sends it SIGTERM when the runner dies, even by SIGKILL,
    so no node outlives a crashed or killed runner (its own session hides it from Ctrl-C)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass  # not Linux/glibc: stop() still ends the nodes on a normal exit


class GraphError(RuntimeError):
    """A node of the graph failed to start or died; the message names it and its log."""


def perception_overrides(perception: Optional[str], detector_model: Optional[str] = None,
                         hmr_model: Optional[str] = None, body_model: Optional[str] = None) -> Overrides:
    """Parameter overrides that choose the perception backends and model files."""
    overrides: Overrides = {"detector_node": {}, "hmr_node": {}}
    if perception:
        overrides["detector_node"]["backend"] = perception
        overrides["hmr_node"]["backend"] = perception
    if detector_model:
        overrides["detector_node"]["model_file_path"] = os.path.abspath(detector_model)
    if hmr_model:
        overrides["hmr_node"]["model_file_path"] = os.path.abspath(hmr_model)
    if body_model:
        overrides["hmr_node"]["body_model_path"] = os.path.abspath(body_model)
    return overrides


def merge_overrides(*parts: Overrides) -> Overrides:
    merged: Overrides = {}
    for part in parts:
        for node, params in part.items():
            merged.setdefault(node, {}).update(params)
    return merged


def parse_set_arguments(items: List[str]) -> Overrides:
    """`node.param=value` strings -> {node: {param: value}}."""
    overrides: Overrides = {}
    for item in items:
        key, sep, value = item.partition("=")
        node, dot, param = key.partition(".")
        if not sep or not dot or not node or not param:
            raise ValueError(f"--set expects node.param=value, got {item!r}")
        overrides.setdefault(node, {})[param] = value
    return overrides


def node_command(spec: NodeSpec, params_file: str, overrides: Dict[str, str]) -> List[str]:
    """The command line of one node process."""
    cmd = [sys.executable, "-m", spec.module, "--ros-args", "-r", f"__ns:={NAMESPACE}",
           "--params-file", params_file]
    for name, value in overrides.items():
        cmd += ["-p", f"{name}:={value}"]
    for source, target in spec.remaps.items():
        cmd += ["-r", f"{source}:={target}"]
    return cmd


class GraphRunner:
    """Runs the graph's node processes; a context manager that always stops what it started."""

    def __init__(self, params_file: Optional[str] = None, overrides: Optional[Overrides] = None,
                 camera_topics: Optional[Dict[str, str]] = None, log_dir: Optional[str] = None,
                 env: Optional[Dict[str, str]] = None) -> None:
        self.params_file = os.path.abspath(params_file or default_params_file())
        if not os.path.exists(self.params_file):
            raise FileNotFoundError(f"parameter file not found: {self.params_file}")
        self.overrides = overrides or {}
        unknown = set(self.overrides) - {spec.name for spec in graph_nodes()}
        if unknown:
            raise ValueError(f"overrides name unknown nodes {sorted(unknown)}")
        self.nodes = graph_nodes(camera_topics)
        self.log_dir = log_dir
        self.env = dict(os.environ if env is None else env)
        self.env.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", fastdds_profile_file())
        self.env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        self.env["PYTHONUNBUFFERED"] = "1"
        self.processes: Dict[str, subprocess.Popen] = {}
        self._logs: Dict[str, object] = {}

    def __enter__(self) -> GraphRunner:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def log_path(self, name: str) -> Optional[str]:
        return os.path.join(self.log_dir, f"{name}.log") if self.log_dir else None

    def start(self) -> None:
        if self.log_dir:
            os.makedirs(self.log_dir, exist_ok=True)
        for spec in self.nodes:
            cmd = node_command(spec, self.params_file, self.overrides.get(spec.name, {}))
            out = None
            if self.log_dir:
                out = open(self.log_path(spec.name), "w")  # noqa: SIM115 - closed in stop()
                self._logs[spec.name] = out
            self.processes[spec.name] = subprocess.Popen(
                cmd, env=self.env, stdout=out, stderr=subprocess.STDOUT if out else None,
                start_new_session=True,  # Ctrl-C in a terminal reaches the runner, which stops them in order
                preexec_fn=_die_with_parent)

    def check_alive(self) -> None:
        for name, proc in self.processes.items():
            if proc.poll() is not None:
                raise GraphError(f"{name} exited with code {proc.returncode}; see {self.log_path(name) or 'stderr'}"
                                 + self._log_tail(name))

    def _log_tail(self, name: str, lines: int = 20) -> str:
        path = self.log_path(name)
        if not path or not os.path.exists(path):
            return ""
        with open(path, errors="replace") as handle:
            return "\n" + "".join(handle.readlines()[-lines:])

    def wait_ready(self, probe_node, timeout_s: float = 30.0) -> float:
        """Spin `probe_node` until every node of the graph is serving; returns the seconds it took.

        A node is serving once it published on /diagnostics: that timer runs only after the
        node's constructor finished (models loaded, kernels compiled, subscriptions made), so
        the first frame sent after this is not lost to a node still starting up.

        Raises:
            GraphError: a node died, or not all were ready before the timeout.
        """
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray

        expected = {f"{NAMESPACE}/{spec.name}" for spec in self.nodes}
        serving = set()

        def on_diagnostics(msg: DiagnosticArray) -> None:
            serving.update(status.name for status in msg.status)

        subscription = probe_node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 50)
        started = time.monotonic()
        try:
            while not expected <= serving:
                self.check_alive()
                if time.monotonic() - started > timeout_s:
                    raise GraphError(f"graph not ready after {timeout_s:.0f} s: "
                                     f"waiting for {sorted(expected - serving)}")
                rclpy.spin_once(probe_node, timeout_sec=0.1)
        finally:
            probe_node.destroy_subscription(subscription)
        return time.monotonic() - started

    def stop(self, timeout_s: float = 10.0) -> Dict[str, int]:
        """SIGINT every node, then SIGTERM / SIGKILL what is left; returns the exit codes."""
        for proc in self.processes.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + timeout_s
        for sig in (signal.SIGTERM, signal.SIGKILL):
            for proc in self.processes.values():
                try:
                    proc.wait(timeout=max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    proc.send_signal(sig)
            deadline = time.monotonic() + 3.0
        codes = {name: proc.wait() for name, proc in self.processes.items()}
        for handle in self._logs.values():
            handle.close()
        self._logs.clear()
        return codes


def add_graph_arguments(parser: argparse.ArgumentParser) -> None:
    """The command-line options every graph-starting tool shares."""
    parser.add_argument("--params", default=None, help="parameter YAML (default: leapnbv_bringup/config/leapnbv.yaml)")
    parser.add_argument("--perception", choices=["onnxruntime", "tensorrt", "ground_truth"], default=None,
                        help="backend of both perception nodes (default: as in the YAML)")
    parser.add_argument("--detector-model", default=None, help="YOLOv8 ONNX file")
    parser.add_argument("--hmr-model", default=None, help="SMPLer-X student ONNX file")
    parser.add_argument("--body-model", default=None, help="SMPL-X .npz body model")
    parser.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE",
                        help="override one parameter, e.g. --set nbv_node.weight_area=0.5 (repeatable)")
    for key, topic in INPUT_TOPICS.items():
        parser.add_argument("--" + key.replace("/", "-").replace("_", "-") + "-topic", default=topic,
                            dest="topic_" + key.replace("/", "_"), help=f"input topic for '{key}'")
    parser.add_argument("--log-dir", default=None, help="write each node's output to DIR/<node>.log")


def runner_from_arguments(args: argparse.Namespace) -> GraphRunner:
    overrides = merge_overrides(
        perception_overrides(args.perception, args.detector_model, args.hmr_model, args.body_model),
        parse_set_arguments(args.set))
    topics = {key: getattr(args, "topic_" + key.replace("/", "_")) for key in INPUT_TOPICS}
    return GraphRunner(args.params, overrides, topics, args.log_dir)


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_graph_arguments(parser)
    parser.add_argument("--ready-timeout", type=float, default=60.0)
    args = parser.parse_args(argv)

    import rclpy
    from rclpy.node import Node

    rclpy.init()
    probe = Node("leapnbv_graph_runner")
    runner = runner_from_arguments(args)
    stopping = []
    signal.signal(signal.SIGTERM, lambda *_: stopping.append(True))
    signal.signal(signal.SIGINT, signal.default_int_handler)  # also when started in the background
    try:
        runner.start()
        took = runner.wait_ready(probe, args.ready_timeout)
        print(f"[graph] ready in {took:.1f} s: {', '.join(runner.processes)} (Ctrl-C stops)", flush=True)
        while not stopping:
            runner.check_alive()
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    except GraphError as exc:
        print(f"[graph] {exc}", file=sys.stderr)
        return 1
    finally:
        codes = runner.stop()
        print(f"[graph] stopped: {codes}", flush=True)
        probe.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
