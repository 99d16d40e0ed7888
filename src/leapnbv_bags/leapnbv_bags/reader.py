"""Reading a rosbag2 bag's messages in log-time order, a bag without its MCAP summary included."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple, Union

from rosbags.highlevel import AnyReader

from leapnbv_bags.check import bag_layout, summary_note, walk_mcap
from leapnbv_bags.errors import BagError
from leapnbv_bags.typestore import make_typestore, normalize_msgtype, register_definitions

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

__all__ = ["read_bag"]


def read_bag(
    path: Union[str, Path], topics: Optional[Sequence[str]] = None, raw: bool = False,
    note: Optional[Callable[[str], Any]] = None,
) -> Iterator[Tuple[str, str, int, object]]:
    """Iterate over a bag's messages in log-time order, deserialized with the bag's own definitions.

    A bag whose MCAP summary or footer is missing but whose data section is complete (a recorder
    stopped before it wrote them) is read sequentially, and ``note`` is told so (by default one
    line on stderr). CRCs are checked by :func:`check_bag` (the bag tools call it first) and on a
    sequential read, not by rosbags' seeking reader.

    Args:
        path: rosbag2 directory (MCAP or SQLite storage).
        topics: Only these topics; all if None.
        raw: Yield the CDR bytes as stored instead of deserialized messages (for replay).
        note: called with a line for each file read without its summary; None prints it on stderr.

    Yields:
        (topic, msgtype, timestamp_ns, message) tuples.

    Raises:
        BagError: The bag cannot be opened (see check_bag), is truncated or corrupt, or a message
            does not deserialize; the text names the path and what is wrong.
    """
    bag_path = Path(path)
    storage, files = bag_layout(bag_path)
    try:
        reader = AnyReader([bag_path])
        reader.open()
    except Exception as error:  # noqa: BLE001 - an MCAP file without its summary: read it sequentially
        if storage != "mcap":
            raise BagError(f"{bag_path}: cannot open bag: {error}") from None
        yield from _read_mcap_sequentially(bag_path, files, topics, raw, note)
        return
    try:
        connections = [c for c in reader.connections if topics is None or c.topic in topics]
        messages = reader.messages(connections=connections)
        while True:
            try:
                connection, timestamp, rawdata = next(messages)
            except StopIteration:
                break
            except Exception as error:  # noqa: BLE001 - a chunk that does not decompress, a short read
                detail = " ".join(str(error).split()) or type(error).__name__
                raise BagError(f"{bag_path}: corrupt data: {type(error).__name__}: {detail}") from None
            if raw:
                yield connection.topic, connection.msgtype, int(timestamp), rawdata
                continue
            try:
                message = reader.deserialize(rawdata, connection.msgtype)
            except Exception as error:
                raise BagError(
                    f"{bag_path}: message on {connection.topic} does not deserialize "
                    f"as {connection.msgtype}: {error}"
                ) from error
            yield connection.topic, connection.msgtype, int(timestamp), message
    finally:
        reader.close()


def _read_mcap_sequentially(bag_path: Path, files: List[Path], topics: Optional[Sequence[str]], raw: bool,
                            note: Optional[Callable[[str], Any]]) -> Iterator[Tuple[str, str, int, object]]:
    """The messages of MCAP files read from their start (no summary needed), in log-time order."""
    collected: List[Tuple[int, int, str, str, bytes]] = []
    schema_texts: Dict[str, str] = {}

    def keep(schema: Any, channel: Any, message: Any) -> None:  # mcap's Schema, Channel, Message records
        if topics is not None and channel.topic not in topics:
            return
        msgtype = schema.name if schema is not None else ""
        if schema is not None and schema.encoding == "ros2msg":
            schema_texts.setdefault(msgtype, schema.data.decode("utf-8", errors="replace"))
        collected.append((int(message.log_time), len(collected), channel.topic, msgtype, message.data))

    for data_file in files:
        found = walk_mcap(data_file, keep)
        if not found.summary:
            line = summary_note(found)
            if note is None:
                print(f"[bag] {line}", file=sys.stderr, flush=True)
            else:
                note(line)
    collected.sort()
    typestore: Optional[Typestore] = None  # None: raw bytes are yielded
    if not raw:
        typestore = make_typestore()
        for msgtype, text in schema_texts.items():
            if normalize_msgtype(msgtype) not in typestore.fielddefs:
                register_definitions(typestore, {msgtype: text.split("\n====", 1)[0]})
    for timestamp, _, topic, msgtype, data in collected:
        if typestore is None:
            yield topic, msgtype, timestamp, data
            continue
        try:
            message = typestore.deserialize_cdr(data, normalize_msgtype(msgtype))
        except Exception as error:
            raise BagError(f"{bag_path}: message on {topic} does not deserialize as {msgtype}: {error}") from error
        yield topic, msgtype, timestamp, message
