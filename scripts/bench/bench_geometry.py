#!/usr/bin/env python3
"""Benchmark the geometry cores on one CPU core: rasterizer, target geometry, mesh registration, RANSAC ground.

Prints median and p95 over many frames, and the ratio to straightforward references run in
the same process (trimesh ray casting for the render, a per-iteration numpy loop for RANSAC).

Usage: .venv/bin/python scripts/bench/bench_geometry.py [--frames 200] [--cold-jit]
"""

from __future__ import annotations

import os
import sys

# One core: set before numpy / numba are imported.
for _name in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_name] = "1"
if "--cold-jit" in sys.argv:
    import tempfile

    os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="leapnbv_numba_cold_")
if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

_REPO = Path(__file__).resolve().parents[2]
for _pkg in ("leapnbv_geometry", "leapnbv_perception"):
    sys.path.insert(0, str(_REPO / "src" / _pkg))

from leapnbv_geometry import raster  # noqa: E402
from leapnbv_geometry.ground import fit_ground_plane, ground_points_from_depth  # noqa: E402
from leapnbv_geometry.mesh_registration import register_mesh_to_depth  # noqa: E402
from leapnbv_geometry.target_geometry import compute_target_geometry  # noqa: E402

WIDTH, HEIGHT = 640, 480
# RealSense-like 640x480 intrinsics.
K = np.array([[615.0, 0.0, 319.5], [0.0, 615.0, 239.5], [0.0, 0.0, 1.0]])
N_VERTICES, N_FACES = 10475, 20908  # SMPL-X sizes


def ellipsoid(centre, radii, segments: int, bands: int):
    """Closed UV ellipsoid: V = segments * (bands - 1) + 2, F = 2 * segments * (bands - 1)."""
    theta = np.linspace(0.0, np.pi, bands + 1)[1:-1]
    phi = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], axis=-1).reshape(-1, 3)
    unit = np.vstack([[0.0, 1.0, 0.0], ring, [0.0, -1.0, 0.0]])
    vertices = unit * np.asarray(radii) + np.asarray(centre)
    faces = []
    for j in range(segments):
        k = (j + 1) % segments
        faces.append([0, 1 + k, 1 + j])
        for i in range(bands - 2):
            a, b = 1 + i * segments + j, 1 + i * segments + k
            c, d = a + segments, b + segments
            faces += [[a, b, d], [a, d, c]]
        last = 1 + (bands - 2) * segments
        faces.append([len(unit) - 1, last + j, last + k])
    return vertices, np.array(faces)


def synthetic_person(z: float = 2.4):
    """A person-sized mesh of exactly 10,475 vertices and 20,908 faces (ten ellipsoids,
    two faces dropped: SMPL-X is not closed either), about 200 x 450 px at 640x480."""
    parts = []
    # Nine limbs / head of 32 x 33 (1,026 vertices each) and a 21 x 60 torso (1,241).
    for centre, radii in [
        ((0.0, -0.78, 0.0), (0.10, 0.12, 0.11)),    # head
        ((-0.25, -0.38, 0.0), (0.05, 0.17, 0.05)),  # upper arms
        ((0.25, -0.38, 0.0), (0.05, 0.17, 0.05)),
        ((-0.32, -0.05, 0.05), (0.04, 0.16, 0.04)),  # forearms
        ((0.32, -0.05, 0.05), (0.04, 0.16, 0.04)),
        ((-0.10, 0.28, 0.0), (0.08, 0.22, 0.08)),   # thighs
        ((0.10, 0.28, 0.0), (0.08, 0.22, 0.08)),
        ((-0.10, 0.70, 0.0), (0.06, 0.21, 0.06)),   # shins
        ((0.10, 0.70, 0.0), (0.06, 0.21, 0.06)),
    ]:
        parts.append(ellipsoid(centre, radii, 32, 33))
    parts.append(ellipsoid((0.0, -0.35, 0.0), (0.19, 0.33, 0.12), 21, 60))
    vertices, faces, base = [], [], 0
    for v, f in parts:
        vertices.append(v)
        faces.append(f + base)
        base += v.shape[0]
    vertices = np.vstack(vertices) + np.array([0.05, 0.0, z])
    faces = np.vstack(faces)[:-2]
    assert vertices.shape[0] == N_VERTICES and faces.shape[0] == N_FACES, (vertices.shape, faces.shape)
    return vertices, faces


