"""The graph runner's command line, and the options every graph-starting tool shares (replay, regression, demo).

    python -m leapnbv_bringup.graph_runner --perception ground_truth --body-model models/x.npz

See leapnbv_bringup.graph_runner for what the runner does; main() here is its command line.
"""
from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from typing import Dict, List, Optional

from leapnbv_bringup.graph import INPUT_TOPICS, node_names
from leapnbv_bringup.supervision import RestartPolicy

Overrides = Dict[str, Dict[str, str]]


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


def sim_time_overrides(nodes: List[str]) -> Overrides:
    """Every node on simulated time: ``use_sim_time`` (rclpy's own parameter: the node clock follows /clock)."""
    return {name: {"use_sim_time": "true"} for name in nodes}


def merge_overrides(*parts: Overrides) -> Overrides:
    """One {node: {parameter: value}} from several, the later ones winning."""
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
    parser.add_argument("--use-sim-time", action="store_true",
                        help="every node on simulated time (use_sim_time: its clock follows /clock, e.g. the "
                        "simulator's with publish_clock)")


def add_supervision_arguments(parser: argparse.ArgumentParser) -> None:
    """The runner's own options: which nodes, restarts, readiness and shutdown."""
    defaults = RestartPolicy()
    parser.add_argument("--nodes", default=None, metavar="NODE[,NODE...]",
                        help="run only these nodes (one host's share of the graph, docs/TWO_HOSTS.md)")
    parser.add_argument("--no-restart", dest="restart", action="store_false",
                        help="a node that dies stops the graph (exit 1) instead of being restarted")
    parser.add_argument("--max-restarts", type=int, default=defaults.max_restarts,
                        help="restarts of one node allowed within --restart-window; one more death exits 1 "
                             "(default %(default)s)")
    parser.add_argument("--restart-window", type=float, default=defaults.window_s,
                        help="seconds over which --max-restarts counts; 0 = the whole run (default %(default)s)")
    parser.add_argument("--restart-backoff", type=float, default=defaults.backoff_s,
                        help="seconds before the first restart, doubled for each further death in the window "
                             "(default %(default)s)")
    parser.add_argument("--restart-backoff-max", type=float, default=defaults.backoff_max_s,
                        help="cap of the back-off, seconds (default %(default)s)")
    parser.add_argument("--no-warm-spares", dest="warm_spares", action="store_false",
                        help="restart with a cold process instead of a standby that has the node's module "
                             "imported (saves one idle process per node; a restart takes seconds longer)")
    parser.add_argument("--ready-timeout", type=float, default=60.0,
                        help="seconds for every node to be serving (managed nodes active; default %(default)s)")
    parser.add_argument("--require-all", action="store_true",
                        help="exit 1 when a node failed (its configure failed: a missing model) or the graph "
                             "is not serving within --ready-timeout, instead of running without that node "
                             "and retrying it (what the regression and the evaluation need)")
    parser.add_argument("--configure-retry", type=float, default=2.0,
                        help="seconds between configure attempts of a node whose configure failed; 0 = never "
                             "again (default %(default)s)")
    parser.add_argument("--stop-timeout", type=float, default=10.0,
                        help="seconds a node has to exit after SIGINT before SIGTERM, then SIGKILL "
                             "(default %(default)s)")


def restart_policy_from_arguments(args: argparse.Namespace) -> Optional[RestartPolicy]:
    """The RestartPolicy of the supervision options (None: --no-restart)."""
    if not getattr(args, "restart", False):
        return None
    return RestartPolicy(max_restarts=args.max_restarts, window_s=args.restart_window,
                         backoff_s=args.restart_backoff, backoff_max_s=args.restart_backoff_max,
                         warm_spares=args.warm_spares)


def runner_from_arguments(args: argparse.Namespace, **kwargs):
    """The GraphRunner that the shared graph arguments describe (``kwargs``: more GraphRunner arguments)."""
    from leapnbv_bringup.graph_runner import GraphRunner

    sim_time = sim_time_overrides(node_names()) if getattr(args, "use_sim_time", False) else {}
    overrides = merge_overrides(
        sim_time, perception_overrides(args.perception, args.detector_model, args.hmr_model, args.body_model),
        parse_set_arguments(args.set))
    topics = {key: getattr(args, "topic_" + key.replace("/", "_")) for key in INPUT_TOPICS}
    return GraphRunner(args.params, overrides, topics, args.log_dir, **kwargs)


