"""Supervision of the graph's node processes: the restart policy, how a process ended, the parent-death signal.

The graph runner (:mod:`leapnbv_bringup.graph_runner`) restarts a node that died after an
exponential back-off, within a limit per time window (:class:`RestartPolicy`), and names how each
process ended (:func:`describe_exit`).
"""
from __future__ import annotations

import signal
from dataclasses import dataclass
from typing import Optional, Sequence

KILL_GRACE_S = 3.0  # after SIGTERM, before SIGKILL


def die_with_parent() -> None:
    """In the child before exec: Linux sends it SIGTERM when the runner dies, even by SIGKILL.

    So no node outlives a crashed or killed runner (its own session hides it from Ctrl-C).
    The signal follows the thread that started the child: the supervisor thread lives until
    stop() has ended every child.
    """
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
