#!/usr/bin/env python3
"""Write the STAND-IN body model and the CONTRACT ONNX models into one folder.

These are test doubles: the stand-in body model is a procedural humanoid in the SMPL-X .npz
layout (not SMPL-X); the contract models have the YOLOv8 / SMPLer-X export names and shapes
but no accuracy. For real results bring SMPLX_NEUTRAL.npz and the real ONNX exports.

Usage: scripts/make_stand_ins.py [folder] [--resolution small|full|both] [--force]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "src", "leapnbv_perception"))

from leapnbv_stand_ins.contract_models import write_contract_detector, write_contract_hmr  # noqa: E402
from leapnbv_stand_ins.stand_in_body_model import write_stand_in_body_model  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", nargs="?", default=os.path.join("models", "stand_in"))
    parser.add_argument("--resolution", choices=("small", "full", "both"), default="both")
    parser.add_argument("--force", action="store_true", help="overwrite files that exist")
    args = parser.parse_args()

    jobs = []
    resolutions = ("small", "full") if args.resolution == "both" else (args.resolution,)
    for resolution in resolutions:
        jobs.append(
            ("stand_in_body_model_%s.npz" % resolution, lambda p, r=resolution: write_stand_in_body_model(p, r))
        )
    jobs.append(("contract_yolov8_detector.onnx", write_contract_detector))
    jobs.append(("contract_smplerx_hmr_512x384.onnx", lambda p: write_contract_hmr(p, (512, 384))))
    jobs.append(("contract_smplerx_hmr_256x192.onnx", lambda p: write_contract_hmr(p, (256, 192))))

    os.makedirs(args.folder, exist_ok=True)
    for name, write in jobs:
        path = os.path.join(args.folder, name)
        if os.path.exists(path) and not args.force:
            print("exists, kept: %s (use --force to rewrite)" % path)
            continue
        start = time.perf_counter()
        write(path)
        print("wrote %s (%.0f kB, %.2f s)" % (path, os.path.getsize(path) / 1024.0, time.perf_counter() - start))
    return 0


if __name__ == "__main__":
    sys.exit(main())
