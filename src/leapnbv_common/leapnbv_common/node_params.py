"""Parameter declaration with defaults and descriptions, in one call per node."""
from __future__ import annotations

from typing import Any, Dict, Tuple

from rcl_interfaces.msg import ParameterDescriptor

ParamTable = Dict[str, Tuple[Any, str]]


def declare_parameters(node, table: ParamTable) -> Dict[str, Any]:
    """Declare every (name -> (default, description)) and return the values in effect.

    The values come from the params file / command line when given, else the defaults.
    """
    values = {}
    for name, (default, description) in table.items():
        node.declare_parameter(name, default, ParameterDescriptor(description=description))
        values[name] = node.get_parameter(name).value
    return values


def run_node(make_node, args=None) -> None:
    """Standard main(): init, make the node (a class or any factory), spin until Ctrl-C or shutdown, clean up."""
    import rclpy
    from rclpy.executors import ExternalShutdownException

    rclpy.init(args=args)
    node = make_node()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
