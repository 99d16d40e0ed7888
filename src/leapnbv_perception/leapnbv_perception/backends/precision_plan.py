"""The FP16 precision plan: which layers of a TensorRT FP16 engine stay in FP32.

An FP16 engine of a ViT loses accuracy in a few places (LayerNorm reductions, softmax, the
last blocks); the FP16 check (a later tool) compares FP16 and FP32 layer by layer and writes
the layers to keep in FP32 into a plan file. The TensorRT backend reads it when it builds an
FP16 engine and pins those layers to FP32.

File format (JSON, version 1)::

    {
      "version": 1,
      "keep_fp32": [
        "/encoder/blocks.11/norm1/*",
        "/encoder/blocks.11/attn/Softmax",
        "/head/*"
      ],
      "model_sha256": "<sha256 of the ONNX the plan was made for>",   (optional)
      "tool": "fp16_check 0.1",                                        (optional, free text)
      "notes": "..."                                                   (optional, free text)
    }

- ``keep_fp32``: layer names. An entry with a glob character (``*``, ``?``, ``[``) is an
  `fnmatch` pattern, any other entry an exact name. TensorRT's ONNX parser names each layer
  after its ONNX node (``/encoder/blocks.11/norm1/ReduceMean``); an ONNX op that the parser
  decomposes into several layers (LayerNormalization on TensorRT 8.5) gives layers whose names
  start with the node's name, so ``"<node name>*"`` covers them.
- Every entry must match at least one layer: an entry that matches nothing means the plan was
  made for another export, and building the engine would silently drop the guard, so the
  build fails with the unmatched entries named.
- Layers whose outputs are not floating point (shape arithmetic, int32 indices, booleans)
  cannot run in FP32 and are skipped (logged).
- Unknown keys are ignored (later versions of the tool may add information).

The plan's digest (over the version and the sorted entries, not the file's bytes) is part of
the engine cache key of an FP16 engine, so a changed plan builds a new engine and reformatting
the file does not.
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import os
from dataclasses import dataclass
from typing import Any, List, Optional, Sequence, Tuple

PLAN_VERSION = 1
_GLOB_CHARS = set("*?[")


class PrecisionPlanError(ValueError):
    """The plan file is missing, not JSON, of another version, or does not fit the model."""


@dataclass(frozen=True)
class PrecisionPlan:
    """A parsed plan.

    Attributes:
        keep_fp32: layer names and patterns, in file order (duplicates removed).
        path: the file it came from ("" when built in code).
        model_sha256: sha256 of the ONNX it was made for ("" when the file does not say).
    """

    keep_fp32: Tuple[str, ...]
    path: str = ""
    model_sha256: str = ""

    @property
    def digest(self) -> str:
        """sha256 over the version and the sorted entries: what the engine depends on."""
        text = json.dumps({"version": PLAN_VERSION, "keep_fp32": sorted(self.keep_fp32)}, sort_keys=True)
        return hashlib.sha256(text.encode("utf-8")).hexdigest()

    def matches(self, layer_name: str) -> bool:
        """True when some entry names this layer."""
        return any(_entry_matches(entry, layer_name) for entry in self.keep_fp32)

    def select(self, layer_names: Sequence[str]) -> Tuple[List[str], List[str]]:
        """(layers the plan names, in network order; entries that matched no layer)."""
        selected = [name for name in layer_names if self.matches(name)]
        unmatched = [entry for entry in self.keep_fp32 if not any(_entry_matches(entry, n) for n in layer_names)]
        return selected, unmatched


def _entry_matches(entry: str, layer_name: str) -> bool:
    if _GLOB_CHARS.intersection(entry):
        return fnmatch.fnmatchcase(layer_name, entry)
    return layer_name == entry


def parse_precision_plan(data: Any, path: str = "") -> PrecisionPlan:
    """Check a decoded plan object and return it as a PrecisionPlan.

    Raises:
        PrecisionPlanError: naming the file and the field at fault.
    """
    where = "precision plan '%s'" % path if path else "precision plan"
    if not isinstance(data, dict):
        raise PrecisionPlanError("%s: expected a JSON object, got %s" % (where, type(data).__name__))
    version = data.get("version")
    if version != PLAN_VERSION:
        raise PrecisionPlanError("%s: version %r is not supported (this code reads version %d)"
                                 % (where, version, PLAN_VERSION))
    entries = data.get("keep_fp32")
    if not isinstance(entries, list) or not all(isinstance(e, str) and e.strip() for e in entries):
        raise PrecisionPlanError("%s: 'keep_fp32' must be a list of non-empty layer names or patterns" % where)
    model_sha256 = data.get("model_sha256", "")
    if not isinstance(model_sha256, str):
        raise PrecisionPlanError("%s: 'model_sha256' must be a string" % where)
    unique: List[str] = []
    for entry in entries:
        if entry.strip() not in unique:
            unique.append(entry.strip())
    return PrecisionPlan(tuple(unique), path, model_sha256.strip().lower())


def load_precision_plan(path: Optional[str]) -> Optional[PrecisionPlan]:
    """Read a plan file; None for an empty path.

    Raises:
        PrecisionPlanError: when the file is missing or invalid (the message names it).
    """
    if not path:
        return None
    if not os.path.isfile(path):
        raise PrecisionPlanError("precision plan not found: '%s' (absolute: '%s')" % (path, os.path.abspath(path)))
    try:
        with open(path, encoding="utf-8") as stream:
            data = json.load(stream)
    except (OSError, ValueError) as error:
        raise PrecisionPlanError("precision plan '%s' is not readable JSON: %s" % (path, error)) from error
    return parse_precision_plan(data, path)


def write_precision_plan(path: str, keep_fp32: Sequence[str], model_sha256: str = "", **extra: Any) -> str:
    """Write a version-1 plan (what the FP16 check calls; tests use it too)."""
    from leapnbv_common.atomic_files import write_file_atomically

    document = {"version": PLAN_VERSION, "keep_fp32": list(keep_fp32)}
    if model_sha256:
        document["model_sha256"] = model_sha256
    document.update(extra)

    def write(temporary: str) -> None:
        with open(temporary, "w", encoding="utf-8") as stream:
            json.dump(document, stream, indent=2)
            stream.write("\n")

    return write_file_atomically(path, write)
