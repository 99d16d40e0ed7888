"""The exit codes of ``python -m leapnbv_model_tools ...`` (one table for the model tools).

0 and 2 mean what they mean in every table of the project (``leapnbv_common.exit_codes``: done; a
usage error); here 2 is also every input that cannot be used (one line on stderr naming the file).
"""

from __future__ import annotations

from enum import IntEnum

__all__ = ["ModelToolExit"]


class ModelToolExit(IntEnum):
    """export-hmr, distill, fp16-check, quantize-int8 and the other subcommands."""

    #: done, every check passed
    OK = 0
    #: a check of the result failed (the tool's last line says which): export-hmr's parity check (nothing is
    #: written at --out), distill's export parity, fp16-check's guarded model over --max-error (written)
    CHECK_FAILED = 1
    #: a wrong argument, or an input that cannot be used (missing, truncated, not a checkpoint / ONNX model,
    #: another variant): one line on stderr names the file
    BAD_INPUT = 2
