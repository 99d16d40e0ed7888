"""The command lines of the graph's node processes, and the warm standby processes a restart turns into a node.

A standby (``python -m leapnbv_bringup.graph_runner --spare ...``) imports the node's module, runs
its warm-up functions (kernels compiled) and loads the message type support, says so on a pipe,
and waits; "go" on its stdin makes it the node, so that a restart does not pay for any of that.
"""
from __future__ import annotations

import importlib
import os
import signal
import sys
from typing import Dict, List

from leapnbv_bringup.graph import NAMESPACE, NodeSpec


def node_command(spec: NodeSpec, params_file: str, overrides: Dict[str, str]) -> List[str]:
    """The command line of one node process.

    The namespace, the params file, ``autostart:=false`` (the runner drives a managed node through
    its lifecycle; a node that is not one ignores it), the overrides and the remaps.
    """
    cmd = [sys.executable, "-m", spec.module, "--ros-args", "-r", f"__ns:={NAMESPACE}",
           "--params-file", params_file, "-p", "autostart:=false"]
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
    """Load the C type support of every message and service type imported so far.

    Also that of the parameter services every node creates: the node's constructor would otherwise
    load them (about 0.1 s on an idle core, much more under load) while the graph waits for it.

    Returns:
        How many types were loaded.
    """
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

