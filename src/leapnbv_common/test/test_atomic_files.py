"""Atomic writes: the old file survives a failing writer, and no temporary file is left behind."""
from __future__ import annotations

import os

import pytest

from leapnbv_common.atomic_files import write_bytes_atomically, write_file_atomically


def test_failing_writer_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "sub" / "out.png"
    write_bytes_atomically(str(target), b"good")

    def broken(temporary: str) -> None:
        assert temporary.endswith(".png")  # the extension is kept for format-picking writers
        with open(temporary, "wb") as stream:
            stream.write(b"half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        write_file_atomically(str(target), broken)
    assert target.read_bytes() == b"good"
    assert os.listdir(target.parent) == ["out.png"]
    assert oct(target.stat().st_mode & 0o777) == oct(0o644)