def person_mesh():
    """The full-size stand-in body when its generator exists, else the synthetic mesh."""
    try:
        from leapnbv_perception.smplx_layer import SMPLXModel, SMPLXParams
        from leapnbv_stand_ins.stand_in_body_model import build_stand_in_body_model
    except ImportError:
        return synthetic_person(), "synthetic ellipsoid person"
    model = SMPLXModel(build_stand_in_body_model("full"))
    body = np.zeros(63)
    body[15 * 3 + 2], body[16 * 3 + 2] = -1.1, 1.1  # arms down
    params = SMPLXParams.from_axis_angle(np.array([np.pi, 0.0, 0.0]), body, np.zeros(45), np.zeros(45),
                                         np.zeros(3))  # y up -> optical y down, facing the camera
    vertices = model.forward(params).vertices.astype(np.float64) + np.array([0.0, 0.05, 3.0])
    return (vertices, np.asarray(model.faces, dtype=np.int64)), "posed full-size stand-in body"


def scene_depth(person_vertices, person_faces):
    """Depth of person + occluder + wall + floor (floor 1.0 m below the camera)."""
    z = float(np.median(person_vertices[:, 2]))
    quads = [
        np.array([[-20, 1.0, -5.0], [20, 1.0, -5.0], [20, 1.0, 30.0], [-20, 1.0, 30.0]]),  # floor
        np.array([[-6, -3, z + 2.0], [6, -3, z + 2.0], [6, 1.0, z + 2.0], [-6, 1.0, z + 2.0]]),  # wall
        np.array([[-0.5, 0.0, z - 0.8], [0.1, 0.0, z - 0.8], [0.1, 0.5, z - 0.8], [-0.5, 0.5, z - 0.8]]),
    ]
    vertices = [person_vertices]
    faces = [person_faces]
    base = person_vertices.shape[0]
    for quad in quads:
        vertices.append(quad)
        faces.append(np.array([[0, 1, 2], [0, 2, 3]]) + base)
        base += 4
    result = raster.rasterize_mesh(np.vstack(vertices), np.vstack(faces), K, WIDTH, HEIGHT)
    rng = np.random.default_rng(0)
    depth = result.depth + rng.normal(0, 0.003, result.depth.shape).astype(np.float32) * (result.depth > 0)
    return depth.astype(np.float32), result.silhouette


def timed(function, frames: int):
    times = np.empty(frames)
    for i in range(frames):
        start = time.perf_counter()
        function()
        times[i] = time.perf_counter() - start
    return times * 1e3


def report(name: str, times_ms: np.ndarray, goal_ms: float) -> float:
    median = float(np.median(times_ms))
    p95 = float(np.percentile(times_ms, 95))
    verdict = "OK" if median <= goal_ms else "OVER"
    print(f"{name:<44s} median {median:7.3f} ms  p95 {p95:7.3f} ms  goal <= {goal_ms:.0f} ms  {verdict}")
    return median


def raycast_reference(vertices, faces):
    """Straightforward render: trimesh ray casting, one ray per pixel centre."""
    import trimesh

    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    intersector = trimesh.ray.ray_triangle.RayMeshIntersector(mesh)
    rows, cols = np.mgrid[0:HEIGHT, 0:WIDTH]
    directions = np.stack([
        (cols.ravel() - K[0, 2]) / K[0, 0], (rows.ravel() - K[1, 2]) / K[1, 1], np.ones(rows.size)
    ], axis=1)
    locations, index_ray, _ = intersector.intersects_location(
        np.zeros_like(directions), directions, multiple_hits=False
    )
    depth = np.zeros(rows.size)
    depth[index_ray] = locations[:, 2]
    return depth.reshape(HEIGHT, WIDTH)


