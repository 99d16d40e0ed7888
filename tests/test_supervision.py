"""Supervision of the graph: a killed node comes back and the graph plans again; a stalled node
leaves no stale goal; readiness means engines loaded; SIGINT/SIGTERM stop every node with exit 0.

The graph runs on ground-truth perception with the simulator as the camera (a separate process
at 5 FPS, the camera driving to each goal), so goals keep coming while nodes are killed.
"""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from typing import Dict, List, Optional, Tuple

import pytest

pytest.importorskip("rclpy")

from geometry_msgs.msg import PoseStamped  # noqa: E402
from node_harness import Probe, diag_value  # noqa: E402
from rclpy.parameter_client import AsyncParameterClient  # noqa: E402

from leapnbv_bringup.graph import NAMESPACE, node_names  # noqa: E402
from leapnbv_bringup.graph_runner import (  # noqa: E402
    RUNNER_STATUS_NAME,
    GraphRunner,
    RestartPolicy,
    perception_overrides,
)
from leapnbv_common.conversions import stamp_to_ns  # noqa: E402
from leapnbv_common.qos import latched_goal_qos  # noqa: E402
from leapnbv_common.topics import NEXT_BEST_VIEW_TOPIC  # noqa: E402
from leapnbv_stand_ins.files import ensure_stand_in_body_model  # noqa: E402

pytestmark = pytest.mark.ros

RECOVERY_LIMIT_S = 3.0  # issue 12: goals again within 3 s of a kill -9
# The graph's own frame latency counts in the 3 s. On a machine shared beyond its cores the
# steady-state latency alone can exceed 1 s (up to 3 s measured at load 8 on 2 cores); the limit
# then grows by the measured excess over this, printed with the figures.
NOMINAL_LATENCY_S = 1.0
SIM_RATE_HZ = 5.0


class Goals:
    """Every next_best_view the probe receives: (receive monotonic, receive wall ns, frame stamp ns, msg)."""

    def __init__(self, probe: Probe) -> None:
        self.items: List[Tuple[float, int, int, PoseStamped]] = []
        probe.node.create_subscription(PoseStamped, NEXT_BEST_VIEW_TOPIC, self._on_goal, latched_goal_qos())

    def _on_goal(self, msg: PoseStamped) -> None:
        self.items.append((time.monotonic(), time.time_ns(), stamp_to_ns(msg.header.stamp), msg))

    def first_from_frame_after(self, wall_ns: int) -> Optional[Tuple[float, int, int, PoseStamped]]:
        return next((g for g in self.items if g[2] > wall_ns), None)


def start_simulator(log_path: str) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "leapnbv_sim.nodes.simulator_node", "--ros-args", "-p", f"rate_hz:={SIM_RATE_HZ}",
           "-p", "scene_seed:=3", "-r", f"goal:={NEXT_BEST_VIEW_TOPIC}"]
    log = open(log_path, "w")  # noqa: SIM115 - closed by the fixture
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"))
    proc.log_handle = log
    return proc


def start_monitor(log_path: str) -> subprocess.Popen:
    """The launch file's graph monitor, as the robot runs it (here beside the runner, which reports too)."""
    cmd = [sys.executable, "-m", "leapnbv_bringup.graph_monitor", "--ros-args", "-r", f"__ns:={NAMESPACE}"]
    log = open(log_path, "w")  # noqa: SIM115 - closed by the fixture
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"))
    proc.log_handle = log
    return proc


