"""rosbag2 (MCAP storage) writing, reading and checking with rosbags, without ROS installed."""

from __future__ import annotations

import os
import shutil
import uuid
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, Dict, Iterator, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
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

    from leapnbv_sim.scene import RenderedFrame

#: RealSense-driver topic names the simulator records under (ROS 2 realsense2_camera defaults).
COLOR_IMAGE_TOPIC = "/camera/color/image_raw"
COLOR_INFO_TOPIC = "/camera/color/camera_info"
DEPTH_IMAGE_TOPIC = "/camera/aligned_depth_to_color/image_raw"
DEPTH_INFO_TOPIC = "/camera/aligned_depth_to_color/camera_info"
GROUND_TRUTH_TOPIC = "/leapnbv/sim/ground_truth"

#: rosbag2 metadata version written (9 is what ROS 2 Jazzy's rosbag2 writes).
BAG_VERSION = 9

# rclcpp's "infinite" duration as rosbag2 (Jazzy) records it in metadata.yaml.
_INFINITE = QosTime(9223372036, 854775807)

#: rclcpp::SensorDataQoS(): best effort, keep last 5, volatile.
SENSOR_DATA_QOS = Qos(
    QosHistory.KEEP_LAST,
    5,
    QosReliability.BEST_EFFORT,
    QosDurability.VOLATILE,
    _INFINITE,
    _INFINITE,
    QosLiveliness.AUTOMATIC,
    _INFINITE,
    False,
)

#: rclcpp default publisher QoS: reliable, keep last 10, volatile.
RELIABLE_QOS = Qos(
    QosHistory.KEEP_LAST,
    10,
    QosReliability.RELIABLE,
    QosDurability.VOLATILE,
    _INFINITE,
    _INFINITE,
    QosLiveliness.AUTOMATIC,
    _INFINITE,
    False,
)

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
        self._writer.start(profile="ros2", library="leapnbv_sim.bag_io")
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


def _stamp(typestore: Typestore, stamp_ns: int) -> object:
    time_type = typestore.types["builtin_interfaces/msg/Time"]
    return time_type(sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000))


def make_header(typestore: Typestore, stamp_ns: int, frame_id: str) -> object:
    """Build a std_msgs/Header.

    Args:
        typestore: Typestore whose message classes to use.
        stamp_ns: Stamp in nanoseconds since the epoch.
        frame_id: Frame name.

    Returns:
        The header message.
    """
    header_type = typestore.types["std_msgs/msg/Header"]
    return header_type(stamp=_stamp(typestore, stamp_ns), frame_id=frame_id)


def make_image(typestore: Typestore, header: object, array: np.ndarray, encoding: str) -> object:
    """Build a sensor_msgs/Image from an (H,W,3) uint8 ``rgb8`` or (H,W) uint16 ``16UC1`` array.

    Args:
        typestore: Typestore whose message classes to use.
        header: The header.
        array: Pixels, (H,W,3) uint8 or (H,W) uint16 (stored little-endian).
        encoding: ``rgb8`` or ``16UC1``.

    Returns:
        The image message.

    Raises:
        BagError: The array does not match the encoding.
    """
    expected = {"rgb8": (np.uint8, 3), "16UC1": (np.uint16, 2)}
    if encoding not in expected:
        raise BagError(f"image encoding {encoding} not supported (rgb8, 16UC1)")
    dtype, ndim = expected[encoding]
    if array.dtype != dtype or array.ndim != ndim or (ndim == 3 and array.shape[2] != 3):
        raise BagError(f"image array {array.dtype} {array.shape} does not match encoding {encoding}")
    contiguous = np.ascontiguousarray(array.astype(np.dtype(dtype).newbyteorder("<"), copy=False))
    height, width = int(array.shape[0]), int(array.shape[1])
    step = width * (3 if encoding == "rgb8" else 2)
    image_type = typestore.types["sensor_msgs/msg/Image"]
    return image_type(
        header=header,
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=step,
        data=np.frombuffer(contiguous.tobytes(), dtype=np.uint8),
    )


