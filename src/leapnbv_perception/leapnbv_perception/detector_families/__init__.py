"""The detector families by name: the ``detector_family`` parameter picks one.

A new output layout is one module defining ``FAMILY`` (a :class:`DetectorFamily`) plus one line
in :data:`DETECTOR_FAMILY_MODULES`; :func:`register_detector_family` adds one at runtime
(a plug-in, or a test) without touching this file.
"""
from __future__ import annotations

import importlib
from typing import Dict, List

from leapnbv_perception.detector_families.base import DEFAULT_MAX_DETECTIONS, DetectorFamily, nms

# detector_family parameter value -> the module that defines FAMILY (imported on first use).
DETECTOR_FAMILY_MODULES: Dict[str, str] = {
    "yolov8": "leapnbv_perception.detector_families.yolov8",
}
DEFAULT_DETECTOR_FAMILY = "yolov8"

_registered: Dict[str, DetectorFamily] = {}


def register_detector_family(family: DetectorFamily) -> None:
    """Make ``family`` selectable by its name (replacing a family of the same name)."""
    if not isinstance(family, DetectorFamily) or not family.name:
        raise TypeError(f"a detector family must be a named DetectorFamily, got {family!r}")
    _registered[family.name] = family


def detector_family_names() -> List[str]:
    """Every selectable family name, sorted."""
    return sorted(set(DETECTOR_FAMILY_MODULES) | set(_registered))


def get_detector_family(name: str) -> DetectorFamily:
    """The family called ``name``.

    Raises:
        ValueError: an unknown name (the message lists the known ones).
    """
    if name in _registered:
        return _registered[name]
    if name not in DETECTOR_FAMILY_MODULES:
        raise ValueError(f"unknown detector family {name!r}; known: {', '.join(detector_family_names())}")
    return importlib.import_module(DETECTOR_FAMILY_MODULES[name]).FAMILY


__all__ = [
    "DEFAULT_MAX_DETECTIONS",
    "DEFAULT_DETECTOR_FAMILY",
    "DETECTOR_FAMILY_MODULES",
    "DetectorFamily",
    "detector_family_names",
    "get_detector_family",
    "nms",
    "register_detector_family",
]
