"""The committed sample bags: two synthetic scenes, ten frames each, as a RealSense would record them.

    python -m leapnbv_sim.sample_bags [--out bags] [--force]

The robot drifts 2 cm sideways per frame (10 Hz), so consecutive frames differ by more than
noise and the HMR stage has a target to track. Deterministic: the same seeds and stand-in body
give byte-identical images.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

from leapnbv_sim.scene import CameraPose, SceneConfig, generate_scene

# name -> scene seed and options; two different scenes (with and without walls).
SAMPLE_BAGS = {
    "sample_a": {"seed": 3, "walls": True},
    "sample_b": {"seed": 11, "walls": False},
}
NUM_FRAMES = 10
DRIFT_M_PER_FRAME = 0.02


def render_drifting_frames(scene, num_frames: int = NUM_FRAMES, drift_m: float = DRIFT_M_PER_FRAME) -> List:
    """Frames from the start view moved drift_m per frame along the camera's x axis (level)."""
    start = scene.start_camera
    frames = []
    for i in range(num_frames):
        position = start.position + start.rotation[:, 0] * (drift_m * i)
        frames.append(scene.render(CameraPose(start.rotation, position), frame_index=i))
    return frames


def make_sample_bag(path: Path, seed: int, walls: bool, body_model, body_model_id: str, overwrite: bool) -> Dict:
    scene = generate_scene(SceneConfig(seed=seed, walls=walls, body_resolution="small"), body_model)
    frames = render_drifting_frames(scene)
    from leapnbv_sim.bag_io import write_scene_bag

    counts = write_scene_bag(path, frames, body_model_id=body_model_id, overwrite=overwrite)
    shares = [f.ground_truth.occluder_share for f in frames]
    return {"counts": counts, "occluder_share": (float(np.min(shares)), float(np.max(shares)))}


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="bags", help="folder for the bags")
    parser.add_argument("--force", action="store_true", help="replace existing bags (atomically)")
    args = parser.parse_args(argv)

    from leapnbv_perception.smplx_layer import SMPLXModel
    from leapnbv_sim.stand_ins import ensure_stand_in_body_model

    body_model = SMPLXModel.load(ensure_stand_in_body_model("small"))
    for name, spec in SAMPLE_BAGS.items():
        path = Path(args.out) / name
        if path.exists() and not args.force:
            print(f"[bags] {path} exists (use --force to replace)")
            continue
        info = make_sample_bag(path, spec["seed"], spec["walls"], body_model, "stand_in_small", args.force)
        print(f"[bags] wrote {path}: {info['counts']}; occluder share {info['occluder_share']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
