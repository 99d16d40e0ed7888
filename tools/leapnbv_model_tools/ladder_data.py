"""The ladder's synthetic data: simulator scenes of the dense stand-in body (run with the robot's .venv).

    .venv/bin/python -m leapnbv_model_tools.ladder_data --out DIR --body stand_in_smplx_dense.npz --train 8 ...
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np


def make_dataset(folder: Path, counts: Dict[str, int], body_path: str, seed: int = 1000) -> Dict[str, str]:
    """Render the scenes (see ladder.py); returns split -> manifest path."""
    import cv2

    from leapnbv_perception.smplx_layer import SMPLXModel
    from leapnbv_sim.generation import SceneConfig, generate_scene
    from leapnbv_sim.scene import SceneError

    folder.mkdir(parents=True, exist_ok=True)
    body = SMPLXModel.load(body_path)
    manifests = {}
    scene_seed = seed
    for split in ("train", "val", "test"):
        lines: List[str] = []
        while len(lines) < counts[split]:
            scene_seed += 1
            config = SceneConfig(seed=scene_seed, person_distance_range=(1.5, 4.0), occluder_share_range=(0.05, 0.45),
                                 depth_noise=False, body_resolution="full")
            try:
                scene = generate_scene(config, body)
            except SceneError:
                continue
            frame = scene.render()
            truth = frame.ground_truth
            if truth.person_box_xyxy is None or truth.person_pixel_count < 400:
                continue
            name = f"{split}_{scene_seed}.png"
            cv2.imwrite(str(folder / name), np.ascontiguousarray(frame.rgb[:, :, ::-1]))
            p = truth.body_params_camera
            params = {"root": p.root_pose, "body": p.body_pose, "lhand": p.left_hand_pose, "rhand": p.right_hand_pose,
                      "jaw": p.jaw_pose, "betas": p.betas, "expression": p.expression}
            fx, fy, cx, cy = (float(frame.K[i, j]) for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)))
            lines.append(json.dumps({"image": name, "box": [float(v) for v in truth.person_box_xyxy],
                                     "params": {k: np.asarray(v, dtype=float).tolist() for k, v in params.items()},
                                     "camera": {"K": [fx, fy, cx, cy],
                                                "translation": [float(v) for v in truth.translation_camera]},
                                     "occluder_share": float(truth.occluder_share)}))
        manifests[split] = str(folder / f"{split}.jsonl")
        Path(manifests[split]).write_text("\n".join(lines) + "\n")
    return manifests


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m leapnbv_model_tools.ladder_data")
    parser.add_argument("--out", required=True)
    parser.add_argument("--body", required=True)
    parser.add_argument("--seed", type=int, default=1000)
    for split in ("train", "val", "test"):
        parser.add_argument(f"--{split}", type=int, required=True)
    args = parser.parse_args(argv)
    make_dataset(Path(args.out), {"train": args.train, "val": args.val, "test": args.test}, args.body, args.seed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
