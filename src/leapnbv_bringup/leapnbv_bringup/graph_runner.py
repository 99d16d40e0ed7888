"""Start the five LEAP-NBV nodes as separate processes from the one parameter file, and keep them up.

Used where `ros2 launch` is not available (the CPU machines, tests, the demo, replay): each
node runs as `python -m <module> --ros-args ...` with the namespace, the params file, the
command-line overrides and the topic remaps of `leapnbv_bringup.graph`.

Readiness: every node is up and reports its engine loaded (its /diagnostics status has
engine_state "ready"); otherwise the runner names each node that is not, and why.

Supervision (the command line; a library user passes a RestartPolicy): a node that dies is
restarted after an exponential back-off (0.1 s, 0.2 s, 0.4 s, ... capped at 8 s), at most
--max-restarts times within --restart-window seconds; one more death and the runner stops
the graph and exits 1, naming the node. A restart uses a standby process that has already
imported the node's module and compiled its kernels (--no-warm-spares: a cold start), so the
graph plans again within a few seconds. The runner publishes each node's state, pid, restart
count and last exit on /diagnostics (status "/leapnbv/graph_runner"; with --nodes, followed by
"/" and the nodes it runs).

Shutdown: SIGINT or SIGTERM to the runner is forwarded to every node as SIGINT; a node still
running after --stop-timeout seconds gets SIGTERM, then SIGKILL 3 s later. The runner prints
each node's exit code.

Exit codes: 0 stopped by SIGINT/SIGTERM and every node exited 0; 1 a node kept dying (or died
with restarts off) or the graph was not ready in time; 2 usage; 3 stopped, but a node exited
non-zero or had to be killed.

    python -m leapnbv_bringup.graph_runner --perception ground_truth --body-model models/x.npz
"""
from __future__ import annotations

import argparse
import collections
import importlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Deque, Dict, List, Optional, Sequence, Tuple

from leapnbv_bringup.graph import (
    INPUT_TOPICS,
    NAMESPACE,
    NodeSpec,
    default_params_file,
    fastdds_profile_file,
    graph_nodes,
)

Overrides = Dict[str, Dict[str, str]]
RUNNER_STATUS_NAME = f"{NAMESPACE}/graph_runner"
EXIT_OK, EXIT_GRAPH_FAILED, EXIT_USAGE, EXIT_UNCLEAN_STOP = 0, 1, 2, 3
KILL_GRACE_S = 3.0  # after SIGTERM, before SIGKILL


def _die_with_parent() -> None:
    """In the child before exec: Linux sends it SIGTERM when the runner dies, even by SIGKILL,
    so no node outlives a crashed or killed runner (its own session hides it from Ctrl-C).
    The signal follows the thread that started the child: the supervisor thread lives until
    stop() has ended every child."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass  # not Linux/glibc: stop() still ends the nodes on a normal exit


class GraphError(RuntimeError):
    """A node of the graph failed to start or died; the message names it and its log."""


def describe_exit(code: Optional[int]) -> str:
    """'exit 0', 'exit 1', 'killed by SIGKILL' for a Popen return code."""
    if code is None:
        return "running"
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit {code}"


@dataclass(frozen=True)
class RestartPolicy:
    """How the runner restarts a node that died.

    A node may be restarted ``max_restarts`` times within any ``window_s`` seconds (0: in
    total); the k-th death in the window is followed by a restart after
    ``min(backoff_s * 2**(k-1), backoff_max_s)`` seconds, and the death after the limit makes
    the runner give up. ``warm_spares`` keeps one standby process per node (module imported,
    kernels compiled) that a restart turns into the node, started ``spare_delay_s`` after the
    graph is ready or after a spare was used.
    """

    max_restarts: int = 5
    window_s: float = 60.0
    backoff_s: float = 0.1
    backoff_max_s: float = 8.0
    warm_spares: bool = True
    spare_delay_s: float = 5.0

    def __post_init__(self) -> None:
        if self.max_restarts < 0 or self.window_s < 0 or self.backoff_s < 0 or self.backoff_max_s < 0:
            raise ValueError(f"restart policy values must be >= 0: {self}")

    def recent(self, deaths: Sequence[float], now: float) -> int:
        """How many of the death times count against the limit at time ``now``."""
        if self.window_s <= 0:
            return len(deaths)
        return sum(1 for t in deaths if now - t <= self.window_s)

    def gives_up(self, recent_deaths: int) -> bool:
        return recent_deaths > self.max_restarts

    def delay_s(self, recent_deaths: int) -> float:
        """Back-off before the restart that follows the ``recent_deaths``-th death in the window."""
        return min(self.backoff_s * 2.0 ** max(0, recent_deaths - 1), self.backoff_max_s)


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


def spare_command(spec: NodeSpec, params_file: str, overrides: Dict[str, str], ready_fd: int = -1) -> List[str]:
    """The command line of a node's standby process (see run_spare)."""
    ros_args = node_command(spec, params_file, overrides)[3:]
    return [sys.executable, "-m", "leapnbv_bringup.graph_runner", "--spare", str(ready_fd), spec.module,
            *spec.warm_up, "--", *ros_args]


