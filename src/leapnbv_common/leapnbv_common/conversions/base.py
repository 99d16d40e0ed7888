"""What every converter shares: the error type, the contract checks re-raised as it, typed sequence fields."""
from __future__ import annotations

import array
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np

from leapnbv_common.contracts import ContractError, check_finite

if TYPE_CHECKING:
    import numpy.typing as npt


class ConversionError(ContractError):
    """A message cannot be turned into the array it should hold, or breaks its contract
    (:mod:`leapnbv_common.contracts`); the text says what is wrong."""


def check_finite_fields(what: str, fields: Mapping[str, Any]) -> None:
    """Check that every value of ``fields`` (name -> array or number) is finite.

    Raises:
        ConversionError: naming the first field with a NaN or inf.
    """
    for name, values in fields.items():
        try:
            check_finite(f"{what} {name}", values)
        except ContractError as error:
            raise ConversionError(str(error)) from None


def float32_sequence(values: npt.ArrayLike) -> array.array[float]:
    """An array.array('f') for a float32[] message field (fast, and accepted with field checks on)."""
    return array.array("f", np.ascontiguousarray(values, dtype=np.float32).tobytes())


def uint32_sequence(values: npt.ArrayLike) -> array.array[int]:
    """An array.array('I') for a uint32[] message field."""
    return array.array("I", np.ascontiguousarray(values, dtype=np.uint32).tobytes())
