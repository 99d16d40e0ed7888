"""Writing rosbag2 bags (MCAP storage, with CRCs): BagWriter and the QoS profiles it records."""

from __future__ import annotations

import os
import shutil
import uuid
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, Dict, Final, List, Literal, Mapping, Optional, Sequence, Union, cast

from rosbags.interfaces import (
    Connection,
    ConnectionExtRosbag2,
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import StoragePlugin, Writer

from leapnbv_bags.errors import BagError
from leapnbv_bags.typestore import make_typestore, normalize_msgtype, register_definitions

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

__all__ = ["BAG_VERSION", "RELIABLE_QOS", "SENSOR_DATA_QOS", "TRANSIENT_LOCAL_QOS", "BagWriter", "MessageOrBytes"]

#: rosbag2 metadata version written (9 is what ROS 2 Jazzy's rosbag2 writes).
BAG_VERSION: Final = 9

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
            message_encoding=cast(ConnectionExtRosbag2, connection.ext).serialization_format,
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
        self._writer.finish()  # type: ignore[no-untyped-call, unused-ignore]  # (untyped in some mcap releases)
        self._stream.close()

    def discard(self) -> None:
        """Close the file without finishing it (the caller deletes it)."""
        self._stream.close()


class _McapWriterWithCrcs(Writer):
    """rosbags' rosbag2 writer (metadata.yaml, QoS, type hashes) over :class:`_CrcMcapStorage`."""

    STORAGE_PLUGINS = {StoragePlugin.MCAP: _CrcMcapStorage}


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
        name = normalize_msgtype(msgtype)
        if msgdef is not None:
            register_definitions(self.typestore, {name: msgdef})
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
    ) -> Literal[False]:
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