def warm_type_support() -> int:
    """Load the C type support of every message and service type imported so far, and of the
    parameter services every node creates: the node's constructor would otherwise load them
    (about 0.1 s on an idle core, much more under load) while the graph waits for it.
    Returns how many types were loaded."""
    import importlib

    for extra in ("rcl_interfaces.msg", "rcl_interfaces.srv", "type_description_interfaces.srv"):
        try:
            importlib.import_module(extra)
        except ImportError:
            pass
    loaded, before = 0, -1
    while loaded != before:  # loading a type can import the modules of the types it nests
        before = loaded
        for name, module in list(sys.modules.items()):
            if module is None or not (name.endswith(".msg") or name.endswith(".srv")):
                continue
            for value in list(vars(module).values()):
                metaclass = type(value) if isinstance(value, type) else None
                if metaclass is not None and hasattr(metaclass, "__import_type_support__") and \
                        getattr(metaclass, "_TYPE_SUPPORT", None) is None:
                    metaclass.__import_type_support__()
                    loaded += 1
    return loaded


def run_spare(argv: List[str]) -> int:
    """A standby node process: ``READY_FD MODULE [WARM_UP_FUNCTION ...] -- ROS_ARGS``.

    Imports the node's module and calls its warm-up functions, writes one byte to READY_FD (a
    pipe to the runner; -1: none) and then waits for one line on stdin: "go" makes it the node
    (``MODULE.main()`` with the ROS arguments, the same signal handling as ``python -m MODULE``);
    end of file or anything else exits 0.
    """
    signal.signal(signal.SIGINT, signal.SIG_DFL)  # a spare ends quietly on any signal
    separator = argv.index("--")
    ready_fd, module_name = int(argv[0]), argv[1]
    warm_ups, ros_args = argv[2:separator], argv[separator + 1:]
    module = importlib.import_module(module_name)
    for dotted in warm_ups:
        owner, _, function = dotted.rpartition(".")
        try:
            getattr(importlib.import_module(owner), function)()
        except Exception as exc:  # noqa: BLE001 - warming up is an optimisation; the node does it again
            print(f"[spare] warm-up {dotted} failed: {type(exc).__name__}: {exc}", flush=True)
    warm_type_support()
    if ready_fd >= 0:
        try:
            os.write(ready_fd, b"1")
            os.close(ready_fd)
        except OSError:
            return 0  # the runner is stopping (it closed the pipe)
    line = sys.stdin.readline()
    if line.strip() != "go":
        return 0
    devnull = os.open(os.devnull, os.O_RDONLY)
    os.dup2(devnull, 0)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    sys.argv = [getattr(module, "__file__", module_name), *ros_args]
    module.main()
    return 0


