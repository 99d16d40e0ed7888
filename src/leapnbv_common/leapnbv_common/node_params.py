"""A node's parameters from its core's params dataclass: declared with ranges, changed at runtime safely.

The dataclass (see :mod:`leapnbv_common.params`) is the one source of each parameter's default,
description, range and read-only flag. :class:`NodeParams` declares them all, reads the values
given by the params file and the command line, validates them (a node refuses to start with an
invalid value, naming it), and applies ``ros2 param set`` at runtime: the new values are validated
as a whole, then the node's ``on_change`` rebuilds what depends on them; a change that fails
either step is refused with the reason, and the old values stay in force.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Generic, List, Optional, Set, Type, TypeVar

# rcl_interfaces has no stubs (mypy.ini does not list it yet; once it does, the ignore is unused, and allowed to be).
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)

from leapnbv_common.params import ParamsError, ParamSpec, param_specs, params_from_values, replace_params

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

    P = TypeVar("P", bound=DataclassInstance)  # a params dataclass, as leapnbv_common.params types it
else:
    P = TypeVar("P")
ChangeHandler = Callable[[Any, Set[str]], None]


def parameter_descriptor(spec: ParamSpec) -> ParameterDescriptor:
    """The ROS descriptor of one parameter: description, read-only flag, range, choices."""
    descriptor = ParameterDescriptor(description=spec.description, read_only=bool(spec.read_only))
    constraints = []
    if spec.choices is not None:
        constraints.append("one of: " + ", ".join(str(c) for c in spec.choices))
    if spec.kind in (int, float) and (spec.min is not None or spec.max is not None):
        low = spec.min if spec.min is not None else -1e300
        high = spec.max if spec.max is not None else 1e300
        if spec.kind is int:
            low, high = int(max(low, -2**63)), int(min(high, 2**63 - 1))
            descriptor.integer_range = [IntegerRange(from_value=low, to_value=high, step=0)]
        else:
            descriptor.floating_point_range = [FloatingPointRange(from_value=float(low), to_value=float(high),
                                                                   step=0.0)]
    elif spec.min is not None or spec.max is not None:
        constraints.append(f"each value in [{spec.min}, {spec.max}]")
    descriptor.additional_constraints = "; ".join(constraints)
    return descriptor


class NodeParams(Generic[P]):
    """The parameters of one node, as an instance of its params dataclass (``.value``).

    Args:
        node: The rclpy node.
        params_class: The core's params dataclass.
        on_change: Called as ``on_change(new_params, changed_names)`` before a runtime change takes
            effect; it rebuilds the node's state, or raises ValueError to refuse the change.

    Raises:
        ParamsError: a value from the params file or the command line is invalid (the node
            cannot start with it).
    """

    def __init__(self, node, params_class: Type[P], on_change: Optional[ChangeHandler] = None) -> None:
        self.node = node
        self.specs = {spec.name: spec for spec in param_specs(params_class)}
        self.on_change = on_change
        values = {}
        for spec in self.specs.values():
            node.declare_parameter(spec.name, spec.default, parameter_descriptor(spec))
            values[spec.name] = node.get_parameter(spec.name).value
        try:
            self.value: P = params_from_values(params_class, values)
        except ParamsError as error:
            raise ParamsError(f"{node.get_name()}: {error}") from error
        node.add_on_set_parameters_callback(self._on_set)
        self.changes_applied = 0
        self.changes_refused = 0

    def _on_set(self, parameters: List[Any]) -> SetParametersResult:
        changes = {p.name: p.value for p in parameters if p.name in self.specs}
        if not changes:  # e.g. use_sim_time: not ours
            return SetParametersResult(successful=True)
        try:
            updated = replace_params(self.value, changes)
            if self.on_change is not None:
                self.on_change(updated, set(changes))
        except (ParamsError, ValueError) as error:
            self.changes_refused += 1
            self.node.get_logger().warning(f"parameter change refused: {error}")
            return SetParametersResult(successful=False, reason=str(error))
        self.value = updated
        self.changes_applied += 1
        changed = ", ".join(f"{name}={value!r}" for name, value in sorted(changes.items()))
        self.node.get_logger().info(f"parameters changed: {changed}")
        return SetParametersResult(successful=True)


# Exit code of a node that refuses to start with the parameters it was given (a ParamsError, or
# another ValueError from the node's constructor: an unknown camera-pose source, ...).
EXIT_BAD_PARAMETERS = 2
STOP_SIGNALS = ("SIGINT", "SIGTERM")


def run_node(make_node, args=None) -> None:
    """Standard main(): init, make the node, spin until a signal or a shutdown, clean up, return.

    The node is made by ``make_node`` (a class or any factory); it spins until SIGINT, SIGTERM or an
    external shutdown; the clean-up ends with exit code 0 and no traceback.

    rclpy's own signal handler is off: on SIGINT it shuts the context down under the callback that
    is running, whose next publish then fails (a pybind ``RCLError`` traceback, exit 1; a planner
    kernel's caller counting an ``internal_error``). Here SIGINT and SIGTERM only ask the spin loop
    to stop: the running callback finishes, then the node is destroyed and rclpy shut down, in that
    order. A signal while the node is still being built (an engine load, the numba warm-up) ends the
    start at once (raised again every STOP_RETRY_S until it takes, since a C library's callback drops
    it); a second signal while stopping ends at once too.

    A parameter value the node refuses (:class:`ParamsError`, rclpy's range or type check of a
    declared parameter, or another ValueError raised while it is built) ends the process with one
    line on stderr naming it and exit code EXIT_BAD_PARAMETERS (2), not a traceback.

    A managed node (:class:`leapnbv_common.managed_node.ManagedNode`) with ``autostart`` configures and
    activates itself here, before the spin (a signal during its engine load ends the start at once; a
    configure that fails on its parameters exits 2); one whose configure fails otherwise spins
    unconfigured and retries. The spin ends when the node is shut down (the lifecycle's shutdown
    transition, exit 0); on a signal a managed node goes through shutdown before it is destroyed, so
    its hooks release what it holds whatever its state.
    """
    import faulthandler
    import signal
    import sys

    import rclpy
    from rclpy.exceptions import ParameterException
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    state = {"signals": 0, "spinning": False, "retrying": False}

    def on_signal(signum, frame) -> None:
        state["signals"] += 1
        if not state["spinning"] or state["signals"] > 1:
            _retry_stop_while_starting(state)
            raise KeyboardInterrupt  # not spinning yet (or asked twice): unwind now
        # Spinning: the loop below sees the flag once the running callback returned.

    def on_retry(signum, frame) -> None:
        # The first one fell into a C callback, which drops it: again. Never in this function's own
        # frame (between its statements, or catching the first one: a stop seen there is seen anyway).
        if state["retrying"] and (frame is None or frame.f_code not in own_code):
            raise KeyboardInterrupt

    def on_unraisable(unraisable) -> None:
        # A stop that lands in a C library's Python callback (llvmlite's, during the numba warm-up) is
        # dropped there with a traceback on stderr; the retry above stops the start instead.
        if issubclass(unraisable.exc_type, KeyboardInterrupt):
            return
        previous_unraisable(unraisable)

    # SIGUSR1 writes every thread's Python stack to stderr (the node's log), even while the main thread
    # is blocked in C: the graph runner sends it to a node that does not stop, before it escalates.
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    previous = {}
    for name in STOP_SIGNALS:
        number = getattr(signal, name)
        previous[number] = signal.signal(number, on_signal)
    own_code = {run_node.__code__, on_signal.__code__, _stop_retrying.__code__,
                _retry_stop_while_starting.__code__}
    previous[signal.SIGALRM] = signal.signal(signal.SIGALRM, on_retry)
    previous_unraisable = sys.unraisablehook
    sys.unraisablehook = on_unraisable
    node = None
    executor = None
    exit_code = 0
    starting = True
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
        node = make_node()
        start_up = getattr(node, "start_up", None) if getattr(node, "autostart", False) else None
        if start_up is not None:
            start_up()  # a managed node started alone: configure + activate (ParamsError: exit 2)
        starting = False
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        _stop_retrying(state)
        state["spinning"] = True
        while not state["signals"] and rclpy.ok() and not getattr(node, "finalized", False):
            executor.spin_once(timeout_sec=0.1)  # wakes at least every 0.1 s to see a signal
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, ParameterException) as error:  # ParamsError, rclpy's range and type checks
        if not starting:
            raise
        print(f"[{_node_name(args, make_node)}] cannot start: {error}", file=sys.stderr, flush=True)
        exit_code = EXIT_BAD_PARAMETERS
    finally:
        _stop_retrying(state)
        state["spinning"] = False
        try:
            if executor is not None:
                executor.shutdown(timeout_sec=1.0)
            if node is not None:
                shut_down = getattr(node, "shut_down", None)
                if shut_down is not None and not starting:
                    shut_down()  # a managed node releases its engines and subscriptions in order
                node.destroy_node()
            rclpy.try_shutdown()
        except KeyboardInterrupt:  # a second signal during the clean-up: it is done enough
            pass
        for number, handler in previous.items():
            signal.signal(number, handler)
        sys.unraisablehook = previous_unraisable
    if exit_code:
        sys.exit(exit_code)


# While a node is being built, a stop is raised again every STOP_RETRY_S until it takes: a
# KeyboardInterrupt raised inside a C library's Python callback is dropped there (numba's compiler
# calls back from llvmlite), and the warm-up would run on for seconds.
STOP_RETRY_S = 0.2


def _retry_stop_while_starting(state) -> None:
    import signal

    if not state["spinning"] and not state["retrying"]:
        state["retrying"] = True
        signal.setitimer(signal.ITIMER_REAL, STOP_RETRY_S, STOP_RETRY_S)


def _stop_retrying(state) -> None:
    import signal

    if state["retrying"]:
        state["retrying"] = False
        signal.setitimer(signal.ITIMER_REAL, 0.0)


def _node_name(args, make_node) -> str:
    """The node's name for a start-up error line: ``__node:=`` from the arguments, else the program's."""
    import os
    import sys

    for arg in list(args or sys.argv):
        if str(arg).startswith(("__node:=", "__name:=")):
            return str(arg).split(":=", 1)[1]
    program = os.path.splitext(os.path.basename(sys.argv[0] if sys.argv and sys.argv[0] else ""))[0]
    return program if program and program != "-c" else getattr(make_node, "__name__", "node")
