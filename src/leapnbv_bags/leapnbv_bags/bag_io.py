"""rosbag2 (MCAP storage) writing, reading and checking with rosbags, without ROS installed."""

from __future__ import annotations

import os
import shutil
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, Dict, Iterator, List, Mapping, Optional, Sequence, Tuple, Union

from rosbags.highlevel import AnyReader
from rosbags.interfaces import (
    Connection,
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

#: rosbag2 metadata version written (9 is what ROS 2 Jazzy's rosbag2 writes).
BAG_VERSION = 9

# rclcpp's "infinite" duration as rosbag2 (Jazzy) records it in metadata.yaml.
_INFINITE = QosTime(9223372036, 854775807)



def _recorded_qos(reliability: QosReliability, depth: int) -> Qos:
    """A keep-last, volatile QoS profile with rclcpp's default (infinite) durations, as rosbag2 records it."""
    return Qos(QosHistory.KEEP_LAST, depth, reliability, QosDurability.VOLATILE, _INFINITE, _INFINITE,
               QosLiveliness.AUTOMATIC, _INFINITE, False)


#: rclcpp::SensorDataQoS(): best effort, keep last 5, volatile.
SENSOR_DATA_QOS = _recorded_qos(QosReliability.BEST_EFFORT, 5)

#: rclcpp default publisher QoS: reliable, keep last 10, volatile.
RELIABLE_QOS = _recorded_qos(QosReliability.RELIABLE, 10)

#: Reliable + transient local (latched), as the next-best-view pose is published.
TRANSIENT_LOCAL_QOS = RELIABLE_QOS._replace(durability=QosDurability.TRANSIENT_LOCAL, depth=1)

MessageOrBytes = Union[object, bytes, bytearray, memoryview]


class BagError(Exception):
    """A bag could not be written, read or validated; the message names the path at fault."""


def find_leapnbv_msg_dir() -> Path:
    """Locate the directory holding leapnbv_msgs' ``*.msg`` files.

    Looks, in order, at ``$LEAPNBV_MSGS_DIR``, the source tree next to this package
    (``src/leapnbv_msgs/msg``) and ``share/leapnbv_msgs/msg`` under each ``$AMENT_PREFIX_PATH``
    entry (the colcon install space).

    Returns:
        The directory.

    Raises:
        BagError: No candidate directory holds ``.msg`` files.
    """
    candidates: List[Path] = []
    env_dir = os.environ.get("LEAPNBV_MSGS_DIR")
    if env_dir:
        candidates.append(Path(env_dir))
    candidates.append(Path(__file__).resolve().parents[2] / "leapnbv_msgs" / "msg")
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix:
            candidates.append(Path(prefix) / "share" / "leapnbv_msgs" / "msg")
    for candidate in candidates:
        if candidate.is_dir() and any(candidate.glob("*.msg")):
            return candidate
    raise BagError("no leapnbv_msgs .msg files found in: " + ", ".join(str(c) for c in candidates))


def load_leapnbv_msg_definitions(msg_dir: Optional[Path] = None) -> Dict[str, str]:
    """Read every ``*.msg`` file of leapnbv_msgs.

    Args:
        msg_dir: Directory of the ``.msg`` files; found with :func:`find_leapnbv_msg_dir` if None.

    Returns:
        Map from type name (``leapnbv_msgs/msg/SceneGroundTruth``) to the ``.msg`` text.

    Raises:
        BagError: The directory holds no ``.msg`` file.
    """
    directory = Path(msg_dir) if msg_dir is not None else find_leapnbv_msg_dir()
    files = sorted(directory.glob("*.msg"))
    if not files:
        raise BagError(f"{directory}: no .msg files")
    return {"leapnbv_msgs/msg/" + f.stem: f.read_text(encoding="utf-8") for f in files}


def make_typestore(extra_definitions: Optional[Mapping[str, str]] = None) -> Typestore:
    """Build a ROS 2 Jazzy typestore with leapnbv_msgs (and any extra ``.msg`` types) registered.

    Args:
        extra_definitions: More type name -> ``.msg`` text pairs to register.

    Returns:
        The typestore.

    Raises:
        BagError: A definition does not parse.
    """
    typestore = get_typestore(Stores.ROS2_JAZZY)
    definitions = dict(load_leapnbv_msg_definitions())
    if extra_definitions:
        definitions.update(extra_definitions)
    _register_definitions(typestore, definitions)
    return typestore


def _register_definitions(typestore: Typestore, definitions: Mapping[str, str]) -> None:
    """Register ``.msg`` texts (type name -> text) that the typestore does not know yet."""
    types: Dict[str, Any] = {}
    for msgtype, text in definitions.items():
        name = _normalize_msgtype(msgtype)
        if name in typestore.fielddefs:
            continue
        try:
            types.update(get_types_from_msg(text, name))
        except Exception as error:  # rosbags raises TypesysError and parser errors
            raise BagError(f"message definition of {name} does not parse: {error}") from error
    if types:
        typestore.register(types)


def _normalize_msgtype(msgtype: str) -> str:
    """Turn ``pkg/Type`` into ``pkg/msg/Type`` (rosbags' and rosbag2's spelling)."""
    parts = msgtype.split("/")
    if len(parts) == 2:
        return parts[0] + "/msg/" + parts[1]
    return msgtype


class _CrcMcapStorage:
    """rosbags storage plugin writing MCAP through the ``mcap`` library, with CRCs.

    rosbags' own MCAP storage writes every CRC as 0, which makes CRC validation vacuous. This
    plugin writes the same records (ros2 profile, one schema per type with the full ``.msg``
    definition, channels carrying ``offered_qos_profiles`` and ``topic_type_hash`` metadata as
    rosbag2 does, a ``rosbag2`` metadata record with ``serialized_metadata``) with chunk,
    data-section and summary CRCs, zstd-compressed chunks, and a statistics record.
    """

    def __init__(self, path: Path, compression: Any) -> None:
        from mcap.writer import CompressionType
        from mcap.writer import Writer as McapFileWriter

        del compression  # chunks are always zstd-compressed (what rosbag2's MCAP preset does)
        self.path = path / f"{path.name}.mcap"
        self._stream = self.path.open("xb")
        self._writer = McapFileWriter(
            self._stream, compression=CompressionType.ZSTD, enable_crcs=True, enable_data_crcs=True
        )
        self._writer.start(profile="ros2", library="leapnbv_bags.bag_io")
        self._schema_ids: Dict[str, int] = {}
        self._channel_ids: Dict[int, int] = {}

    def add_msgtype(self, connection: Connection) -> None:
        from rosbags.interfaces import MessageDefinitionFormat

        encoding = "ros2msg" if connection.msgdef.format == MessageDefinitionFormat.MSG else "ros2idl"
        self._schema_ids[connection.msgtype] = self._writer.register_schema(
            name=connection.msgtype, encoding=encoding, data=connection.msgdef.data.encode("utf-8")
        )

    def add_connection(self, connection: Connection, offered_qos_profiles: str) -> None:
        self._channel_ids[connection.id] = self._writer.register_channel(
            topic=connection.topic,
            message_encoding=connection.ext.serialization_format,
            schema_id=self._schema_ids[connection.msgtype],
            metadata={"offered_qos_profiles": offered_qos_profiles, "topic_type_hash": connection.digest},
        )

    def write(self, connection: Connection, timestamp: int, data: Union[bytes, memoryview]) -> None:
        self._writer.add_message(
            channel_id=self._channel_ids[connection.id],
            log_time=timestamp,
            publish_time=timestamp,
            data=bytes(data),
        )

    def close(self, version: int, metadata: str) -> None:
        del version
        self._writer.add_metadata("rosbag2", {"serialized_metadata": metadata})
        self._writer.finish()
        self._stream.close()

    def discard(self) -> None:
        """Close the file without finishing it (the caller deletes it)."""
        self._stream.close()


class _McapWriterWithCrcs(Writer):
    """rosbags' rosbag2 writer (metadata.yaml, QoS, type hashes) over :class:`_CrcMcapStorage`."""

    STORAGE_PLUGINS = {StoragePlugin.MCAP: _CrcMcapStorage}  # type: ignore[assignment]


class BagWriter:
    """Write a rosbag2 directory with MCAP storage; the bag appears at ``path`` only when complete.

    Messages go into ``<parent>/.<name>.partial-<random>/<name>`` and that directory is renamed
    to ``path`` on a clean exit, so a failed or interrupted recording never leaves a half-written
    bag at ``path`` nor replaces a good one. With ``overwrite=True`` an existing bag is moved
    aside, the new one renamed into place, and the old one deleted (restored if the rename
    fails).

    Use as a context manager::

        with BagWriter(path) as bag:
            bag.add_topic("/chatter", "std_msgs/msg/String", qos=RELIABLE_QOS)
            bag.write("/chatter", stamp_ns, message_or_cdr_bytes)
    """

    def __init__(
        self,
        path: Union[str, Path],
        *,
        overwrite: bool = False,
        typestore: Optional[Typestore] = None,
        custom_data: Optional[Mapping[str, str]] = None,
    ) -> None:
        """Prepare the writer (nothing is created until ``open``/``__enter__``).

        Args:
            path: Bag directory to create.
            overwrite: Replace an existing bag at ``path`` once the new one is complete.
            typestore: Typestore to serialize message objects with; :func:`make_typestore` if None.
            custom_data: String pairs stored in metadata.yaml's ``custom_data``.

        Raises:
            BagError: ``path`` exists and ``overwrite`` is False.
        """
        self.path = Path(path)
        self.overwrite = overwrite
        if self.path.exists() and not overwrite:
            raise BagError(f"{self.path} exists already, not overwriting (use overwrite=True)")
        self.typestore = typestore if typestore is not None else make_typestore()
        self.custom_data = dict(custom_data or {})
        self._staging_dir: Optional[Path] = None
        self._writer: Optional[Writer] = None
        self._connections: Dict[str, Connection] = {}
        self._msgtypes: Dict[str, str] = {}
        self.message_counts: Dict[str, int] = {}

    def open(self) -> None:
        """Create the staging directory and open the MCAP writer.

        Raises:
            BagError: Already open, or the staging directory cannot be created.
        """
        if self._writer is not None:
            raise BagError(f"{self.path}: bag already open")
        parent = self.path.parent
        parent.mkdir(parents=True, exist_ok=True)
        staging = parent / f".{self.path.name}.partial-{uuid.uuid4().hex[:12]}"
        try:
            staging.mkdir()
        except OSError as error:
            raise BagError(f"{self.path}: cannot create staging directory {staging}: {error}") from error
        self._staging_dir = staging
        writer = _McapWriterWithCrcs(staging / self.path.name, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP)
        for key, value in self.custom_data.items():
            writer.set_custom_data(key, value)
        try:
            writer.open()
        except Exception as error:
            self._discard_staging()
            raise BagError(f"{self.path}: cannot open writer: {error}") from error
        self._writer = writer

    def add_topic(
        self,
        topic: str,
        msgtype: str,
        *,
        qos: Union[Qos, Sequence[Qos], None] = None,
        msgdef: Optional[str] = None,
    ) -> None:
        """Declare a topic before writing to it.

        Args:
            topic: Topic name.
            msgtype: Type name, ``pkg/msg/Type`` or ``pkg/Type``.
            qos: Offered QoS profile(s) recorded in metadata.yaml; :data:`RELIABLE_QOS` if None.
            msgdef: The type's own ``.msg`` text, needed when the typestore does not know the
                type yet (its dependencies must be known, e.g. standard Jazzy messages).

        Raises:
            BagError: Bag not open, topic declared twice, or the type is unknown.
        """
        writer = self._require_open()
        if topic in self._connections:
            raise BagError(f"{self.path}: topic {topic} declared twice")
        name = _normalize_msgtype(msgtype)
        if msgdef is not None:
            _register_definitions(self.typestore, {name: msgdef})
        if name not in self.typestore.fielddefs:
            raise BagError(f"{self.path}: type {name} of topic {topic} is unknown; pass msgdef")
        if qos is None:
            profiles: List[Qos] = [RELIABLE_QOS]
        elif isinstance(qos, Qos):
            profiles = [qos]
        else:
            profiles = list(qos)
        self._connections[topic] = writer.add_connection(
            topic, name, typestore=self.typestore, offered_qos_profiles=profiles
        )
        self._msgtypes[topic] = name
        self.message_counts[topic] = 0

    def write(self, topic: str, timestamp_ns: int, message: MessageOrBytes) -> None:
        """Write one message.

        Args:
            topic: A topic declared with :meth:`add_topic`.
            timestamp_ns: Receive time in nanoseconds (the bag's log time).
            message: A message object of this writer's typestore, or its CDR bytes (e.g. from
                ``rclpy.serialization.serialize_message``; rosbags' CDR is byte-identical).

        Raises:
            BagError: Bag not open, unknown topic, or the message does not serialize.
        """
        writer = self._require_open()
        connection = self._connections.get(topic)
        if connection is None:
            raise BagError(f"{self.path}: topic {topic} was not declared with add_topic")
        if isinstance(message, (bytes, bytearray, memoryview)):
            data: Union[bytes, memoryview] = bytes(message) if isinstance(message, bytearray) else message
        else:
            try:
                data = self.typestore.serialize_cdr(message, self._msgtypes[topic])
            except Exception as error:
                raise BagError(
                    f"{self.path}: message on {topic} does not serialize as {self._msgtypes[topic]}: {error}"
                ) from error
        writer.write(connection, int(timestamp_ns), data)
        self.message_counts[topic] += 1

    def close(self) -> None:
        """Finish the bag and move it into place at ``path``.

        Raises:
            BagError: The bag cannot be finished or moved into place (the staging data is
                removed and any previous bag at ``path`` is left as it was).
        """
        writer = self._require_open()
        self._writer = None
        staged_bag = writer.path
        try:
            writer.close()
            self._move_into_place(staged_bag)
        finally:
            self._discard_staging()

    def abort(self) -> None:
        """Drop everything written so far; ``path`` is left untouched."""
        writer = self._writer
        self._writer = None
        if writer is not None and isinstance(writer.storage, _CrcMcapStorage):
            writer.storage.discard()
        self._discard_staging()

    def __enter__(self) -> BagWriter:
        """Open the bag."""
        self.open()
        return self

    def __exit__(
        self,
        exc_type: Optional[type],
        exc_val: Optional[BaseException],
        exc_tb: Optional[TracebackType],
    ) -> bool:
        """Finish the bag, or abort it when the block raised."""
        if exc_type is not None:
            self.abort()
            return False
        self.close()
        return False

    def _require_open(self) -> Writer:
        if self._writer is None:
            raise BagError(f"{self.path}: bag is not open")
        return self._writer

    def _move_into_place(self, staged_bag: Path) -> None:
        target = self.path
        if not target.exists():
            # os.rename would silently replace an empty directory; exists() was checked above.
            _rename(staged_bag, target)
            return
        if not self.overwrite:
            raise BagError(f"{target} appeared while recording, not overwriting")
        assert self._staging_dir is not None
        previous = self._staging_dir / (target.name + ".previous")
        _rename(target, previous)
        try:
            _rename(staged_bag, target)
        except BagError:
            _rename(previous, target)
            raise

    def _discard_staging(self) -> None:
        if self._staging_dir is not None and self._staging_dir.exists():
            shutil.rmtree(self._staging_dir, ignore_errors=True)
        self._staging_dir = None


def _rename(source: Path, destination: Path) -> None:
    try:
        os.rename(source, destination)
    except OSError as error:
        raise BagError(f"cannot move {source} to {destination}: {error}") from error


# Exit codes of the bag tools (this module's check, leapnbv_bringup.replay and .regression).
EXIT_OK = 0
EXIT_OUTPUTS_CHANGED = 1
EXIT_USAGE = 2  # a wrong argument, or a missing golden file
EXIT_UNREADABLE_BAG = 3

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


def _bag_layout(bag_path: Path) -> Tuple[str, List[Path]]:
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


def _walk_mcap(path: Path, on_message: Optional[Any] = None) -> McapFileCheck:
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
        BagError: one line naming the path and what is wrong (see _bag_layout and _walk_mcap).
    """
    bag_path = Path(path)
    storage, files = _bag_layout(bag_path)
    check = BagCheck(bag_path, storage, files)
    if storage != "mcap":
        return check
    for data_file in files:
        found = _walk_mcap(data_file)
        check.mcap.append(found)
        check.messages += found.messages
        if not found.summary:
            check.notes.append(_summary_note(found))
    return check


def _summary_note(found: McapFileCheck) -> str:
    why = f" ({found.summary_problem})" if found.summary_problem else ""
    return (f"{found.path}: no MCAP summary/footer{why}; the data section is complete ({found.messages} "
            "messages, CRCs right): read sequentially")


def read_bag(
    path: Union[str, Path], topics: Optional[Sequence[str]] = None, raw: bool = False,
    note: Optional[Any] = None,
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
    storage, files = _bag_layout(bag_path)
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
                            note: Optional[Any]) -> Iterator[Tuple[str, str, int, object]]:
    """The messages of MCAP files read from their start (no summary needed), in log-time order."""
    import sys

    collected: List[Tuple[int, int, str, str, bytes]] = []
    schema_texts: Dict[str, str] = {}

    def keep(schema, channel, message) -> None:
        if topics is not None and channel.topic not in topics:
            return
        msgtype = schema.name if schema is not None else ""
        if schema is not None and schema.encoding == "ros2msg":
            schema_texts.setdefault(msgtype, schema.data.decode("utf-8", errors="replace"))
        collected.append((int(message.log_time), len(collected), channel.topic, msgtype, message.data))

    for data_file in files:
        found = _walk_mcap(data_file, keep)
        if not found.summary:
            line = _summary_note(found)
            if note is None:
                print(f"[bag] {line}", file=sys.stderr, flush=True)
            else:
                note(line)
    collected.sort()
    typestore = None
    if not raw:
        typestore = make_typestore()
        for msgtype, text in schema_texts.items():
            if _normalize_msgtype(msgtype) not in typestore.fielddefs:
                _register_definitions(typestore, {msgtype: text.split("\n====", 1)[0]})
    for timestamp, _, topic, msgtype, data in collected:
        if raw:
            yield topic, msgtype, timestamp, data
            continue
        try:
            message = typestore.deserialize_cdr(data, _normalize_msgtype(msgtype))
        except Exception as error:
            raise BagError(f"{bag_path}: message on {topic} does not deserialize as {msgtype}: {error}") from error
        yield topic, msgtype, timestamp, message


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


def main(argv: Optional[Sequence[str]] = None) -> int:
    """``python -m leapnbv_bags.bag_io BAG``: check a bag and print its topics and message counts."""
    import argparse
    import sys

    parser = argparse.ArgumentParser(
        prog="python -m leapnbv_bags.bag_io",
        description="Check a rosbag2 bag (metadata.yaml, every MCAP chunk's CRC) and print its topics. "
                    f"Exit codes: {EXIT_OK} readable, {EXIT_USAGE} usage, {EXIT_UNREADABLE_BAG} unreadable bag "
                    "(one line: the path and what is wrong).")
    parser.add_argument("bag", help="rosbag2 directory")
    args = parser.parse_args(argv)
    try:
        check = check_bag(args.bag)
        counts: Dict[str, int] = {}
        for topic, msgtype, _, _ in read_bag(args.bag, raw=True):
            counts[f"{topic} ({msgtype})"] = counts.get(f"{topic} ({msgtype})", 0) + 1
    except BagError as error:
        print(f"[bag] unreadable bag: {error}", file=sys.stderr)
        return EXIT_UNREADABLE_BAG
    print(f"[bag] {args.bag}: {check.storage}, {len(check.files)} file(s), {sum(counts.values())} messages")
    for name, count in sorted(counts.items()):
        print(f"  {count:6d}  {name}")
    return EXIT_OK


if __name__ == "__main__":
    raise SystemExit(main())
