#!/usr/bin/env python3
"""Write the STAND-IN body models and the CONTRACT ONNX models into one folder.

These are test doubles: the stand-in body model is a procedural humanoid in the SMPL-X .npz
layout (not SMPL-X); the contract models have the YOLOv8 / SMPLer-X export names and shapes
but no accuracy. For real results bring SMPLX_NEUTRAL.npz and the real ONNX exports.
File names: leapnbv_stand_ins.files (the same names the tests and the simulator use).

Usage: scripts/env.sh python scripts/make_stand_ins.py [folder] [--force]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from leapnbv_stand_ins.files import (
    ensure_contract_models,
    ensure_stand_in_body_model,
    ensure_stand_in_smplx_dense,
    stand_in_dir,
)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", nargs="?", default=str(stand_in_dir()))
    parser.add_argument("--force", action="store_true", help="rewrite files that exist")
    args = parser.parse_args()
    start = time.perf_counter()
    paths = [ensure_stand_in_body_model(resolution, args.folder, args.force) for resolution in ("small", "full")]
    paths.append(ensure_stand_in_smplx_dense(args.folder, args.force))
    for hmr_input in ((512, 384), (256, 192)):
        paths.extend(ensure_contract_models(args.folder, args.force, hmr_input))
    for path in sorted(set(paths)):
        print("%s (%.0f kB)" % (path, os.path.getsize(path) / 1024.0))
    print("%.1f s" % (time.perf_counter() - start))
    return 0


if __name__ == "__main__":
    sys.exit(main())
