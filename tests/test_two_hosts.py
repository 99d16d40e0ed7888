"""The graph split over two hosts (docs/TWO_HOSTS.md), as two network namespaces joined by a veth pair.

The suite's case, "geometry off-board": host A (namespace 1) runs the camera (the simulator, 5 FPS,
driving to each goal) + detector_node + hmr_node; host B (namespace 2) raster_node + ground_node +
nbv_node. Colour stays on A; depth, camera infos, camera poses, the obstacle map and the meshes cross
to B; goals cross back to A. Both use src/leapnbv_bringup/config/fastdds_two_hosts.xml and
ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET, as the document says. The namespaces, the veth and every
process are made here and removed in a finally; the test needs root (`ip netns`) and skips with the
reason otherwise.

Opt-in cases (environment variables below, docs/TWO_HOSTS.md "The test"): the planner off-board
(LEAPNBV_TWO_HOSTS_SPLIT=planner, with fastdds_two_hosts_wifi.xml) on a link shaped to a Wi-Fi-class
rate (LEAPNBV_TWO_HOSTS_RATE=30mbit: tbf with a 50 ms queue on both ends), and the link's traffic per
topic (LEAPNBV_TWO_HOSTS_TRAFFIC=out.json, scripts/experiments/two_host_traffic.py).

This file is also the recording helper it runs inside each namespace:
    python tests/test_two_hosts.py record {a|b} OUT.json
(records until SIGINT, then writes OUT.json).
"""
from __future__ import annotations

import json
import os
import pathlib
import signal
import subprocess
import sys
import time
import uuid
from typing import Dict, List, Optional

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
# The two splits of docs/TWO_HOSTS.md (host A's nodes, host B's nodes).
SPLITS = {
    "planner": ("detector_node,hmr_node,raster_node,ground_node", "nbv_node"),
    "geometry": ("detector_node,hmr_node", "raster_node,ground_node,nbv_node"),
}
# LEAPNBV_TWO_HOSTS_SPLIT: planner (off-board) or geometry (off-board, the default case);
# LEAPNBV_TWO_HOSTS_A_NODES / _B_NODES: any other split.
SPLIT = os.environ.get("LEAPNBV_TWO_HOSTS_SPLIT", "geometry")
# The profile of each split (docs/TWO_HOSTS.md): the planner off-board paces what crosses (a Wi-Fi-class
# link); LEAPNBV_TWO_HOSTS_PROFILE: another profile to compare (e.g. fastdds_large_messages.xml, to see the loss).
CONFIG = REPO / "src/leapnbv_bringup/config"
PROFILE = pathlib.Path(os.environ.get("LEAPNBV_TWO_HOSTS_PROFILE", CONFIG / (
    "fastdds_two_hosts_wifi.xml" if SPLIT == "planner" else "fastdds_two_hosts.xml")))
