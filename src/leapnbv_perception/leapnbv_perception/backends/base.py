"""The engine backend interface: named float tensors in, named tensors out."""

from __future__ import annotations

import abc
import os
from dataclasses import dataclass
from typing import Dict, Mapping, Optional, Tuple, Union

import numpy as np

from leapnbv_common.array_types import FloatingArray

Dim = Union[int, str, None]
#: A model's input or output tensor: floating point, as the model contracts declare every tensor
#: (leapnbv_perception.model_contracts; the width is the TensorSpec's dtype).
Tensor = FloatingArray


class ModelFileNotFoundError(FileNotFoundError):
    """The ONNX model (or engine) file a backend was asked to load does not exist."""


class BackendError(RuntimeError):
    """A backend could not be created or could not run its model."""


@dataclass(frozen=True)
class TensorSpec:
    """Declared shape and dtype of one named model input or output.

    Attributes:
        shape: dimensions; int for static ones, None or a string for symbolic ones.
        dtype: numpy dtype name, e.g. "float32".
    """

    shape: Tuple[Dim, ...]
    dtype: str = "float32"

    def static_shape(self) -> Tuple[int, ...]:
        """The shape with symbolic dimensions replaced by 1 (single-image batches)."""
        return tuple(dim if isinstance(dim, int) else 1 for dim in self.shape)


class EngineBackend(abc.ABC):
    """One loaded model that maps named numpy inputs to named numpy outputs.

    Implementations: `OnnxRuntimeBackend` (CPU and tests), `TensorRTBackend` (Jetson). Each sets
    ``model_path``, ``_inputs`` and ``_outputs`` (name -> TensorSpec, in model order) and
    ``_precision`` when it loads its model, and implements ``run``.
    """

    model_path: str = ""
    _inputs: Mapping[str, TensorSpec]
    _outputs: Mapping[str, TensorSpec]
    _precision: str

    @property
    def input_specs(self) -> Mapping[str, TensorSpec]:
        """Model inputs: name -> TensorSpec, in model order."""
        return self._inputs

    @property
    def output_specs(self) -> Mapping[str, TensorSpec]:
        """Model outputs: name -> TensorSpec, in model order."""
        return self._outputs

    @property
    def precision(self) -> str:
        """Arithmetic the engine runs in: "fp32" or "fp16"."""
        return self._precision

    @abc.abstractmethod
    def run(self, inputs: Mapping[str, Tensor]) -> Dict[str, Tensor]:
        """Run the model once.

        Args:
            inputs: name -> array for every model input (shapes as in `input_specs`).

        Returns:
            name -> array for every model output.

        Raises:
            BackendError: on a missing input or an engine failure.
        """


def require_model_file(model_path: Union[str, os.PathLike[str]]) -> str:
    """Return the path as a string if the file exists.

    Raises:
        ModelFileNotFoundError: naming the path when there is no such file.
    """
    path = os.fspath(model_path)
    if not os.path.isfile(path):
        raise ModelFileNotFoundError(
            "model file not found: '%s' (absolute: '%s')" % (path, os.path.abspath(path))
        )
    return path


def check_inputs(inputs: Mapping[str, Tensor], specs: Mapping[str, TensorSpec], model_path: str) -> None:
    """Check that every declared input is given with a compatible shape.

    Raises:
        BackendError: naming the input and the model at fault.
    """
    for name, spec in specs.items():
        if name not in inputs:
            raise BackendError(
                "input '%s' missing for model '%s' (given: %s)" % (name, model_path, sorted(inputs))
            )
        shape = np.shape(inputs[name])
        if len(shape) != len(spec.shape) or any(
            isinstance(dim, int) and dim != got for dim, got in zip(spec.shape, shape)
        ):
            raise BackendError(
                "input '%s' of model '%s' has shape %s, expected %s"
                % (name, model_path, tuple(shape), tuple(spec.shape))
            )


def normalize_precision(precision: Optional[str]) -> str:
    """Map "fp32"/"FP32"/"float32"/"fp16"/"half" to "fp32" or "fp16".

    Raises:
        ValueError: for anything else.
    """
    value = (precision or "fp32").strip().lower()
    if value in ("fp32", "float32", "float"):
        return "fp32"
    if value in ("fp16", "float16", "half"):
        return "fp16"
    raise ValueError("precision must be 'fp32' or 'fp16', got '%s'" % precision)
