"""Start the five LEAP-NBV nodes as separate processes from the one parameter file, bring them up, keep them up.

Used where `ros2 launch` is not available (the CPU machines, tests, the demo, replay): each
node runs as `python -m <module> --ros-args ...` with the namespace, the params file, the
command-line overrides and the topic remaps of `leapnbv_bringup.graph`
(leapnbv_bringup.spares.node_command).

Lifecycle: every node starts with ``autostart:=false``; the runner's lifecycle manager
(leapnbv_bringup.lifecycle_manager, on the runner's own ROS node) takes each managed node through
configure and activate over its lifecycle services, tries a failed configure again every
--configure-retry seconds, and brings a restarted node up the same way.

Readiness (leapnbv_bringup.readiness): a managed node is serving when it is active (and its
inputs have publishers); a node that is not managed yet, when its /diagnostics say engine_state
"ready". Otherwise the runner names each node that is not, and why. A node that failed (its
configure failed: a missing model; an engine that did not load) is reported, retried, and the
rest of the graph runs; --require-all makes that, and a graph not serving within
--ready-timeout, exit 1 (the library's wait_ready(require_all=True), which the regression and
the evaluation use, raises GraphError).

Supervision (the command line; a library user passes a RestartPolicy,
leapnbv_bringup.supervision): a node that dies is restarted after an exponential back-off
(0.1 s, 0.2 s, 0.4 s, ... capped at 8 s), at most --max-restarts times within --restart-window
seconds; one more death and the runner stops the graph and exits 1, naming the node. A restart
uses a standby process that has already imported the node's module and compiled its kernels
(leapnbv_bringup.spares; --no-warm-spares: a cold start), so the graph plans again within a few
seconds. The runner publishes each node's state, pid, restart count, last exit and lifecycle
state on /diagnostics (status "/leapnbv/graph_runner"; with --nodes, followed by "/" and the
nodes it runs).

Shutdown: SIGINT or SIGTERM to the runner is forwarded to every node as SIGINT; a node still
running after --stop-timeout seconds gets SIGTERM, then SIGKILL 3 s later. The runner prints
each node's exit code.

Exit codes: 0 stopped by SIGINT/SIGTERM and every node exited 0; 1 a node kept dying (or died
with restarts off), or (--require-all) a node failed or the graph was not ready in time;
2 usage; 3 stopped, but a node exited non-zero or had to be killed.

    python -m leapnbv_bringup.graph_runner --perception ground_truth --body-model models/x.npz
"""
from __future__ import annotations

import collections
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import IO, TYPE_CHECKING, Callable, Deque, Dict, List, Optional, Sequence, Tuple

from leapnbv_bringup.graph import (
    NAMESPACE,
    NodeSpec,
    default_params_file,
    fastdds_environment,
    fastdds_profile_file,
    graph_nodes,
)
from leapnbv_bringup.readiness import (
    AWAITING_PUBLISHER,
    NOT_HEARD,
    NodeHealth,
    engine_state_of,
    health_from_status,
    judge,
)
from leapnbv_bringup.runner_cli import (  # noqa: F401 - re-exported: tools import them from here
    Overrides,
    add_graph_arguments,
    add_supervision_arguments,
    merge_overrides,
    parse_set_arguments,
    perception_overrides,
    restart_policy_from_arguments,
    runner_from_arguments,
)
from leapnbv_bringup.spares import node_command, run_spare, spare_command, warm_type_support  # noqa: F401
from leapnbv_bringup.supervision import (  # noqa: F401 - re-exported
    KILL_GRACE_S,
    GraphError,
    RestartPolicy,
    describe_exit,
    die_with_parent,
)

if TYPE_CHECKING:  # imported where the manager starts (it brings lifecycle_msgs)
    from leapnbv_bringup.lifecycle_manager import LifecycleManager
from leapnbv_common.exit_codes import GraphRunnerExit

RUNNER_STATUS_NAME = f"{NAMESPACE}/graph_runner"
# The exit codes (leapnbv_common.exit_codes, the one table), under the names the tools import from here.
EXIT_OK, EXIT_GRAPH_FAILED, EXIT_USAGE, EXIT_UNCLEAN_STOP = (GraphRunnerExit.OK, GraphRunnerExit.GRAPH_FAILED,
                                                            GraphRunnerExit.USAGE, GraphRunnerExit.UNCLEAN_STOP)
