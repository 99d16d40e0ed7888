"""Bag faults: every unreadable bag is named in one line with exit code 3 before anything starts; a bag whose
MCAP summary/footer is missing but whose data is whole is read (and said so)."""
from __future__ import annotations

import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Dict

import pytest

from leapnbv_bags.bag_io import EXIT_UNREADABLE_BAG, BagError, check_bag, read_bag

SAMPLE = "bags/sample_a"
MCAP = "sample_a.mcap"


def data_end_offset(path: Path) -> int:
    """The byte where the data section of an MCAP file ends (just after its DataEnd record)."""
    from mcap.records import DataEnd
    from mcap.stream_reader import StreamReader

    with open(path, "rb") as stream:
        for record in StreamReader(stream).records:
            if isinstance(record, DataEnd):
                return stream.tell()
    raise AssertionError("no DataEnd record")


def chunk_offsets(path: Path) -> list:
    from mcap.reader import make_reader

    with open(path, "rb") as stream:
        return [(c.chunk_start_offset, c.chunk_length) for c in make_reader(stream).get_summary().chunk_indexes]


def _cut(fraction: float) -> Callable[[Path], None]:
    def damage(bag: Path) -> None:
        data = (bag / MCAP).read_bytes()
        (bag / MCAP).write_bytes(data[: int(len(data) * fraction)])
    return damage


def _flip(where: Callable[[Path], int]) -> Callable[[Path], None]:
    def damage(bag: Path) -> None:
        data = bytearray((bag / MCAP).read_bytes())
        data[where(bag / MCAP)] ^= 0x01
        (bag / MCAP).write_bytes(bytes(data))
    return damage


def _no_metadata(bag: Path) -> None:
    (bag / "metadata.yaml").unlink()


def _garbled_metadata(bag: Path) -> None:
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")


def _empty_dir(bag: Path) -> None:
    for child in bag.iterdir():
        child.unlink()


def _zero_bytes(bag: Path) -> None:
    (bag / MCAP).write_bytes(b"")


def _missing_file(bag: Path) -> None:
    (bag / MCAP).rename(bag / "renamed.mcap")


def _first_chunk_crc(mcap: Path) -> int:
    start, _ = chunk_offsets(mcap)[2]
    return start + 1 + 8 + 8 + 8 + 8  # opcode, length, start time, end time, uncompressed size -> the CRC


def _inside_a_chunk(mcap: Path) -> int:
    start, length = chunk_offsets(mcap)[3]
    return start + length // 2


# name -> (damage, text that names the problem)
UNREADABLE: Dict[str, tuple] = {
    "metadata.yaml missing": (_no_metadata, "metadata.yaml is missing (the directory holds sample_a.mcap)"),
    "metadata.yaml unparsable": (_garbled_metadata, "not rosbag2 metadata"),
    "empty directory": (_empty_dir, "empty directory, not a rosbag2 bag"),
    "data file of 0 bytes": (_zero_bytes, "empty file (0 bytes)"),
    "listed data file missing": (_missing_file, "listed in metadata.yaml but missing"),
    "truncated in the data section": (_cut(0.5), "truncated: the data section stops inside a record"),
    "truncated after the header": (_cut(0.001), "truncated"),
    "chunk CRC that does not match": (_flip(_first_chunk_crc), "crc validation failed in Chunk"),
    "chunk that does not decompress": (_flip(_inside_a_chunk), "corrupt data after byte"),
}


@pytest.fixture()
def bag_copy(repo_root, tmp_path) -> Path:
    bag = tmp_path / "bag"
    shutil.copytree(repo_root / SAMPLE, bag)
    return bag


@pytest.mark.parametrize("fault", sorted(UNREADABLE))
def test_an_unreadable_bag_is_named_in_one_line(bag_copy, fault):
    damage, text = UNREADABLE[fault]
    damage(bag_copy)
    with pytest.raises(BagError) as checked:
        check_bag(bag_copy)
    errors = [checked.value]
    if fault != "chunk CRC that does not match":  # the data itself is intact: rosbags' reader needs no CRC
        with pytest.raises(BagError) as read:
            list(read_bag(bag_copy, raw=True))
        errors.append(read.value)
    for error in errors:
        message = str(error)
        assert str(bag_copy) in message and "\n" not in message, message
    assert text in str(checked.value), str(checked.value)
    assert not any("Is a directory" in str(error) for error in errors)


def test_no_such_path_and_a_file_are_named(tmp_path, repo_root):
    with pytest.raises(BagError, match="no such bag"):
        check_bag(tmp_path / "nowhere")
    with pytest.raises(BagError, match="a file, not a rosbag2 bag directory"):
        check_bag(repo_root / SAMPLE / MCAP)


