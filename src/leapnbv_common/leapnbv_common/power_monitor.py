"""Energy per frame from the Jetson's INA3221 power rails (ROS-free).

The Xavier NX carries one INA3221 (I2C address 0x40) with three channels: VDD_IN (the module's
whole input), VDD_CPU_GPU_CV (CPU, GPU and the CV accelerators: the compute rail) and VDD_SOC.
Two kernel layouts expose it:

- JetPack 5 (L4T r34/r35, hwmon): ``bus/i2c/devices/<bus>-0040/hwmon/hwmon<N>/`` with
  ``in<K>_label`` (the rail's name), ``in<K>_input`` (bus voltage, mV) and ``curr<K>_input``
  (current, mA); power = mV x mA / 1000 mW. The hwmon number varies from boot to boot, so rails
  are found by label. Channel 7 ("sum of shunt voltages") and labels containing "NC" (not
  connected) are skipped; ``curr<K>_crit`` / ``curr<K>_max`` are limits, not readings.
- JetPack 4 (L4T r32, iio): ``bus/i2c/devices/<bus>-0040/iio:device<N>/`` with
  ``rail_name_<K>`` and ``in_power<K>_input`` (mW), else ``in_voltage<K>_input`` (mV) x
  ``in_current<K>_input`` (mA).

`PowerMonitor` samples the chosen rails in a thread (default 200 Hz, at least 100 Hz) on the
wall clock (the clock ROS stamps camera frames with) and keeps a few seconds of history;
`PowerMonitor.energy(t0, t1)` integrates each rail's power over a frame's window (from the
frame's stamp to the moment its goal came out) with the trapezoid rule on the samples,
interpolated at the window's ends: time-weighted, so irregular sampling does not bias it.

Everything takes a ``sysfs_root`` (default "/sys"), so tests run on a fake tree.
"""
from __future__ import annotations

import collections
import glob
import logging
import os
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Deque, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from leapnbv_common.array_types import FloatArray
from leapnbv_common.params import param

LOGGER = logging.getLogger(__name__)

RAIL_TOTAL = "VDD_IN"
RAIL_COMPUTE = "VDD_CPU_GPU_CV"
DEFAULT_RAILS = (RAIL_TOTAL, RAIL_COMPUTE)
MIN_RATE_HZ = 100.0
SHUNT_SUM_CHANNEL = 7


class PowerRailError(RuntimeError):
    """No usable rail: none found, or every one unreadable (the message says which and where)."""


@dataclass
class PowerParams:
    """power_node: energy and mean power of each frame from the board's power rails."""

    sysfs_root: str = param("/sys", "root of the sysfs tree the INA3221 rails are read from", read_only=True)
    rails: List[str] = param(list(DEFAULT_RAILS), "rail labels to integrate (the first is the per-frame total)",
                             read_only=True)
    rate_hz: float = param(200.0, "Hz: rail sampling rate", min=MIN_RATE_HZ, max=2000.0, read_only=True)
    history_s: float = param(30.0, "s: samples kept; a frame older than this gets no energy", min=1.0, max=600.0,
                             read_only=True)


@dataclass(frozen=True)
class Rail:
    """One INA3221 channel.

    Attributes:
        name: its label (``VDD_IN``).
        layout: "hwmon" (JetPack 5) or "iio" (JetPack 4).
        voltage_path, current_path: mV and mA files ("" when absent).
        power_path: mW file (iio only; "" when absent).
    """

    name: str
    layout: str
    voltage_path: str = ""
    current_path: str = ""
    power_path: str = ""

    def read_power_w(self) -> float:
        """The rail's power now, in watts.

        Raises:
            OSError, ValueError: when a file cannot be read or parsed.
        """
        if self.power_path:
            return _read_number(self.power_path) * 1e-3
        return _read_number(self.voltage_path) * _read_number(self.current_path) * 1e-6


def _read_number(path: str) -> float:
    with open(path, "rb") as stream:
        text = stream.read(64)
    return float(text.split()[0])


def _read_text(path: str) -> str:
    try:
        with open(path, encoding="utf-8", errors="replace") as stream:
            return stream.read().strip()
    except OSError:
        return ""


