"""Puts this folder on sys.path: its tests share `reference_planner_kernels` (pytest's importlib mode adds
nothing)."""

from __future__ import annotations

import os
import sys

_HERE = os.path.dirname(os.path.abspath(__file__))
if _HERE not in sys.path:
    sys.path.insert(0, _HERE)