@dataclass
class NodeHealth:
    """What /diagnostics last said about one node."""

    received: float  # monotonic time of the last status
    engine_ok: bool
    reason: str


def engine_state_of(status) -> Tuple[bool, str]:
    """(engine loaded, why not) from a node's DiagnosticStatus.

    A stage reports ``engine_state`` ("ready" once its model is loaded, the load error
    otherwise); a status without that key is judged by its level (not ERROR).
    """
    from diagnostic_msgs.msg import DiagnosticStatus

    state = next((kv.value for kv in status.values if kv.key == "engine_state"), None)
    if state is not None:
        return state == "ready", f"engine not ready: {state}"
    if status.level == DiagnosticStatus.ERROR:
        return False, f"ERROR: {status.message}"
    return True, ""


@dataclass
class _NodeState:
    """The runner's record of one node."""

    spec: NodeSpec
    process: Optional[subprocess.Popen] = None
    started_at: float = 0.0
    restarts: int = 0
    deaths: Deque[float] = field(default_factory=lambda: collections.deque(maxlen=1000))
    last_exit: Optional[int] = None
    restart_at: Optional[float] = None  # a restart is pending
    failed: Optional[str] = None  # gave up: why
    spare: Optional[subprocess.Popen] = None
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
        on_event: Called with one line per supervision event (death, restart, giving up).
    """

    def __init__(self, params_file: Optional[str] = None, overrides: Optional[Overrides] = None,
                 camera_topics: Optional[Dict[str, str]] = None, log_dir: Optional[str] = None,
                 env: Optional[Dict[str, str]] = None, restart: Optional[RestartPolicy] = None,
                 nodes: Optional[Sequence[str]] = None, on_event: Optional[Callable[[str], None]] = None) -> None:
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
        self.env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        self.env["PYTHONUNBUFFERED"] = "1"
        self.restart = restart
        self.on_event = on_event or (lambda line: None)
        self.processes: Dict[str, subprocess.Popen] = {}
        self.events: List[str] = []
        self.health: Dict[str, NodeHealth] = {}
        self.stop_report: Dict[str, str] = {}
        self._states: Dict[str, _NodeState] = {spec.name: _NodeState(spec) for spec in self.nodes}
        self._logs: Dict[str, object] = {}
        self._lock = threading.RLock()
        self._stopping = threading.Event()
        self._thread_exit = threading.Event()
        self._hurry = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._failure: Optional[str] = None
        self._ready = False
        self._diag_subscription = None
        self._diag_node = None
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

    def _popen(self, name: str, cmd: List[str], stdin=None, pass_fds=()) -> subprocess.Popen:
        out = self._logs.get(name)
        return subprocess.Popen(
            cmd, env=self.env, stdin=stdin, stdout=out, stderr=subprocess.STDOUT if out else None,
            start_new_session=True,  # Ctrl-C in a terminal reaches the runner, which stops them in order
            preexec_fn=_die_with_parent, pass_fds=pass_fds)

    def _command(self, spec: NodeSpec) -> List[str]:
        return node_command(spec, self.params_file, self.overrides.get(spec.name, {}))

    def start(self) -> None:
        if self.log_dir:
            os.makedirs(self.log_dir, exist_ok=True)
        with self._lock:
            for spec in self.nodes:
                if self.log_dir:
                    self._logs[spec.name] = open(self.log_path(spec.name), "w")  # noqa: SIM115 - closed in stop()
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
        if spare is not None and spare.poll() is None:
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
                how = "warm spare" if state.process.args and "--spare" in state.process.args else "cold start"
                self._event(f"{name} restarted ({how}, pid {state.process.pid}), restart {state.restarts}")
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
        recent = self.restart.recent(state.deaths, now)
        log = self.log_path(name) or "stderr"
        if self.restart.gives_up(recent):
            window = f"within {self.restart.window_s:.0f} s" if self.restart.window_s > 0 else "in total"
            state.failed = (f"{name} died {recent} times {window} (last: {describe_exit(code)}), more than "
                            f"--max-restarts {self.restart.max_restarts}; giving up; see {log}")
            self._failure = self._failure or state.failed
            self._event(state.failed)
            return
        delay = self.restart.delay_s(recent)
        state.restart_at = now + delay
        self._event(f"{name} died ({describe_exit(code)}); restarting in {delay:.2f} s "
                    f"({recent} of {self.restart.max_restarts} restarts used); see {log}")

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

    def watch_diagnostics(self, probe_node) -> None:
        """Follow the nodes' /diagnostics on ``probe_node`` (which the caller spins) into ``health``."""
        if self._diag_subscription is not None:
            return
        from diagnostic_msgs.msg import DiagnosticArray

        names = {f"{NAMESPACE}/{spec.name}": spec.name for spec in self.nodes}

        def on_diagnostics(msg: DiagnosticArray) -> None:
            for status in msg.status:
                name = names.get(status.name)
                if name is None:
                    continue
                ok, reason = engine_state_of(status)
                self.health[name] = NodeHealth(time.monotonic(), ok, reason)
                self._note_serving(name, ok)

        self._diag_node = probe_node
        self._diag_subscription = probe_node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 50)

    def unwatch_diagnostics(self) -> None:
        if self._diag_subscription is not None:
            self._diag_node.destroy_subscription(self._diag_subscription)
        self._diag_subscription = self._diag_node = None

    def _note_serving(self, name: str, ok: bool) -> None:
        with self._lock:
            state = self._states[name]
            if ok and state.restarted_at is not None and time.monotonic() > state.restarted_at:
                took = time.monotonic() - (state.died_at or state.restarted_at)
                state.restarted_at = None
                self._event(f"{name} serving again (engine ready), {took:.1f} s after it died")

    def not_ready(self, since: float) -> Dict[str, str]:
        """{node: why it is not ready} judged on statuses received after ``since`` (monotonic)."""
        waiting = {}
        with self._lock:
            for spec in self.nodes:
                state = self._states[spec.name]
                health = self.health.get(spec.name)
                proc = state.process
                if state.failed:
                    waiting[spec.name] = state.failed
                elif proc is None or proc.poll() is not None or state.restart_at is not None:
                    waiting[spec.name] = f"not running ({describe_exit(state.last_exit)}, restart pending)"
                elif health is None or health.received < max(since, state.started_at):
                    up = time.monotonic() - state.started_at
                    waiting[spec.name] = f"no diagnostics yet (pid {proc.pid}, up {up:.1f} s)"
                elif not health.engine_ok:
                    waiting[spec.name] = health.reason
        return waiting

    def wait_ready(self, probe_node, timeout_s: float = 30.0,
                   spin: Optional[Callable[[float], None]] = None) -> float:
        """Spin `probe_node` until every node is serving with its engine loaded; returns the seconds it took.

        A node is serving once it published on /diagnostics: that timer runs only after the
        node's constructor finished (models loaded, kernels compiled, subscriptions made), so
        the first frame sent after this is not lost to a node still starting up. Its engine is
        loaded when its status says engine_state "ready" (a perception node whose model failed
        to load keeps running and says why).

        ``spin(timeout_s)`` runs the probe's callbacks (default: rclpy.spin_once on the global
        executor; a caller with its own executor passes its spin_once).

        Raises:
            GraphError: a node died, or not all were ready before the timeout (each node that
                is not is named, with the reason).
        """
        if spin is None:
            import rclpy

            def spin(timeout: float) -> None:
                rclpy.spin_once(probe_node, timeout_sec=timeout)
        owned = self._diag_subscription is None
        self.watch_diagnostics(probe_node)
        started = time.monotonic()
        try:
            while True:
                self.check_alive()
                waiting = self.not_ready(started)
                if not waiting:
                    break
                if time.monotonic() - started > timeout_s:
                    reasons = "; ".join(f"{name}: {why}" for name, why in waiting.items())
                    raise GraphError(f"graph not ready after {timeout_s:.0f} s: {reasons}")
                spin(0.1)
        finally:
            if owned:
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
        """The runner's own DiagnosticStatus: each node's state, pid, restarts and last exit.

        OK: all running, no restart in the restart window; WARN: a node restarted in the window or
        is restarting; ERROR: the runner gave up on a node.
        """
        from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

        now = time.monotonic()
        values: List[Tuple[str, str]] = []
        level, problems = DiagnosticStatus.OK, []
        with self._lock:
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
                spare = "ready" if state.spare is not None and state.spare_warm else (
                    "warming" if state.spare is not None else "none")
                values += [(f"{name}.state", run_state), (f"{name}.pid", str(proc.pid if proc else 0)),
                           (f"{name}.standby", spare),
                           (f"{name}.restarts", str(state.restarts)),
                           (f"{name}.last_exit", describe_exit(state.last_exit) if state.last_exit is not None else ""),
                           (f"{name}.up_s", f"{now - state.started_at:.1f}" if run_state == "running" else "0")]
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
                spare.stdin.close()
            except OSError:
                pass
            if not warm and spare.poll() is None:
                spare.terminate()  # still importing: SIGTERM ends it quietly (default action)
        spares = [spare for spare, _ in spares]
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
        for spare in spares:
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
        for handle in self._logs.values():
            handle.close()
        self._logs.clear()
        return codes

    @property
    def stopped_cleanly(self) -> bool:
        """Every node exited 0 on the last stop() without escalation (true when none had started)."""
        return all(report == "exit 0" for report in self.stop_report.values())


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
                        help="seconds for every node to be up with its engine loaded (default %(default)s)")
    parser.add_argument("--stop-timeout", type=float, default=10.0,
                        help="seconds a node has to exit after SIGINT before SIGTERM, then SIGKILL "
                             "(default %(default)s)")