def _ina3221_device_dirs(sysfs_root: str) -> List[str]:
    """Folders of INA3221 I2C devices (JetPack 5 names them ina3221, JetPack 4 ina3221x)."""
    found = []
    patterns = [os.path.join(sysfs_root, "bus", "i2c", "devices", "*"),
                os.path.join(sysfs_root, "bus", "i2c", "drivers", "ina3221*", "*-*")]
    seen = set()
    for pattern in patterns:
        for path in sorted(glob.glob(pattern)):
            real = os.path.realpath(path)
            if real in seen or not os.path.isdir(path):
                continue
            name = _read_text(os.path.join(path, "name"))
            if "ina3221" in name or "/drivers/ina3221" in path:
                seen.add(real)
                found.append(path)
    return found


def _hwmon_rails(folder: str) -> List[Rail]:
    rails = []
    for label_path in sorted(glob.glob(os.path.join(folder, "in*_label"))):
        channel = os.path.basename(label_path)[2:-len("_label")]
        if not channel.isdigit() or int(channel) == SHUNT_SUM_CHANNEL:
            continue
        label = _read_text(label_path)
        if not label or "NC" in label.split() or label.upper() == "NC" or "sum of shunt" in label.lower():
            continue
        voltage = os.path.join(folder, "in%s_input" % channel)
        current = os.path.join(folder, "curr%s_input" % channel)
        if os.path.exists(voltage) and os.path.exists(current):
            rails.append(Rail(label, "hwmon", voltage_path=voltage, current_path=current))
    return rails


def _iio_rails(folder: str) -> List[Rail]:
    rails = []
    for name_path in sorted(glob.glob(os.path.join(folder, "rail_name_*"))):
        channel = os.path.basename(name_path)[len("rail_name_"):]
        label = _read_text(name_path)
        if not channel.isdigit() or not label:
            continue
        power = os.path.join(folder, "in_power%s_input" % channel)
        voltage = os.path.join(folder, "in_voltage%s_input" % channel)
        current = os.path.join(folder, "in_current%s_input" % channel)
        if os.path.exists(power):
            rails.append(Rail(label, "iio", power_path=power))
        elif os.path.exists(voltage) and os.path.exists(current):
            rails.append(Rail(label, "iio", voltage_path=voltage, current_path=current))
    return rails


def discover_rails(sysfs_root: str = "/sys") -> Dict[str, Rail]:
    """Every INA3221 rail under the sysfs root, by label (JetPack 5 hwmon and JetPack 4 iio layouts)."""
    rails: Dict[str, Rail] = {}
    for device in _ina3221_device_dirs(sysfs_root):
        for folder in sorted(glob.glob(os.path.join(device, "hwmon", "hwmon*"))):
            for rail in _hwmon_rails(folder):
                rails.setdefault(rail.name, rail)
        for folder in sorted(glob.glob(os.path.join(device, "iio:device*"))):
            for rail in _iio_rails(folder):
                rails.setdefault(rail.name, rail)
    return rails


def open_rails(sysfs_root: str = "/sys", wanted: Sequence[str] = DEFAULT_RAILS) -> Tuple[Dict[str, Rail], List[str]]:
    """The wanted rails that exist and read, and one note per wanted rail that does not.

    Returns:
        (name -> Rail in the order of `wanted`, notes such as "VDD_CPU_GPU_CV: not found").

    Raises:
        PowerRailError: when no wanted rail is usable; the message names the root, the rails
            that exist and why each wanted one was not taken.
    """
    found = discover_rails(sysfs_root)
    usable: Dict[str, Rail] = {}
    notes: List[str] = []
    for name in wanted:
        rail = found.get(name)
        if rail is None:
            notes.append("%s: not found" % name)
            continue
        try:
            rail.read_power_w()
        except (OSError, ValueError) as error:
            notes.append("%s: unreadable (%s: %s)" % (name, type(error).__name__, error))
            continue
        usable[name] = rail
    if not usable:
        where = os.path.join(sysfs_root, "bus", "i2c", "devices")
        present = ", ".join(sorted(found)) if found else "no INA3221 rails at all"
        raise PowerRailError("none of the rails is usable under %s (%s; present: %s)"
                             % (where, "; ".join(notes), present))
    return usable, notes


