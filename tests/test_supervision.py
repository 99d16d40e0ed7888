"""Supervision by the graph runner's command line.

Readiness means every node serving (a node whose model is missing is reported and the rest runs;
--require-all exits 1), SIGINT/SIGTERM stop every node with exit 0, a node that keeps dying ends the
runner with exit 1, the runner's status on /diagnostics; and the restart policy itself.
"""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from typing import List, Tuple

import pytest

pytest.importorskip("rclpy")

from node_harness import Probe, diag_value  # noqa: E402

from leapnbv_bringup.graph import node_names  # noqa: E402
from leapnbv_bringup.graph_runner import RUNNER_STATUS_NAME, RestartPolicy  # noqa: E402
from leapnbv_stand_ins.files import ensure_stand_in_body_model  # noqa: E402

pytestmark = pytest.mark.ros


def runner_cli(log_dir, *args: str) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "leapnbv_bringup.graph_runner", "--log-dir", str(log_dir), *args]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))


def read_until(proc: subprocess.Popen, pattern: str, timeout_s: float) -> Tuple[bool, str]:
    """Lines of the runner's output until one matches (or it exits, or the time is up).

    Reads the pipe's file descriptor a byte at a time: the text wrapper's readline would pull several
    lines into its own buffer, where select() no longer sees them, and a match among them would wait
    for the next line the runner prints (none, when it waits for a model file). Nothing is read past
    the matching line, so a later communicate() gets the rest.
    """
    import selectors

    fd = proc.stdout.fileno()
    out: List[str] = []
    line = bytearray()
    selector = selectors.DefaultSelector()
    selector.register(fd, selectors.EVENT_READ)
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline:
            if not selector.select(timeout=0.2):
                if proc.poll() is not None:
                    break
                continue
            byte = os.read(fd, 1)
            if not byte:
                break
            line += byte
            if byte != b"\n":
                continue
            text = line.decode("utf-8", errors="replace")
            line.clear()
            out.append(text)
            if re.search(pattern, text):
                return True, "".join(out)
    finally:
        selector.close()
    if line:
        out.append(line.decode("utf-8", errors="replace"))
    return False, "".join(out)


def ground_truth_args() -> List[str]:
    return ["--perception", "ground_truth", "--body-model", ensure_stand_in_body_model("small")]


@pytest.mark.slow
@pytest.mark.parametrize("stop_signal", [signal.SIGTERM, signal.SIGINT])
def test_signal_to_runner_ends_every_node_with_exit_0_and_no_traceback(tmp_path, stop_signal):
    proc = runner_cli(tmp_path, *ground_truth_args())
    try:
        ready, out = read_until(proc, r"\[graph\] ready in", 90.0)
        assert ready, out
        if stop_signal == signal.SIGTERM:
            # The runner reports each node on /diagnostics; kill one by the pid it reports, see it come back.
            probe = Probe("runner_status_probe")
            try:
                assert probe.spin_until(lambda: probe.status_where(RUNNER_STATUS_NAME, lambda s: True), 15.0)
                status = probe.status_where(RUNNER_STATUS_NAME, lambda s: True)
                pid = int(diag_value(status, "nbv_node.pid"))
                assert diag_value(status, "nbv_node.restarts") == "0"
                assert diag_value(status, "nbv_node.state") == "running"
                os.kill(pid, signal.SIGKILL)
                back = probe.spin_until(lambda: probe.status_where(
                    RUNNER_STATUS_NAME, lambda s: diag_value(s, "nbv_node.restarts") == "1"
                    and diag_value(s, "nbv_node.state") == "running"), 20.0)
                assert back, probe.statuses.get(RUNNER_STATUS_NAME, [])[-1:]
                status = probe.status_where(RUNNER_STATUS_NAME, lambda s: diag_value(s, "nbv_node.restarts") == "1")
                assert diag_value(status, "nbv_node.last_exit") == "killed by SIGKILL"
                assert int(diag_value(status, "nbv_node.pid")) != pid
                assert status.level == status.WARN and "nbv_node restarted" in status.message
            finally:
                probe.close()
            served, more = read_until(proc, r"nbv_node serving again", 20.0)
            out += more
            assert served, out
        proc.send_signal(stop_signal)
        rest, _ = proc.communicate(timeout=40)
        out += rest
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, out
    assert f"[graph] {stop_signal.name}: stopping the nodes" in out
    stopped = re.search(r"\[graph\] stopped: (.*)", out).group(1)
    assert stopped == ", ".join(f"{n}: exit 0" for n in node_names()), out
    for log in tmp_path.glob("*.log"):
        text = log.read_text(errors="replace")
        assert "Traceback" not in text and "internal_error" not in text, f"{log.name}:\n{text[-3000:]}"