def stop_process(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.fixture(scope="module")
def supervised_graph(tmp_path_factory):
    """(runner, probe, goals): the supervised ground-truth graph, the simulator, goals flowing."""
    logs = tmp_path_factory.mktemp("supervision")
    overrides = perception_overrides("ground_truth", body_model=ensure_stand_in_body_model("small"))
    events: List[str] = []
    runner = GraphRunner(None, overrides, log_dir=str(logs), on_event=events.append,
                         restart=RestartPolicy(max_restarts=3, window_s=120.0, spare_delay_s=2.0))
    runner.events_seen = events
    probe = sim = monitor = None
    try:
        probe = Probe("supervision_probe")
        goals = Goals(probe)
        runner.start()
        sim = start_simulator(str(logs / "simulator.log"))
        monitor = start_monitor(str(logs / "graph_monitor.log"))
        runner.wait_ready(probe.node, timeout_s=90.0, spin=lambda t: probe.executor.spin_once(timeout_sec=t))
        assert probe.spin_until(lambda: len(goals.items) >= 3, 90.0), "no goals from the graph"
        # The standby processes start spare_delay_s after readiness; let them finish importing.
        probe.spin_for(8.0)
        yield runner, probe, goals
    finally:
        for proc in (sim, monitor):
            if proc is not None:
                stop_process(proc)
                proc.log_handle.close()
        runner.stop()
        if probe is not None:
            probe.close()


def wait_serving(runner: GraphRunner, probe: Probe, name: str, timeout_s: float) -> bool:
    """Until the runner's record says `name` runs and its diagnostics (after the restart) say engine ready."""
    since = time.monotonic()
    return probe.spin_until(lambda: name not in runner.not_ready(since - 30.0) and
                            runner.health.get(name) is not None and
                            runner.health[name].received > runner._states[name].started_at, timeout_s)


@pytest.mark.slow
def test_kill_9_each_node_goals_again_within_3_s(supervised_graph):
    runner, probe, goals = supervised_graph
    runner.watch_diagnostics(probe.node)
    recovery: Dict[str, float] = {}
    first_any: Dict[str, float] = {}
    budget: Dict[str, float] = {}
    for name in node_names():
        before = sorted((g[1] - g[2]) * 1e-9 for g in goals.items[-10:])
        budget[name] = RECOVERY_LIMIT_S + max(0.0, before[len(before) // 2] - NOMINAL_LATENCY_S)
        old_pid = runner.processes[name].pid
        killed_wall_ns = time.time_ns()
        killed = time.monotonic()
        os.kill(old_pid, signal.SIGKILL)
        got = probe.spin_until(lambda after=killed_wall_ns: goals.first_from_frame_after(after) is not None, 20.0)
        assert got, f"no goal from a frame after kill -9 of {name} within 20 s; events: {runner.events_seen}"
        goal = goals.first_from_frame_after(killed_wall_ns)
        recovery[name] = goal[0] - killed
        print(f"\n[supervision] {name}: first goal {recovery[name]:.2f} s after kill -9, from a frame taken "
              f"{(goal[2] - killed_wall_ns) * 1e-9:.2f} s after it (latency {(goal[1] - goal[2]) * 1e-9:.2f} s); "
              f"latency p50 of the 10 goals before: {before[len(before) // 2]:.2f} s; limit {budget[name]:.2f} s")
        first_any[name] = next(g[0] for g in goals.items if g[0] > killed) - killed
        assert runner.processes[name].pid != old_pid
        assert wait_serving(runner, probe, name, 20.0), f"{name} not serving again: {runner.not_ready(0.0)}"
        probe.spin_for(2.0)  # the next kill finds a graph in its steady state
    print("[supervision] kill -9 -> first goal of any frame: "
          + ", ".join(f"{n} {t:.2f} s" for n, t in first_any.items()))
    assert runner.restart_counts() == {name: 1 for name in node_names()}
    # The graph monitor (the launch file's reporter) saw each node start twice, and hears all of them.
    monitor_name = f"{NAMESPACE}/graph_monitor"
    seen = probe.spin_until(lambda: probe.status_where(monitor_name, lambda s: all(
        diag_value(s, f"{n}.restarts") == "1" and diag_value(s, f"{n}.state") == "alive" for n in node_names())), 10.0)
    assert seen, probe.statuses.get(monitor_name, [None])[-1]
    assert probe.statuses[monitor_name][-1].level == probe.statuses[monitor_name][-1].WARN
    assert all("warm spare" in e for e in runner.events_seen if "restarted (" in e), runner.events_seen
    slow = {n: (round(t, 2), round(budget[n], 2)) for n, t in recovery.items() if t > budget[n]}
    assert not slow, f"goals again later than the limit after kill -9 (seconds, limit): {slow}"


def nbv_parameter(probe: Probe, name: str):
    """The nbv_node's value of parameter `name`, or None when the node does not declare it."""
    client = AsyncParameterClient(probe.node, f"{NAMESPACE}/nbv_node")
    assert client.wait_for_services(10.0), "nbv_node parameter services"
    future = client.get_parameters([name])
    assert probe.spin_until(future.done, 10.0), "get_parameters timed out"
    values = future.result().values
    from rcl_interfaces.msg import ParameterType

    if not values or values[0].type == ParameterType.PARAMETER_NOT_SET:
        return None
    return values[0].double_value


@pytest.mark.slow
def test_sigstop_each_node_for_3_s_gives_no_stale_goal(supervised_graph):
    runner, probe, goals = supervised_graph
    max_age_s = nbv_parameter(probe, "max_goal_age_s")
    if max_age_s is None:
        pytest.skip("nbv_node has no max_goal_age_s parameter in this branch (the stale-goal rule, issue 12 "
                    "deliverable 3, is written in parallel); this test runs once it is merged")
    start = len(goals.items)
    for name in node_names():
        proc = runner.processes[name]
        proc.send_signal(signal.SIGSTOP)
        try:
            probe.spin_for(3.0)
        finally:
            proc.send_signal(signal.SIGCONT)
        probe.spin_for(3.0)
        assert runner.processes[name] is proc, f"{name} was restarted although it was only stopped"
    seen = goals.items[start:]
    assert len(seen) > 10, f"only {len(seen)} goals while stopping nodes"
    # A goal is stale when its frame is older than max_goal_age_s when it reaches a subscriber.
    # An explicit "no current goal" message carries no frame: it has an empty frame_id.
    stale = [(stamp, round((received - stamp) * 1e-9, 2)) for _, received, stamp, msg in seen
             if msg.header.frame_id and (received - stamp) * 1e-9 > max_age_s]
    assert not stale, f"{len(stale)} goals older than max_goal_age_s={max_age_s}: {stale[:10]}"
    assert runner.restart_counts() == {name: runner.restart_counts()[name] for name in node_names()}


# ----------------------------------------------------------------------------- the runner's command line


def runner_cli(log_dir, *args: str) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "leapnbv_bringup.graph_runner", "--log-dir", str(log_dir), *args]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))


