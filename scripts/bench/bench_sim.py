#!/usr/bin/env python3
"""Benchmark the simulator on one core: scene generation and 640x480 frame rendering.

Prints median and p95 over many runs, and the ratio of a full ``Scene.render`` (RGB, noisy
depth, object ids, ground truth with visibility) to the bare rasterization of the same mesh
(the reference: what any renderer must pay), plus the benchmark set's starting occlusion.

Usage: .venv/bin/python scripts/bench/bench_sim.py [--scenes 20] [--renders 50] [--resolution small]
"""

from __future__ import annotations

import os

for _name in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_name] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

_ROOT = Path(__file__).resolve().parents[2]
for _package in ("leapnbv_common", "leapnbv_perception", "leapnbv_geometry", "leapnbv_sim"):
    sys.path.insert(0, str(_ROOT / "src" / _package))

from leapnbv_evaluation.benchmark_set import BENCHMARK_SEEDS  # noqa: E402
from leapnbv_geometry.raster import rasterize_mesh, warm_up  # noqa: E402
from leapnbv_perception.smplx_layer import SMPLXModel  # noqa: E402
from leapnbv_sim.generation import SceneConfig, generate_scene  # noqa: E402
from leapnbv_stand_ins.stand_in_body_model import build_stand_in_body_model  # noqa: E402


def _stats(samples_ms: list) -> str:
    values = np.asarray(samples_ms)
    return "median %7.2f ms  p95 %7.2f ms  (n=%d)" % (np.median(values), np.percentile(values, 95), values.size)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=20)
    parser.add_argument("--renders", type=int, default=50)
    parser.add_argument("--resolution", default="small", choices=["small", "full"])
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {0})

    print("raster JIT warm-up: %.2f s" % warm_up())
    model = SMPLXModel(build_stand_in_body_model(args.resolution), source="stand_in_" + args.resolution)
    print("body: %d vertices, %d faces (%s)" % (model.num_vertices, model.num_faces, args.resolution))

    generate_ms = []
    scenes = []
    for seed in BENCHMARK_SEEDS[: args.scenes]:
        start = time.perf_counter()
        scenes.append(generate_scene(SceneConfig(seed=seed, body_resolution=args.resolution), model))
        generate_ms.append((time.perf_counter() - start) * 1e3)
    print("generate_scene      ", _stats(generate_ms))

    render_ms = []
    raster_ms = []
    for index in range(args.renders):
        scene = scenes[index % len(scenes)]
        camera = scene.start_camera
        start = time.perf_counter()
        rasterize_mesh(
            camera.world_to_camera(scene.vertices_world),
            scene.faces,
            scene.K,
            scene.config.width,
            scene.config.height,
            face_object_id=scene.face_object_id,
        )
        raster_ms.append((time.perf_counter() - start) * 1e3)
        start = time.perf_counter()
        scene.render(camera, frame_index=index)
        render_ms.append((time.perf_counter() - start) * 1e3)
    print("Scene.render 640x480", _stats(render_ms))
    print("reference raster    ", _stats(raster_ms))
    print("render / raster ratio (median): %.2f" % (np.median(render_ms) / np.median(raster_ms)))

    shares = np.array([scene.start_occluder_share for scene in scenes])
    print(
        "start occluder share over %d benchmark scenes: min %.3f  p25 %.3f  median %.3f  p75 %.3f  max %.3f"
        % (shares.size, shares.min(), *np.percentile(shares, [25, 50, 75]), shares.max())
    )


if __name__ == "__main__":
    main()
