"""Tests of the scene bags (leapnbv_sim.sample_bags) and leapnbv_bags.bag_io under them: rosbag2/MCAP writing,
reading back, CRCs, safe overwrite."""

from __future__ import annotations

from pathlib import Path
from typing import List

import numpy as np
import pytest
import yaml

from leapnbv_bags import bag_io
from leapnbv_bags.bag_io import BagError, BagWriter, read_bag, validate_bag_crcs
from leapnbv_common import topics
from leapnbv_common.conversions import ConversionError
from leapnbv_sim.body import BodyParams
from leapnbv_sim.poses import CameraPose
from leapnbv_sim.render import FrameGroundTruth, RenderedFrame
from leapnbv_sim.sample_bags import write_scene_bag


def _frame(seed: int, width: int = 32, height: int = 24) -> RenderedFrame:
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8)
    depth_mm = rng.integers(0, 5000, size=(height, width), dtype=np.uint16)
    params = BodyParams(
        root_pose=rng.normal(size=3),
        body_pose=rng.normal(size=63),
        left_hand_pose=rng.normal(size=45),
        right_hand_pose=rng.normal(size=45),
        jaw_pose=rng.normal(size=3),
        betas=rng.normal(size=10),
        expression=rng.normal(size=10),
    )
    truth = FrameGroundTruth(
        person_box_xyxy=(3, 4, 20, 22),
        body_params_camera=params,
        translation_camera=np.array([0.1, 0.2, 2.5]),
        vertices_camera=np.zeros((5, 3)),
        visible_vertices=np.ones(5, dtype=bool),
        occlusion_share=0.25 + 0.01 * seed,
        occluder_share=0.3,
        person_pixel_count=100,
    )
    K = np.array([[30.0, 0.0, 16.0], [0.0, 30.0, 12.0], [0.0, 0.0, 1.0]])
    return RenderedFrame(
        rgb=rgb,
        depth_mm=depth_mm,
        depth_m=depth_mm.astype(np.float32) / 1000.0,
        depth_clean_m=depth_mm.astype(np.float32) / 1000.0,
        object_id=np.zeros((height, width), dtype=np.int16),
        K=K,
        camera_pose=CameraPose(np.eye(3), np.zeros(3)),
        ground_truth=truth,
    )


def test_scene_bag_reads_back_identically(tmp_path: Path) -> None:
    frames = [_frame(0), _frame(1), _frame(2)]
    path = tmp_path / "scene_bag"
    counts = write_scene_bag(
        path, frames, start_stamp_ns=1_000_000_000, period_ns=50_000_000, body_model_id="stand_in_small"
    )
    assert counts[topics.COLOR_IMAGE_TOPIC] == 3
    assert sorted(p.name for p in path.iterdir()) == ["metadata.yaml", "scene_bag.mcap"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]

    colour, depth, truths, infos = [], [], [], []
    for topic, msgtype, stamp, message in read_bag(path):
        if topic == topics.COLOR_IMAGE_TOPIC:
            colour.append((stamp, message))
        elif topic == topics.DEPTH_IMAGE_TOPIC:
            depth.append(message)
        elif topic == topics.GROUND_TRUTH_TOPIC:
            assert msgtype == "leapnbv_msgs/msg/SceneGroundTruth"
            truths.append(message)
        elif topic == topics.COLOR_INFO_TOPIC:
            infos.append(message)
    assert [s for s, _ in colour] == [1_000_000_000, 1_050_000_000, 1_100_000_000]
    for frame, (_, image), depth_image, truth, info in zip(frames, colour, depth, truths, infos):
        assert image.encoding == "rgb8" and image.step == 32 * 3
        assert bytes(image.data) == frame.rgb.tobytes()
        assert depth_image.encoding == "16UC1" and depth_image.is_bigendian == 0
        assert bytes(depth_image.data) == frame.depth_mm.astype("<u2").tobytes()
        assert image.header.frame_id == "camera_color_optical_frame"
        assert truth.header.stamp.sec == 1
        np.testing.assert_allclose(
            truth.body_pose, frame.ground_truth.body_params_camera.body_pose, rtol=1e-6, atol=1e-6
        )
        np.testing.assert_allclose(truth.translation, [0.1, 0.2, 2.5], rtol=1e-6)
        assert truth.person_box.x_max == 20.0 and truth.person_box.score == 1.0
        assert truth.occlusion_share == pytest.approx(frame.ground_truth.occlusion_share, abs=1e-6)
        assert truth.body_model_id == "stand_in_small"
        np.testing.assert_allclose(np.asarray(info.k).reshape(3, 3), frame.K)

    assert validate_bag_crcs(path) == {topic: 3 for topic in counts}
    # The CRCs are really there (a writer that stores 0 would make the check vacuous).
    from mcap.records import Chunk, DataEnd
    from mcap.stream_reader import StreamReader

    records = list(StreamReader(str(path / "scene_bag.mcap")).records)
    assert all(r.uncompressed_crc != 0 for r in records if isinstance(r, Chunk))
    assert [r.data_section_crc != 0 for r in records if isinstance(r, DataEnd)] == [True]

    metadata = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert metadata["version"] == 9 and metadata["storage_identifier"] == "mcap"
    qos = {
        t["topic_metadata"]["name"]: t["topic_metadata"]["offered_qos_profiles"]
        for t in metadata["topics_with_message_count"]
    }
    assert qos[topics.COLOR_IMAGE_TOPIC][0]["reliability"] == "best_effort"
    assert qos[topics.COLOR_IMAGE_TOPIC][0]["depth"] == 5
    assert qos[topics.COLOR_IMAGE_TOPIC][0]["durability"] == "volatile"
    assert qos[topics.GROUND_TRUTH_TOPIC][0]["reliability"] == "reliable"


