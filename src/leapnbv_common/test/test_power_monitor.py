"""Tests for the power monitor: rails found in both sysfs layouts, energy of a known power curve."""
from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import List

import numpy as np
import pytest

from leapnbv_common.power_monitor import (
    RAIL_COMPUTE,
    RAIL_TOTAL,
    FakeIna3221,
    PowerMonitor,
    PowerParams,
    PowerRailError,
    discover_rails,
    integrate_power,
    measure_energy,
    open_rails,
    power_rails_present,
    start_power_monitor,
)


@pytest.mark.parametrize("layout", ["hwmon", "iio"])
def test_rails_are_found_by_label_in_both_layouts(tmp_path: Path, layout: str) -> None:
    board = FakeIna3221(str(tmp_path), layout, hwmon_index=5)
    board.set_rail(RAIL_TOTAL, 5080.0, 1240.0)
    board.set_rail(RAIL_COMPUTE, 5070.0, 410.0)
    rails = discover_rails(str(tmp_path))
    assert sorted(rails) == ["VDD_CPU_GPU_CV", "VDD_IN", "VDD_SOC"]  # no "sum of shunt voltages"
    assert {rail.layout for rail in rails.values()} == {layout}
    assert rails[RAIL_TOTAL].read_power_w() == pytest.approx(5.080 * 1.240, rel=1e-3)
    assert rails[RAIL_COMPUTE].read_power_w() == pytest.approx(5.070 * 0.410, rel=1e-3)
    if layout == "iio":
        assert rails[RAIL_TOTAL].power_path.endswith("in_power0_input")  # the mW file, not V x I
    else:
        assert "/hwmon5/" in rails[RAIL_TOTAL].voltage_path and rails[RAIL_TOTAL].current_path.endswith("curr1_input")


def test_hwmon_number_and_channel_order_do_not_matter(tmp_path: Path) -> None:
    FakeIna3221(str(tmp_path), "hwmon", channels=("VDD_SOC", RAIL_COMPUTE, RAIL_TOTAL), hwmon_index=1)
    board_rails = discover_rails(str(tmp_path))
    assert board_rails[RAIL_TOTAL].voltage_path.endswith("hwmon1/in3_input")
    usable, notes = open_rails(str(tmp_path))
    assert list(usable) == [RAIL_TOTAL, RAIL_COMPUTE] and notes == []


def test_missing_rails_give_a_clear_message(tmp_path: Path) -> None:
    with pytest.raises(PowerRailError) as error:
        open_rails(str(tmp_path))
    message = str(error.value)
    assert str(tmp_path / "bus" / "i2c" / "devices") in message
    assert "VDD_IN: not found" in message and "no INA3221 rails at all" in message
    monitor, text = start_power_monitor(PowerParams(sysfs_root=str(tmp_path)))
    assert monitor is None and text.startswith("no power rails:")
    assert not power_rails_present(str(tmp_path))
    assert not power_rails_present(str(tmp_path / "does" / "not" / "exist"))
    FakeIna3221(str(tmp_path), "hwmon", channels=("VDD_SOC",))
    with pytest.raises(PowerRailError, match="present: VDD_SOC"):
        open_rails(str(tmp_path))


def test_unreadable_rails_are_left_out_with_the_reason(tmp_path: Path) -> None:
    board = FakeIna3221(str(tmp_path), "hwmon")
    board.set_rail(RAIL_COMPUTE, 5000.0, 300.0)
    Path(board.paths(RAIL_TOTAL)["current"]).write_text("not a number\n")
    usable, notes = open_rails(str(tmp_path))
    assert list(usable) == [RAIL_COMPUTE]
    assert len(notes) == 1 and notes[0].startswith("VDD_IN: unreadable (ValueError")
    monitor, text = start_power_monitor(PowerParams(sysfs_root=str(tmp_path)))
    try:
        assert monitor is not None and "sampling VDD_CPU_GPU_CV" in text and "VDD_IN: unreadable" in text
    finally:
        monitor.stop()
    current = board.paths(RAIL_COMPUTE)["current"]
    os.remove(current)
    os.mkdir(current)  # reading a folder fails like an I2C read error (EIO) would
    with pytest.raises(PowerRailError, match=r"VDD_IN: unreadable.*VDD_CPU_GPU_CV: unreadable \(IsADirectoryError"):
        open_rails(str(tmp_path))