def make_camera_info(typestore: Typestore, header: object, K: np.ndarray, width: int, height: int) -> object:
    """Build a distortion-free sensor_msgs/CameraInfo (plumb_bob, zero coefficients).

    Args:
        typestore: Typestore whose message classes to use.
        header: The header.
        K: (3,3) intrinsics.
        width: Image width in pixels.
        height: Image height in pixels.

    Returns:
        The camera info message.
    """
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    projection = np.zeros((3, 4), dtype=np.float64)
    projection[:, :3] = K
    info_type = typestore.types["sensor_msgs/msg/CameraInfo"]
    roi_type = typestore.types["sensor_msgs/msg/RegionOfInterest"]
    return info_type(
        header=header,
        height=int(height),
        width=int(width),
        distortion_model="plumb_bob",
        d=np.zeros(5, dtype=np.float64),
        k=K.reshape(9).copy(),
        r=np.eye(3, dtype=np.float64).reshape(9),
        p=projection.reshape(12),
        binning_x=0,
        binning_y=0,
        roi=roi_type(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )


def make_scene_ground_truth(typestore: Typestore, header: object, frame: RenderedFrame, body_model_id: str) -> object:
    """Build a leapnbv_msgs/SceneGroundTruth from a rendered frame's ground truth.

    Args:
        typestore: Typestore with leapnbv_msgs registered.
        header: The header of the frame.
        frame: The rendered frame (``frame.ground_truth``).
        body_model_id: Which body model the parameters belong to.

    Returns:
        The ground-truth message (an all-zero box with score 0 when the person is not visible).
    """
    truth = frame.ground_truth
    detection_type = typestore.types["leapnbv_msgs/msg/PersonDetection"]
    if truth.person_box_xyxy is None:
        box = detection_type(x_min=0.0, y_min=0.0, x_max=0.0, y_max=0.0, score=0.0)
    else:
        x0, y0, x1, y1 = (float(v) for v in truth.person_box_xyxy)
        box = detection_type(x_min=x0, y_min=y0, x_max=x1, y_max=y1, score=1.0)
    params = truth.body_params_camera

    def f32(values: np.ndarray, size: int) -> np.ndarray:
        array = np.asarray(values, dtype=np.float32).reshape(-1)
        if array.size != size:
            raise BagError(f"ground truth field has {array.size} values, expected {size}")
        return array

    gt_type = typestore.types["leapnbv_msgs/msg/SceneGroundTruth"]
    return gt_type(
        header=header,
        person_box=box,
        root_pose=f32(params.root_pose, 3),
        body_pose=f32(params.body_pose, 63),
        left_hand_pose=f32(params.left_hand_pose, 45),
        right_hand_pose=f32(params.right_hand_pose, 45),
        jaw_pose=f32(params.jaw_pose, 3),
        betas=f32(params.betas, 10),
        expression=f32(params.expression, 10),
        translation=f32(truth.translation_camera, 3),
        occlusion_share=float(truth.occlusion_share),
        body_model_id=body_model_id,
    )


def write_scene_bag(
    path: Union[str, Path],
    frames: Sequence[RenderedFrame],
    *,
    frame_id: str = "camera_color_optical_frame",
    start_stamp_ns: int = 1_700_000_000_000_000_000,
    period_ns: int = 100_000_000,
    body_model_id: str = "stand_in_small",
    overwrite: bool = False,
) -> Dict[str, int]:
    """Record rendered frames under RealSense topic names plus the simulator's ground truth.

    Each frame i gets stamp ``start_stamp_ns + i * period_ns`` on all five topics (header stamp
    and bag log time alike). The depth is aligned to colour, so both camera infos are the same.

    Args:
        path: Bag directory to create.
        frames: Rendered frames (all the same size).
        frame_id: Optical frame of the colour camera.
        start_stamp_ns: Stamp of the first frame, nanoseconds since the epoch.
        period_ns: Time between frames, nanoseconds.
        body_model_id: Stored in each SceneGroundTruth.
        overwrite: Replace an existing bag atomically once the new one is complete.

    Returns:
        Message count per topic.

    Raises:
        BagError: ``path`` exists (without overwrite) or writing fails.
    """
    typestore = make_typestore()
    with BagWriter(path, overwrite=overwrite, typestore=typestore) as bag:
        bag.add_topic(COLOR_IMAGE_TOPIC, "sensor_msgs/msg/Image", qos=SENSOR_DATA_QOS)
        bag.add_topic(COLOR_INFO_TOPIC, "sensor_msgs/msg/CameraInfo", qos=SENSOR_DATA_QOS)
        bag.add_topic(DEPTH_IMAGE_TOPIC, "sensor_msgs/msg/Image", qos=SENSOR_DATA_QOS)
        bag.add_topic(DEPTH_INFO_TOPIC, "sensor_msgs/msg/CameraInfo", qos=SENSOR_DATA_QOS)
        bag.add_topic(GROUND_TRUTH_TOPIC, "leapnbv_msgs/msg/SceneGroundTruth", qos=RELIABLE_QOS)
        for index, frame in enumerate(frames):
            stamp = int(start_stamp_ns) + index * int(period_ns)
            header = make_header(typestore, stamp, frame_id)
            height, width = frame.depth_mm.shape
            info = make_camera_info(typestore, header, frame.K, width, height)
            bag.write(COLOR_IMAGE_TOPIC, stamp, make_image(typestore, header, frame.rgb, "rgb8"))
            bag.write(COLOR_INFO_TOPIC, stamp, info)
            bag.write(DEPTH_IMAGE_TOPIC, stamp, make_image(typestore, header, frame.depth_mm, "16UC1"))
            bag.write(DEPTH_INFO_TOPIC, stamp, info)
            bag.write(GROUND_TRUTH_TOPIC, stamp, make_scene_ground_truth(typestore, header, frame, body_model_id))
        counts = dict(bag.message_counts)
    return counts


def read_bag(
    path: Union[str, Path], topics: Optional[Sequence[str]] = None, raw: bool = False
) -> Iterator[Tuple[str, str, int, object]]:
    """Iterate over a bag's messages in log-time order, deserialized with the bag's own definitions.

    Args:
        path: rosbag2 directory (MCAP or SQLite storage).
        topics: Only these topics; all if None.
        raw: Yield the CDR bytes as stored instead of deserialized messages (for replay).

    Yields:
        (topic, msgtype, timestamp_ns, message) tuples.

    Raises:
        BagError: The bag cannot be opened or a message does not deserialize.
    """
    bag_path = Path(path)
    try:
        reader = AnyReader([bag_path])
        reader.open()
    except Exception as error:
        raise BagError(f"{bag_path}: cannot open bag: {error}") from error
    try:
        connections = [c for c in reader.connections if topics is None or c.topic in topics]
        for connection, timestamp, rawdata in reader.messages(connections=connections):
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