class _StopSignal(Exception):  # noqa: N818 - a request to stop, not an error
    """SIGINT or SIGTERM reached the runner."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def main(argv: Optional[List[str]] = None) -> int:
    """The graph runner's command line (see leapnbv_bringup.graph_runner); returns the exit code."""
    from leapnbv_bringup.graph_runner import (
        EXIT_GRAPH_FAILED,
        EXIT_OK,
        EXIT_UNCLEAN_STOP,
        EXIT_USAGE,
        GraphError,
    )
    from leapnbv_bringup.graph_runner import __doc__ as runner_doc

    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="python -m leapnbv_bringup.graph_runner", description=runner_doc,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_graph_arguments(parser)
    add_supervision_arguments(parser)
    args = parser.parse_args(argv)
    try:
        runner = runner_from_arguments(
            args, restart=restart_policy_from_arguments(args),
            nodes=[n for n in args.nodes.split(",") if n] if args.nodes else None,
            on_event=lambda line: print(line, flush=True), configure_retry_s=args.configure_retry)
        policy_error = None
    except (ValueError, FileNotFoundError) as exc:
        policy_error = exc
    if policy_error is not None:
        print(f"[graph] {policy_error}", file=sys.stderr)
        return EXIT_USAGE

    stop_requests: List[int] = []

    def on_signal(signum, _frame) -> None:
        stop_requests.append(signum)
        raise _StopSignal(signum)

    def on_signal_while_stopping(signum, _frame) -> None:
        print(f"[graph] {signal.Signals(signum).name} again: escalating now", flush=True)
        runner.hurry()

    # The runner handles its signals itself (rclpy's handlers would shut its context down first).
    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)  # also when started in the background
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions

    result = EXIT_OK
    probe = None
    try:
        rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        probe = Node(runner.probe_name)
        diagnostics = probe.create_publisher(DiagnosticArray, "/diagnostics", 10)
        started = time.monotonic()
        runner.start()
        took = runner.wait_ready(probe, args.ready_timeout, require_all=args.require_all)
        restarts = "off" if runner.restart is None else runner.restart.max_restarts
        down = runner.not_ready(started)
        if not down:
            print(f"[graph] ready in {took:.1f} s: {', '.join(runner.processes)} serving "
                  f"(restarts: {restarts}; Ctrl-C stops)", flush=True)
        else:
            retry = (f"a failed configure is tried again every {args.configure_retry:g} s"
                     if args.configure_retry > 0 else "no configure retries")
            print(f"[graph] running without {', '.join(down)} after {took:.1f} s: "
                  + "; ".join(f"{name}: {why}" for name, why in down.items())
                  + f" (the other nodes serve; {retry}; --require-all exits instead)", flush=True)
        runner.watch_diagnostics(probe)
        next_publish = next_check = 0.0
        while True:
            runner.check_alive()
            rclpy.spin_once(probe, timeout_sec=0.1)
            if down and time.monotonic() >= next_check:
                down = runner.not_ready(started)
                next_check = time.monotonic() + 0.5
                if not down:
                    print(f"[graph] ready in {time.monotonic() - started:.1f} s: every node serving now "
                          f"(restarts: {restarts}; Ctrl-C stops)", flush=True)
            if time.monotonic() >= next_publish:
                msg = DiagnosticArray()
                msg.header.stamp = probe.get_clock().now().to_msg()
                msg.status = [runner.diagnostic_status()]
                diagnostics.publish(msg)
                next_publish = time.monotonic() + 1.0
    except _StopSignal as stop:
        print(f"[graph] {stop}: stopping the nodes", flush=True)
    except GraphError as exc:
        print(f"[graph] {exc}", file=sys.stderr, flush=True)
        result = EXIT_GRAPH_FAILED
    except Exception:
        # A signal that lands while rclpy converts a message comes out of the C++ binding as
        # its own RuntimeError (the _StopSignal is its cause): still a requested stop.
        if not stop_requests:
            raise
        print(f"[graph] {_StopSignal(stop_requests[0])}: stopping the nodes", flush=True)
    finally:
        signal.signal(signal.SIGTERM, on_signal_while_stopping)
        signal.signal(signal.SIGINT, on_signal_while_stopping)
        runner.stop(args.stop_timeout)
        report = ", ".join(f"{name}: {how}" for name, how in runner.stop_report.items())
        print(f"[graph] stopped: {report}", flush=True)
        if result == EXIT_OK and not runner.stopped_cleanly:
            result = EXIT_UNCLEAN_STOP
        if probe is not None:
            probe.destroy_node()
        rclpy.try_shutdown()
    return result

