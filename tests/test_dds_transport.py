"""Large messages cross process boundaries over DDS bit-exact (Fast DDS profile loaded)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from dds_payloads import NUM_FACES, NUM_VERTICES, make_payloads  # noqa: E402
from rclpy.node import Node  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402

from leapnbv_common.conversions import human_mesh_to_arrays, image_to_numpy  # noqa: E402
from leapnbv_common.qos import stage_input_qos  # noqa: E402
from leapnbv_msgs.msg import HumanMesh  # noqa: E402

pytestmark = pytest.mark.ros


def test_images_and_mesh_arrive_bit_exact_in_another_process(repo_root):
    assert os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE", "").endswith("fastdds_large_messages.xml")
    env = dict(os.environ, PYTHONPATH=f"{repo_root / 'tests'}:{os.environ.get('PYTHONPATH', '')}")
    publisher = subprocess.Popen([sys.executable, str(repo_root / "tests/dds_publisher.py")], env=env)
    rclpy.init()
    node = Node("dds_test_subscriber")
    received = {}
    qos = stage_input_qos(depth=1)
    node.create_subscription(Image, "depth", lambda m: received.setdefault("depth", m), qos)
    node.create_subscription(Image, "image", lambda m: received.setdefault("rgb", m), qos)
    node.create_subscription(HumanMesh, "mesh", lambda m: received.setdefault("mesh", m), qos)
    try:
        deadline = time.monotonic() + 30.0
        while len(received) < 3 and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
    finally:
        publisher.send_signal(signal.SIGINT)
        publisher.wait(timeout=10)
        node.destroy_node()
        rclpy.shutdown()
    assert set(received) == {"depth", "rgb", "mesh"}, f"only {sorted(received)} arrived"
    depth, rgb, vertices, faces = make_payloads()
    got_depth = image_to_numpy(received["depth"])
    assert got_depth.dtype == np.uint16 and got_depth.shape == (480, 640)
    assert got_depth.tobytes() == depth.tobytes()
    assert image_to_numpy(received["rgb"]).tobytes() == rgb.tobytes()
    mesh = human_mesh_to_arrays(received["mesh"])
    assert mesh.vertices.shape == (NUM_VERTICES, 3) and mesh.faces.shape == (NUM_FACES, 3)
    assert mesh.vertices.tobytes() == vertices.tobytes()
    assert mesh.faces.tobytes() == faces.tobytes()
    assert received["mesh"].header.frame_id == "camera_color_optical_frame"
    np.testing.assert_array_equal(mesh.body_pose, (np.arange(63) * 0.01).astype(np.float32))
