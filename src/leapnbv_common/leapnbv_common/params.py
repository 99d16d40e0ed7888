"""Parameters as plain dataclasses: one source for default, description, range and read-only flag.

A core module declares its parameters as a dataclass whose fields are made with :func:`param`;
its node declares them to ROS from that class (:func:`leapnbv_common.node_params.declare_params`),
so the default, the description and the valid range exist once. No ROS import here: cores and
tests use the same classes without ROS.

    @dataclass
    class RingParams:
        radius: float = param(2.5, "metres: ring radius around the target", min=0.5, max=10.0)

Validation (:func:`validate_params`) checks each field's type, range and choices, then calls the
class's ``check()`` method when it has one (for rules between fields).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Dict, List, Mapping, Optional, Sequence, Type, TypeVar

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

    P = TypeVar("P", bound=DataclassInstance)  # a params dataclass
else:
    P = TypeVar("P")


class ParamsError(ValueError):
    """A parameter value is out of range, of the wrong type, unknown, or read-only; the text says which."""


@dataclass(frozen=True)
class ParamSpec:
    """Everything declared about one parameter."""

    name: str
    default: Any
    description: str
    min: Optional[float] = None
    max: Optional[float] = None
    read_only: bool = False
    choices: Optional[Sequence[Any]] = None

    @property
    def kind(self) -> type:
        """bool, int, float, str or list (the ROS parameter type follows the default's)."""
        return list if isinstance(self.default, (list, tuple)) else type(self.default)


def param(default: Any, description: str, *, min: Optional[float] = None, max: Optional[float] = None,
          read_only: bool = False, choices: Optional[Sequence[Any]] = None) -> Any:
    """A dataclass field that is a node parameter.

    Args:
        default: The value that works on the robot (lists are copied per instance).
        description: One line for ``ros2 param describe``: unit first where there is one.
        min: Inclusive lower bound of a number (or of each element of a list of numbers).
        max: Inclusive upper bound, likewise.
        read_only: Settable only at start-up (the node builds state from it that it cannot rebuild).
        choices: The allowed values of a string parameter (or of each element of a list).
    """
    metadata = {"description": description, "min": min, "max": max, "read_only": read_only,
                "choices": tuple(choices) if choices is not None else None}
    if isinstance(default, (list, tuple)):
        items = list(default)
        return dataclasses.field(default_factory=lambda: list(items), metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


#: s: how far a stamp may be ahead of a node's clock (StageParams.max_stamp_ahead_s).
MAX_STAMP_AHEAD_S = 0.5


@dataclass
class StageParams:
    """What every stage node takes (leapnbv_common.stage.Stage reads it): the clock sanity rule of its inputs.

    0.5 s: a robot whose clocks are synchronised (chrony / PTP: well under 10 ms) never stamps a frame ahead
    of a node's clock (a camera stamps at exposure, in the past), while a frame from a host whose clock runs
    ahead is refused before it is planned: it would never age out (its age is negative). Offline runs are
    not affected: recorded and simulated stamps lie in the clock's past, and a sim-time node follows the
    /clock its frames are stamped from.
    """

    max_stamp_ahead_s: float = param(MAX_STAMP_AHEAD_S, "s: an input stamped later than the node clock's now + this"
                                     " is refused (rejected.stamp_in_future): clocks out of sync, a bad driver;"
                                     " 0 = no limit", min=0.0, max=3600.0)


def param_specs(cls: Type[Any]) -> List[ParamSpec]:
    """The ParamSpec of every field of a params dataclass, in declaration order."""
    specs = []
    for f in dataclasses.fields(cls):
        if "description" not in f.metadata:
            raise TypeError(f"{cls.__name__}.{f.name} is not declared with param()")
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            raise TypeError(f"{cls.__name__}.{f.name} has no default")
        meta = f.metadata
        specs.append(ParamSpec(f.name, default, meta["description"], meta["min"], meta["max"], meta["read_only"],
                               meta["choices"]))
    return specs


def _check_value(spec: ParamSpec, value: Any) -> None:
    kind = spec.kind
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if kind is list:
        if not isinstance(value, (list, tuple)):
            raise ParamsError(f"{spec.name} must be a list, got {value!r}")
        items = list(value)
    else:
        if kind is bool and not isinstance(value, bool) or kind is not bool and isinstance(value, bool) \
                or not isinstance(value, kind):
            raise ParamsError(f"{spec.name} must be a {kind.__name__}, got {value!r}")
        items = [value]
    for item in items:
        if isinstance(item, (int, float)) and not isinstance(item, bool):
            if item != item:  # NaN
                raise ParamsError(f"{spec.name} must be a number, got NaN")
            if spec.min is not None and item < spec.min:
                raise ParamsError(f"{spec.name} = {item!r} is below its minimum {spec.min}")
            if spec.max is not None and item > spec.max:
                raise ParamsError(f"{spec.name} = {item!r} is above its maximum {spec.max}")
        if spec.choices is not None and item not in spec.choices:
            raise ParamsError(f"{spec.name} = {item!r} is not one of {list(spec.choices)}")


def validate_params(params: Any) -> None:
    """Check every field of a params instance, then its ``check()`` (rules between fields).

    Raises:
        ParamsError: the first value that is wrong, by name.
    """
    for spec in param_specs(type(params)):
        _check_value(spec, getattr(params, spec.name))
    check = getattr(params, "check", None)
    if check is not None:
        try:
            check()
        except ParamsError:
            raise
        except ValueError as error:
            raise ParamsError(str(error)) from error


def _coerce(spec: ParamSpec, value: Any) -> Any:
    """Ints given for float parameters become floats; tuples become lists."""
    if spec.kind is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if spec.kind is list and isinstance(value, tuple):
        return list(value)
    return value


def params_from_values(cls: Type[P], values: Mapping[str, Any]) -> P:
    """A validated instance from name -> value (missing names keep their defaults).

    Raises:
        ParamsError: an unknown name or an invalid value.
    """
    specs = {spec.name: spec for spec in param_specs(cls)}
    unknown = sorted(set(values) - set(specs))
    if unknown:
        raise ParamsError(f"unknown parameter(s) of {cls.__name__}: {', '.join(unknown)}")
    params = cls(**{name: _coerce(specs[name], value) for name, value in values.items()})
    validate_params(params)
    return params


def replace_params(params: P, changes: Mapping[str, Any], allow_read_only: bool = False) -> P:
    """A validated copy of ``params`` with ``changes`` applied.

    Raises:
        ParamsError: an unknown name, a read-only parameter (unless allowed) or an invalid value.
    """
    specs = {spec.name: spec for spec in param_specs(type(params))}
    for name in changes:
        if name not in specs:
            raise ParamsError(f"unknown parameter {name!r} of {type(params).__name__}")
        if specs[name].read_only and not allow_read_only:
            raise ParamsError(f"{name} is read-only: it is set at start-up (restart the node to change it)")
    updated = dataclasses.replace(params, **{name: _coerce(specs[name], value) for name, value in changes.items()})
    validate_params(updated)
    return updated


def params_as_dict(params: Any) -> Dict[str, Any]:
    """The name -> value of every field (lists copied)."""
    values = {}
    for spec in param_specs(type(params)):
        value = getattr(params, spec.name)
        values[spec.name] = list(value) if isinstance(value, list) else value
    return values
