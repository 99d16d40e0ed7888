"""What every report writer shares: atomic file writes (text, JSON, PNG, figures) and Agg figures.

Every file is written atomically: a failed write leaves the previous file intact.
"""
from __future__ import annotations

import json
import math
from typing import Any, Mapping, Tuple

import cv2
import numpy as np

from leapnbv_common.array_types import UInt8Array
from leapnbv_common.atomic_files import write_file_atomically


class ReportError(ValueError):
    """An input to the report writers is malformed (names the field and shape at fault)."""


# ---------------------------------------------------------------------------------------------
# Atomic file writing
# ---------------------------------------------------------------------------------------------


def write_text_atomically(path: str, text: str) -> str:
    def write(temporary: str) -> None:
        with open(temporary, "w", encoding="utf-8") as stream:
            stream.write(text)

    return write_file_atomically(path, write)


def write_json_atomically(path: str, payload: Any) -> str:
    return write_text_atomically(path, json.dumps(to_plain(payload), indent=2, allow_nan=False) + "\n")


def write_rgb_png_atomically(path: str, rgb: UInt8Array) -> str:
    bgr = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR)

    def write(temporary: str) -> None:
        if not cv2.imwrite(temporary, bgr):
            raise ReportError(f"cv2.imwrite could not write {path}")

    return write_file_atomically(path, write)


def save_figure_atomically(figure: Any, path: str) -> str:
    return write_file_atomically(path, lambda temporary: figure.savefig(temporary, format="png", dpi=110))


def to_plain(value: Any) -> Any:
    """numpy scalars/arrays, tuples and NaN/inf -> plain JSON types (non-finite floats -> None)."""
    if isinstance(value, Mapping):
        return {str(key): to_plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_plain(item) for item in value]
    if isinstance(value, np.ndarray):
        return [to_plain(item) for item in value.tolist()]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        number = float(value)
        return number if math.isfinite(number) else None
    if value is None or isinstance(value, str):
        return value
    return str(value)


def new_figure(size_in: Tuple[float, float]) -> Any:
    """A pyplot-free Agg figure: no global figure registry to leak, safe off the main thread.

    matplotlib is imported here, on the first plot: it takes about a second to import, and the
    tables and the demo's text need none of it.
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=size_in)
    FigureCanvasAgg(figure)
    return figure
