"""The exit codes of the project's command-line tools, one table per family of tools (ROS-free).

Each table is defined here once; the tools return its members (ints: ``sys.exit`` and a shell see
the number). 0 and 2 mean the same in every table (done; a usage error); the other numbers mean
what their table says, so a code is read together with the tool that returned it: 1 is "outputs
changed" from the regression tool but "the graph failed" from the graph runner.
"""
from __future__ import annotations

from enum import IntEnum

__all__ = ["BagToolExit", "GraphRunnerExit"]


class BagToolExit(IntEnum):
    """``python -m leapnbv_bags.bag_io BAG`` (the bag check), ``leapnbv_bringup.replay`` and ``.regression``."""

    #: pass (regression), replayed (replay), readable (the bag check)
    OK = 0
    #: regression: outputs changed (the report names topics, frames and fields) or are missing
    OUTPUTS_CHANGED = 1
    #: a wrong argument, or the golden file is missing or unreadable
    USAGE = 2
    #: the bag cannot be used: one line on stderr names the path and what is wrong
    UNREADABLE_BAG = 3
    #: regression: the graph failed (a node died or never became ready)
    GRAPH_FAILED = 4


class GraphRunnerExit(IntEnum):
    """``python -m leapnbv_bringup.graph_runner``: how the graph it ran ended."""

    #: stopped by SIGINT / SIGTERM and every node exited 0
    OK = 0
    #: a node kept dying (or died with restarts off), or the graph was not ready in time
    GRAPH_FAILED = 1
    #: a wrong argument
    USAGE = 2
    #: stopped, but a node exited non-zero or had to be killed
    UNCLEAN_STOP = 3