@dataclass
class FrameEnergy:
    """Energy of one frame's window.

    Attributes:
        window_s: t1 - t0.
        energy_j: rail -> joules over the window.
        mean_power_w: rail -> energy / window.
        samples: samples inside the window.
        complete: False when the samples do not reach the window's ends within `max_gap_s` (the
            numbers then hold the nearest sample's power over the uncovered part).
    """

    window_s: float
    energy_j: Dict[str, float] = field(default_factory=dict)
    mean_power_w: Dict[str, float] = field(default_factory=dict)
    samples: int = 0
    complete: bool = True


def integrate_power(times: FloatArray, powers: FloatArray, t0: float, t1: float) -> float:
    """Integral of a sampled power over [t0, t1] (joules for watts and seconds).

    Trapezoids on the samples, linear interpolation at the ends, the edge sample's power held
    outside the sampled span.
    """
    if t1 <= t0 or len(times) == 0:
        return 0.0
    inside = (times > t0) & (times < t1)
    knots = np.concatenate(([t0], times[inside], [t1]))
    values = np.interp(knots, times, powers)  # np.interp holds the edge values outside the span
    return float(np.sum((values[1:] + values[:-1]) * 0.5 * np.diff(knots)))


class PowerMonitor:
    """Samples rails in a thread and integrates them over frame windows.

    Args:
        rails: name -> Rail (from `open_rails`), or anything with ``read_power_w()``.
        rate_hz: sampling rate (>= 100 Hz).
        history_s: how long samples are kept.
        clock: seconds; default time.time (the wall clock camera stamps use).
        max_gap_s: how far beyond the newest or before the oldest sample a window may reach and
            still count as complete (default three sample periods).
    """

    def __init__(self, rails: Mapping[str, Rail], rate_hz: float = 200.0, history_s: float = 30.0,
                 clock: Callable[[], float] = time.time, max_gap_s: Optional[float] = None) -> None:
        if not rails:
            raise PowerRailError("PowerMonitor needs at least one rail")
        if rate_hz < MIN_RATE_HZ:
            raise ValueError("rate_hz must be at least %g Hz, got %g" % (MIN_RATE_HZ, rate_hz))
        self.rails = dict(rails)
        self.names = list(self.rails)
        self.rate_hz = float(rate_hz)
        self.history_s = float(history_s)
        self.clock = clock
        self.max_gap_s = 3.0 / self.rate_hz if max_gap_s is None else float(max_gap_s)
        capacity = int(self.rate_hz * self.history_s) + 16
        self._times: Deque[float] = collections.deque(maxlen=capacity)
        self._values: Deque[Tuple[float, ...]] = collections.deque(maxlen=capacity)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self.read_errors = 0
        self.last_error = ""
        self.samples_taken = 0
        self._started_at = float("nan")

    # -- sampling ------------------------------------------------------------------------

    def sample(self) -> bool:
        """Read every rail once and keep the sample; False (counted, remembered) when a read fails."""
        t_before = self.clock()
        try:
            values = tuple(self.rails[name].read_power_w() for name in self.names)
        except (OSError, ValueError) as error:
            self.read_errors += 1
            self.last_error = "%s: %s" % (type(error).__name__, error)
            return False
        t = 0.5 * (t_before + self.clock())  # the reads' midpoint
        self.add_sample(t, values)
        return True

    def add_sample(self, t: float, values: Sequence[float]) -> None:
        """Keep one sample (seconds, watts per rail in `names` order); samples must come in time order."""
        with self._lock:
            if self._times and t <= self._times[-1]:
                return
            self._times.append(float(t))
            self._values.append(tuple(float(v) for v in values))
            self.samples_taken += 1

    def start(self) -> PowerMonitor:
        """Start the sampling thread (a daemon: it never keeps a process alive)."""
        if self._thread is None:
            self._stop.clear()
            self._started_at = time.monotonic()
            self._thread = threading.Thread(target=self._run, name="power-monitor", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def __enter__(self) -> PowerMonitor:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        next_time = time.monotonic()
        while not self._stop.is_set():
            self.sample()
            next_time += period
            delay = next_time - time.monotonic()
            if delay < -period:  # fell behind (a busy machine): restart the schedule, do not burst
                next_time = time.monotonic()
                delay = 0.0
            if delay > 0:
                self._stop.wait(delay)

    def achieved_rate_hz(self) -> float:
        """Samples per second over the kept history (0 before two samples)."""
        with self._lock:
            if len(self._times) < 2:
                return 0.0
            return (len(self._times) - 1) / (self._times[-1] - self._times[0])

    def latest_time(self) -> float:
        with self._lock:
            return self._times[-1] if self._times else float("-inf")

    # -- integration ---------------------------------------------------------------------

    def energy(self, t0: float, t1: float) -> Optional[FrameEnergy]:
        """Energy of each rail over [t0, t1] (seconds on the monitor's clock).

        Returns:
            FrameEnergy, or None when no kept sample lies within `max_gap_s` of the window
            (the window is older than the history, in the future, or nothing was sampled).
        """
        with self._lock:
            times = np.fromiter(self._times, dtype=float, count=len(self._times))
            values = np.array(self._values, dtype=float).reshape(len(times), len(self.names))
        if len(times) == 0 or t1 < t0:
            return None
        if times[-1] < t0 - self.max_gap_s or times[0] > t1 + self.max_gap_s:
            return None
        lo = int(np.searchsorted(times, t0, side="left"))
        hi = int(np.searchsorted(times, t1, side="right"))
        # the samples just outside the window bound the interpolation at its ends
        first, last = max(lo - 1, 0), min(hi + 1, len(times))
        span_t, span_v = times[first:last], values[first:last]
        window = t1 - t0
        result = FrameEnergy(window_s=window, samples=hi - lo,
                             complete=bool(times[0] <= t0 + self.max_gap_s and times[-1] >= t1 - self.max_gap_s))
        for column, name in enumerate(self.names):
            joules = integrate_power(span_t, span_v[:, column], t0, t1)
            result.energy_j[name] = joules
            if window > 0:
                result.mean_power_w[name] = joules / window
            else:
                result.mean_power_w[name] = float(np.interp(t0, span_t, span_v[:, column]))
        return result


def start_power_monitor(params: Optional[PowerParams] = None, clock: Callable[[], float] = time.time
                        ) -> Tuple[Optional[PowerMonitor], str]:
    """Open the rails the params name and start sampling on `clock` (seconds); never raises.

    Returns:
        (monitor or None, a one-line message: the rails and layout in use, or why there are none).
    """
    params = params or PowerParams()
    try:
        rails, notes = open_rails(params.sysfs_root, params.rails)
    except PowerRailError as error:
        return None, "no power rails: %s" % error
    except OSError as error:  # an unreadable sysfs tree
        return None, "no power rails: %s: %s" % (type(error).__name__, error)
    monitor = PowerMonitor(rails, params.rate_hz, params.history_s, clock=clock).start()
    layouts = sorted({rail.layout for rail in rails.values()})
    message = "sampling %s at %g Hz (%s)" % (", ".join(rails), params.rate_hz, "/".join(layouts))
    if notes:
        message += "; " + "; ".join(notes)
    return monitor, message


def power_rails_present(sysfs_root: str = "/sys", wanted: Sequence[str] = DEFAULT_RAILS) -> bool:
    """True when at least one wanted rail exists and reads (what decides whether power_node runs)."""
    try:
        open_rails(sysfs_root, wanted)
    except (PowerRailError, OSError):
        return False
    return True


POWER_NODE_ENV = "LEAPNBV_POWER_NODE"


def power_node_wanted(sysfs_root: str = "/sys") -> bool:
    """Whether the graph runs power_node.

    $LEAPNBV_POWER_NODE "1"/"on" always, "0"/"off" never, unset or "auto" when the board's rails
    exist (a Jetson).
    """
    choice = os.environ.get(POWER_NODE_ENV, "auto").strip().lower()
    if choice in ("1", "on", "true", "yes"):
        return True
    if choice in ("0", "off", "false", "no"):
        return False
    return power_rails_present(sysfs_root)


def measure_energy(fn: Callable[[], object], monitor: Optional[PowerMonitor], settle_s: float = 0.0
                   ) -> Tuple[object, Optional[FrameEnergy]]:
    """Run `fn()` and integrate the rails over its run (benchmarks: J per call); (result, None) without rails."""
    t0 = monitor.clock() if monitor is not None else 0.0
    result = fn()
    if monitor is None:
        return result, None
    t1 = monitor.clock()
    deadline = time.monotonic() + max(settle_s, 2.0 / monitor.rate_hz) + 0.05
    while monitor.latest_time() < t1 and time.monotonic() < deadline:
        time.sleep(1.0 / monitor.rate_hz)
    return result, monitor.energy(t0, t1)


# ----------------------------------------------------------------------------------------
# A fake INA3221 tree (tests, and trying power_node on a machine without rails)
# ----------------------------------------------------------------------------------------

XAVIER_NX_CHANNELS = (RAIL_TOTAL, RAIL_COMPUTE, "VDD_SOC")


class FakeIna3221:
    """Writes an INA3221 sysfs tree in the JetPack 5 (hwmon) or JetPack 4 (iio) layout.

    Args:
        sysfs_root: folder standing in for /sys.
        layout: "hwmon" or "iio".
        channels: rail labels, channel 1.. (hwmon) or 0.. (iio).

    `set_rail(name, millivolts, milliamps)` updates a rail with atomic file replacements, so a
    sampling reader never sees a half-written value.
    """

    def __init__(self, sysfs_root: str, layout: str = "hwmon", channels: Sequence[str] = XAVIER_NX_CHANNELS,
                 hwmon_index: int = 3) -> None:
        if layout not in ("hwmon", "iio"):
            raise ValueError("layout must be 'hwmon' or 'iio'")
        self.layout = layout
        device = os.path.join(sysfs_root, "bus", "i2c", "devices", "7-0040")
        os.makedirs(device, exist_ok=True)
        self._write(os.path.join(device, "name"), "ina3221" if layout == "hwmon" else "ina3221x")
        drivers = os.path.join(sysfs_root, "bus", "i2c", "drivers", "ina3221" if layout == "hwmon" else "ina3221x")
        os.makedirs(drivers, exist_ok=True)
        link = os.path.join(drivers, "7-0040")
        if not os.path.lexists(link):
            os.symlink(os.path.relpath(device, drivers), link)  # as in sysfs: the same device twice
        self.channels: Dict[str, int] = {}
        if layout == "hwmon":
            self.folder = os.path.join(device, "hwmon", "hwmon%d" % hwmon_index)
            os.makedirs(self.folder, exist_ok=True)
            self._write(os.path.join(self.folder, "name"), "ina3221")
            for index, label in enumerate(channels, start=1):
                self.channels[label] = index
                self._write(os.path.join(self.folder, "in%d_label" % index), label)
                self._write(os.path.join(self.folder, "curr%d_crit" % index), "5000")
                self._write(os.path.join(self.folder, "curr%d_max" % index), "4000")
                self.set_rail(label, 5000.0, 0.0)
            self._write(os.path.join(self.folder, "in7_label"), "sum of shunt voltages")
            self._write(os.path.join(self.folder, "in7_input"), "40")
            self._write(os.path.join(self.folder, "curr7_input"), "9999")
        else:
            self.folder = os.path.join(device, "iio:device0")
            os.makedirs(self.folder, exist_ok=True)
            for index, label in enumerate(channels):
                self.channels[label] = index
                self._write(os.path.join(self.folder, "rail_name_%d" % index), label)
                self.set_rail(label, 5000.0, 0.0)

    @staticmethod
    def _write(path: str, text: str) -> None:
        temporary = path + ".tmp"
        with open(temporary, "w", encoding="utf-8") as stream:
            stream.write(text + "\n")
        os.replace(temporary, path)

    def paths(self, name: str) -> Dict[str, str]:
        """The files of one rail: voltage, current (and power for iio)."""
        k = self.channels[name]
        if self.layout == "hwmon":
            return {"voltage": os.path.join(self.folder, "in%d_input" % k),
                    "current": os.path.join(self.folder, "curr%d_input" % k)}
        return {"voltage": os.path.join(self.folder, "in_voltage%d_input" % k),
                "current": os.path.join(self.folder, "in_current%d_input" % k),
                "power": os.path.join(self.folder, "in_power%d_input" % k)}

    def set_rail(self, name: str, millivolts: float, milliamps: float) -> None:
        paths = self.paths(name)
        self._write(paths["voltage"], "%d" % round(millivolts))
        self._write(paths["current"], "%d" % round(milliamps))
        if "power" in paths:
            self._write(paths["power"], "%d" % round(millivolts * milliamps / 1000.0))