CONFIGURE_RETRY_S = 2.0  # a node whose configure failed is tried again this often
__all__ = ["GraphRunner", "GraphError", "RestartPolicy", "NodeHealth", "engine_state_of", "describe_exit",
           "RUNNER_STATUS_NAME", "EXIT_OK", "EXIT_GRAPH_FAILED", "EXIT_USAGE", "EXIT_UNCLEAN_STOP", "main"]


@dataclass
class _NodeState:
    """The runner's record of one node."""

    spec: NodeSpec
    process: Optional[subprocess.Popen[bytes]] = None
    started_at: float = 0.0
    restarts: int = 0
    deaths: Deque[float] = field(default_factory=lambda: collections.deque(maxlen=1000))
    last_exit: Optional[int] = None
    restart_at: Optional[float] = None  # a restart is pending
    failed: Optional[str] = None  # gave up: why
    spare: Optional[subprocess.Popen[bytes]] = None
    spare_ready_fd: Optional[int] = None  # read end of the spare's "warmed up" pipe, until it said so
    spare_warm: bool = False
    spare_due: Optional[float] = None
    died_at: Optional[float] = None
    restarted_at: Optional[float] = None  # last restart, until it serves again


class GraphRunner:
    """Runs the graph's node processes; a context manager that always stops what it started.

    Args:
        params_file: The parameter YAML (default: the package's leapnbv.yaml).
        overrides: {node: {parameter: value}} after the YAML.
        camera_topics: Input topic remaps (keys of INPUT_TOPICS).
        log_dir: Each node's output goes to DIR/<node>.log (restarts append to it).
        env: The nodes' environment (default: this process's).
        restart: Restart dead nodes with this policy; None: a dead node is an error
            (check_alive raises), as the regression and the evaluation want.
        nodes: Run only these nodes (e.g. one host's share of the graph); default all.
        on_event: Called with one line per supervision or lifecycle event (death, restart, giving up;
            a node active, a configure that failed and why).
        configure_retry_s: Seconds between configure attempts of a managed node whose configure
            failed (0: never again).
        transition_timeout_s: Seconds a node has to answer a lifecycle transition (configure loads
            its engine).
    """

    def __init__(self, params_file: Optional[str] = None, overrides: Optional[Overrides] = None,
                 camera_topics: Optional[Dict[str, str]] = None, log_dir: Optional[str] = None,
                 env: Optional[Dict[str, str]] = None, restart: Optional[RestartPolicy] = None,
                 nodes: Optional[Sequence[str]] = None, on_event: Optional[Callable[[str], None]] = None,
                 configure_retry_s: float = CONFIGURE_RETRY_S, transition_timeout_s: float = 120.0) -> None:
        self.params_file = os.path.abspath(params_file or default_params_file())
        if not os.path.exists(self.params_file):
            raise FileNotFoundError(f"parameter file not found: {self.params_file}")
        self.overrides = overrides or {}
        all_names = [spec.name for spec in graph_nodes()]
        unknown = set(self.overrides) - set(all_names)
        if unknown:
            raise ValueError(f"overrides name unknown nodes {sorted(unknown)}")
        unknown = set(nodes or ()) - set(all_names)
        if unknown:
            raise ValueError(f"unknown nodes {sorted(unknown)}; the graph has {all_names}")
        self.nodes = [spec for spec in graph_nodes(camera_topics) if not nodes or spec.name in nodes]
        self.log_dir = log_dir
        self.env = dict(os.environ if env is None else env)
        self.env.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", fastdds_profile_file())
        for key, value in fastdds_environment(self.env["FASTRTPS_DEFAULT_PROFILES_FILE"]).items():
            self.env.setdefault(key, value)
        self.env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        self.env["PYTHONUNBUFFERED"] = "1"
        self.restart = restart
        self.on_event = on_event or (lambda line: None)
        self.processes: Dict[str, subprocess.Popen[bytes]] = {}
        self.events: List[str] = []
        self.health: Dict[str, NodeHealth] = {}
        self.stop_report: Dict[str, str] = {}
        self._states: Dict[str, _NodeState] = {spec.name: _NodeState(spec) for spec in self.nodes}
        self._logs: Dict[str, IO[str]] = {}
        self._lock = threading.RLock()
        self._stopping = threading.Event()
        self._thread_exit = threading.Event()
        self._hurry = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._failure: Optional[str] = None
        self._ready = False
        self._diag_subscription = None
        self._diag_node = None
        self.configure_retry_s = float(configure_retry_s)
        self.transition_timeout_s = float(transition_timeout_s)
        #: The lifecycle manager on the caller's ROS node (made by watch_diagnostics / wait_ready).
        self.lifecycle: Optional[LifecycleManager] = None
        names = [spec.name for spec in self.nodes]
        partial = names != all_names
        #: The runner's status name on /diagnostics (one host's share of the graph names its nodes).
        self.status_name = RUNNER_STATUS_NAME + ("/" + "+".join(names) if partial else "")
        #: The runner's own ROS node name (unique per share, when the graph is split over hosts).
        self.probe_name = "leapnbv_graph_runner" + ("_" + "_".join(names) if partial else "")

    def __enter__(self) -> GraphRunner:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------ processes

    def log_path(self, name: str) -> Optional[str]:
        return os.path.join(self.log_dir, f"{name}.log") if self.log_dir else None

    def _event(self, line: str) -> None:
        stamped = f"[graph] {line}"
        self.events.append(stamped)
        self.on_event(stamped)

    def _popen(self, name: str, cmd: List[str], stdin: Optional[int] = None,
               pass_fds: Sequence[int] = ()) -> subprocess.Popen[bytes]:
        out = self._logs.get(name)
        return subprocess.Popen(
            cmd, env=self.env, stdin=stdin, stdout=out, stderr=subprocess.STDOUT if out else None,
            start_new_session=True,  # Ctrl-C in a terminal reaches the runner, which stops them in order
            preexec_fn=die_with_parent, pass_fds=pass_fds)

    def _command(self, spec: NodeSpec) -> List[str]:
        return node_command(spec, self.params_file, self.overrides.get(spec.name, {}))

    def start(self) -> None:
        if self.log_dir:
            os.makedirs(self.log_dir, exist_ok=True)
        with self._lock:
            for spec in self.nodes:
                log = self.log_path(spec.name)
                if log is not None:
                    self._logs[spec.name] = open(log, "w")  # noqa: SIM115 - closed in stop()
                self._launch(self._states[spec.name])
        if self.restart is not None:
            # Spawned from this thread, the children's PR_SET_PDEATHSIG follows its life: it ends after stop().
            self._thread = threading.Thread(target=self._supervise, name="graph-supervisor", daemon=True)
            self._thread.start()

    def _launch(self, state: _NodeState) -> None:
        """Start a node: its warm spare if one is waiting, else a fresh process."""
        name = state.spec.name
        proc = None
        spare, state.spare = state.spare, None
        self._drop_spare_pipe(state)
        if spare is not None and spare.poll() is None and spare.stdin is not None:
            try:
                spare.stdin.write(b"go\n")
                spare.stdin.flush()
                spare.stdin.close()
                proc = spare
            except OSError:
                spare.kill()
        if proc is None:
            proc = self._popen(name, self._command(state.spec))
        state.process = proc
        state.started_at = time.monotonic()
        self.processes[name] = proc
        if self.lifecycle is not None:
            self.lifecycle.reset(self.full_name(name))  # a new process: bring it up from unconfigured
        if self.restart is not None and self.restart.warm_spares and self._ready:
            state.spare_due = time.monotonic() + self.restart.spare_delay_s

    def _start_spare(self, state: _NodeState) -> None:
        state.spare_due = None
        read_fd, write_fd = os.pipe()
        os.set_blocking(read_fd, False)
        cmd = spare_command(state.spec, self.params_file, self.overrides.get(state.spec.name, {}), write_fd)
        try:
            state.spare = self._popen(state.spec.name, cmd, stdin=subprocess.PIPE, pass_fds=(write_fd,))
        finally:
            os.close(write_fd)
        state.spare_ready_fd, state.spare_warm = read_fd, False

    @staticmethod
    def _drop_spare_pipe(state: _NodeState) -> None:
        if state.spare_ready_fd is not None:
            os.close(state.spare_ready_fd)
            state.spare_ready_fd = None
        state.spare_warm = False

    def _check_spare(self, state: _NodeState) -> None:
        """Notice a spare that finished warming up, or one that died (restarts then start cold)."""
        if state.spare is None:
            return
        if state.spare_ready_fd is not None:
            try:
                said = os.read(state.spare_ready_fd, 1)
            except BlockingIOError:
                said = None
            if said:
                state.spare_warm = True
                os.close(state.spare_ready_fd)
                state.spare_ready_fd = None
        code = state.spare.poll()
        if code is not None:
            self._event(f"standby process of {state.spec.name} exited ({describe_exit(code)}); "
                        f"its next restart starts cold")
            state.spare = None
            self._drop_spare_pipe(state)

    def spares_ready(self) -> Dict[str, bool]:
        """{node: a warmed-up standby process is waiting} (restart policy with warm_spares)."""
        with self._lock:
            return {name: state.spare is not None and state.spare_warm for name, state in self._states.items()}

    def _supervise(self) -> None:
        """The supervisor thread: restarts, spares; lives until stop() has ended every child."""
        while not self._thread_exit.is_set():
            if not self._stopping.is_set():
                with self._lock:
                    if not self._stopping.is_set():
                        for state in self._states.values():
                            self._supervise_one(state)
            self._thread_exit.wait(0.05)

    def _supervise_one(self, state: _NodeState) -> None:
        now = time.monotonic()
        name = state.spec.name
        if state.failed:
            return
        if state.restart_at is not None:
            if now >= state.restart_at:
                state.restart_at = None
                state.restarts += 1
                self._append_log(name, f"restart {state.restarts} of {name}")
                self._launch(state)
                state.restarted_at = time.monotonic()
                proc = self.processes[name]  # the one _launch started
                how = "warm spare" if isinstance(proc.args, list) and "--spare" in proc.args else "cold start"
                self._event(f"{name} restarted ({how}, pid {proc.pid}), restart {state.restarts}")
            return
        if state.spare_due is not None and now >= state.spare_due:
            self._start_spare(state)
        self._check_spare(state)
        code = state.process.poll() if state.process is not None else None
        if code is None:
            return
        state.last_exit = code
        state.died_at = now
        state.deaths.append(now)
        policy = self.restart
        if policy is None:
            return  # not supervised: check_alive reports the death
        recent = policy.recent(state.deaths, now)
        log = self.log_path(name) or "stderr"
        if policy.gives_up(recent):
            window = f"within {policy.window_s:.0f} s" if policy.window_s > 0 else "in total"
            state.failed = (f"{name} died {recent} times {window} (last: {describe_exit(code)}), more than "
                            f"--max-restarts {policy.max_restarts}; giving up; see {log}")
            self._failure = self._failure or state.failed
            self._event(state.failed)
            return
        delay = policy.delay_s(recent)
        state.restart_at = now + delay
        self._event(f"{name} died ({describe_exit(code)}); restarting in {delay:.2f} s "
                    f"({recent} of {policy.max_restarts} restarts used); see {log}")

    def _append_log(self, name: str, line: str) -> None:
        handle = self._logs.get(name)
        if handle is not None:
            handle.write(f"----- [graph] {time.strftime('%H:%M:%S')} {line} -----\n")
            handle.flush()

    def restart_counts(self) -> Dict[str, int]:
        with self._lock:
            return {name: state.restarts for name, state in self._states.items()}

    def check_alive(self) -> None:
        """Raise GraphError when a node is dead for good (restarts off, or past the limit)."""
        if self.restart is not None:
            if self._failure:
                raise GraphError(self._failure + self._log_tail(self._failure.split()[0]))
            return
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

    # ------------------------------------------------------------------ readiness and diagnostics

    def full_name(self, name: str) -> str:
        return f"{NAMESPACE}/{name}"

    def watch_diagnostics(self, probe_node) -> None:
        """Follow the nodes' /diagnostics into ``health`` and drive their lifecycles, on ``probe_node``.

        The caller spins ``probe_node``. ``lifecycle`` is a LifecycleManager whose timer runs on that
        node; it stays, also after unwatch_diagnostics, so that a restarted node is brought up.
        """
        self.manage(probe_node)
        if self._diag_subscription is not None:
            return
        from diagnostic_msgs.msg import DiagnosticArray

        names = {self.full_name(spec.name): spec.name for spec in self.nodes}

        def on_diagnostics(msg: DiagnosticArray) -> None:
            for status in msg.status:
                name = names.get(status.name)
                if name is None:
                    continue
                self.health[name] = health_from_status(status)
                self._note_serving(name)

        self._diag_node = probe_node
        self._diag_subscription = probe_node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 50)

    def unwatch_diagnostics(self) -> None:
        if self._diag_subscription is not None:
            self._diag_node.destroy_subscription(self._diag_subscription)
        self._diag_subscription = self._diag_node = None

    def manage(self, probe_node) -> None:
        """Start the lifecycle manager of the graph's nodes on ``probe_node`` (once)."""
        if self.lifecycle is not None:
            return
        from leapnbv_bringup.lifecycle_manager import LifecycleManager

        self.lifecycle = LifecycleManager(probe_node, [self.full_name(spec.name) for spec in self.nodes],
                                          configure_retry_s=self.configure_retry_s,
                                          transition_timeout_s=self.transition_timeout_s, on_event=self._event)

    def _lifecycle_of(self, name: str):
        """(the manager's record of the node or None, its phrase for the node's state)."""
        if self.lifecycle is None:
            return None, ""
        full = self.full_name(name)
        return self.lifecycle.state(full), self.lifecycle.describe(full)

    def _judge(self, name: str, since: float) -> Tuple[str, bool]:
        """(why `name` is not serving, "" when it is; whether that is a failure it may stay in)."""
        state = self._states[name]
        proc = state.process
        if state.failed:
            return state.failed, True
        if proc is None or proc.poll() is not None or state.restart_at is not None:
            return f"not running ({describe_exit(state.last_exit)}, restart pending)", False
        record, describe = self._lifecycle_of(name)
        reason, failed = judge(self.health.get(name), record, describe, max(since, state.started_at))
        if reason == NOT_HEARD:
            up = time.monotonic() - state.started_at
            reason = f"no diagnostics yet (pid {proc.pid}, up {up:.1f} s)"
        return reason, failed

    def _note_serving(self, name: str) -> None:
        with self._lock:
            state = self._states[name]
            if state.restarted_at is None or time.monotonic() <= state.restarted_at:
                return
            reason, _ = self._judge(name, state.restarted_at)
            if not reason:
                took = time.monotonic() - (state.died_at or state.restarted_at)
                state.restarted_at = None
                health = self.health.get(name)
                how = "active" if health is not None and health.lifecycle_state else "engine ready"
                self._event(f"{name} serving again ({how}), {took:.1f} s after it died")

    def not_ready(self, since: float) -> Dict[str, str]:
        """{node: why it is not serving} judged on statuses received after ``since`` (monotonic)."""
        return {name: why for name, (why, _) in self.readiness(since).items() if why}

    def failed_nodes(self, since: float = 0.0) -> Dict[str, str]:
        """{node: why} of the nodes in a failure they may stay in.

        A configure that failed, an engine not loaded: the runner reports and retries them while the
        rest of the graph runs.
        """
        return {name: why for name, (why, failed) in self.readiness(since).items() if why and failed}

    def readiness(self, since: float) -> Dict[str, Tuple[str, bool]]:
        """{node: (why it is not serving or "", whether that is a failure)} for every node."""
        with self._lock:
            judged = {spec.name: self._judge(spec.name, since) for spec in self.nodes}
            if any(failed for _, failed in judged.values()):
                # With a node in a failure (a missing model) its downstream nodes are active and wait for its
                # output: they serve as far as they can, and the graph runs without the failed node.
                judged = {name: ("", False) if why.startswith(AWAITING_PUBLISHER) else (why, failed)
                          for name, (why, failed) in judged.items()}
            for name in judged:
                if self._states[name].restarted_at is not None:
                    self._note_serving(name)
        return judged

    def wait_ready(self, probe_node, timeout_s: float = 30.0,
                   spin: Optional[Callable[[float], None]] = None, require_all: bool = True) -> float:
        """Spin `probe_node` (bringing the nodes up) until every node is serving; returns the seconds it took.

        A managed node is serving once it is active (configured: its engine loaded; activated: its
        subscriptions made) and its inputs have publishers; a node that is not managed, once it
        published on /diagnostics (its constructor finished) with engine_state "ready"
        (leapnbv_bringup.readiness). The first frame sent after this is not lost to a node still
        starting up.

        Args:
            probe_node: The caller's ROS node: the lifecycle manager's calls and the diagnostics.
            timeout_s: Seconds to wait.
            spin: ``spin(timeout_s)`` runs the probe's callbacks (default: rclpy.spin_once on the global
                executor; a caller with its own executor passes its spin_once).
            require_all: True: every node must serve (the regression, the evaluation). False: return
                as soon as every node serves or is in a failure (``failed_nodes``: a missing model),
                or at the timeout, whatever is left; the lifecycle manager keeps retrying and ``not_ready``
                stays current while the caller spins ``probe_node``.

        Raises:
            GraphError: a node died for good, or (require_all) not all were serving before the timeout
                (each node that is not is named, with the reason).
        """
        if spin is None:
            import rclpy

            def spin(timeout: float) -> None:
                rclpy.spin_once(probe_node, timeout_sec=timeout)
        owned = self._diag_subscription is None
        self.watch_diagnostics(probe_node)
        started = time.monotonic()
        waiting: Dict[str, str] = {}
        try:
            while True:
                self.check_alive()
                judged = self.readiness(started)
                waiting = {name: why for name, (why, _) in judged.items() if why}
                if not waiting:
                    break
                if not require_all and all(judged[name][1] for name in waiting):
                    break
                if time.monotonic() - started > timeout_s:
                    if not require_all:
                        break
                    reasons = "; ".join(f"{name}: {why}" for name, why in waiting.items())
                    raise GraphError(f"graph not ready after {timeout_s:.0f} s: {reasons}")
                spin(0.1)
        finally:
            if owned and not waiting:  # a node not serving yet: keep following it (not_ready stays current)
                self.unwatch_diagnostics()
        with self._lock:
            if not self._ready:
                self._ready = True
                if self.restart is not None and self.restart.warm_spares:
                    due = time.monotonic() + self.restart.spare_delay_s
                    for state in self._states.values():
                        state.spare_due = due
        return time.monotonic() - started

    def diagnostic_status(self):
        """The runner's own DiagnosticStatus: each node's process, restarts, lifecycle and whether it serves.

        Per node: state, pid, standby, restarts, last exit, up time, lifecycle state and
        ``<node>.serving`` ("yes" or why not).

        OK: all running and serving, no restart in the restart window; WARN: a node restarted in the
        window, is restarting or is coming up; ERROR: the runner gave up on a node, or a node failed
        (its configure failed: a missing model; its engine did not load) and is being retried.
        """
        from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

        now = time.monotonic()
        values: List[Tuple[str, str]] = []
        level, problems = DiagnosticStatus.OK, []
        with self._lock:
            judged = self.readiness(0.0)
            for name, state in self._states.items():
                proc = state.process
                if state.failed:
                    run_state = "failed"
                    level = DiagnosticStatus.ERROR
                    problems.append(f"{name} failed")
                elif state.restart_at is not None or proc is None or proc.poll() is not None:
                    run_state = "restarting"
                    problems.append(f"{name} restarting")
                else:
                    run_state = "running"
                recent = self.restart.recent(state.deaths, now) if self.restart else len(state.deaths)
                if recent and run_state == "running":
                    problems.append(f"{name} restarted {recent}x recently")
                why, failed = judged[name]
                record, _ = self._lifecycle_of(name)
                lifecycle = "" if record is None else ("not managed" if record.managed is False else record.state)
                if run_state == "running" and why and (failed or record is not None and record.managed):
                    problems.append(f"{name} {why}")
                    if failed:
                        level = DiagnosticStatus.ERROR
                spare = "ready" if state.spare is not None and state.spare_warm else (
                    "warming" if state.spare is not None else "none")
                values += [(f"{name}.state", run_state), (f"{name}.pid", str(proc.pid if proc else 0)),
                           (f"{name}.standby", spare),
                           (f"{name}.restarts", str(state.restarts)),
                           (f"{name}.last_exit", describe_exit(state.last_exit) if state.last_exit is not None else ""),
                           (f"{name}.up_s", f"{now - state.started_at:.1f}" if run_state == "running" else "0"),
                           (f"{name}.lifecycle", lifecycle), (f"{name}.serving", why or "yes")]
        if problems and level == DiagnosticStatus.OK:
            level = DiagnosticStatus.WARN
        limit = (f"{self.restart.max_restarts} per {self.restart.window_s:.0f} s" if self.restart else "off")
        values.append(("restart_limit", limit))
        return DiagnosticStatus(level=level, name=self.status_name, message="; ".join(problems)[:200] or "ok",
                                hardware_id=socket.gethostname(), values=[KeyValue(key=k, value=v) for k, v in values])

    # ------------------------------------------------------------------ shutdown

    def hurry(self) -> None:
        """Escalate a stop in progress at once (a second Ctrl-C)."""
        self._hurry.set()

    def _wait_all(self, procs: Dict[str, subprocess.Popen], timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not self._hurry.is_set():
            if all(p.poll() is not None for p in procs.values()):
                return
            time.sleep(0.05)

    def stop(self, timeout_s: float = 10.0) -> Dict[str, int]:
        """SIGINT every node, then SIGTERM / SIGKILL what is left; returns the exit codes.

        ``stop_report`` says for each node how it ended ("exit 0", or e.g. "exit -15 after
        SIGTERM (no exit 10 s after SIGINT)").
        """
        self._stopping.set()
        with self._lock:
            spares = [(s.spare, s.spare_warm) for s in self._states.values() if s.spare is not None]
            for state in self._states.values():
                state.spare = None
                self._drop_spare_pipe(state)
        for spare, warm in spares:  # a waiting spare exits 0 at the end of its stdin
            try:
                if spare.stdin is not None:
                    spare.stdin.close()
            except OSError:
                pass
            if not warm and spare.poll() is None:
                spare.terminate()  # still importing: SIGTERM ends it quietly (default action)
        procs = dict(self.processes)
        for proc in procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        self._wait_all(procs, timeout_s)
        escalated: Dict[str, str] = {}
        for proc in procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGUSR1)  # its threads' stacks into its log, for the report
        for sig, grace in ((signal.SIGTERM, KILL_GRACE_S), (signal.SIGKILL, KILL_GRACE_S)):
            left = {name: p for name, p in procs.items() if p.poll() is None}
            if not left:
                break
            for name, proc in left.items():
                proc.send_signal(sig)
                escalated[name] = (f"after {sig.name} (no exit {timeout_s:.0f} s after SIGINT; "
                                   f"its stacks are in its log)")
            self._wait_all(left, grace)
        for spare, _ in spares:
            try:
                spare.wait(timeout=2.0)
            except subprocess.TimeoutExpired:
                spare.kill()
                spare.wait()
        codes = {name: proc.wait() for name, proc in procs.items()}
        self.stop_report = {name: describe_exit(code) + (" " + escalated[name] if name in escalated else "")
                            for name, code in codes.items()}
        self._thread_exit.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        if self.lifecycle is not None:
            try:
                self.lifecycle.close()
            except Exception:  # noqa: BLE001 - the caller's node may be gone already
                pass
            self.lifecycle = None
        for handle in self._logs.values():
            handle.close()
        self._logs.clear()
        return codes

    @property
    def stopped_cleanly(self) -> bool:
        """Every node exited 0 on the last stop() without escalation (true when none had started)."""
        return all(report == "exit 0" for report in self.stop_report.values())



def main(argv: Optional[List[str]] = None) -> int:
    """``python -m leapnbv_bringup.graph_runner``: the command line (leapnbv_bringup.runner_cli), or a standby."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--spare"]:
        return run_spare(argv[1:])
    from leapnbv_bringup.runner_cli import main as cli_main

    return cli_main(argv)


if __name__ == "__main__":
    sys.exit(main())
