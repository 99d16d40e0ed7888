"""The numpy array types of the cores' annotations: one name per dtype, the shapes in each docstring.

numpy's stubs carry an array's dtype but not its shape, so an annotation says ``FloatArray`` and
the docstring says ``(N, 3)``. Each alias is a ``numpy.typing.NDArray`` of one scalar type, which
numpy 1.21 and later (the robot has 1.24) also build at run time on Python 3.8. ``IntArray``
(indices, ids, faces: int32 or int64, as each producer chose) and ``FloatingArray`` (float32 or
float64: depth images, inputs a function converts itself) take any width of their kind.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
Float32Array = NDArray[np.float32]
Int64Array = NDArray[np.int64]
Int32Array = NDArray[np.int32]
Int16Array = NDArray[np.int16]
UInt8Array = NDArray[np.uint8]
UInt16Array = NDArray[np.uint16]
BoolArray = NDArray[np.bool_]
# Any dtype at all: a file's arrays before they are checked and converted.
GenericArray = NDArray[np.generic]
if TYPE_CHECKING:
    IntArray = NDArray[np.integer[Any]]
    FloatingArray = NDArray[np.floating[Any]]
else:  # np.integer[...] needs Python 3.9 at run time; annotations are never evaluated (PEP 563)
    IntArray = FloatingArray = np.ndarray

__all__ = [
    "BoolArray",
    "Float32Array",
    "FloatArray",
    "FloatingArray",
    "GenericArray",
    "Int16Array",
    "Int32Array",
    "Int64Array",
    "IntArray",
    "UInt16Array",
    "UInt8Array",
]
