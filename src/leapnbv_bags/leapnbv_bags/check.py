"""Checking a rosbag2 bag before it is used: its directory, metadata.yaml, and every MCAP record's CRC."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple, Union

from leapnbv_bags.errors import BagError

__all__ = ["METADATA_FILE", "BagCheck", "McapFileCheck", "bag_layout", "check_bag", "summary_note",
           "validate_bag_crcs", "walk_mcap"]

METADATA_FILE = "metadata.yaml"


@dataclass
class McapFileCheck:
    """What a sequential, CRC-checked walk of one MCAP file found.

    ``data_complete``: the data section ends with its DataEnd record (every chunk read and its CRC
    right); ``summary``: the summary and footer followed (a seeking reader can open the file).
    """

    path: Path
    messages: int = 0
    data_complete: bool = False
    summary: bool = False
    summary_problem: str = ""


@dataclass
class BagCheck:
    """A rosbag2 directory checked before use: its storage, files, message count, and notes."""

    path: Path
    storage: str
    files: List[Path]
    messages: int = 0
    mcap: List[McapFileCheck] = field(default_factory=list)
    notes: List[str] = field(default_factory=list)

    @property
    def summary_intact(self) -> bool:
        """Every MCAP file has its summary and footer (rosbags' seeking reader can open them)."""
        return all(f.summary for f in self.mcap)


def bag_layout(bag_path: Path) -> Tuple[str, List[Path]]:
    """(storage identifier, data files) of a rosbag2 directory, after the checks that cost nothing.

    Raises:
        BagError: no such path, a file instead of a directory, an empty directory, no or an
            unreadable metadata.yaml, or a listed data file that is missing or empty.
    """
    if not bag_path.exists():
        raise BagError(f"{bag_path}: no such bag (the path does not exist)")
    if not bag_path.is_dir():
        raise BagError(f"{bag_path}: a file, not a rosbag2 bag directory (pass the directory that holds "
                       f"{METADATA_FILE})")
    entries = sorted(p.name for p in bag_path.iterdir())
    if not entries:
        raise BagError(f"{bag_path}: empty directory, not a rosbag2 bag (no {METADATA_FILE}, no data files)")
    metadata_path = bag_path / METADATA_FILE
    if not metadata_path.is_file():
        raise BagError(f"{bag_path}: {METADATA_FILE} is missing (the directory holds {', '.join(entries)}); "
                       f"`ros2 bag reindex {bag_path}` rebuilds it")
    import yaml

    try:
        document = yaml.safe_load(metadata_path.read_text(encoding="utf-8"))
        info = document["rosbag2_bagfile_information"]
        storage = str(info.get("storage_identifier") or "")
        relative = [str(f) for f in (info.get("relative_file_paths") or [])]
    except Exception as error:  # noqa: BLE001 - yaml errors, a missing key, a document that is not a mapping
        detail = " ".join(str(error).split())
        raise BagError(f"{metadata_path}: not rosbag2 metadata ({type(error).__name__}: {detail})") from None
    if not relative:
        raise BagError(f"{metadata_path}: lists no data files")
    files = [bag_path / name for name in relative]
    for data_file in files:
        if not data_file.is_file():
            raise BagError(f"{data_file}: listed in {METADATA_FILE} but missing")
        if data_file.stat().st_size == 0:
            raise BagError(f"{data_file}: empty file (0 bytes)")
    return storage, files


def walk_mcap(path: Path, on_message: Optional[Callable[[Any, Any, Any], Any]] = None) -> McapFileCheck:
    """Read an MCAP file record by record from its start, checking every chunk's and the data section's CRC.

    Args:
        path: the .mcap file.
        on_message: called as ``on_message(schema, channel, message)`` for each message (mcap records).

    Returns:
        What was found; a missing or damaged summary / footer after a complete data section is noted,
        not raised: the data is whole.

    Raises:
        BagError: the data section is truncated (the file ends before its DataEnd record) or corrupt
            (a CRC that does not match, a chunk that does not decompress, a record that does not parse).
    """
    from mcap.exceptions import EndOfFile, RecordLengthLimitExceeded
    from mcap.records import Channel, DataEnd, Footer, Message, Schema
    from mcap.stream_reader import StreamReader

    check = McapFileCheck(path)
    size = path.stat().st_size
    schemas: Dict[int, Any] = {}
    channels: Dict[int, Any] = {}
    with open(path, "rb") as stream:
        last_good = 0
        try:
            for record in StreamReader(stream, validate_crcs=True, record_size_limit=max(size, 1)).records:
                if isinstance(record, Message):
                    check.messages += 1
                    if on_message is not None:
                        channel = channels[record.channel_id]
                        on_message(schemas.get(channel.schema_id), channel, record)
                elif isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, DataEnd):
                    check.data_complete = True
                elif isinstance(record, Footer):
                    check.summary = True
                last_good = stream.tell()
        except Exception as error:  # noqa: BLE001 - mcap, zstd, struct, KeyError (a message before its channel)
            # A record longer than the whole file (the limit) runs past its end: cut, like an early end of file.
            ends = isinstance(error, (EndOfFile, RecordLengthLimitExceeded)) or stream.tell() >= size
            detail = "the file ends" if isinstance(error, EndOfFile) else \
                f"{type(error).__name__}: {' '.join(str(error).split())}"
            if check.data_complete:
                check.summary_problem = detail
                return check
            if ends:
                raise BagError(f"{path}: truncated: the data section stops inside a record after byte {last_good} "
                               f"of {size} ({check.messages} complete messages before it, no DataEnd record; "
                               f"{detail})") from None
            raise BagError(f"{path}: corrupt data after byte {last_good} of {size} ({check.messages} messages "
                           f"read before it): {detail}") from None
    return check