def test_integration_of_exact_samples() -> None:
    times = np.array([0.0, 1.0, 2.0, 3.0])
    powers = np.array([2.0, 4.0, 4.0, 0.0])
    assert integrate_power(times, powers, 0.0, 3.0) == pytest.approx(3.0 + 4.0 + 2.0)
    assert integrate_power(times, powers, 0.5, 1.5) == pytest.approx(0.5 * 3.5 + 0.5 * 4.0)  # ends interpolated
    assert integrate_power(times, powers, 2.5, 2.5) == 0.0
    assert integrate_power(times, powers, -1.0, 0.0) == pytest.approx(2.0)  # edge power held outside
    # Irregular sampling: 1000 samples at 10 W in the first second, 11 at 0 W in the next: time-weighted
    # the window holds ~10 J (a mean of the samples times the window would say ~19.8 J).
    dense = np.concatenate((np.arange(1000) * 0.001, 1.0 + np.arange(11) * 0.1))
    level = np.where(dense < 1.0, 10.0, 0.0)
    assert integrate_power(dense, level, 0.0, 2.0) == pytest.approx(9.99 + 0.005)


class ListClockRail:
    """A rail whose power is a function of an injected clock (deterministic sampling)."""

    def __init__(self, clock: List[float], fn) -> None:
        self.clock, self.fn = clock, fn

    def read_power_w(self) -> float:
        return self.fn(self.clock[0])


def test_energy_of_a_frame_window_on_a_manual_clock() -> None:
    now = [0.0]
    rails = {RAIL_TOTAL: ListClockRail(now, lambda t: 5.0 + t), RAIL_COMPUTE: ListClockRail(now, lambda t: 2.0)}
    monitor = PowerMonitor(rails, rate_hz=100.0, clock=lambda: now[0])
    for step in range(301):  # 0 .. 3 s at 100 Hz
        now[0] = step / 100.0
        assert monitor.sample()
    frame = monitor.energy(1.005, 2.505)
    assert frame.complete and frame.samples == 150
    assert frame.energy_j[RAIL_TOTAL] == pytest.approx(5.0 * 1.5 + (2.505 ** 2 - 1.005 ** 2) / 2, rel=1e-9)
    assert frame.energy_j[RAIL_COMPUTE] == pytest.approx(3.0, rel=1e-9)
    assert frame.mean_power_w[RAIL_COMPUTE] == pytest.approx(2.0)
    assert not monitor.energy(2.9, 3.5).complete  # reaches past the newest sample
    assert monitor.energy(10.0, 11.0) is None and monitor.energy(-5.0, -4.0) is None


def test_sampling_rate_is_at_least_100_hz() -> None:
    rails = {RAIL_TOTAL: ListClockRail([0.0], lambda t: 1.0)}
    with pytest.raises(ValueError, match="at least 100"):
        PowerMonitor(rails, rate_hz=50.0)
    with PowerMonitor(rails, rate_hz=200.0) as monitor:
        time.sleep(0.6)
    assert monitor.achieved_rate_hz() >= 100.0, monitor.achieved_rate_hz()


CURVE_PERIOD_S = 2.0
# A separate process moves VDD_IN along P(t) = 5 + 2 sin(2 pi t / period) W at 5 V (wall clock), as
# fast as it can: no GIL shared with the sampler, so the files lag the curve by the OS's scheduling only.
WRITER = """
import math, os, sys, time
current, ready = sys.argv[1], sys.argv[2]
def put(path, text):
    with open(path + '.tmp', 'w') as stream:
        stream.write(text)
    os.replace(path + '.tmp', path)
while True:
    watts = 5.0 + 2.0 * math.sin(2.0 * math.pi * time.time() / %r)
    put(current, '%%d\\n' %% round(watts * 200.0))
    if ready and not os.path.exists(ready):
        put(ready, 'ok')
    time.sleep(0.0002)
""" % CURVE_PERIOD_S


