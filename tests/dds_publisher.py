"""Publishes a 16UC1 depth image, an rgb8 image and a 10,475-vertex HumanMesh until killed."""
from __future__ import annotations

import sys

import numpy as np
import rclpy
from dds_payloads import make_payloads
from rclpy.node import Node
from sensor_msgs.msg import Image

from leapnbv_common.conversions import HumanMeshArrays, arrays_to_human_mesh, numpy_to_image
from leapnbv_common.qos import stage_output_qos
from leapnbv_msgs.msg import HumanMesh


def main() -> int:
    rclpy.init()
    node = Node("dds_test_publisher")
    depth, rgb, vertices, faces = make_payloads()
    mesh = HumanMeshArrays(
        vertices=vertices, faces=faces, virtual_intrinsics=(5000.0, 5000.0, 320.0, 240.0),
        image_size=(640, 480), detection=np.array([1, 2, 3, 4, 0.5], np.float32),
        processed_box=np.zeros(4), root_pose=np.zeros(3), body_pose=np.arange(63) * 0.01,
        left_hand_pose=np.zeros(45), right_hand_pose=np.zeros(45), jaw_pose=np.zeros(3),
        betas=np.ones(10), expression=np.zeros(10), cam_translation=np.array([0.1, -0.2, 28.19]),
        model_id="dds_test")
    qos = stage_output_qos(depth=1)
    pubs = {
        "depth": (node.create_publisher(Image, "depth", qos), numpy_to_image(depth, "16UC1")),
        "rgb": (node.create_publisher(Image, "image", qos), numpy_to_image(rgb, "rgb8")),
        "mesh": (node.create_publisher(HumanMesh, "mesh", qos), arrays_to_human_mesh(mesh)),
    }
    count = [0]

    def tick() -> None:
        count[0] += 1
        for pub, msg in pubs.values():
            msg.header.stamp.sec = count[0]
            msg.header.frame_id = "camera_color_optical_frame"
            pub.publish(msg)

    node.create_timer(0.1, tick)
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
