"""leapnbv_bags.bag_io: one import for the bag modules, the bag tools' exit codes, and the bag check's command line."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from leapnbv_bags import bag_io, check, cli, errors, reader, typestore, writer
from leapnbv_common.exit_codes import BagToolExit, GraphRunnerExit

SRC = Path(__file__).resolve().parents[2]


def test_bag_io_is_the_names_of_its_modules():
    for module in (check, cli, errors, reader, typestore, writer):
        for name in module.__all__:
            if name in bag_io.__all__:
                assert getattr(bag_io, name) is getattr(module, name), f"{module.__name__}.{name}"
    assert {"BagWriter", "read_bag", "check_bag", "validate_bag_crcs", "BagError", "make_typestore", "RELIABLE_QOS",
            "SENSOR_DATA_QOS", "TRANSIENT_LOCAL_QOS", "main"} <= set(bag_io.__all__)
    assert all(hasattr(bag_io, name) for name in bag_io.__all__)


def test_the_exit_code_tables_are_the_documented_ones():
    # README, "Bag tools: checks and exit codes" and the graph runner's exit codes.
    assert [(e.name, int(e)) for e in BagToolExit] == [
        ("OK", 0), ("OUTPUTS_CHANGED", 1), ("USAGE", 2), ("UNREADABLE_BAG", 3), ("GRAPH_FAILED", 4)]
    assert [(e.name, int(e)) for e in GraphRunnerExit] == [("OK", 0), ("GRAPH_FAILED", 1), ("USAGE", 2),
                                                           ("UNCLEAN_STOP", 3)]
    assert (bag_io.EXIT_OK, bag_io.EXIT_OUTPUTS_CHANGED, bag_io.EXIT_USAGE, bag_io.EXIT_UNREADABLE_BAG) == (
        BagToolExit.OK, BagToolExit.OUTPUTS_CHANGED, BagToolExit.USAGE, BagToolExit.UNREADABLE_BAG)
    assert f"{BagToolExit.UNREADABLE_BAG}" == "3"  # as the tools print it, on every Python


def _write_bag(path: Path) -> None:
    with writer.BagWriter(path) as bag:
        bag.add_topic("/chatter", "std_msgs/msg/String", qos=writer.TRANSIENT_LOCAL_QOS)
        string = bag.typestore.types["std_msgs/msg/String"]
        for i in range(3):
            bag.write("/chatter", 1_000 + i, string(data=f"hello {i}"))


def test_the_check_prints_topics_and_counts_or_one_line_with_exit_3(tmp_path, capsys):
    _write_bag(tmp_path / "bag")
    assert cli.main([str(tmp_path / "bag")]) == BagToolExit.OK
    out = capsys.readouterr().out
    assert "mcap, 1 file(s), 3 messages" in out and "3  /chatter (std_msgs/msg/String)" in out
    assert cli.main([str(tmp_path / "missing")]) == BagToolExit.UNREADABLE_BAG
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing: no such bag" in err[0]


def test_python_m_bag_io_is_the_check(tmp_path):
    _write_bag(tmp_path / "bag")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(SRC / "leapnbv_bags"), str(SRC / "leapnbv_common"), os.environ.get("PYTHONPATH", "")]))
    run = [sys.executable, "-m", "leapnbv_bags.bag_io"]
    ok = subprocess.run([*run, str(tmp_path / "bag")], capture_output=True, text=True, env=env, timeout=120)
    assert ok.returncode == 0 and "3 messages" in ok.stdout, ok.stderr
    (tmp_path / "empty").mkdir()
    bad = subprocess.run([*run, str(tmp_path / "empty")], capture_output=True, text=True, env=env, timeout=120)
    assert bad.returncode == 3 and bad.stderr.count("\n") == 1 and "empty directory" in bad.stderr
    usage = subprocess.run(run, capture_output=True, text=True, env=env, timeout=120)
    assert usage.returncode == 2 and "Exit codes: 0 readable, 2 usage, 3 unreadable bag" in " ".join(
        subprocess.run([*run, "--help"], capture_output=True, text=True, env=env, timeout=120).stdout.split())


def test_a_half_written_bag_never_appears(tmp_path):
    with pytest.raises(RuntimeError):
        with writer.BagWriter(tmp_path / "bag") as bag:
            bag.add_topic("/chatter", "std_msgs/msg/String")
            raise RuntimeError("recording interrupted")
    assert not (tmp_path / "bag").exists() and list(tmp_path.iterdir()) == []
    with pytest.raises(errors.BagError, match="exists already"):
        (tmp_path / "taken").mkdir()
        writer.BagWriter(tmp_path / "taken")