HOST_A_NODES = os.environ.get("LEAPNBV_TWO_HOSTS_A_NODES", SPLITS.get(SPLIT, SPLITS["geometry"])[0])
HOST_B_NODES = os.environ.get("LEAPNBV_TWO_HOSTS_B_NODES", SPLITS.get(SPLIT, SPLITS["geometry"])[1])
# LEAPNBV_TWO_HOSTS_RATE: shape the link (tc tbf on both ends, a 50 ms queue), e.g. 30mbit; "" for none.
RATE = os.environ.get("LEAPNBV_TWO_HOSTS_RATE", "")
# LEAPNBV_TWO_HOSTS_TRAFFIC=OUT.json: count the link's traffic per topic and direction
# (scripts/experiments/two_host_traffic.py capture, on host B's end) and write it, with the run's frames.
TRAFFIC_OUT = os.environ.get("LEAPNBV_TWO_HOSTS_TRAFFIC", "")
TRAFFIC_SCRIPT = REPO / "scripts/experiments/two_host_traffic.py"
# LEAPNBV_TWO_HOSTS_PACE_MBIT: the profile's flow controller (leapnbv_link) paced at this many Mbit/s
# instead of its own value (a copy of the profile is written): for a link slower than 30 Mbit/s.
PACE_MBIT = os.environ.get("LEAPNBV_TWO_HOSTS_PACE_MBIT", "")
# LEAPNBV_TWO_HOSTS_MIN_PLANNED: the share of published frames that must become goals (CPU-bound on a loaded
# machine: the link's own share is asserted apart, see the end of the test).
MIN_PLANNED = float(os.environ.get("LEAPNBV_TWO_HOSTS_MIN_PLANNED", "0.3"))
# LEAPNBV_TWO_HOSTS_BODY: the stand-in body model's resolution: small (2707 vertices, the default) or full
# (SMPL-X's 10,475 vertices and 20,908 triangles: the mesh a real model sends).
BODY = os.environ.get("LEAPNBV_TWO_HOSTS_BODY", "small")
# LEAPNBV_TWO_HOSTS_SET: more parameter overrides for both runners, space-separated NODE.PARAM=VALUE.
EXTRA_SET = os.environ.get("LEAPNBV_TWO_HOSTS_SET", "").split()
# LEAPNBV_TWO_HOSTS_IN_FLIGHT: detector_node's max_frames_in_flight. With the planner on host B a frame in
# flight is mostly on the link or on B's CPU, not A's: 2 lets A work on the next frame meanwhile
# (docs/TWO_HOSTS.md); the other split keeps the parameter file's value unless this is set.
IN_FLIGHT = os.environ.get("LEAPNBV_TWO_HOSTS_IN_FLIGHT", "2" if SPLIT == "planner" else "")
# LEAPNBV_TWO_HOSTS_TARGET_STRIDE: raster_node's target_stride. With the planner on host B the target points
# cross the link: 2 (a quarter of them) fits SMPL-X-size meshes into 30 Mbit/s (docs/TWO_HOSTS.md).
TARGET_STRIDE = os.environ.get("LEAPNBV_TWO_HOSTS_TARGET_STRIDE", "2" if SPLIT == "planner" else "")
SIM_RATE_HZ = 5.0
RECORD_S = 50.0  # seconds the camera runs
DEPTH_FRAME_BYTES = 640 * 480 * 2


# ----------------------------------------------------------------------------- the recorder (inside a namespace)


def record(role: str, out_path: str) -> int:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped
    from rclpy.executors import ExternalShutdownException

    from leapnbv_common.conversions import stamp_to_ns
    from leapnbv_common.qos import latched_goal_qos, stage_input_qos
    from leapnbv_common.topics import GROUND_PLANE, GROUND_TRUTH_TOPIC, NAMESPACE, NEXT_BEST_VIEW_TOPIC, VIEW_CANDIDATES
    from leapnbv_msgs.msg import GroundPlane, SceneGroundTruth, ViewCandidates

    rclpy.init()
    node = rclpy.create_node(f"two_hosts_recorder_{role}")
    data: Dict[str, object] = {"frames": [], "goals": [], "planes": [], "candidates": [], "diagnostics": {}}
    if role == "a":
        # The simulator's ground truth: one per published frame, reliable, on this host.
        node.create_subscription(SceneGroundTruth, GROUND_TRUTH_TOPIC,
                                 lambda m: data["frames"].append(stamp_to_ns(m.header.stamp)), stage_input_qos(100))
    else:
        node.create_subscription(PoseStamped, NEXT_BEST_VIEW_TOPIC, lambda m: data["goals"].append(
            [stamp_to_ns(m.header.stamp), time.time_ns(), m.header.frame_id]), latched_goal_qos())
        node.create_subscription(GroundPlane, f"{NAMESPACE}/{GROUND_PLANE}",
                                 lambda m: data["planes"].append(stamp_to_ns(m.header.stamp)), stage_input_qos(50))

        def on_candidates(msg: ViewCandidates) -> None:
            inputs = [[i.name, stamp_to_ns(i.stamp), int(i.relation)] for i in getattr(msg, "inputs", [])]
            data["candidates"].append([stamp_to_ns(msg.header.stamp), msg.chosen_index, inputs])

        node.create_subscription(ViewCandidates, f"{NAMESPACE}/{VIEW_CANDIDATES}", on_candidates, stage_input_qos(50))

        def on_diagnostics(msg: DiagnosticArray) -> None:
            for status in msg.status:
                data["diagnostics"][status.name] = {kv.key: kv.value for kv in status.values}

        node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 50)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        with open(out_path + ".tmp", "w") as handle:
            json.dump(data, handle)
        os.replace(out_path + ".tmp", out_path)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