def curve_energy(t0: float, t1: float) -> float:
    w = 2.0 * math.pi / CURVE_PERIOD_S
    return 5.0 * (t1 - t0) - 2.0 / w * (math.cos(w * t1) - math.cos(w * t0))


@pytest.mark.parametrize("layout", ["hwmon", "iio"])
def test_energy_of_a_known_power_curve_within_one_percent(tmp_path: Path, layout: str) -> None:
    board = FakeIna3221(str(tmp_path / "sys"), layout)
    board.set_rail(RAIL_TOTAL, 5000.0, 1000.0)
    board.set_rail(RAIL_COMPUTE, 5000.0, 500.0)
    if layout == "iio":  # no in_power file: the monitor multiplies volts and amps, as on boards without it
        os.remove(board.paths(RAIL_TOTAL)["power"])
    ready = tmp_path / "writer_ready"
    writer = subprocess.Popen([sys.executable, "-c", WRITER, board.paths(RAIL_TOTAL)["current"], str(ready)])
    try:
        deadline = time.time() + 10.0
        while not ready.exists() and time.time() < deadline:
            time.sleep(0.01)
        monitor, message = start_power_monitor(PowerParams(sysfs_root=str(tmp_path / "sys"), rate_hz=200.0))
        assert monitor is not None, message
        assert "VDD_IN, VDD_CPU_GPU_CV at 200 Hz (%s)" % layout in message
        start = time.time()
        time.sleep(1.6)
        windows = [(start + 0.1, start + 0.6), (start + 0.5, start + 1.3), (start + 0.05, start + 1.5)]
        deadline = time.time() + 2.0
        while monitor.latest_time() < windows[-1][1] and time.time() < deadline:
            time.sleep(0.01)
        monitor.stop()
    finally:
        writer.kill()
        writer.wait()
    for t0, t1 in windows:
        frame = monitor.energy(t0, t1)
        expected = curve_energy(t0, t1)
        assert frame.complete and frame.samples > 20
        assert frame.energy_j[RAIL_TOTAL] == pytest.approx(expected, rel=0.01), (t0 - start, t1 - start)
        assert frame.energy_j[RAIL_COMPUTE] == pytest.approx(2.5 * (t1 - t0), rel=0.01)
        assert frame.mean_power_w[RAIL_TOTAL] == pytest.approx(expected / (t1 - t0), rel=0.01)
    # the curve is not flat over these windows: a constant 5 W would miss by more than the tolerance
    assert max(abs(curve_energy(t0, t1) / (5.0 * (t1 - t0)) - 1.0) for t0, t1 in windows) > 0.05


def test_a_rail_that_breaks_while_sampling_is_counted_not_fatal(tmp_path: Path) -> None:
    board = FakeIna3221(str(tmp_path), "hwmon")
    board.set_rail(RAIL_TOTAL, 5000.0, 1000.0)
    monitor, _ = start_power_monitor(PowerParams(sysfs_root=str(tmp_path), rate_hz=200.0))
    time.sleep(0.2)
    shutil.rmtree(board.folder)  # the driver went away
    time.sleep(0.1)
    monitor.stop()
    assert monitor.read_errors > 0 and "FileNotFoundError" in monitor.last_error
    t_last = monitor.latest_time()
    frame = monitor.energy(t_last - 0.1, t_last)
    assert frame.complete and frame.energy_j[RAIL_TOTAL] == pytest.approx(0.5, rel=1e-6)


def test_measure_energy_of_a_call() -> None:
    now = time.time
    rails = {RAIL_TOTAL: ListClockRail([0.0], lambda t: 3.0)}
    with PowerMonitor(rails, rate_hz=200.0, clock=now) as monitor:
        time.sleep(0.05)
        result, frame = measure_energy(lambda: time.sleep(0.2) or "done", monitor)
    assert result == "done" and frame.complete
    assert frame.energy_j[RAIL_TOTAL] == pytest.approx(3.0 * frame.window_s, rel=1e-6)
    assert frame.window_s == pytest.approx(0.2, abs=0.05)
    assert measure_energy(lambda: 7, None) == (7, None)