# How a node whose model did not load is named: a managed node stays unconfigured with its configure's
# reason; a node that is not managed yet reports its engine state.
NOT_LOADED = r"(?:engine not ready|unconfigured: configure failed): "


@pytest.mark.slow
def test_readiness_names_nodes_whose_engine_did_not_load(tmp_path):
    # onnxruntime with model paths that do not exist: both perception nodes fail to load, and with
    # --require-all the runner exits 1 after its ready timeout.
    missing = tmp_path / "no_such_model.onnx"
    proc = runner_cli(tmp_path, "--perception", "onnxruntime", "--detector-model", str(missing),
                      "--hmr-model", str(missing), "--body-model", ensure_stand_in_body_model("small"),
                      "--ready-timeout", "20", "--require-all")
    try:
        out, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 1, out
    assert "[graph] ready" not in out
    line = next(ln for ln in out.splitlines() if "graph not ready after 20 s" in ln)
    assert re.search(r"detector_node: " + NOT_LOADED + r"detector model .*no_such_model\.onnx.* not loaded", line), line
    assert re.search(r"hmr_node: " + NOT_LOADED + r".*not loaded", line), line
    for name in ("raster_node", "ground_node", "nbv_node"):
        assert f"{name}:" not in line, line  # they are ready: only the two are named
    assert ", ".join(f"{n}: exit 0" for n in node_names()) in out


@pytest.mark.slow
def test_graph_runs_without_a_node_whose_model_is_missing_and_takes_it_in_when_the_file_appears(tmp_path):
    # By default the runner reports the detector (its model missing), runs the rest, retries the
    # detector, and is ready once the file is there.
    from leapnbv_stand_ins.files import ensure_contract_models

    detector_model, hmr_model = ensure_contract_models()
    late = tmp_path / "late_detector.onnx"
    proc = runner_cli(tmp_path, "--perception", "onnxruntime", "--detector-model", str(late), "--hmr-model",
                      hmr_model, "--body-model", ensure_stand_in_body_model("small"), "--configure-retry", "1")
    try:
        running, out = read_until(proc, r"\[graph\] (running without|ready in)", 120.0)
        assert running and "[graph] running without detector_node after" in out, out
        line = next(ln for ln in out.splitlines() if "running without" in ln)
        assert re.search(r"detector_node: " + NOT_LOADED + r"detector model .*late_detector\.onnx.* not loaded",
                         line), line
        for name in ("hmr_node", "raster_node", "ground_node", "nbv_node"):
            assert f"{name}:" not in line, line
        assert proc.poll() is None
        probe = Probe("runner_partial_probe")
        try:
            status = probe.status_where  # the runner's status names the node and why, at ERROR
            assert probe.spin_until(lambda: status(RUNNER_STATUS_NAME, lambda s: "detector_node" in s.message), 15.0)
            latest = status(RUNNER_STATUS_NAME, lambda s: "detector_node" in s.message)
            assert latest.level == latest.ERROR and "late_detector.onnx" in diag_value(latest, "detector_node.serving")
            assert diag_value(latest, "nbv_node.serving") == "yes"
        finally:
            probe.close()
        import shutil

        shutil.copy(detector_model, late)  # the model appears: the next retry loads it
        ready, more = read_until(proc, r"\[graph\] ready in .* every node serving now", 60.0)
        out += more
        assert ready, out
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=40)
        out += rest
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, out
    assert ", ".join(f"{n}: exit 0" for n in node_names()) in out