def check_bag(path: Union[str, Path]) -> BagCheck:
    """Open a rosbag2 bag and check all of it before it is used (the bag tools call this first).

    Checks the directory and metadata.yaml, then walks every MCAP file from its start with CRC
    checks. A file whose summary or footer is missing or damaged after a complete data section is
    readable (noted in ``notes``: :func:`read_bag` reads it sequentially); SQLite storage is left to
    rosbags.

    Raises:
        BagError: one line naming the path and what is wrong (see bag_layout and walk_mcap).
    """
    bag_path = Path(path)
    storage, files = bag_layout(bag_path)
    check = BagCheck(bag_path, storage, files)
    if storage != "mcap":
        return check
    for data_file in files:
        found = walk_mcap(data_file)
        check.mcap.append(found)
        check.messages += found.messages
        if not found.summary:
            check.notes.append(summary_note(found))
    return check


def summary_note(found: McapFileCheck) -> str:
    why = f" ({found.summary_problem})" if found.summary_problem else ""
    return (f"{found.path}: no MCAP summary/footer{why}; the data section is complete ({found.messages} "
            "messages, CRCs right): read sequentially")


def validate_bag_crcs(path: Union[str, Path]) -> Dict[str, int]:
    """Read every MCAP file of a rosbag2 directory with CRC checks and count messages per topic.

    Args:
        path: rosbag2 directory, or a single ``.mcap`` file.

    Returns:
        Message count per topic over all files.

    Raises:
        BagError: No MCAP file found, a CRC does not match, or a file does not parse.
    """
    from mcap.reader import NonSeekingReader

    bag_path = Path(path)
    files = [bag_path] if bag_path.is_file() else sorted(bag_path.glob("*.mcap"))
    if not files:
        raise BagError(f"{bag_path}: no .mcap file")
    counts: Dict[str, int] = {}
    for mcap_file in files:
        try:
            with open(mcap_file, "rb") as stream:
                # The non-seeking reader walks every record, so it checks the data-section CRC
                # as well as each chunk's.
                reader = NonSeekingReader(stream, validate_crcs=True)
                for _schema, channel, _message in reader.iter_messages():
                    counts[channel.topic] = counts.get(channel.topic, 0) + 1
        except Exception as error:
            raise BagError(f"{mcap_file}: MCAP validation failed: {error}") from error
    return counts
