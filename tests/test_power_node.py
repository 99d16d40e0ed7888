"""power_node: per-frame energy on /diagnostics from a fake INA3221 board, and no rails at all."""
from __future__ import annotations

import time
from pathlib import Path

import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from node_harness import diag_value, running_graph, start_node

from leapnbv_bringup.graph import graph_nodes
from leapnbv_common.power_monitor import RAIL_COMPUTE, RAIL_TOTAL, FakeIna3221, power_rails_present
from leapnbv_common.qos import stage_output_qos
from leapnbv_msgs.msg import ViewCandidates

pytestmark = pytest.mark.ros

MODULE = "leapnbv_bringup.nodes.power_node"
LATENCY_S = 0.25  # how old the frames' stamps are when their candidates come out


def test_graph_runs_power_node_only_with_rails(monkeypatch: pytest.MonkeyPatch) -> None:
    def names() -> list:
        return [spec.name for spec in graph_nodes()]

    monkeypatch.delenv("LEAPNBV_POWER_NODE", raising=False)
    assert ("power_node" in names()) == power_rails_present("/sys")
    monkeypatch.setenv("LEAPNBV_POWER_NODE", "1")
    assert names()[-1] == "power_node" and len(names()) == 6
    assert graph_nodes()[-1].module == MODULE
    monkeypatch.setenv("LEAPNBV_POWER_NODE", "off")
    assert "power_node" not in names() and len(names()) == 5


def test_power_node_reports_energy_per_frame(tmp_path: Path) -> None:
    board = FakeIna3221(str(tmp_path / "board"), "hwmon")
    board.set_rail(RAIL_TOTAL, 5000.0, 1200.0)  # 6 W
    board.set_rail(RAIL_COMPUTE, 5000.0, 400.0)  # 2 W
    broken = FakeIna3221(str(tmp_path / "broken"), "iio")
    broken.set_rail(RAIL_COMPUTE, 5000.0, 300.0)
    Path(broken.paths(RAIL_TOTAL)["power"]).write_text("garbage\n")
    procs = {
        "/leapnbv/power_node": start_node(MODULE, str(tmp_path / "power.log"),
                                          params={"sysfs_root": str(tmp_path / "board")}),
        "/leapnbv_norails/power_node": start_node(MODULE, str(tmp_path / "norails.log"), namespace="/leapnbv_norails",
                                                  params={"sysfs_root": str(tmp_path / "empty")}),
        "/leapnbv_broken/power_node": start_node(MODULE, str(tmp_path / "broken.log"), namespace="/leapnbv_broken",
                                                 params={"sysfs_root": str(tmp_path / "broken")}),
    }
    with running_graph("power_probe", procs) as probe:
        assert probe.spin_until(lambda: all(name in probe.statuses for name in procs), 30.0), read_logs(procs)
        publishers = {ns: probe.node.create_publisher(ViewCandidates, ns + "/view_candidates", stage_output_qos())
                      for ns in ("/leapnbv", "/leapnbv_norails", "/leapnbv_broken")}
        probe.spin_until(lambda: all(p.get_subscription_count() > 0 for p in publishers.values()), 10.0)
        for _ in range(3):
            for publisher in publishers.values():
                msg = ViewCandidates()
                msg.header.frame_id = "camera_color_optical_frame"
                msg.header.stamp = probe.node.get_clock().now().to_msg()
                publisher.publish(msg)
            probe.spin_for(LATENCY_S)
        # frames stamped LATENCY_S ago: their windows are at least that long
        for _ in range(3):
            for publisher in publishers.values():
                msg = ViewCandidates()
                stamp_ns = probe.node.get_clock().now().nanoseconds - int(LATENCY_S * 1e9)
                msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 10**9)
                publisher.publish(msg)
            probe.spin_for(0.1)

        def measured(name: str, count: int):
            return probe.status_where(name, lambda s: int(diag_value(s, "frames_measured")) >= count)

        assert probe.spin_until(lambda: measured("/leapnbv/power_node", 6) is not None, 20.0), read_logs(procs)
        assert probe.spin_until(lambda: measured("/leapnbv_broken/power_node", 6) is not None, 20.0)
        assert probe.spin_until(lambda: int(diag_value(probe.statuses["/leapnbv_norails/power_node"][-1],
                                                       "frames_in")) >= 6, 10.0)

        status = measured("/leapnbv/power_node", 6)
        assert status.level == DiagnosticStatus.OK and status.message.startswith("VDD_IN ")
        window_s = float(diag_value(status, "window_ms")) * 1e-3
        assert window_s >= LATENCY_S
        assert float(diag_value(status, "energy_j.VDD_IN")) == pytest.approx(6.0 * window_s, rel=0.01)
        assert float(diag_value(status, "energy_j.VDD_CPU_GPU_CV")) == pytest.approx(2.0 * window_s, rel=0.01)
        assert float(diag_value(status, "mean_power_w.VDD_IN")) == pytest.approx(6.0, rel=0.01)
        assert float(diag_value(status, "sample_rate_hz")) >= 100.0
        assert diag_value(status, "rails") == "VDD_IN, VDD_CPU_GPU_CV"
        per_frame = float(diag_value(status, "energy_j_per_frame.VDD_IN"))
        assert per_frame > 6.0 * 0.9 * LATENCY_S / 2  # 3 young frames, 3 frames LATENCY_S old

        broken_status = measured("/leapnbv_broken/power_node", 6)
        assert diag_value(broken_status, "rails") == "VDD_CPU_GPU_CV"
        assert "VDD_IN: unreadable (ValueError" in diag_value(broken_status, "power_rails", "")
        assert float(diag_value(broken_status, "mean_power_w.VDD_CPU_GPU_CV")) == pytest.approx(1.5, rel=0.01)

        norails = probe.statuses["/leapnbv_norails/power_node"][-1]
        assert norails.level == DiagnosticStatus.OK
        assert norails.message.startswith("no power rails: none of the rails is usable under")
        assert "VDD_IN: not found" in norails.message
        assert diag_value(norails, "frames_measured") == "0"
        assert not any(kv.key.startswith("energy_j") for kv in norails.values)
        for proc in procs.values():
            assert proc.poll() is None


def read_logs(procs: dict) -> str:
    time.sleep(0.2)
    return "\n".join(f"--- {name}\n{open(p.log_path).read()[-1500:]}" for name, p in procs.items())