# ----------------------------------------------------------------------------- the test


class Namespaces:
    """Two network namespaces joined by a veth pair, 10.200.<n>.1/30 <-> .2/30; removed by close()."""

    def __init__(self, tag: str, subnet: int) -> None:
        self.a, self.b = f"lnbv{tag}a", f"lnbv{tag}b"
        self.veth_a, self.veth_b = f"lnbv{tag}va", f"lnbv{tag}vb"
        self.addr_a, self.addr_b = f"10.200.{subnet}.1", f"10.200.{subnet}.2"
        self.made: List[str] = []

    def setup(self, multicast: bool = True) -> None:
        for ns in (self.a, self.b):
            run(["ip", "netns", "add", ns])
            self.made.append(ns)
        run(["ip", "link", "add", self.veth_a, "netns", self.a, "type", "veth", "peer", "name", self.veth_b,
             "netns", self.b])
        for ns, dev, addr in ((self.a, self.veth_a, self.addr_a), (self.b, self.veth_b, self.addr_b)):
            run(["ip", "-n", ns, "addr", "add", f"{addr}/30", "dev", dev])
            run(["ip", "-n", ns, "link", "set", "lo", "up"])
            run(["ip", "-n", ns, "link", "set", dev, "up"])
            if multicast:  # DDS discovery multicast (239.255.0.1) leaves through the veth: the only way out
                run(["ip", "-n", ns, "route", "add", "224.0.0.0/4", "dev", dev])

    def shape(self, rate: str) -> None:
        """A token bucket of ``rate`` with a 50 ms queue on both ends (a Wi-Fi-class link's bottleneck)."""
        for ns, dev in ((self.a, self.veth_a), (self.b, self.veth_b)):
            run(["ip", "netns", "exec", ns, "tc", "qdisc", "add", "dev", dev, "root", "tbf", "rate", rate,
                 "burst", "32kbit", "latency", "50ms"])

    def rx_bytes(self, ns: str, dev: str) -> int:
        out = run(["ip", "-n", ns, "-s", "-j", "link", "show", "dev", dev])
        return int(json.loads(out)[0]["stats64"]["rx"]["bytes"])

    def link_stats(self) -> Dict[str, int]:
        """Bytes each way, the queue's drops on each end, and UDP receive-buffer errors on each host."""
        stats = {"a_to_b_bytes": self.rx_bytes(self.b, self.veth_b), "b_to_a_bytes": self.rx_bytes(self.a, self.veth_a)}
        for side, ns, dev in (("a", self.a, self.veth_a), ("b", self.b, self.veth_b)):
            qdisc = json.loads(run(["ip", "netns", "exec", ns, "tc", "-s", "-j", "qdisc", "show", "dev", dev]) or "[]")
            stats[f"qdisc_drops_{side}"] = sum(int(q.get("drops", 0)) for q in qdisc)
            stats[f"qdisc_packets_{side}"] = sum(int(q.get("packets", 0)) for q in qdisc)
            snmp = run(["ip", "netns", "exec", ns, "cat", "/proc/net/snmp"]).splitlines()
            udp = [line.split()[1:] for line in snmp if line.startswith("Udp:")]
            if len(udp) == 2:
                stats[f"udp_rcvbuf_errors_{side}"] = int(dict(zip(*udp)).get("RcvbufErrors", 0))
        return stats

    def close(self) -> None:
        for ns in reversed(self.made):  # the veth pair goes with its namespaces
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=30)
        self.made.clear()


def run(cmd: List[str]) -> str:
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=30)
    if result.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)}: {result.stderr.strip()}")
    return result.stdout


def netns_allowed() -> Optional[str]:
    """None when this process may create network namespaces, else why not."""
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        return "needs root to create network namespaces (ip netns add)"
    name = f"lnbvprobe{os.getpid() % 100000}"
    result = subprocess.run(["ip", "netns", "add", name], capture_output=True, text=True)
    if result.returncode != 0:
        return f"ip netns add is not permitted here: {result.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", name], capture_output=True)
    return None