@pytest.mark.slow
def test_node_that_keeps_dying_is_reported_and_runner_exits_1(tmp_path):
    # radius is range-checked: nbv_node refuses to start with it, every time.
    proc = runner_cli(tmp_path, *ground_truth_args(), "--set", "nbv_node.radius=-1.0", "--max-restarts", "2",
                      "--restart-backoff", "0.1", "--no-warm-spares", "--ready-timeout", "120")
    try:
        # Three cold starts of nbv_node take seconds alone; under CI's load they took longer once.
        # Past --ready-timeout the runner itself must have exited, so the wait is the runner's
        # limit plus its stop, and a hang fails with the runner's output (not a bare TimeoutExpired).
        out, _ = proc.communicate(timeout=240)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # the runner and the nodes it started (its own session)
        out, _ = proc.communicate()
        pytest.fail(f"graph_runner still running 240 s after start (--ready-timeout 120):\n{out}")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 1, out
    deaths = re.findall(r"nbv_node died \(exit 2\); restarting in ([0-9.]+) s", out)
    assert [float(d) for d in deaths] == [0.1, 0.2], out  # exponential back-off
    assert re.search(r"nbv_node died 3 times within 60 s \(last: exit 2\), more than --max-restarts 2; giving up",
                     out), out
    assert "radius" in (tmp_path / "nbv_node.log").read_text()


def test_restart_policy_back_off_and_limit():
    policy = RestartPolicy(max_restarts=4, window_s=10.0, backoff_s=0.5, backoff_max_s=3.0)
    assert [policy.delay_s(k) for k in range(1, 6)] == [0.5, 1.0, 2.0, 3.0, 3.0]
    assert not policy.gives_up(4) and policy.gives_up(5)
    assert policy.recent([0.0, 5.0, 9.0, 12.0], now=14.0) == 3  # the death at 0 s left the window
    assert RestartPolicy(window_s=0.0).recent([0.0, 1e6], now=2e6) == 2  # 0: the whole run
    with pytest.raises(ValueError):
        RestartPolicy(max_restarts=-1)


# A node stuck in C (here: a sleep with SIGINT and SIGTERM ignored), as run_node's own stack-dump
# registration leaves it: the runner asks for its stacks, escalates, and says so.
STUCK_NODE = """
import faulthandler, signal, sys, time
faulthandler.register(signal.SIGUSR1, all_threads=True)
signal.signal(signal.SIGINT, signal.SIG_IGN)
signal.signal(signal.SIGTERM, signal.SIG_IGN)
print("stuck node up", flush=True)
def wait_in_c_for_ever():
    time.sleep(3600)
wait_in_c_for_ever()
"""


def test_stop_dumps_the_stacks_of_a_node_that_does_not_exit_then_kills_it(tmp_path, monkeypatch):
    from leapnbv_bringup.graph_runner import GraphRunner

    runner = GraphRunner(log_dir=str(tmp_path), nodes=["raster_node"])
    monkeypatch.setattr(runner, "_command", lambda spec: [sys.executable, "-c", STUCK_NODE])
    runner.start()
    log = tmp_path / "raster_node.log"
    deadline = time.monotonic() + 20
    while "stuck node up" not in log.read_text() and time.monotonic() < deadline:
        time.sleep(0.05)
    codes = runner.stop(timeout_s=0.5)
    assert codes == {"raster_node": -signal.SIGKILL}
    assert runner.stop_report["raster_node"].startswith("killed by SIGKILL after SIGKILL (no exit 0 s after SIGINT"), \
        runner.stop_report
    assert not runner.stopped_cleanly
    text = log.read_text()
    assert "wait_in_c_for_ever" in text and "File " in text, text  # faulthandler's stack of the main thread


def test_standby_process_loads_the_type_support_of_every_imported_message_type():
    # In a fresh interpreter (the test process has loaded many types already): what a standby does
    # before it says it is warm, so that the node it becomes builds without loading them.
    code = ("import leapnbv_msgs.msg as m, rcl_interfaces.srv as s\n"
            "from leapnbv_bringup.graph_runner import warm_type_support\n"
            "assert type(m.GoalStatus)._TYPE_SUPPORT is None\n"
            "n = warm_type_support()\n"
            "assert type(m.GoalStatus)._TYPE_SUPPORT is not None and type(m.HumanMesh)._TYPE_SUPPORT is not None\n"
            "assert type(s.SetParameters)._TYPE_SUPPORT is not None\n"
            "assert warm_type_support() == 0\n"
            "print(n)\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert int(result.stdout.split()[-1]) > 20
