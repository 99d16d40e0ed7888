"""The array type of the planner's annotations.

numpy arrays are typed as ``Array`` (``numpy.typing.NDArray`` of any dtype): the shapes and dtypes
are in each docstring (``(C, 3)`` float64, ``(C,)`` bool, ...), as numpy's own stubs cannot carry
shapes. One alias keeps ``mypy --strict`` (which refuses a bare ``np.ndarray``) and the docstrings
the one place that says what an array holds.
"""

from __future__ import annotations

from typing import Any

from numpy.typing import NDArray

Array = NDArray[Any]

__all__ = ["Array"]