def stop(proc: subprocess.Popen, sig: int = signal.SIGINT, timeout_s: float = 20.0) -> None:
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def wait_for_line(path: pathlib.Path, text: str, timeout_s: float, procs: List[subprocess.Popen]) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if path.exists() and text in path.read_text(errors="replace"):
            return True
        if any(p.poll() is not None for p in procs):
            return False
        time.sleep(0.2)
    return False


def paced_profile(xml: str, mbit_s: float) -> str:
    """The profile with its flow controller's bytes per period set for ``mbit_s`` (its period unchanged)."""
    import re

    found = re.search(r"<period_ms>(\d+)</period_ms>", xml)
    period_ms = int(found.group(1)) if found else 100  # Fast DDS's default period
    per_period = int(mbit_s * 1e6 / 8 * period_ms / 1000)
    return re.sub(r"<max_bytes_per_period>\d+</max_bytes_per_period>",
                  f"<max_bytes_per_period>{per_period}</max_bytes_per_period>", xml)


# "static_peers": no multicast route at all (a Wi-Fi that drops multicast); each host names the other in
# ROS_STATIC_PEERS. LEAPNBV_TWO_HOSTS_DISCOVERY=static_peers runs that variant (the suite runs "subnet").
DISCOVERY = os.environ.get("LEAPNBV_TWO_HOSTS_DISCOVERY", "subnet")