def ransac_loop_reference(points, iterations=128, max_points=2048, threshold=0.02, max_tilt_deg=30.0, seed=0):
    """Straightforward RANSAC: one hypothesis per Python iteration, then the same refinement."""
    up = np.array([0.0, -1.0, 0.0])
    cos_max = np.cos(np.radians(max_tilt_deg))
    rng = np.random.default_rng(seed)
    sample = points[rng.integers(0, points.shape[0], size=min(max_points, points.shape[0]))].astype(np.float64)
    best_count, best = -1, None
    for _ in range(iterations):
        p0, p1, p2 = sample[rng.integers(0, sample.shape[0], size=3)]
        normal = np.cross(p1 - p0, p2 - p0)
        length = np.linalg.norm(normal)
        if length < 1e-12:
            continue
        normal /= length
        if normal @ up < 0:
            normal = -normal
        if normal @ up < cos_max:
            continue
        offset = -normal @ p0
        count = np.count_nonzero(np.abs(sample @ normal + offset) <= threshold)
        if count > best_count:
            best_count, best = count, (normal, offset)
    normal, offset = best
    for _ in range(2):
        inliers = points[np.abs(points @ normal + offset) <= threshold].astype(np.float64)
        centre = inliers.mean(axis=0)
        _, _, vt = np.linalg.svd(inliers - centre, full_matrices=False)
        normal = vt[-1] if vt[-1] @ up > 0 else -vt[-1]
        offset = -normal @ centre
    return normal, offset


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--cold-jit", action="store_true", help="compile into a fresh numba cache")
    args = parser.parse_args()

    print(f"one core: affinity {sorted(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else 'n/a'}, "
          f"python {sys.version.split()[0]}, numpy {np.__version__}")
    jit_seconds = raster.warm_up()
    print(f"numba warm-up (first call in this process{', cold cache' if args.cold_jit else ''}): "
          f"{jit_seconds:.2f} s")

    (vertices, faces), mesh_name = person_mesh()
    result = raster.rasterize_mesh(vertices, faces, K, WIDTH, HEIGHT)
    rows, cols = np.nonzero(result.silhouette)
    print(f"mesh: {mesh_name}, {vertices.shape[0]} vertices, {faces.shape[0]} faces, footprint "
          f"{cols.max() - cols.min() + 1} x {rows.max() - rows.min() + 1} px, "
          f"{rows.size} silhouette px at {WIDTH}x{HEIGHT}")

    raster_ms = timed(lambda: raster.rasterize_mesh(vertices, faces, K, WIDTH, HEIGHT), args.frames)
    raster_median = report("rasterize_mesh 640x480", raster_ms, 5.0)

    depth, _ = scene_depth(vertices, faces)
    box = (cols.min(), rows.min(), cols.max(), rows.max())
    plane = (np.array([0.0, -1.0, 0.0]), 1.0)
    target = compute_target_geometry(vertices, faces, depth, K, box, ground_plane=plane)
    print(f"target: valid {target.valid}, {target.mask_pixel_count} px kept, visible fraction "
          f"{target.visible_fraction:.2f}, {target.background_points.shape[0]} background points")
    target_ms = timed(
        lambda: compute_target_geometry(vertices, faces, depth, K, box, ground_plane=plane), args.frames
    )
    report("compute_target_geometry (whole frame)", target_ms, 10.0)

    # The mesh 30 % too far (same image): the registration's cost per frame, on top of the target stage.
    registration = register_mesh_to_depth(vertices * 1.3, faces, depth, K, box)
    print(f"registration: ok {registration.ok} {registration.reason}, depth recovered to "
          f"{abs(registration.vertices[:, 2].mean() - vertices[:, 2].mean()) * 100:.1f} cm, residual "
          f"{registration.residual * 100:.1f} cm, inlier share {registration.inlier_share:.2f}")
    registration_ms = timed(lambda: register_mesh_to_depth(vertices * 1.3, faces, depth, K, box), args.frames)
    report("register_mesh_to_depth (whole frame)", registration_ms, 10.0)

    def registered_frame():
        fit = register_mesh_to_depth(vertices * 1.3, faces, depth, K, box)
        return compute_target_geometry(fit.vertices, faces, depth, K, box, ground_plane=plane, depth_offset=0.0,
                                       mesh_raster=fit.raster)

    report("  registration + target (one render)", timed(registered_frame, args.frames), 15.0)

    def ground_frame():
        points = ground_points_from_depth(depth, K, exclude_mask=target.mask, stride=4)
        return fit_ground_plane(points)

    ground = ground_frame()
    print(f"ground: valid {ground.valid}, normal {np.round(ground.normal, 4)}, d {ground.offset:.4f}, "
          f"{ground.inlier_count} inliers ({ground.inlier_ratio:.2f})")
    ground_ms = timed(ground_frame, args.frames)
    ground_median = report("ground points + RANSAC (640x480, stride 4)", ground_ms, 10.0)
    points = ground_points_from_depth(depth, K, exclude_mask=target.mask, stride=4)
    fit_ms = timed(lambda: fit_ground_plane(points), args.frames)
    fit_median = report(f"  fit_ground_plane alone ({points.shape[0]} points)", fit_ms, 10.0)

    print("references (same process):")
    start = time.perf_counter()
    reference_depth = raycast_reference(vertices, faces)
    reference_ms = (time.perf_counter() - start) * 1e3
    hit = reference_depth > 0
    agree = np.count_nonzero(hit & result.silhouette) / np.count_nonzero(hit | result.silhouette)
    print(f"  trimesh ray casting, {WIDTH * HEIGHT} rays: {reference_ms:9.1f} ms  "
          f"-> rasterizer is {reference_ms / raster_median:,.0f}x faster (silhouette IoU {agree:.4f})")
    loop_ms = timed(lambda: ransac_loop_reference(points), max(10, args.frames // 10))
    loop_median = float(np.median(loop_ms))
    print(f"  per-iteration numpy RANSAC loop: median {loop_median:7.3f} ms  "
          f"-> vectorized fit is {loop_median / fit_median:.1f}x faster "
          f"(whole ground frame {loop_median / ground_median:.1f}x of the loop's fit)")


if __name__ == "__main__":
    main()