@pytest.mark.parametrize("cut", ["last 4 KiB", "whole summary and footer"])
def test_a_bag_without_its_summary_is_read_whole_and_says_so(repo_root, bag_copy, cut):
    data = (bag_copy / MCAP).read_bytes()
    keep = len(data) - 4096 if cut == "last 4 KiB" else data_end_offset(bag_copy / MCAP)
    assert keep >= data_end_offset(bag_copy / MCAP)  # the data section itself is untouched
    (bag_copy / MCAP).write_bytes(data[:keep])
    check = check_bag(bag_copy)
    assert check.messages == 60 and not check.summary_intact  # 10 frames x 6 topics
    assert "no MCAP summary/footer" in check.notes[0] and "60 messages" in check.notes[0]
    notes = []
    got = list(read_bag(bag_copy, raw=True, note=notes.append))
    want = list(read_bag(repo_root / SAMPLE, raw=True))
    assert len(notes) == 1 and "read sequentially" in notes[0]
    key = lambda m: (m[2], m[0], bytes(m[3]))  # noqa: E731 - (log time, topic, CDR)
    assert sorted(map(key, got)) == sorted(map(key, want))
    assert [m[2] for m in got] == sorted(m[2] for m in got)  # in log-time order
    decoded = list(read_bag(bag_copy, topics=["/leapnbv/sim/ground_truth"], note=notes.append))
    assert len(decoded) == 10 and decoded[0][3].body_model_id == "stand_in_small"


def run_tool(repo_root, *args, timeout=120):
    started = time.monotonic()
    result = subprocess.run([sys.executable, "-m", *args], cwd=repo_root, capture_output=True, text=True,
                            timeout=timeout)
    return result, time.monotonic() - started


@pytest.mark.ros
@pytest.mark.parametrize("fault", ["metadata.yaml missing", "truncated in the data section",
                                   "chunk CRC that does not match", "empty directory"])
def test_the_tools_exit_3_with_one_line_before_starting_anything(repo_root, bag_copy, tmp_path, fault):
    UNREADABLE[fault][0](bag_copy)
    out = tmp_path / "regression_out"
    tools = [["leapnbv_bringup.regression", str(bag_copy), "--out", str(out)]]
    if fault == "truncated in the data section":
        tools += [["leapnbv_bringup.replay", str(bag_copy)], ["leapnbv_bags.bag_io", str(bag_copy)]]
    for tool in tools:
        result, _ = run_tool(repo_root, *tool)
        assert result.returncode == EXIT_UNREADABLE_BAG, (tool, result.stdout, result.stderr)
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and "unreadable bag" in lines[0] and str(bag_copy) in lines[0], result.stderr
        assert "Traceback" not in result.stderr + result.stdout
    assert not (out / "logs").exists()  # no node was started


@pytest.mark.ros
def test_usage_and_golden_problems_exit_2(repo_root, tmp_path):
    result, _ = run_tool(repo_root, "leapnbv_bringup.regression", SAMPLE, "--golden", str(tmp_path / "nope.npz"))
    assert result.returncode == 2 and str(tmp_path / "nope.npz") in result.stderr, result.stderr
    (tmp_path / "broken.npz").write_bytes(b"PK\x03\x04 not a zip")
    result, _ = run_tool(repo_root, "leapnbv_bringup.regression", SAMPLE, "--golden", str(tmp_path / "broken.npz"))
    assert result.returncode == 2 and "unreadable" in result.stderr and "Traceback" not in result.stderr
    result, _ = run_tool(repo_root, "leapnbv_bringup.regression")
    assert result.returncode == 2 and "usage" in result.stderr
    result, _ = run_tool(repo_root, "leapnbv_bringup.regression", "--help")
    assert result.returncode == 0 and "3  unreadable bag" in result.stdout and "4  the graph failed" in result.stdout


@pytest.mark.ros
@pytest.mark.slow
def test_regression_passes_on_a_bag_without_its_footer(repo_root, bag_copy, tmp_path):
    data = (bag_copy / MCAP).read_bytes()
    (bag_copy / MCAP).write_bytes(data[:-4096])
    result, _ = run_tool(repo_root, "leapnbv_bringup.regression", str(bag_copy), "--golden",
                         str(repo_root / f"{SAMPLE}.golden.npz"), "--out", str(tmp_path / "out"), timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "PASS: 0 problems over 10 frames x 10 topics" in result.stdout
    assert "no MCAP summary/footer" in result.stderr and "read sequentially" in result.stderr
