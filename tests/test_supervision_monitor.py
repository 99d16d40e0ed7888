"""The graph monitor's core: starts from /diagnostics writer GIDs, silence from missing statuses."""
from __future__ import annotations

from leapnbv_bringup.graph_monitor import ALIVE, ERROR, NEVER_SEEN, OK, SILENT, WARN, GraphHealth


def values(summary):
    return dict(summary[2])


def test_new_writer_of_a_node_is_a_restart_and_old_ones_count_once():
    health = GraphHealth(["ground_node", "nbv_node"], silence_s=3.0, recent_s=60.0)
    assert health.writers_seen("ground_node", [b"g1"], now=0.0) == []
    assert health.writers_seen("nbv_node", [b"n1"], now=0.0) == []
    health.heard("ground_node", 0.5)
    health.heard("nbv_node", 0.5)
    assert health.summary(1.0)[:2] == (OK, "ok")
    # kill -9: the dead writer stays listed until its DDS lease ends; the respawned node adds one.
    assert health.writers_seen("nbv_node", [b"n1", b"n2"], now=10.0) == ["nbv_node started again: start 2 (1 restarts)"]
    assert health.writers_seen("nbv_node", [b"n2"], now=30.0) == []
    health.heard("ground_node", 10.5)
    health.heard("nbv_node", 10.5)
    level, message, pairs = health.summary(11.0)
    assert (level, message) == (WARN, "nbv_node restarted (1x)")
    assert dict(pairs)["nbv_node.starts"] == "2" and dict(pairs)["nbv_node.restarts"] == "1"
    assert dict(pairs)["nbv_node.last_start_s_ago"] == "1.0"
    assert dict(pairs)["ground_node.restarts"] == "0"
    health.heard("ground_node", 80.0)
    health.heard("nbv_node", 80.0)
    assert health.summary(80.5)[0] == OK  # the restart is older than recent_s
    assert values(health.summary(80.5))["nbv_node.restarts"] == "1"  # but still counted


def test_silent_and_never_seen_nodes_are_errors():
    health = GraphHealth(["hmr_node", "raster_node"], silence_s=3.0)
    health.writers_seen("hmr_node", [b"h1"], now=0.0)
    health.heard("hmr_node", 1.0)
    assert health.state("hmr_node", 3.9) == ALIVE
    assert health.state("hmr_node", 4.1) == SILENT
    assert health.state("raster_node", 4.1) == NEVER_SEEN
    level, message, pairs = health.summary(4.1)
    assert level == ERROR and message == "hmr_node silent; raster_node never seen"
    assert dict(pairs)["raster_node.starts"] == "0" and dict(pairs)["hmr_node.last_heard_s_ago"] == "3.1"


def test_unwatched_nodes_are_ignored():
    health = GraphHealth(["nbv_node"])
    assert health.writers_seen("simulator_node", [b"s1", b"s2"], now=0.0) == []
    health.heard("simulator_node", 0.0)
    assert list(health.nodes) == ["nbv_node"]
