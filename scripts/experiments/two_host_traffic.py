#!/usr/bin/env python3
"""What crosses the link between two hosts of the graph, per topic and direction (docs/TWO_HOSTS.md).

Two parts:

``capture DEV OUT.json`` (root, run inside the namespace that holds DEV, as tests/test_two_hosts.py
does): counts every frame on the interface with a packet socket until SIGINT, then writes OUT.json.
Each UDP datagram is read as RTPS: its submessages are attributed to the DDS writer (or, for
ACKNACK/NACK_FRAG, the reader) they belong to, and the writers and readers to their topics from the
SEDP announcements seen on the same link (so start it before the graph). Bytes are the frames' bytes
on the wire (Ethernet header included, every IP fragment), after the sender's queue discipline (a
frame a tbf queue dropped is not counted). Labels: ``rt/<topic>`` (user data, with its heartbeats,
gaps and acknacks), ``DDS discovery (SPDP|SEDP)``, ``DDS liveliness``, ``DDS type lookup``, ``RTPS
unattributed`` (a writer announced before the capture started), ``non-RTPS`` (ARP, IGMP, ...).
Per topic it also counts the samples sent (DATA, first fragment) and how many of those were
repeats of a sequence number already sent (reliable repairs, or the same sample to a second
reader participant).

``table RUN.json [--frames N] [--seconds S]``: prints the table of a run's capture (the test writes
``traffic.json`` next to its logs when LEAPNBV_TWO_HOSTS_TRAFFIC names a file), per frame and per
second, and the link it would need at 5 and 30 FPS.

    ip netns exec HOST_B python scripts/experiments/two_host_traffic.py capture veth0 /tmp/cap.json
    LEAPNBV_TWO_HOSTS_TRAFFIC=/tmp/run.json scripts/env.sh python -m pytest tests/test_two_hosts.py
    python scripts/experiments/two_host_traffic.py table /tmp/run.json
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import signal
import socket
import struct
import sys
import time
from typing import Any, Dict, List, Optional, Tuple

ETH_P_ALL = 0x0003
PACKET_OUTGOING = 4
# RTPS submessage ids (DDSI-RTPS 2.3, 9.4.5).
PAD, ACKNACK, HEARTBEAT, GAP, INFO_TS, INFO_SRC, INFO_REPLY_IP4, INFO_DST, INFO_REPLY = \
    0x01, 0x06, 0x07, 0x08, 0x09, 0x0C, 0x0D, 0x0E, 0x0F
NACK_FRAG, HEARTBEAT_FRAG, DATA, DATA_FRAG = 0x12, 0x13, 0x15, 0x16
WRITER_SENT = {DATA, DATA_FRAG, HEARTBEAT, GAP, HEARTBEAT_FRAG}  # sent by the writer
READER_SENT = {ACKNACK, NACK_FRAG}  # sent by the reader to the writer
PID_SENTINEL, PID_TOPIC_NAME, PID_ENDPOINT_GUID = 0x0001, 0x0005, 0x005A
SEDP_PUB_WRITER, SEDP_SUB_WRITER = 0x000003C2, 0x000004C2
BUILTIN = {0x000100C2: "DDS discovery (SPDP)", 0x000100C7: "DDS discovery (SPDP)",
           0x000003C2: "DDS discovery (SEDP)", 0x000003C7: "DDS discovery (SEDP)",
           0x000004C2: "DDS discovery (SEDP)", 0x000004C7: "DDS discovery (SEDP)",
           0x000200C2: "DDS liveliness", 0x000200C7: "DDS liveliness"}
UNATTRIBUTED = "RTPS unattributed"


def _builtin_label(entity: int) -> Optional[str]:
    if entity in BUILTIN:
        return BUILTIN[entity]
    if entity & 0xC0 == 0xC0:  # any other builtin entity kind (type lookup service, ...)
        return "DDS type lookup" if entity >> 8 in (0x0003, 0x0301) else "DDS builtin"
    return None


def _parameter_list(payload: bytes) -> Dict[int, bytes]:
    """The parameters of a PL_CDR payload (encapsulation header first)."""
    if len(payload) < 4:
        return {}
    little = payload[1] in (0x03, 0x01)  # PL_CDR_LE / CDR_LE
    fmt = "<HH" if little else ">HH"
    out, pos = {}, 4
    while pos + 4 <= len(payload):
        pid, size = struct.unpack_from(fmt, payload, pos)
        pos += 4
        if pid == PID_SENTINEL:
            break
        out[pid & 0x3FFF] = payload[pos:pos + size]
        pos += size
    out[-1] = b"\x01" if little else b"\x00"
    return out


def _topic_of(params: Dict[int, bytes]) -> Optional[Tuple[bytes, str]]:
    guid, name = params.get(PID_ENDPOINT_GUID), params.get(PID_TOPIC_NAME)
    if guid is None or name is None or len(guid) < 16 or len(name) < 4:
        return None
    size = struct.unpack_from("<I" if params[-1] == b"\x01" else ">I", name)[0]
    return guid[:16], name[4:4 + size].rstrip(b"\x00").decode(errors="replace")


class Counter:
    """Bytes and samples per (direction, label), from Ethernet frames."""

    def __init__(self) -> None:
        self.endpoints: Dict[bytes, str] = {}  # 16-byte GUID -> topic name
        self.bytes: Dict[Tuple[str, str], int] = collections.defaultdict(int)
        self.frames: Dict[Tuple[str, str], int] = collections.defaultdict(int)
        self.samples: Dict[Tuple[str, str], int] = collections.defaultdict(int)
        self.repeats: Dict[Tuple[str, str], int] = collections.defaultdict(int)
        self.sample_bytes: Dict[Tuple[str, str], int] = collections.defaultdict(int)
        self._sent: Dict[Tuple[bytes, int], int] = {}  # (writer GUID, SN) -> times sent
        self._shares: Dict[Tuple[bytes, int], List[Tuple[str, float]]] = {}  # IP datagram -> label shares
        self._pending: Dict[Tuple[bytes, int], List[bytes]] = {}  # metatraffic fragments to reassemble
        self._direction = ""

    def add(self, direction: str, frame: bytes) -> None:
        wire = len(frame)
        if len(frame) < 34 or frame[12:14] != b"\x08\x00":
            self._count(direction, [("non-RTPS", 1.0)], wire)
            return
        ip = frame[14:]
        ihl = (ip[0] & 0x0F) * 4
        total_len, ident, frag = struct.unpack_from(">HHH", ip, 2)
        offset, more = (frag & 0x1FFF) * 8, bool(frag & 0x2000)
        key = (ip[12:20], ident)
        if ip[9] != 17:  # not UDP
            self._count(direction, [("non-RTPS", 1.0)], wire)
            return
        if offset == 0:
            udp = ip[ihl:total_len]
            dport = struct.unpack_from(">H", udp, 2)[0]
            payload = udp[8:]
            if more and dport % 2 == 0:  # metatraffic (even port): reassembled for the SEDP contents
                self._pending[key] = [payload]
            udp_len = struct.unpack_from(">H", udp, 4)[0]
            shares = self._parse(payload, udp_len - 8) if not (more and dport % 2 == 0) else [(UNATTRIBUTED, 1.0)]
            if more:
                self._shares[key] = shares
        else:
            shares = self._shares.get(key, [(UNATTRIBUTED, 1.0)])
            if key in self._pending:
                self._pending[key].append(ip[ihl:total_len])
                if not more:
                    whole = b"".join(self._pending.pop(key))
                    shares = self._shares[key] = self._parse(whole)
            if not more:
                self._shares.pop(key, None)
        self._count(direction, shares, wire)

    def _count(self, direction: str, shares: List[Tuple[str, float]], wire: int) -> None:
        for label, share in shares:
            self.bytes[direction, label] += int(round(wire * share))
            self.frames[direction, label] += 1

    def _parse(self, msg: bytes, full_len: int = 0) -> List[Tuple[str, float]]:
        """Label shares of one RTPS message (by submessage length); SEDP announcements are learnt.

        ``msg`` may be the first IP fragment only: ``full_len`` is then the whole message's length.
        """
        limit = max(full_len, len(msg))
        if len(msg) < 20 or msg[:4] != b"RTPS":
            return [("non-RTPS", 1.0)]
        src, dst = msg[8:20], b""
        sizes: Dict[str, int] = collections.defaultdict(int)
        carry, pos = 20, 20  # header and INFO_* bytes go to the next labelled submessage
        while pos + 4 <= len(msg):
            sid, flags = msg[pos], msg[pos + 1]
            little = flags & 1
            size = struct.unpack_from("<H" if little else ">H", msg, pos + 2)[0]
            body = pos + 4
            end = limit if size == 0 else min(limit, body + size)
            label = None
            if sid == INFO_SRC and end - body >= 20:
                src = msg[body + 8:body + 20]
            elif sid == INFO_DST and end - body >= 12:
                dst = msg[body:body + 12]
            elif sid in WRITER_SENT and end - body >= 12:
                at = body + 8 if sid in (DATA, DATA_FRAG) else body + 4  # DATA: extraFlags, octetsToInlineQos first
                writer = struct.unpack_from(">I", msg, at)[0]
                guid = src + msg[at:at + 4]
                label = _builtin_label(writer) or self.endpoints.get(guid, UNATTRIBUTED)
                if sid in (DATA, DATA_FRAG) and end - body >= 16:
                    self._sample(sid, flags, msg, body, end, guid, writer, label)
            elif sid in READER_SENT and end - body >= 8:
                reader, writer = struct.unpack_from(">II", msg, body)
                label = (_builtin_label(writer) or self.endpoints.get(src + msg[body:body + 4])
                         or self.endpoints.get(dst + msg[body + 4:body + 8], UNATTRIBUTED))
            carry += end - pos
            if label is not None:
                sizes[label] += carry
                carry = 0
            pos = end
        if carry and sizes:
            sizes[max(sizes, key=lambda k: sizes[k])] += carry
        total = sum(sizes.values())
        return [(k, v / total) for k, v in sizes.items()] if total else [(UNATTRIBUTED, 1.0)]

    def _sample(self, sid: int, flags: int, msg: bytes, body: int, end: int, guid: bytes, writer: int,
                label: str) -> None:
        little = flags & 1
        e = "<" if little else ">"
        to_inline = struct.unpack_from(e + "H", msg, body + 2)[0]
        sn_high, sn_low = struct.unpack_from(e + "iI", msg, body + 12)
        sn = (sn_high << 32) | sn_low
        if sid == DATA_FRAG:
            first = struct.unpack_from(e + "I", msg, body + 20)[0] if end - body >= 32 else 0
            if first != 1:
                return
            size = struct.unpack_from(e + "I", msg, body + 28)[0]
            payload = b""
        else:
            start = body + 4 + to_inline
            if flags & 0x02:  # inline QoS: a parameter list up to its sentinel
                pl_end = start
                while pl_end + 4 <= end:
                    pid, plen = struct.unpack_from(e + "HH", msg, pl_end)
                    pl_end += 4 + plen
                    if pid == PID_SENTINEL:
                        break
                start = pl_end
            payload = msg[start:end]
            size = end - start
        key = (self._direction, label)
        self.samples[key] += 1
        self.sample_bytes[key] += size
        times = self._sent.get((guid, sn), 0)
        self._sent[guid, sn] = times + 1
        if times:
            self.repeats[key] += 1
        if writer in (SEDP_PUB_WRITER, SEDP_SUB_WRITER) and payload:
            found = _topic_of(_parameter_list(payload))
            if found:
                self.endpoints[found[0]] = found[1]

    def reset_counts(self) -> None:
        """Start counting afresh (the endpoints learnt so far are kept)."""
        for table in (self.bytes, self.frames, self.samples, self.repeats, self.sample_bytes):
            table.clear()

    def feed(self, direction: str, frame: bytes) -> None:
        """Count one Ethernet frame that went in ``direction`` ("a_to_b" or "b_to_a")."""
        self._direction = direction
        self.add(direction, frame)

    def result(self) -> Dict[str, Any]:
        labels = sorted({label for _, label in self.bytes} | {label for _, label in self.samples})
        rows = []
        for label in labels:
            row: Dict[str, Any] = {"label": label}
            for direction in ("a_to_b", "b_to_a"):
                key = (direction, label)
                row[direction] = {"bytes": self.bytes.get(key, 0), "frames": self.frames.get(key, 0),
                                  "samples": self.samples.get(key, 0), "repeats": self.repeats.get(key, 0),
                                  "sample_bytes": self.sample_bytes.get(key, 0)}
            rows.append(row)
        return {"rows": rows, "endpoints": len(self.endpoints)}


def capture(dev: str, out_path: str) -> int:
    """Count the frames on dev (inside its namespace) until SIGINT/SIGTERM, then write out_path."""
    sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ALL))
    sock.bind((dev, 0))
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 32 * 1024 * 1024)
    sock.settimeout(0.2)
    counter = Counter()
    stopping = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stopping.append(1))
    started = time.time()
    startup: Dict[str, Any] = {}

    def on_usr1(*_) -> None:  # the run starts now: what came before (discovery, start-up) is kept apart
        nonlocal started
        startup.update(counter.result(), seconds=time.time() - started)
        counter.reset_counts()
        started = time.time()

    signal.signal(signal.SIGUSR1, on_usr1)
    print(f"[capture] counting on {dev}", flush=True)
    while not stopping:
        try:
            frame, address = sock.recvfrom(65535)
        except socket.timeout:
            continue
        except InterruptedError:
            continue
        # Captured on host B's end of the link: outgoing frames go B -> A.
        counter.feed("b_to_a" if address[2] == PACKET_OUTGOING else "a_to_b", frame)
    result = counter.result()
    result["seconds"] = time.time() - started
    result["startup"] = startup
    with open(out_path + ".tmp", "w") as handle:
        json.dump(result, handle)
    os.replace(out_path + ".tmp", out_path)
    return 0


def table(run: Dict[str, Any], frames: Optional[int] = None, seconds: Optional[float] = None,
          fps: Tuple[float, ...] = (5.0, 30.0)) -> str:
    """The per-topic table of a run (the test's traffic.json: the capture plus frames and seconds).

    Per camera frame each way, samples per frame, repeated samples, the mean serialized sample, the
    measured kbit/s, and what the same bytes per frame make at each rate of ``fps`` (Mbit/s, both ways).
    """
    cap = run["capture"] if "capture" in run else run
    frames = frames or int(run.get("frames", 0)) or 1
    seconds = seconds or float(run.get("seconds", cap.get("seconds", 1.0)))
    rows = sorted(cap["rows"], key=lambda r: -(r["a_to_b"]["bytes"] + r["b_to_a"]["bytes"]))
    lines = [f"{frames} frames in {seconds:.1f} s ({frames / seconds:.2f} FPS); bytes on the wire per frame",
             f"{'label':44s} {'A->B B/frame':>13s} {'B->A B/frame':>13s} {'samples/frame':>14s} "
             f"{'repeats':>8s} {'B/sample':>9s} {'kbit/s':>9s}" + "".join(f" {f'Mb/s@{f:g}':>9s}" for f in fps)]
    total = 0
    for row in rows:
        ab, ba = row["a_to_b"], row["b_to_a"]
        nbytes = ab["bytes"] + ba["bytes"]
        total += nbytes
        samples = ab["samples"] + ba["samples"]
        per_sample = (ab["sample_bytes"] + ba["sample_bytes"]) / samples if samples else 0.0
        lines.append(f"{row['label'][:44]:44s} {ab['bytes'] / frames:13.0f} {ba['bytes'] / frames:13.0f} "
                     f"{samples / frames:14.2f} {ab['repeats'] + ba['repeats']:8d} {per_sample:9.0f} "
                     f"{nbytes * 8e-3 / seconds:9.1f}" + "".join(f" {nbytes / frames * f * 8e-6:9.3f}" for f in fps))
    lines.append(f"{'total':44s} {total / frames:13.0f} bytes/frame, {total * 8e-6 / seconds:.2f} Mbit/s; "
                 + ", ".join(f"{total / frames * f * 8e-6:.1f} Mbit/s at {f:g} FPS" for f in fps))
    return "\n".join(lines)


def main(argv=None) -> int:
    """``capture`` or ``table`` (module docstring); exit 2 when the run file cannot be read."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    cap = sub.add_parser("capture")
    cap.add_argument("dev")
    cap.add_argument("out")
    tab = sub.add_parser("table")
    tab.add_argument("run")
    tab.add_argument("--frames", type=int)
    tab.add_argument("--seconds", type=float)
    tab.add_argument("--fps", type=float, nargs="+", default=[5.0, 30.0], help="rates to scale the bytes to")
    args = parser.parse_args(argv)
    if args.command == "capture":
        return capture(args.dev, args.out)
    try:
        with open(args.run) as handle:
            run = json.load(handle)
    except (OSError, ValueError) as error:
        print(f"two_host_traffic: cannot read {args.run}: {error}", file=sys.stderr)
        return 2
    print(table(run, args.frames, args.seconds, tuple(args.fps)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
