"""Managed (lifecycle) stage nodes: configure loads, activate serves, every state on /diagnostics.

A stage node is an ``rclpy.lifecycle.LifecycleNode`` (the ROS 2 managed node of nav2 and the
robots' stacks, driven with ``ros2 lifecycle get/set`` or a lifecycle manager over the
``<node>/get_state``, ``<node>/change_state`` and ``<node>/get_available_transitions`` services):

============  =====================================================================================
state         what exists
============  =====================================================================================
unconfigured  the parameters (declared and validated in the constructor: a bad value ends the
              process, exit 2) and /diagnostics; nothing loaded
inactive      what ``configure_stage`` made: engines and models loaded, cores built, publishers
active        what ``activate_stage`` made: subscriptions and timers; lifecycle publishers publish
finalized     nothing (``shutdown`` from any state released it); the process ends
============  =====================================================================================

A subclass writes four hooks; each raises any Exception to fail its transition, and the exception's
text is the reason (logged, ``lifecycle_reason`` on /diagnostics, what the lifecycle manager reports).
A failed configure leaves the node unconfigured with what it made released (``cleanup_stage`` runs,
so it must accept a half-made state); a failed activate leaves it inactive. Entities a hook made and
its counterpart did not destroy are destroyed by the base class: the subscriptions and timers of
``activate_stage`` on deactivate, the publishers, subscriptions and timers of ``configure_stage`` on
cleanup; so are the resources a hook hands to :meth:`ManagedNode.owned` (a camera-pose source: its
``destroy()`` releases what it made). Publishers: made in ``configure_stage`` with
``create_lifecycle_publisher`` (they drop what is published while the node is not active), so that a
downstream node's subscriptions find them as soon as it activates.

``autostart`` (default true): a node started alone configures and activates itself before it spins
(``run_node``), and while it is unconfigured tries configure again every
``configure_retry_period_s`` (a model file that appears later is loaded then). The graph runner and
the launch file start nodes with ``autostart:=false`` and drive the transitions
(:mod:`leapnbv_bringup.lifecycle_manager`). A :class:`~leapnbv_common.params.ParamsError` from
``configure_stage`` is not retried (the parameters must change first); a node started alone exits
with code 2 on it, as for a bad value in the constructor.
"""
from __future__ import annotations

import os
import socket
import traceback
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional, Set, Tuple, Type, TypeVar, Union

from lifecycle_msgs.msg import State
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.lifecycle.publisher import LifecyclePublisher

from leapnbv_common.diagnostics import StageDiagnostics
from leapnbv_common.node_params import NodeParams, run_node
from leapnbv_common.params import ParamsError, param
from leapnbv_common.process_tuning import tune_node_process

__all__ = ["ManagedNode", "LifecycleParams", "StageNotReadyError", "UNCONFIGURED", "INACTIVE", "ACTIVE", "FINALIZED",
           "STATE_LABELS", "managed_node_main"]

R = TypeVar("R")

UNCONFIGURED, INACTIVE, ACTIVE, FINALIZED = "unconfigured", "inactive", "active", "finalized"
#: lifecycle_msgs/State ids -> labels (the primary states and the transition states).
STATE_LABELS = {State.PRIMARY_STATE_UNKNOWN: "unknown", State.PRIMARY_STATE_UNCONFIGURED: UNCONFIGURED,
                State.PRIMARY_STATE_INACTIVE: INACTIVE, State.PRIMARY_STATE_ACTIVE: ACTIVE,
                State.PRIMARY_STATE_FINALIZED: FINALIZED, State.TRANSITION_STATE_CONFIGURING: "configuring",
                State.TRANSITION_STATE_CLEANINGUP: "cleaningup", State.TRANSITION_STATE_SHUTTINGDOWN: "shuttingdown",
                State.TRANSITION_STATE_ACTIVATING: "activating", State.TRANSITION_STATE_DEACTIVATING: "deactivating",
                State.TRANSITION_STATE_ERRORPROCESSING: "errorprocessing"}