@pytest.mark.ros
@pytest.mark.slow
def test_graph_split_over_two_network_namespaces(tmp_path):
    why_not = netns_allowed()
    if why_not:
        pytest.skip(why_not)
    from leapnbv_stand_ins.files import ensure_stand_in_body_model

    body = ensure_stand_in_body_model(BODY)
    domain = os.environ.get("ROS_DOMAIN_ID", "0")
    tag = uuid.uuid4().hex[:4]
    hosts = Namespaces(tag, 200 + int(domain) % 50)
    profile = PROFILE
    if PACE_MBIT:
        profile = tmp_path / PROFILE.name
        profile.write_text(paced_profile(PROFILE.read_text(), float(PACE_MBIT)))
    env = dict(os.environ, ROS_DOMAIN_ID=domain, ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET",
               FASTRTPS_DEFAULT_PROFILES_FILE=str(profile), PYTHONUNBUFFERED="1")
    # The Wi-Fi profile's flow controller needs asynchronous writers (fastdds_two_hosts_wifi.xml).
    if "wifi" in profile.name:
        env.setdefault("RMW_FASTRTPS_PUBLICATION_MODE", "ASYNCHRONOUS")
    env.pop("ROS_STATIC_PEERS", None)
    peers = {hosts.a: hosts.addr_b, hosts.b: hosts.addr_a} if DISCOVERY == "static_peers" else {}
    procs: Dict[str, subprocess.Popen] = {}
    logs: List[object] = []

    def start(name: str, ns: str, cmd: List[str]) -> subprocess.Popen:
        log = open(tmp_path / f"{name}.log", "w")  # noqa: SIM115 - closed in the finally
        logs.append(log)
        ns_env = dict(env, ROS_STATIC_PEERS=peers[ns]) if peers else env
        procs[name] = subprocess.Popen(["ip", "netns", "exec", ns, *cmd], env=ns_env, stdout=log,
                                       stderr=subprocess.STDOUT, start_new_session=True, cwd=REPO)
        return procs[name]

    runner = [sys.executable, "-m", "leapnbv_bringup.graph_runner", "--perception", "ground_truth",
              "--body-model", body, "--no-restart", "--ready-timeout", "120"]
    if IN_FLIGHT:
        runner += ["--set", f"detector_node.max_frames_in_flight={IN_FLIGHT}"]
    if TARGET_STRIDE:
        runner += ["--set", f"raster_node.target_stride={TARGET_STRIDE}"]
    for override in EXTRA_SET:
        runner += ["--set", override]
    try:
        hosts.setup(multicast=not peers)
        if RATE:
            hosts.shape(RATE)
        if TRAFFIC_OUT:  # counting from before the graph starts: it learns every topic's writers from SEDP
            start("capture", hosts.b, [sys.executable, str(TRAFFIC_SCRIPT), "capture", hosts.veth_b,
                                       str(tmp_path / "capture.json")])
            assert wait_for_line(tmp_path / "capture.log", "counting", 20.0, list(procs.values()))
        start("graph_a", hosts.a, [*runner, "--nodes", HOST_A_NODES, "--log-dir", str(tmp_path / "a")])
        start("graph_b", hosts.b, [*runner, "--nodes", HOST_B_NODES, "--log-dir", str(tmp_path / "b")])
        for name in ("graph_a", "graph_b"):
            assert wait_for_line(tmp_path / f"{name}.log", "[graph] ready", 150.0, list(procs.values())), \
                (tmp_path / f"{name}.log").read_text()
        start("record_a", hosts.a, [sys.executable, __file__, "record", "a", str(tmp_path / "a.json")])
        start("record_b", hosts.b, [sys.executable, __file__, "record", "b", str(tmp_path / "b.json")])
        time.sleep(3.0)  # the recorders discover the graph before the first frame
        link_before = hosts.link_stats()
        rx_before = link_before["a_to_b_bytes"]
        camera_started = time.monotonic()
        if TRAFFIC_OUT:
            procs["capture"].send_signal(signal.SIGUSR1)  # counts from the first frame on
        start("camera", hosts.a, [sys.executable, "-m", "leapnbv_sim.nodes.simulator_node", "--ros-args",
                                  "-p", f"rate_hz:={SIM_RATE_HZ}", "-p", "scene_seed:=3"])
        # Bounded: the camera runs RECORD_S seconds (its start-up, a few seconds, included).
        deadline = time.monotonic() + RECORD_S
        while time.monotonic() < deadline:
            dead = {n: p.returncode for n, p in procs.items() if p.poll() is not None}
            assert not dead, f"exited early: {dead}"
            time.sleep(0.5)
        stop(procs["camera"])
        time.sleep(3.0)  # the last frames drain through the graph; the nodes' diagnostics tick
        link_after = hosts.link_stats()
        camera_s = time.monotonic() - camera_started
        rx_bytes = link_after["a_to_b_bytes"] - rx_before
        link = {k: link_after[k] - link_before.get(k, 0) for k in link_after}
        if TRAFFIC_OUT:
            stop(procs["capture"])
        stop(procs["record_a"])
        stop(procs["record_b"])
        codes = {name: None for name in ("graph_a", "graph_b")}
        for name in codes:
            stop(procs[name], signal.SIGTERM, 40.0)
            codes[name] = procs[name].returncode
    finally:
        for proc in procs.values():
            stop(proc, signal.SIGTERM, 20.0)
        for log in logs:
            log.close()
        hosts.close()
    a = json.loads((tmp_path / "a.json").read_text())
    b = json.loads((tmp_path / "b.json").read_text())
    frames = set(a["frames"])
    goals = [g for g in b["goals"] if g[2]]  # an empty frame_id is an explicit "no goal"
    diag = b["diagnostics"]
    ground = diag.get("/leapnbv/ground_node", {})
    ground_in = int(ground.get("frames_in", 0))
    lat = sorted((r - s) * 1e-9 for s, r, _ in goals)
    nbv = diag.get("/leapnbv/nbv_node", {})
    # What the link delivered of what host A produced (CPU-independent): raster_node's target geometries
    # out on A, nbv_node's in on B.
    raster_out = int(diag.get("/leapnbv/raster_node", {}).get("frames_out", 0))
    nbv_in = int(nbv.get("frames_in", 0))
    # CPU, not the link: the frames each node dropped (busy, superseded, not taken) by its own count.
    node_drops = {name.rsplit("/", 1)[-1]: {k[8:]: int(v) for k, v in values.items()
                                              if k.startswith("dropped.") and int(v)}
                  for name, values in diag.items() if name.startswith("/leapnbv/") and "graph_runner" not in name}
    summary = (f"A: {HOST_A_NODES}; B: {HOST_B_NODES}; discovery {DISCOVERY}; link {RATE or 'unshaped'}: "
               f"{len(frames)} frames published on A, {len(goals)} goals on B "
               f"({len(goals) / max(1, len(frames)):.0%}), raster_node frames_out {raster_out}, nbv_node frames_in "
               f"{nbv_in} (target_geometry transport {nbv.get('transport_ms.target_geometry', '?')} ms, last), "
               f"ground_node received {ground_in} depth frames, {rx_bytes / 1e6:.1f} MB into B and "
               f"{link['b_to_a_bytes'] / 1e6:.1f} MB into A over the veth in {camera_s:.0f} s, "
               f"queue drops A {link.get('qdisc_drops_a', 0)} B {link.get('qdisc_drops_b', 0)}, "
               f"UDP receive-buffer errors A {link.get('udp_rcvbuf_errors_a', 0)} "
               f"B {link.get('udp_rcvbuf_errors_b', 0)}, "
               f"goal latency p50 {lat[len(lat) // 2] if lat else float('nan'):.2f} s; node drops {node_drops}")
    print(f"\n[two hosts] {summary}")
    if TRAFFIC_OUT:
        run_record = {"split": [HOST_A_NODES, HOST_B_NODES], "rate": RATE, "frames": len(frames),
                      "goals": len(goals), "seconds": camera_s, "link": link, "node_drops": node_drops,
                      "capture": json.loads((tmp_path / "capture.json").read_text())}
        pathlib.Path(TRAFFIC_OUT).write_text(json.dumps(run_record, indent=1))
        sys.path.insert(0, str(TRAFFIC_SCRIPT.parent))
        import two_host_traffic

        print(two_host_traffic.table(run_record))
    assert codes == {"graph_a": 0, "graph_b": 0}, codes
    assert len(frames) >= 0.5 * SIM_RATE_HZ * RECORD_S, summary
    assert len(goals) >= MIN_PLANNED * len(frames), summary
    if "raster_node" in HOST_A_NODES.split(",") and "nbv_node" in HOST_B_NODES.split(","):
        # The link lost no frame: nbv_node received what raster_node published (its first frames may go out
        # before the recorder on B hears the diagnostics: a 5 % margin).
        assert nbv_in >= 0.95 * raster_out, summary
        # ... and the queue of a shaped link overflowed on at most 1 % of the packets.
        drops = link.get("qdisc_drops_a", 0) + link.get("qdisc_drops_b", 0)
        assert drops <= 0.01 * (link.get("qdisc_packets_a", 0) + link.get("qdisc_packets_b", 0) + drops), summary
    # Every goal is from a published frame: the recorder on A hears every frame (reliable) from the
    # first it heard (the camera's first frames can go out before the recorder is matched).
    assert not [g for g in goals if g[0] >= min(frames) and g[0] not in frames], summary
    # Depth crossed the link (not shared memory) and was not lost: each depth subscriber on B
    # (raster_node, ground_node) receives every depth frame over UDP.
    depth_readers_on_b = len({"raster_node", "ground_node"} & set(HOST_B_NODES.split(",")))
    assert rx_bytes >= depth_readers_on_b * 0.9 * len(frames) * DEPTH_FRAME_BYTES, summary
    if "ground_node" in HOST_B_NODES.split(","):
        assert ground_in >= 0.9 * len(frames), summary
    # One frame per goal: the view candidates list their inputs (InputStamp); no SAME_FRAME input may carry
    # another stamp, and the floor is the frame's own or one CARRIED into it by the camera-pose delta.
    with_inputs = [c for c in b["candidates"] if c[2]]
    assert with_inputs and len(with_inputs) == len(b["candidates"]), summary
    mixed = [c for c in with_inputs if any(rel == 0 and stamp != c[0] for _, stamp, rel in c[2])]
    assert not mixed, f"view candidates with a SAME_FRAME input of another stamp: {mixed[:5]}"
    floors = [c for c in with_inputs if c[1] >= 0 and not any(
        name == "ground_plane" and (stamp == c[0] or rel == 1) for name, stamp, rel in c[2])]
    assert not floors, f"goals whose floor is neither the frame's own nor carried: {floors[:5]}"