def test_validate_bag_crcs_detects_corruption(tmp_path: Path) -> None:
    path = tmp_path / "bag"
    write_scene_bag(path, [_frame(0)])
    mcap_file = path / "bag.mcap"
    data = bytearray(mcap_file.read_bytes())
    middle = len(data) // 2
    data[middle] ^= 0xFF
    mcap_file.write_bytes(bytes(data))
    with pytest.raises(BagError, match="bag.mcap"):
        validate_bag_crcs(path)


def test_existing_path_is_refused_and_left_intact(tmp_path: Path) -> None:
    path = tmp_path / "bag"
    write_scene_bag(path, [_frame(0)])
    before = (path / "bag.mcap").read_bytes()
    with pytest.raises(BagError, match=str(path)):
        write_scene_bag(path, [_frame(1)])
    assert (path / "bag.mcap").read_bytes() == before


def test_overwrite_replaces_only_when_complete(tmp_path: Path) -> None:
    path = tmp_path / "bag"
    write_scene_bag(path, [_frame(0)])
    before = (path / "bag.mcap").read_bytes()

    # A recording that fails half-way leaves the old bag untouched and no staging debris.
    bad = _frame(1)
    bad.rgb = bad.rgb[:, :, :2]  # wrong channel count -> refused by the image conversion at frame 2
    with pytest.raises(ConversionError):
        write_scene_bag(path, [_frame(1), bad], overwrite=True)
    assert (path / "bag.mcap").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag"]

    write_scene_bag(path, [_frame(1), _frame(2)], overwrite=True)
    assert validate_bag_crcs(path)[topics.COLOR_IMAGE_TOPIC] == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag"]


def test_bag_writer_records_raw_cdr_of_a_custom_type(tmp_path: Path) -> None:
    typestore = bag_io.make_typestore()
    header = typestore.types["std_msgs/msg/Header"](
        stamp=typestore.types["builtin_interfaces/msg/Time"](sec=0, nanosec=123), frame_id="cam")
    ground = typestore.types["leapnbv_msgs/msg/GroundPlane"](
        header=header,
        normal=typestore.types["geometry_msgs/msg/Vector3"](x=0.0, y=-1.0, z=0.0),
        offset=1.2,
        inlier_count=10,
        inlier_ratio=0.5,
        valid=True,
        compute_time_ms=1.5,
        source=1,
        quality=0.5,
        inputs=[],  # the InputStamp list: empty here
    )
    cdr = bytes(typestore.serialize_cdr(ground, "leapnbv_msgs/msg/GroundPlane"))
    text = (bag_io.find_leapnbv_msg_dir() / "GroundPlane.msg").read_text()
    path = tmp_path / "raw"
    # A fresh typestore that does not know the type: the .msg text registers it.
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    # GroundPlane lists its inputs (leapnbv_msgs/InputStamp): a dependency the fresh store must know first.
    store.register(get_types_from_msg((bag_io.find_leapnbv_msg_dir() / "InputStamp.msg").read_text(),
                                      "leapnbv_msgs/msg/InputStamp"))
    with BagWriter(path, typestore=store) as bag:
        bag.add_topic("/leapnbv/ground_plane", "leapnbv_msgs/GroundPlane", msgdef=text)
        bag.write("/leapnbv/ground_plane", 123, cdr)
        bag.add_topic("/chatter", "std_msgs/msg/String", qos=bag_io.TRANSIENT_LOCAL_QOS)
        bag.write("/chatter", 124, typestore.types["std_msgs/msg/String"](data="hi"))
    messages: List[tuple] = list(read_bag(path))
    assert [m[0] for m in messages] == ["/leapnbv/ground_plane", "/chatter"]
    assert messages[0][3].offset == pytest.approx(1.2) and messages[0][3].valid and messages[0][3].source == 1
    assert messages[1][3].data == "hi"


def test_bag_writer_aborts_on_exception(tmp_path: Path) -> None:
    path = tmp_path / "aborted"
    with pytest.raises(RuntimeError):
        with BagWriter(path) as bag:
            bag.add_topic("/chatter", "std_msgs/msg/String")
            raise RuntimeError("recording interrupted")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(BagError, match="not declared"):
        with BagWriter(path) as bag:
            bag.write("/nope", 0, b"")
    assert list(tmp_path.iterdir()) == []
