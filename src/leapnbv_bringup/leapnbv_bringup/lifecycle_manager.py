"""Bring managed nodes up through their lifecycle over the lifecycle_msgs services, and say where each is.

:class:`LifecycleManager` drives a list of nodes (full names, e.g. ``/leapnbv/hmr_node``) to active:
``get_state``, then ``change_state`` configure, then activate, each call with a timeout, every node
on its own (one that stays unconfigured does not hold the others back). A configure that fails is
tried again every ``configure_retry_s`` (a model file that appears later is loaded then); the reason
comes from the node's ``lifecycle_reason`` on /diagnostics (the ChangeState answer has none). A node
seen with a new process (``process`` on /diagnostics: a restart) or told to by :meth:`reset` is asked
for its state again and brought up again. A node that answers no ``get_state`` but publishes
/diagnostics without ``lifecycle_state`` is not a managed node (``managed`` False): the manager leaves
it alone and the caller judges it otherwise.

It runs on any rclpy node that someone spins: the graph runner's probe node (in-process) or its own
node, which the launch file starts (``node_names`` and ``autostart`` parameters, as nav2's
lifecycle_manager)::

    ros2 run leapnbv_bringup lifecycle_manager --ros-args -p node_names:=[detector_node,hmr_node]

The node publishes ``/leapnbv/lifecycle_manager`` on /diagnostics once a second: each node's state and
reason (``<node>.state``, ``<node>.reason``, ``<node>.configure_attempts``); OK when all are active,
WARN while one comes up, ERROR when one failed a transition.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Sequence, Set, Tuple

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.client import Client
from rclpy.task import Future

from leapnbv_common.managed_node import ACTIVE, FINALIZED, INACTIVE, STATE_LABELS, UNCONFIGURED

UNKNOWN = "unknown"
#: Transition -> (its id, the state it ends in when it succeeds).
TRANSITIONS: Dict[str, Tuple[int, str]] = {
    "configure": (Transition.TRANSITION_CONFIGURE, INACTIVE),
    "activate": (Transition.TRANSITION_ACTIVATE, ACTIVE),
    "deactivate": (Transition.TRANSITION_DEACTIVATE, INACTIVE),
    "cleanup": (Transition.TRANSITION_CLEANUP, UNCONFIGURED),
    "shutdown": (Transition.TRANSITION_UNCONFIGURED_SHUTDOWN, FINALIZED),  # the id follows the state
}
_SHUTDOWN_FROM = {UNCONFIGURED: Transition.TRANSITION_UNCONFIGURED_SHUTDOWN,
                  INACTIVE: Transition.TRANSITION_INACTIVE_SHUTDOWN, ACTIVE: Transition.TRANSITION_ACTIVE_SHUTDOWN}
REASON_WAIT_S = 2.0  # after a failed transition, how long the reason may take to come on /diagnostics
_DOING = {"configure": "configuring", "activate": "activating", "deactivate": "deactivating",
          "cleanup": "cleaning up", "shutdown": "shutting down"}


@dataclass
class NodeLifecycle:
    """What the manager knows of one node."""

    name: str
    state: str = UNKNOWN  # a lifecycle label, or "unknown" until get_state answers
    managed: Optional[bool] = None  # True: it has the lifecycle services; False: a plain node; None: not known yet
    reason: str = ""  # why the last transition failed or why the node is not managed yet ("" when none)
    failed: bool = False  # the last transition failed (the reason says how); cleared by a success
    reason_pending: bool = False  # failed, and its reason is still on its way on /diagnostics
    configure_attempts: int = 0
    since: float = 0.0  # monotonic: the manager (re)started on this node
    heard: float = -1.0  # monotonic: its last /diagnostics status
    diag_state: Optional[str] = None  # lifecycle_state of that status (None: the status had none)
    diag_reason: str = ""
    process: str = ""
    state_since: float = 0.0  # monotonic: when `state` last changed
    reported: str = ""  # the last failure reason said as an event (a retry failing the same way is not said again)
    retired: Set[str] = field(default_factory=set)  # processes replaced by a newer one: their statuses are ignored


@dataclass
class _Call:
    what: str  # "get_state" or a transition name
    future: Future
    client: Client
    sent: float
    deadline: float


class LifecycleManager:
    """Drives nodes to active over their lifecycle services (see the module docstring).

    Args:
        node: The rclpy node that makes the calls; the caller spins it (a timer steps the manager).
        names: Full node names (``/namespace/name``).
        autostart: Bring every node up (configure + activate); False: only follow their states.
        configure_retry_s: Seconds between configure attempts of a node that failed one (0: never again).
        call_timeout_s: Seconds for a get_state answer.
        transition_timeout_s: Seconds for a change_state answer (configure loads engines).
        period_s: How often the manager looks at its nodes.
        on_event: Called with one line per event (a node active, a failure with its reason, a retry).
    """

    def __init__(self, node, names: Sequence[str], *, autostart: bool = True, configure_retry_s: float = 2.0,
                 call_timeout_s: float = 1.0, transition_timeout_s: float = 120.0, period_s: float = 0.1,
                 on_event: Optional[Callable[[str], None]] = None) -> None:
        self.node = node
        self.autostart = autostart
        self.configure_retry_s = float(configure_retry_s)
        self.call_timeout_s = float(call_timeout_s)
        self.transition_timeout_s = float(transition_timeout_s)
        self.on_event = on_event or (lambda line: None)
        now = time.monotonic()
        self.nodes: Dict[str, NodeLifecycle] = {name: NodeLifecycle(name, since=now, state_since=now)
                                                for name in names}
        self._clients = {name: (node.create_client(GetState, f"{name}/get_state"),
                                node.create_client(ChangeState, f"{name}/change_state")) for name in names}
        self._calls: Dict[str, _Call] = {}
        self._configure_at: Dict[str, float] = {}
        self._goal: Dict[str, Optional[str]] = {name: ACTIVE if autostart else None for name in names}
        self._failure_report: Dict[str, Tuple[str, float]] = {}  # name -> (transition, failed at): reason pending
        self._resets: List[str] = []
        self._verify: Set[str] = set()  # nodes whose state to read again (after a failed transition)
        self._reset_lock = threading.Lock()
        self._subscription = node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 50)
        self._timer = node.create_timer(period_s, self.step)

    # ------------------------------------------------------------------ what callers use

    def state(self, name: str) -> NodeLifecycle:
        return self.nodes[name]

    def reset(self, name: str) -> None:
        """A new process of ``name`` started (thread-safe): forget its state, bring it up again."""
        with self._reset_lock:
            self._resets.append(name)

    def request(self, name: str, transition: str) -> None:
        """Ask for one transition now (``ros2 lifecycle set``); autostart then stops driving that node."""
        if transition not in TRANSITIONS:
            raise ValueError(f"unknown transition {transition!r}; one of {sorted(TRANSITIONS)}")
        self._goal[name] = None
        self._send_transition(self.nodes[name], transition, time.monotonic())

    def all_active(self) -> bool:
        return all(n.state == ACTIVE for n in self.nodes.values() if n.managed is not False)

    def close(self) -> None:
        """Destroy the manager's timer, subscription and clients on its node."""
        self.node.destroy_timer(self._timer)
        self.node.destroy_subscription(self._subscription)
        for get_client, change_client in self._clients.values():
            self.node.destroy_client(get_client)
            self.node.destroy_client(change_client)
        self._calls.clear()

    # ------------------------------------------------------------------ the loop

    def step(self) -> None:
        now = time.monotonic()
        self._take_resets(now)
        for record in self.nodes.values():
            self._step_one(record, now)

    def _take_resets(self, now: float) -> None:
        with self._reset_lock:
            resets, self._resets = self._resets, []
        for name in resets:
            self._forget(self.nodes[name], now)

    def _forget(self, record: NodeLifecycle, now: float) -> None:
        self._calls.pop(record.name, None)  # an answer from the old process no longer counts
        self._failure_report.pop(record.name, None)
        record.since, record.managed, record.failed, record.reason = now, None, False, ""
        if record.process:
            record.retired.add(record.process)
        record.process = ""
        record.reason_pending = False
        record.diag_state = None
        self._set_state(record, UNKNOWN, now)
        self._configure_at[record.name] = now
        if self.autostart:
            self._goal[record.name] = ACTIVE

    def _step_one(self, record: NodeLifecycle, now: float) -> None:
        self._report_failure(record, now)
        call = self._calls.get(record.name)
        if call is not None:
            if call.future.done():
                del self._calls[record.name]
                self._answered(record, call, now)
            elif now > call.deadline:
                del self._calls[record.name]
                call.client.remove_pending_request(call.future)
                self._timed_out(record, call, now)
            return
        get_client, _ = self._clients[record.name]
        if record.managed is None:
            if get_client.service_is_ready():
                record.managed = True
            elif record.heard > record.since and record.diag_state is None:
                record.managed = False  # heard on /diagnostics, no lifecycle: a plain node
                record.reason = "not a managed node (no lifecycle_state on /diagnostics, no get_state service)"
                return
            elif record.diag_state is not None:
                record.managed = True  # its status says it is one; wait for the service
            else:
                record.reason = f"no {record.name}/get_state service yet"
                return
        if not record.managed:
            if record.diag_state is not None:  # it became one (a newer build of the node)
                self._forget(record, now)
            return
        if record.state == UNKNOWN or record.name in self._verify:
            self._verify.discard(record.name)
            if get_client.service_is_ready():
                self._send(record, "get_state", get_client, GetState.Request(), now, self.call_timeout_s)
            return
        goal = self._goal.get(record.name)
        if goal != ACTIVE:
            return
        if record.state == UNCONFIGURED:
            if self.configure_retry_s <= 0 and record.configure_attempts and record.failed:
                return
            if now >= self._configure_at.get(record.name, 0.0):
                self._send_transition(record, "configure", now)
        elif record.state == INACTIVE and not (record.failed and self._last_failed(record) == "activate"
                                               and now < self._configure_at.get(record.name, 0.0)):
            self._send_transition(record, "activate", now)

    def _last_failed(self, record: NodeLifecycle) -> str:
        return record.reason.split(" ", 1)[0] if record.failed else ""

    def _send(self, record: NodeLifecycle, what: str, client, request, now: float, timeout_s: float) -> None:
        future = client.call_async(request)
        self._calls[record.name] = _Call(what, future, client, now, now + timeout_s)
        future.add_done_callback(lambda _future: self.step())  # the next call goes out at once

    def _send_transition(self, record: NodeLifecycle, transition: str, now: float) -> None:
        _, change_client = self._clients[record.name]
        request = ChangeState.Request()
        request.transition.id = _SHUTDOWN_FROM.get(record.state, TRANSITIONS[transition][0]) \
            if transition == "shutdown" else TRANSITIONS[transition][0]
        if transition == "configure":
            record.configure_attempts += 1
        self._send(record, transition, change_client, request, now, self.transition_timeout_s)

    # ------------------------------------------------------------------ answers

    def _answered(self, record: NodeLifecycle, call: _Call, now: float) -> None:
        try:
            response = call.future.result()
        except Exception as error:  # noqa: BLE001 - a broken call is reported, the node is asked again
            record.reason = f"{call.what} call failed: {type(error).__name__}: {error}"
            self._set_state(record, UNKNOWN, now)
            return
        if call.what == "get_state":
            label = STATE_LABELS.get(response.current_state.id, response.current_state.label or UNKNOWN)
            self._set_state(record, label, now)
            if label == UNCONFIGURED and record.diag_reason and not record.failed:
                record.reason, record.failed = record.diag_reason, True  # failed before the manager saw it
            return
        if response.success:
            was_failing = record.failed
            record.failed, record.reason, record.reported, record.reason_pending = False, "", "", False
            self._failure_report.pop(record.name, None)
            self._set_state(record, TRANSITIONS[call.what][1], now)
            if record.state == ACTIVE and (self._goal.get(record.name) == ACTIVE or was_failing):
                took = now - record.since
                attempts = (f", after {record.configure_attempts} configure attempts"
                            if record.configure_attempts > 1 else "")
                self.on_event(f"{short(record.name)} active ({took:.1f} s{attempts})")
            return
        # Failed: a transition that fails goes back to the state it started from (a callback that raised goes
        # through errorprocessing and may end elsewhere: get_state tells); the reason comes on /diagnostics.
        start_state = record.state
        # A node that fails again (a configure retry) stays failed with the reason already said while the new
        # attempt's reason comes: readiness keeps reporting it failed (ERROR), not as coming up between attempts.
        known = record.reported if record.failed and record.reported else ""
        record.failed = True
        record.reason = known or f"{call.what} failed"
        self._failure_report[record.name] = (call.what, call.sent)
        record.reason_pending = not known
        if call.what == "configure":
            self._configure_at[record.name] = now + max(self.configure_retry_s, 0.0)
        elif call.what == "activate":
            self._configure_at[record.name] = now + max(self.configure_retry_s, 0.0)
        self._set_state(record, start_state, now)
        self._verify.add(record.name)

    def _timed_out(self, record: NodeLifecycle, call: _Call, now: float) -> None:
        limit = call.deadline - call.sent
        if call.what != "get_state":
            record.failed = True
            record.reason = f"{call.what} failed: no answer from {record.name}/change_state within {limit:.0f} s"
            self.on_event(f"{short(record.name)}: {record.reason}")
        else:
            record.reason = f"no answer from {record.name}/get_state within {limit:.0f} s"
        self._set_state(record, UNKNOWN, now)

    def _report_failure(self, record: NodeLifecycle, now: float) -> None:
        """Say a failed transition once its reason came on /diagnostics (or after REASON_WAIT_S without)."""
        pending = self._failure_report.get(record.name)
        if pending is None:
            return
        transition, sent = pending
        fresh = record.heard >= sent and record.diag_reason.startswith(transition)
        if not fresh and now - sent < REASON_WAIT_S:
            return
        del self._failure_report[record.name]
        record.reason_pending = False
        record.reason = record.diag_reason if fresh else f"{transition} failed (no reason on /diagnostics)"
        if record.reason == record.reported:
            return
        record.reported = record.reason
        retry = (f"; trying again every {self.configure_retry_s:g} s"
                 if self.configure_retry_s > 0 and self._goal.get(record.name) == ACTIVE else "")
        self.on_event(f"{short(record.name)}: {record.reason}{retry}")

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        now = time.monotonic()
        self._take_resets(now)  # a reset asked for before this status: its new process is expected
        for status in msg.status:
            record = self.nodes.get(status.name)
            if record is None:
                continue
            values = {kv.key: kv.value for kv in status.values}
            process = values.get("process", "")
            if process in record.retired:
                continue  # a status of a process that was replaced (still in flight, or its DDS lease)
            record.heard = now
            record.diag_state = values.get("lifecycle_state")
            record.diag_reason = values.get("lifecycle_reason", "")
            if process and record.process and process != record.process:
                # Restarted by someone else (launch's respawn): bring the new process up.
                self.on_event(f"{short(record.name)} runs in a new process ({process}): bringing it up")
                self.reset(record.name)
            if process:
                record.process = process
            if record.diag_reason and record.failed and record.diag_state == record.state \
                    and record.name not in self._failure_report:
                record.reason = record.diag_reason  # a later attempt failed another way

    def _set_state(self, record: NodeLifecycle, state: str, now: float) -> None:
        if state != record.state:
            record.state, record.state_since = state, now

    # ------------------------------------------------------------------ reporting

    def describe(self, name: str, now: Optional[float] = None) -> str:
        """One phrase: 'active', 'unconfigured: configure failed: ...', 'configuring (3.2 s)', ..."""
        record = self.nodes[name]
        now = time.monotonic() if now is None else now
        call = self._calls.get(name)
        if record.failed:  # also while it is tried again: the reason is what a reader needs
            return f"{record.state}: {record.reason}" if record.state != UNKNOWN else record.reason
        if call is not None and call.what != "get_state":
            return f"{_DOING[call.what]} ({now - call.sent:.1f} s)"
        if record.state == UNKNOWN:
            return record.reason or "state not known yet"
        return record.state

    def diagnostic_status(self, status_name: str, hardware_id: str = "") -> DiagnosticStatus:
        """Each node's state and reason; OK all active, WARN one coming up, ERROR one failed."""
        now = time.monotonic()
        level, problems, values = DiagnosticStatus.OK, [], []
        for name, record in self.nodes.items():
            if record.managed is False:
                state = "not managed"
            else:
                state = record.state
                if record.failed:
                    level = DiagnosticStatus.ERROR
                    problems.append(f"{short(name)} {self.describe(name, now)}")
                elif state != ACTIVE:
                    level = max(level, DiagnosticStatus.WARN)
                    problems.append(f"{short(name)} {self.describe(name, now)}")
            values += [(f"{short(name)}.state", state), (f"{short(name)}.reason", record.reason),
                       (f"{short(name)}.configure_attempts", str(record.configure_attempts))]
        return DiagnosticStatus(level=bytes([level]) if isinstance(level, int) else level, name=status_name,
                                message="; ".join(problems)[:200] or "ok", hardware_id=hardware_id,
                                values=[KeyValue(key=k, value=v) for k, v in values])