def read_until(proc: subprocess.Popen, pattern: str, timeout_s: float) -> Tuple[bool, str]:
    """Lines of the runner's output until one matches (or it exits, or the time is up)."""
    import selectors

    out = []
    selector = selectors.DefaultSelector()
    selector.register(proc.stdout, selectors.EVENT_READ)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if not selector.select(timeout=0.2):
            if proc.poll() is not None:
                break
            continue
        line = proc.stdout.readline()
        if not line:
            break
        out.append(line)
        if re.search(pattern, line):
            return True, "".join(out)
    return False, "".join(out)


def ground_truth_args() -> List[str]:
    return ["--perception", "ground_truth", "--body-model", ensure_stand_in_body_model("small")]


@pytest.mark.slow
@pytest.mark.parametrize("stop_signal", [signal.SIGTERM, signal.SIGINT])
def test_signal_to_runner_ends_every_node_with_exit_0_and_no_traceback(tmp_path, stop_signal):
    proc = runner_cli(tmp_path, *ground_truth_args())
    try:
        ready, out = read_until(proc, r"\[graph\] ready in", 90.0)
        assert ready, out
        if stop_signal == signal.SIGTERM:
            # The runner reports each node on /diagnostics; kill one by the pid it reports, see it come back.
            probe = Probe("runner_status_probe")
            try:
                assert probe.spin_until(lambda: probe.status_where(RUNNER_STATUS_NAME, lambda s: True), 15.0)
                status = probe.status_where(RUNNER_STATUS_NAME, lambda s: True)
                pid = int(diag_value(status, "nbv_node.pid"))
                assert diag_value(status, "nbv_node.restarts") == "0"
                assert diag_value(status, "nbv_node.state") == "running"
                os.kill(pid, signal.SIGKILL)
                back = probe.spin_until(lambda: probe.status_where(
                    RUNNER_STATUS_NAME, lambda s: diag_value(s, "nbv_node.restarts") == "1"
                    and diag_value(s, "nbv_node.state") == "running"), 20.0)
                assert back, probe.statuses.get(RUNNER_STATUS_NAME, [])[-1:]
                status = probe.status_where(RUNNER_STATUS_NAME, lambda s: diag_value(s, "nbv_node.restarts") == "1")
                assert diag_value(status, "nbv_node.last_exit") == "killed by SIGKILL"
                assert int(diag_value(status, "nbv_node.pid")) != pid
                assert status.level == status.WARN and "nbv_node restarted" in status.message
            finally:
                probe.close()
            served, more = read_until(proc, r"nbv_node serving again", 20.0)
            out += more
            assert served, out
        proc.send_signal(stop_signal)
        rest, _ = proc.communicate(timeout=40)
        out += rest
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, out
    assert f"[graph] {stop_signal.name}: stopping the nodes" in out
    stopped = re.search(r"\[graph\] stopped: (.*)", out).group(1)
    assert stopped == ", ".join(f"{n}: exit 0" for n in node_names()), out
    for log in tmp_path.glob("*.log"):
        text = log.read_text(errors="replace")
        assert "Traceback" not in text and "internal_error" not in text, f"{log.name}:\n{text[-3000:]}"