def restart_policy_from_arguments(args: argparse.Namespace) -> Optional[RestartPolicy]:
    if not getattr(args, "restart", False):
        return None
    return RestartPolicy(max_restarts=args.max_restarts, window_s=args.restart_window,
                         backoff_s=args.restart_backoff, backoff_max_s=args.restart_backoff_max,
                         warm_spares=args.warm_spares)


def runner_from_arguments(args: argparse.Namespace, **kwargs) -> GraphRunner:
    overrides = merge_overrides(
        perception_overrides(args.perception, args.detector_model, args.hmr_model, args.body_model),
        parse_set_arguments(args.set))
    topics = {key: getattr(args, "topic_" + key.replace("/", "_")) for key in INPUT_TOPICS}
    return GraphRunner(args.params, overrides, topics, args.log_dir, **kwargs)


class _StopSignal(Exception):
    """SIGINT or SIGTERM reached the runner."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def main(argv: Optional[List[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--spare"]:
        return run_spare(argv[1:])
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_graph_arguments(parser)
    add_supervision_arguments(parser)
    args = parser.parse_args(argv)
    try:
        runner = runner_from_arguments(
            args, restart=restart_policy_from_arguments(args),
            nodes=[n for n in args.nodes.split(",") if n] if args.nodes else None,
            on_event=lambda line: print(line, flush=True))
        policy_error = None
    except (ValueError, FileNotFoundError) as exc:
        policy_error = exc
    if policy_error is not None:
        print(f"[graph] {policy_error}", file=sys.stderr)
        return EXIT_USAGE

    def on_signal(signum, _frame) -> None:
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
        runner.start()
        took = runner.wait_ready(probe, args.ready_timeout)
        print(f"[graph] ready in {took:.1f} s: {', '.join(runner.processes)} up, engines loaded "
              f"(restarts: {'off' if runner.restart is None else runner.restart.max_restarts}; Ctrl-C stops)",
              flush=True)
        runner.watch_diagnostics(probe)
        next_publish = 0.0
        while True:
            runner.check_alive()
            rclpy.spin_once(probe, timeout_sec=0.1)
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


if __name__ == "__main__":
    sys.exit(main())
