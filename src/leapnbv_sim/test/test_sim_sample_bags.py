"""leapnbv_sim.sample_bags is a ROS-free core, and the bags it writes are the same bytes on every run."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from leapnbv_sim.body import BodyParams
from leapnbv_sim.poses import CameraPose
from leapnbv_sim.render import FrameGroundTruth, RenderedFrame

SRC = Path(__file__).resolve().parents[2]


def _frame(seed: int, width: int = 40, height: int = 30) -> RenderedFrame:
    rng = np.random.default_rng(seed)
    depth_mm = rng.integers(0, 5000, size=(height, width), dtype=np.uint16)
    params = BodyParams(*(rng.normal(size=n) for n in (3, 63, 45, 45, 3, 10, 10)))
    truth = FrameGroundTruth(
        person_box_xyxy=(3, 4, 20, 22), body_params_camera=params, translation_camera=np.array([0.1, 0.2, 2.5]),
        vertices_camera=np.zeros((5, 3)), visible_vertices=np.ones(5, dtype=bool), occlusion_share=0.25,
        occluder_share=0.3, person_pixel_count=100,
    )
    return RenderedFrame(
        rgb=rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8), depth_mm=depth_mm,
        depth_m=depth_mm.astype(np.float32) / 1000.0, depth_clean_m=depth_mm.astype(np.float32) / 1000.0,
        object_id=np.zeros((height, width), dtype=np.int16),
        K=np.array([[30.0, 0.0, 20.0], [0.0, 30.0, 15.0], [0.0, 0.0, 1.0]]),
        camera_pose=CameraPose(np.eye(3), np.zeros(3)), ground_truth=truth,
    )


def test_importing_sample_bags_loads_no_ros() -> None:
    # The core imports the ROS glue (leapnbv_sim.frame_messages) only when it writes a bag.
    code = (
        "import sys, leapnbv_sim.sample_bags\n"
        "ros = sorted(m for m in sys.modules if m.split('.')[0] in ('rclpy', 'std_msgs', 'sensor_msgs', 'leapnbv_msgs')"
        " or m == 'leapnbv_sim.frame_messages')\n"
        "assert not ros, ros\n"
    )
    paths = [str(p) for p in sorted(SRC.iterdir()) if (p / p.name).is_dir()]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(paths + [os.environ.get("PYTHONPATH", "")]))
    result = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr


@pytest.mark.ros
def test_the_same_frames_give_the_same_bag_bytes(tmp_path: Path) -> None:
    # rclpy leaves CDR alignment padding uninitialised; the bag must not depend on it.
    pytest.importorskip("rclpy")
    from leapnbv_sim.sample_bags import write_scene_bag

    frames = [_frame(0), _frame(1), _frame(2)]
    contents = []
    for run in range(3):
        path = tmp_path / f"run{run}" / "bag"  # one name: the file names are in metadata.yaml
        write_scene_bag(path, frames)
        contents.append({p.name: p.read_bytes() for p in sorted(path.iterdir())})
    assert contents[0] == contents[1] == contents[2]
