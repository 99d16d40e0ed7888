"""python -m leapnbv_model_tools {export-hmr, random-checkpoint, random-yolov8, manifests, fp16-check,
overflow-table, distill, ladder, quantize-int8} ...

Every command runs in the tools environment (tools/run.sh) except quantize-int8, which renders its
calibration frames with the simulator and so runs with the robot's environment:
PYTHONPATH=tools scripts/env.sh python -m leapnbv_model_tools quantize-int8 ..."""

from __future__ import annotations

import argparse
import sys
from typing import Optional, Sequence


def main(argv: Optional[Sequence[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    commands = ("export-hmr", "random-checkpoint", "random-yolov8", "manifests", "fp16-check", "overflow-table",
                "distill", "ladder", "quantize-int8")
    if not argv or argv[0] not in commands:
        print(f"usage: python -m leapnbv_model_tools {{{','.join(commands)}}} ...", file=sys.stderr)
        return 2
    command, rest = argv[0], argv[1:]
    if command == "export-hmr":
        from leapnbv_model_tools.export import main as export_main

        return export_main(rest)
    if command == "random-yolov8":
        from leapnbv_model_tools.yolov8 import SCALES, export_yolov8, random_yolov8

        parser = argparse.ArgumentParser(prog="python -m leapnbv_model_tools random-yolov8",
                                         description="a YOLOv8 of the real architecture with random weights "
                                                     "(a timing stand-in that detects nothing), as ONNX")
        parser.add_argument("--scale", default="s", choices=sorted(SCALES))
        parser.add_argument("--size", type=int, default=640, help="input side (a multiple of 32)")
        parser.add_argument("--seed", type=int, default=0)
        parser.add_argument("--out", required=True)
        args = parser.parse_args(rest)
        if args.size % 32:
            print(f"random-yolov8: --size {args.size} is not a multiple of 32", file=sys.stderr)
            return 2
        print(export_yolov8(random_yolov8(args.scale, args.seed, args.size), args.out, args.size))
        return 0
    if command == "fp16-check":
        from leapnbv_model_tools.fp16 import main as fp16_main

        return fp16_main(rest)
    if command == "overflow-table":
        from leapnbv_model_tools.overflow_table import main as table_main

        return table_main(rest)
    if command == "distill":
        from leapnbv_model_tools.distill import main as distill_main

        return distill_main(rest)
    if command == "ladder":
        from leapnbv_model_tools.ladder import main as ladder_main

        return ladder_main(rest)
    if command == "quantize-int8":
        from leapnbv_model_tools.quantize_int8 import main as quantize_main

        return quantize_main(rest)
    if command == "manifests":
        from leapnbv_model_tools.checkpoint import write_manifests

        for path in write_manifests():
            print(path)
        return 0
    from leapnbv_model_tools.checkpoint import VARIANTS, random_network, save_official

    parser = argparse.ArgumentParser(prog="python -m leapnbv_model_tools random-checkpoint",
                                     description="a randomly initialised SMPLer-X or SMPLest-X checkpoint in the "
                                                 "official file structure")
    parser.add_argument("--variant", required=True, choices=sorted(VARIANTS))
    parser.add_argument("--out", required=True)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(rest)
    print(save_official(random_network(args.variant, args.seed), args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
