"""The closed loop with the learned HMR engine in FP32 and INT8 (scripts/experiments/int8_closed_loop.sh).

Reads OUT/fp32/run.json and OUT/int8/run.json and prints, for leap_nbv, random and oracle with each engine:
scenes, success (%), surface coverage before -> after (%), person area before -> after (k px) and the graph
mesh's PA-MPVPE before -> after (mm), and the graph failures.
Usage: scripts/env.sh python scripts/experiments/int8_closed_loop_table.py OUT
Exit 0; 2 when a run is missing.
"""
from __future__ import annotations

import os
import sys
from typing import List

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from learned_perception_table import print_table  # noqa: E402


def main(argv: List[str]) -> int:
    """Print the table; returns the exit code."""
    if len(argv) != 1:
        print("usage: int8_closed_loop_table.py OUT", file=sys.stderr)
        return 2
    return print_table(argv[0], ("fp32", "int8"), "HMR engine", "int8_closed_loop_table",
                       lambda variant, run: variant.upper(), missing_error=None)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