def short(name: str) -> str:
    """'/leapnbv/hmr_node' -> 'hmr_node'."""
    return name.rsplit("/", 1)[-1]


def full_names(namespace: str, names: Sequence[str]) -> List[str]:
    """Node names as the manager wants them: plain names are put into ``namespace``."""
    namespace = "/" + namespace.strip("/") if namespace.strip("/") else ""
    return [name if name.startswith("/") else f"{namespace}/{name}" for name in names]


def main(args=None) -> None:
    """The lifecycle manager as a node (the launch file's): parameters node_names, autostart, the timeouts."""
    from rclpy.node import Node

    from leapnbv_bringup.graph import node_names
    from leapnbv_common.node_params import run_node

    class LifecycleManagerNode(Node):
        def __init__(self) -> None:
            super().__init__("lifecycle_manager")
            self.declare_parameter("node_names", node_names())
            self.declare_parameter("autostart", True)
            self.declare_parameter("configure_retry_s", 2.0)
            self.declare_parameter("transition_timeout_s", 120.0)
            self.declare_parameter("period_s", 1.0)
            names = full_names(self.get_namespace(), list(self.get_parameter("node_names").value))
            self.manager = LifecycleManager(
                self, names, autostart=bool(self.get_parameter("autostart").value),
                configure_retry_s=float(self.get_parameter("configure_retry_s").value),
                transition_timeout_s=float(self.get_parameter("transition_timeout_s").value),
                on_event=lambda line: self.get_logger().info(line))
            self.status_name = self.get_fully_qualified_name()
            self.publisher = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
            self.create_timer(float(self.get_parameter("period_s").value), self.publish_status)

        def publish_status(self) -> None:
            out = DiagnosticArray()
            out.header.stamp = self.get_clock().now().to_msg()
            out.status = [self.manager.diagnostic_status(self.status_name, "lifecycle_manager")]
            self.publisher.publish(out)

    run_node(LifecycleManagerNode, args)


if __name__ == "__main__":
    main()