# ----------------------------------------------------------------------------- the traffic counter (no root)


def _ip_frames(payload: bytes, ident: int, dport: int, mtu: int = 1500) -> List[bytes]:
    """Ethernet frames of one UDP datagram, cut into IPv4 fragments as the kernel does."""
    import struct

    udp = struct.pack(">HHHH", 7411, dport, 8 + len(payload), 0) + payload
    step = (mtu - 20) // 8 * 8
    frames = []
    for offset in range(0, len(udp), step):
        chunk = udp[offset:offset + step]
        more = offset + step < len(udp)
        ip = struct.pack(">BBHHHBBH4s4s", 0x45, 0, 20 + len(chunk), ident, (0x2000 if more else 0) | offset // 8,
                         64, 17, 0, bytes([10, 200, 1, 1]), bytes([10, 200, 1, 2]))
        frames.append(b"\x02" * 6 + b"\x04" * 6 + b"\x08\x00" + ip + chunk)
    return frames


def test_traffic_counter_attributes_rtps_to_topics():
    """two_host_traffic.Counter counts a writer's traffic on the topic its SEDP announcement names.

    Its fragmented sample, a repeat of it and the reader's ACKNACK (addressed by INFO_DST) are counted
    on the topic, every IP fragment's bytes included.
    """
    import struct

    sys.path.insert(0, str(TRAFFIC_SCRIPT.parent))
    import two_host_traffic as traffic

    writer_prefix, reader_prefix = bytes(range(1, 13)), bytes(range(21, 33))
    writer_entity = bytes([0, 0, 0x12, 0x03])
    header = b"RTPS\x02\x03\x01\x0f"

    def sub(sid: int, flags: int, body: bytes) -> bytes:
        return struct.pack("<BBH", sid, flags | 1, len(body)) + body

    name = b"rt/leapnbv/target_geometry\x00"
    name += b"\x00" * (-len(name) % 4)
    params = (struct.pack("<HH", 0x5A, 16) + writer_prefix + writer_entity
              + struct.pack("<HHI", 0x05, 4 + len(name), len(name.rstrip(b"\x00")) + 1) + name
              + struct.pack("<HH", 1, 0))
    sedp = header + writer_prefix + sub(0x15, 0x04, struct.pack("<HH", 0, 16) + bytes.fromhex("000003c7000003c2")
                                        + struct.pack("<iI", 0, 1) + b"\x00\x03\x00\x00" + params)
    sample = 100_000
    fragment = bytes(4000)
    data_frag = header + writer_prefix + sub(0x16, 0, struct.pack("<HH", 0, 28) + bytes(4) + writer_entity
                                             + struct.pack("<iIIHHI", 0, 7, 1, 1, len(fragment), sample) + fragment)
    small = bytes(3000)  # one DATA, bigger than an IP fragment: its size from the submessage's length
    data = header + writer_prefix + sub(0x15, 0x04, struct.pack("<HH", 0, 16) + bytes(4) + writer_entity
                                        + struct.pack("<iI", 0, 8) + small)
    acknack = header + reader_prefix + sub(0x0E, 0, writer_prefix) + sub(0x06, 0, bytes(4) + writer_entity + bytes(20))
    counter = traffic.Counter()
    sedp_frames = _ip_frames(sedp, 1, 7410)
    data_frames = _ip_frames(data_frag, 2, 7411)
    again = _ip_frames(data_frag, 3, 7411)
    data_frames += _ip_frames(data, 5, 7411)
    for frame in sedp_frames + data_frames + again:
        counter.feed("a_to_b", frame)
    for frame in _ip_frames(acknack, 4, 7413):
        counter.feed("b_to_a", frame)
    rows = {row["label"]: row for row in counter.result()["rows"]}
    topic = rows["rt/leapnbv/target_geometry"]
    assert len(data_frames) == 6  # 4000 B of fragment and 3000 B of DATA: 3 + 3 IP fragments, all on the topic
    assert topic["a_to_b"]["bytes"] == sum(len(f) for f in data_frames + again)
    assert topic["a_to_b"]["samples"] == 3 and topic["a_to_b"]["repeats"] == 1
    # DATA_FRAG's sample size and the whole DATA, not the bytes of the first IP fragment
    assert topic["a_to_b"]["sample_bytes"] == 2 * sample + len(small)
    assert topic["b_to_a"]["bytes"] == len(_ip_frames(acknack, 4, 7413)[0])
    assert rows["DDS discovery (SEDP)"]["a_to_b"]["bytes"] == sum(len(f) for f in sedp_frames)
    assert "RTPS unattributed" not in rows


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "record":
        sys.exit(record(sys.argv[2], sys.argv[3]))
    sys.exit(f"usage: {sys.argv[0]} record {{a|b}} OUT.json")
