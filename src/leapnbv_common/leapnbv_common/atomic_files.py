"""Atomic file writes: a half-written output never replaces a good one (ROS-free)."""
from __future__ import annotations

import os
import tempfile
from typing import Callable


def write_file_atomically(path: str, write_to: Callable[[str], None]) -> str:
    """Write a file through a temporary sibling, then rename it over `path`.

    The rename is atomic on POSIX, so a reader never sees a half-written file, and a failing
    writer leaves the previous file at `path` untouched (the temporary file is removed).

    Args:
        path: Destination file (its folder is created if missing).
        write_to: Called with the temporary path; must create the file there. The temporary
            path keeps `path`'s extension, so writers that pick a format by it (cv2.imwrite) work.

    Returns:
        `path`.

    Raises:
        Whatever `write_to` raises.
    """
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    base, extension = os.path.splitext(os.path.basename(path))
    handle, temporary = tempfile.mkstemp(prefix=f".{base}.", suffix=f".tmp{extension}", dir=folder)
    os.close(handle)
    try:
        write_to(temporary)
        os.chmod(temporary, 0o644)  # mkstemp makes 0600; outputs are shared artefacts
        os.replace(temporary, path)
    except BaseException:
        if os.path.exists(temporary):
            os.remove(temporary)
        raise
    return path


def write_bytes_atomically(path: str, data: bytes) -> str:
    """Write `data` to `path` atomically (see write_file_atomically)."""

    def write(temporary: str) -> None:
        with open(temporary, "wb") as stream:
            stream.write(data)

    return write_file_atomically(path, write)