# The entity kinds a hook can make, with the Node method that destroys one.
_ENTITY_KINDS = (("publishers", "destroy_publisher"), ("subscriptions", "destroy_subscription"),
                 ("timers", "destroy_timer"), ("clients", "destroy_client"), ("services", "destroy_service"))


@dataclass
class LifecycleParams:
    """The parameters every managed node declares beside its own."""

    autostart: bool = param(True, "configure and activate at start; false: wait for a lifecycle manager "
                                  "(the graph runner and the launch file set false)", read_only=True)
    configure_retry_period_s: float = param(2.0, "seconds: with autostart, a failed configure is tried again "
                                                 "this often (0: never)", min=0.0, max=3600.0)


class StageNotReadyError(RuntimeError):
    """Raised by a hook with a complete reason.

    Reported as its text alone; any other exception is reported as ``<type>: <text>``.
    """


def _reason(error: BaseException) -> str:
    if isinstance(error, StageNotReadyError):
        return str(error)
    return f"{type(error).__name__}: {error}"


class ManagedNode(LifecycleNode):
    """A stage node with the lifecycle (see the module docstring).

    Args:
        node_name: The node's name.
        params_class: The core's params dataclass (``self.params``: a NodeParams; ``self.params.value``).
        hardware_id: The /diagnostics hardware id, or a function of the params instance that returns it
            (e.g. ``lambda p: p.backend``: the params are declared only here).
        diagnostics_class: StageDiagnostics or a subclass (``self.diagnostics``).
        **node_kwargs: Passed on to rclpy's Node (e.g. ``parameter_overrides`` in tests).

    Raises:
        ParamsError: a parameter value from the params file or the command line is invalid.
    """

    def __init__(self, node_name: str, params_class: Type[Any], *,
                 hardware_id: Union[str, Callable[[Any], str]] = "",
                 diagnostics_class: Type[StageDiagnostics] = StageDiagnostics, **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        self.params = NodeParams(self, params_class, self._on_params_change)
        self.lifecycle_params = NodeParams(self, LifecycleParams, self._on_lifecycle_params_change)
        if callable(hardware_id):
            hardware_id = str(hardware_id(self.params.value))
        # A StageDiagnostics subclass that takes the node alone works too (without a hardware id).
        self.diagnostics = diagnostics_class(self, hardware_id=hardware_id) if hardware_id else diagnostics_class(self)
        self.process = f"{socket.gethostname()}:{os.getpid()}"
        #: Why the last transition failed ("" once one succeeded); what /diagnostics and the manager say.
        self.lifecycle_reason = ""
        #: The last configure failed on its parameters (ParamsError): retrying cannot help.
        self.bad_parameters = False
        self.configure_attempts = 0
        self.finalized = False
        self._made: Dict[str, List[Tuple[str, Any]]] = {"configure": [], "activate": []}
        self._owned: Dict[str, List[Any]] = {"configure": [], "activate": []}
        self._phase = "configure"  # the hook running: what owned() hands its resources to
        self._retry_timer: Any = None
        self._autostart_timer: Any = None
        self._report()
        if self.autostart:
            # A node spun by other code than run_node starts itself on its first spin.
            self._autostart_timer = self.create_timer(0.001, self._autostart_from_timer)

    # ------------------------------------------------------------------ subclass hooks

    def configure_stage(self) -> None:
        """Read the parameters, load engines and models, build the cores, make the publishers."""

    def activate_stage(self) -> None:
        """Create the subscriptions and timers."""

    def deactivate_stage(self) -> None:
        """Destroy the subscriptions and timers (what is left is destroyed by the base class)."""

    def cleanup_stage(self) -> None:
        """Release engines and caches (also after a configure that failed half-way)."""

    def on_params_change(self, params: Any, changed: Set[str]) -> None:
        """A runtime ``ros2 param set`` while configured (inactive or active), before it takes effect.

        Rebuild what depends on it, or raise ValueError to refuse it. While unconfigured the values are
        only stored: the next configure reads them.
        """

    def owned(self, resource: R) -> R:
        """Release ``resource`` (anything with ``destroy()``) with the entities of the hook that makes it.

        Made in ``configure_stage``: destroyed on cleanup (and after a configure that failed); in
        ``activate_stage``: on deactivate. Returns the resource.
        """
        self._owned[self._phase].append(resource)
        return resource

    # ------------------------------------------------------------------ state

    @property
    def autostart(self) -> bool:
        return bool(self.lifecycle_params.value.autostart)

    @property
    def lifecycle_state(self) -> str:
        """The current state's label: unconfigured, inactive, active, finalized (or a transition state)."""
        return STATE_LABELS.get(self._state_machine.current_state[0], self._state_machine.current_state[1])

    @property
    def configured(self) -> bool:
        return self.lifecycle_state in (INACTIVE, ACTIVE)

    def start_up(self) -> str:
        """Configure, then activate if that succeeded (what autostart does); returns the state.

        Raises:
            ParamsError: configure failed on the node's parameters (a node started alone exits 2).
        """
        self._destroy_timer("_autostart_timer")
        if self.lifecycle_state == UNCONFIGURED:
            self.trigger_configure()
        if self.lifecycle_state == INACTIVE:
            self.trigger_activate()
        if self.bad_parameters:
            raise ParamsError(f"{self.get_name()}: {self.lifecycle_reason}")
        return self.lifecycle_state

    def shut_down(self) -> None:
        """The shutdown transition from whatever state the node is in (releases everything); safe twice."""
        self._destroy_timer("_autostart_timer")
        if self.finalized or self.lifecycle_state not in (UNCONFIGURED, INACTIVE, ACTIVE):
            return
        self.trigger_shutdown()

    # ------------------------------------------------------------------ transitions (rclpy callbacks)

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.configure_attempts += 1
        try:
            self._tracked("configure", self.configure_stage)
        except Exception as error:  # noqa: BLE001 - any failure leaves the node unconfigured with the reason
            self.bad_parameters = isinstance(error, ParamsError)
            self._release("configure", self.cleanup_stage)
            return self._failed("configure", error, UNCONFIGURED)
        self.bad_parameters = False
        self._destroy_timer("_retry_timer")
        self.diagnostics.set_engine_state("ready", ok=True)
        return self._succeeded("configured", INACTIVE)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self._tracked("activate", self.activate_stage)
        except Exception as error:  # noqa: BLE001 - the node stays inactive with the reason
            self._release("activate", self.deactivate_stage)
            return self._failed("activate", error, INACTIVE)
        super().on_activate(state)  # the lifecycle publishers publish from now on
        return self._succeeded("active", ACTIVE)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release("activate", self.deactivate_stage)
        super().on_deactivate(state)
        return self._succeeded("deactivated", INACTIVE)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release("configure", self.cleanup_stage)
        self.diagnostics.set_engine_state(UNCONFIGURED, ok=True)
        return self._succeeded("cleaned up", UNCONFIGURED)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._destroy_timer("_retry_timer")
        if state.label == ACTIVE:
            self._release("activate", self.deactivate_stage)
            super().on_deactivate(state)
        if state.label in (ACTIVE, INACTIVE):
            self._release("configure", self.cleanup_stage)
        self.finalized = True
        self.diagnostics.set_engine_state(FINALIZED, ok=True)
        return self._succeeded("shut down", FINALIZED)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        # Reached only when a callback above raised past its own handling: release all, back to unconfigured.
        self._release("activate", self.deactivate_stage)
        self._release("configure", self.cleanup_stage)
        self._report(UNCONFIGURED)
        return TransitionCallbackReturn.SUCCESS

    # ------------------------------------------------------------------ helpers

    def _tracked(self, phase: str, hook) -> None:
        """Run a hook and remember every entity it made (destroyed with its phase by _release)."""
        before = {kind: set(map(id, getattr(self, kind))) for kind, _ in _ENTITY_KINDS}
        self._phase = phase
        try:
            hook()
        finally:
            for kind, destroy in _ENTITY_KINDS:
                self._made[phase] += [(destroy, e) for e in getattr(self, kind) if id(e) not in before[kind]]

    def _release(self, phase: str, hook) -> None:
        """Run the releasing hook (its failure is logged, never kept), then destroy what the phase made."""
        try:
            hook()
        except Exception:  # noqa: BLE001 - releasing goes on: the entities below are destroyed anyway
            self.get_logger().error(f"{hook.__name__} failed:\n{traceback.format_exc()}")
        owned, self._owned[phase] = self._owned[phase], []
        for resource in reversed(owned):
            try:
                resource.destroy()
            except Exception:  # noqa: BLE001 - releasing goes on
                self.get_logger().error(f"destroying {type(resource).__name__} failed:\n{traceback.format_exc()}")
        made, self._made[phase] = self._made[phase], []
        for destroy, entity in made:
            if isinstance(entity, LifecyclePublisher):
                self.destroy_lifecycle_publisher(entity)
            else:
                getattr(self, destroy)(entity)  # returns False for one the hook destroyed already

    def _failed(self, transition: str, error: BaseException, state: str) -> TransitionCallbackReturn:
        self.lifecycle_reason = f"{transition} failed: {_reason(error)}"
        self.get_logger().error(self.lifecycle_reason, throttle_duration_sec=30.0)
        if transition == "configure":
            self.diagnostics.set_engine_state(self.lifecycle_reason, ok=False)
            period = float(self.lifecycle_params.value.configure_retry_period_s)
            if self.autostart and period > 0 and not self.bad_parameters and self._retry_timer is None:
                self._retry_timer = self.create_timer(period, self._retry_configure)
        self._report(state)
        return TransitionCallbackReturn.FAILURE

    def _succeeded(self, what: str, state: str) -> TransitionCallbackReturn:
        self.lifecycle_reason = ""
        self.get_logger().info(what)
        self._report(state)
        return TransitionCallbackReturn.SUCCESS

    def _report(self, state: Optional[str] = None) -> None:
        """Put the state on /diagnostics now (a manager waiting for the reason need not wait a second)."""
        self.diagnostics.set_lifecycle_state(state or self.lifecycle_state, self.lifecycle_reason, self.process)
        if state is None:  # the constructor: nothing loaded yet
            self.diagnostics.set_engine_state(UNCONFIGURED, ok=True)
            return
        self.diagnostics.publish()

    def _retry_configure(self) -> None:
        if self.lifecycle_state != UNCONFIGURED or not self.autostart:
            self._destroy_timer("_retry_timer")
            return
        self.start_up()

    def _autostart_from_timer(self) -> None:
        try:
            self.start_up()
        except ParamsError as error:
            self.get_logger().error(f"cannot start: {error}")

    def _destroy_timer(self, attribute: str) -> None:
        timer = getattr(self, attribute)
        if timer is not None:
            self.destroy_timer(timer)
            setattr(self, attribute, None)

    def _on_params_change(self, params: Any, changed: Set[str]) -> None:
        if self.configured:
            self.on_params_change(params, changed)

    def _on_lifecycle_params_change(self, params: LifecycleParams, changed: Set[str]) -> None:
        if "configure_retry_period_s" in changed:
            self._destroy_timer("_retry_timer")  # the next failure starts one with the new period
            if self.autostart and self.lifecycle_state == UNCONFIGURED and params.configure_retry_period_s > 0 \
                    and self.configure_attempts and not self.bad_parameters:
                self._retry_timer = self.create_timer(params.configure_retry_period_s, self._retry_configure)


def managed_node_main(node_class: Callable[[], ManagedNode]) -> Callable[..., None]:
    """A stage node's ``main(args=None)`` (its console script): the process tuned, then the node run.

    The tuning (:func:`leapnbv_common.process_tuning.tune_node_process`): one BLAS thread, image buffers
    kept in the heap; the run: :func:`leapnbv_common.node_params.run_node`.
    """

    def main(args: Optional[List[str]] = None) -> None:
        tune_node_process()
        run_node(node_class, args)

    main.__doc__ = f"Run {node_class.__name__} (a console script's entry point)."
    return main