@pytest.mark.slow
def test_readiness_names_nodes_whose_engine_did_not_load(tmp_path):
    # onnxruntime with the YAML's model paths (not on this machine): both perception engines are in ERROR.
    missing = tmp_path / "no_such_model.onnx"
    proc = runner_cli(tmp_path, "--perception", "onnxruntime", "--detector-model", str(missing),
                      "--hmr-model", str(missing), "--body-model", ensure_stand_in_body_model("small"),
                      "--ready-timeout", "20")
    try:
        out, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 1, out
    assert "[graph] ready" not in out
    line = next(ln for ln in out.splitlines() if "graph not ready after 20 s" in ln)
    assert re.search(r"detector_node: engine not ready: detector model .*no_such_model\.onnx.* not loaded", line), line
    assert re.search(r"hmr_node: engine not ready: .*not loaded", line), line
    for name in ("raster_node", "ground_node", "nbv_node"):
        assert f"{name}:" not in line, line  # they are ready: only the two are named
    assert ", ".join(f"{n}: exit 0" for n in node_names()) in out


@pytest.mark.slow
def test_node_that_keeps_dying_is_reported_and_runner_exits_1(tmp_path):
    # radius is range-checked: nbv_node refuses to start with it, every time.
    proc = runner_cli(tmp_path, *ground_truth_args(), "--set", "nbv_node.radius=-1.0", "--max-restarts", "2",
                      "--restart-backoff", "0.1", "--no-warm-spares", "--ready-timeout", "120")
    try:
        out, _ = proc.communicate(timeout=150)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 1, out
    deaths = re.findall(r"nbv_node died \(exit 1\); restarting in ([0-9.]+) s", out)
    assert [float(d) for d in deaths] == [0.1, 0.2], out  # exponential back-off
    assert re.search(r"nbv_node died 3 times within 60 s \(last: exit 1\), more than --max-restarts 2; giving up",
                     out), out
    assert "radius" in (tmp_path / "nbv_node.log").read_text()


def test_restart_policy_back_off_and_limit():
    policy = RestartPolicy(max_restarts=4, window_s=10.0, backoff_s=0.5, backoff_max_s=3.0)
    assert [policy.delay_s(k) for k in range(1, 6)] == [0.5, 1.0, 2.0, 3.0, 3.0]
    assert not policy.gives_up(4) and policy.gives_up(5)
    assert policy.recent([0.0, 5.0, 9.0, 12.0], now=14.0) == 3  # the death at 0 s left the window
    assert RestartPolicy(window_s=0.0).recent([0.0, 1e6], now=2e6) == 2  # 0: the whole run
    with pytest.raises(ValueError):
        RestartPolicy(max_restarts=-1)
