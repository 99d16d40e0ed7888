"""The detector families by name: the ``detector_family`` parameter picks one.

A new output layout is one module defining ``FAMILY`` (a :class:`DetectorFamily`) plus one line
in :data:`DETECTOR_FAMILY_MODULES`; :func:`register_detector_family` adds one at runtime
(a plug-in, or a test) without touching this file. The families are a
:class:`leapnbv_common.registry.Registry` (:data:`DETECTOR_FAMILIES`), the pattern of every plug-in seam.
"""
from __future__ import annotations

from typing import Dict, List

from leapnbv_common.registry import Registry
from leapnbv_perception.detector_families.base import DEFAULT_MAX_DETECTIONS, DetectorFamily, nms

# detector_family parameter value -> the module that defines FAMILY (imported on first use).
DETECTOR_FAMILY_MODULES: Dict[str, str] = {
    "yolov8": "leapnbv_perception.detector_families.yolov8",
}
DEFAULT_DETECTOR_FAMILY = "yolov8"


def _check_family(family: object) -> None:
    if not isinstance(family, DetectorFamily) or not family.name:
        raise TypeError(f"a detector family must be a named DetectorFamily, got {family!r}")


def family_registry() -> Registry[DetectorFamily]:
    """A registry of the built-in families only (the module's own, or an empty one for a test)."""
    return Registry("detector family", modules=DETECTOR_FAMILY_MODULES, attribute="FAMILY", check=_check_family)


DETECTOR_FAMILIES: Registry[DetectorFamily] = family_registry()


def register_detector_family(family: DetectorFamily) -> None:
    """Make ``family`` selectable by its name (replacing a family of the same name).

    Raises:
        TypeError: not a named DetectorFamily.
    """
    _check_family(family)
    DETECTOR_FAMILIES.register(family.name, family, replace=True)


def detector_family_names() -> List[str]:
    """Every selectable family name, sorted."""
    return DETECTOR_FAMILIES.names()


def get_detector_family(name: str) -> DetectorFamily:
    """The family called ``name``.

    Raises:
        ValueError: an unknown name (the message lists the known ones).
    """
    return DETECTOR_FAMILIES.get(name)


__all__ = [
    "DEFAULT_MAX_DETECTIONS",
    "DEFAULT_DETECTOR_FAMILY",
    "DETECTOR_FAMILIES",
    "DETECTOR_FAMILY_MODULES",
    "DetectorFamily",
    "detector_family_names",
    "family_registry",
    "get_detector_family",
    "nms",
    "register_detector_family",
]
