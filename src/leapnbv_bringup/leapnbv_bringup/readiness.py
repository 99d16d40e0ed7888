"""When a node of the graph is serving, and why it is not: from its lifecycle state, else from its diagnostics.

A **managed** node (leapnbv_common.managed_node) is serving when it is active, as its lifecycle
services say (the lifecycle manager's record, from ``get_state`` / ``change_state``), and its own
status confirms it: ``lifecycle_state`` active, received after the process started, and no input
without a publisher yet (``awaiting_publishers``: a reliable, volatile stage output published before
its subscriber was discovered is lost, and with it the frame). A managed node whose configure failed
(a missing model) stays unconfigured: a *failure* with its reason, retried, that the rest of the
graph can run without.

A node that is **not managed** (no ``lifecycle_state`` in its status, no ``get_state`` service) is
judged by its diagnostics as before: serving once it published a status (its constructor finished)
whose ``engine_state`` is "ready" (a status without that key: by its level); an engine that did not
load (an ERROR status) is its failure.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional, Tuple

from leapnbv_common.managed_node import ACTIVE, UNCONFIGURED

if TYPE_CHECKING:  # the manager imports this module
    from leapnbv_bringup.lifecycle_manager import NodeLifecycle

ERROR_LEVEL = 2
NOT_HEARD = "no diagnostics yet"
#: How a judge says that an active node waits for a publisher of one of its inputs.
AWAITING_PUBLISHER = "active, waiting for a publisher of "


@dataclass
class NodeHealth:
    """What /diagnostics last said about one node."""

    received: float  # monotonic time of the last status
    engine_ok: bool
    reason: str
    lifecycle_state: Optional[str] = None  # None: not a managed node
    lifecycle_reason: str = ""
    awaiting: str = ""  # inputs without a publisher yet (managed nodes)
    error: bool = False  # the status level is ERROR


def _level(status) -> int:
    level = status.level
    return level[0] if isinstance(level, (bytes, bytearray)) else int(level)


def engine_state_of(status) -> Tuple[bool, str]:
    """(engine loaded, why not) from a node's DiagnosticStatus (a node that is not managed).

    A stage reports ``engine_state`` ("ready" once its model is loaded, the load error
    otherwise); a status without that key is judged by its level (not ERROR).
    """
    state = next((kv.value for kv in status.values if kv.key == "engine_state"), None)
    if state is not None:
        return state == "ready", f"engine not ready: {state}"
    if _level(status) == ERROR_LEVEL:
        return False, f"ERROR: {status.message}"
    return True, ""


def health_from_status(status, received: Optional[float] = None) -> NodeHealth:
    """The NodeHealth of one DiagnosticStatus of a node."""
    values = {kv.key: kv.value for kv in status.values}
    ok, reason = engine_state_of(status)
    return NodeHealth(time.monotonic() if received is None else received, ok, reason,
                      lifecycle_state=values.get("lifecycle_state"),
                      lifecycle_reason=values.get("lifecycle_reason", ""),
                      awaiting=values.get("awaiting_publishers", ""), error=_level(status) == ERROR_LEVEL)


def judge(health: Optional[NodeHealth], lifecycle: Optional[NodeLifecycle], describe: str,
          heard_after: float) -> Tuple[str, bool]:
    """Why a running node is not serving ("" when it is), and whether that is a failure it may stay in.

    Args:
        health: Its last status (None: none yet).
        lifecycle: The lifecycle manager's record of it (leapnbv_bringup.lifecycle_manager.NodeLifecycle),
            or None without a manager.
        describe: The manager's phrase for its state ("unconfigured: configure failed: ...").
        heard_after: Statuses received before this (monotonic) do not count (the process started later,
            or the caller waits from then).

    Returns:
        (reason, failed): ("", False) when serving.
    """
    fresh = health if health is not None and health.received >= heard_after else None
    managed = (lifecycle is not None and lifecycle.managed) or (fresh is not None and fresh.lifecycle_state is not None)
    if managed:
        # Without a manager's record, a managed node is one whose fresh status says so.
        state = lifecycle.state if lifecycle is not None else fresh.lifecycle_state if fresh is not None else None
        if state == ACTIVE and fresh is not None and fresh.lifecycle_state == ACTIVE:
            if fresh.awaiting:
                return f"{AWAITING_PUBLISHER}{fresh.awaiting}", False
            return "", False
        failed = bool(lifecycle is not None and lifecycle.failed and not lifecycle.reason_pending) or (
            lifecycle is None and fresh is not None and fresh.lifecycle_state == UNCONFIGURED
            and bool(fresh.lifecycle_reason))
        if state == ACTIVE:
            return "active, its status not received yet", False
        return describe or (health.lifecycle_reason if health is not None else "") or str(state), failed
    if fresh is None:
        return NOT_HEARD, False
    if not fresh.engine_ok:
        return fresh.reason, fresh.error
    return "", False
