"""Benchmark of the planner core: candidate scoring (the registered score terms), feasibility and one
whole plan_views call per frame, one core.

Scene: a level RGB-D camera 1.2 m above the floor looks at a person (a 1.7 m cylinder
surface, 3 m ahead) in a room (back and side walls, a box occluder in front of the person,
a pillar behind it, a cabinet). Both clouds are back-projected from a ray-cast depth image in raster order, as
the geometry stage produces them (floor pixels removed from the background). Point counts
are set by the depth-image sampling grid.

Reference ("slow"): per candidate, numpy projection, a min-depth image built with
np.minimum.at, then a Python loop over the in-view target points taking the min of the
(2h+1)^2 window of that image: the same definition as the compiled kernel, written the
obvious way. Its S_o must equal the fast one exactly.

The ring and every other parameter are the nbv node's defaults (the robot's values, radius 2.5 m).

Usage: .venv/bin/python scripts/bench/bench_planner.py [--repeats 200] [--reference-repeats 3] [--robot-only]
"""

from __future__ import annotations

import os

# One core: set before numpy / numba are imported.
os.environ["NUMBA_NUM_THREADS"] = "1"
os.environ["OMP_NUM_THREADS"] = "1"
os.environ["OPENBLAS_NUM_THREADS"] = "1"
os.environ["MKL_NUM_THREADS"] = "1"

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from functools import partial  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Callable, List, Tuple  # noqa: E402

import numpy as np  # noqa: E402

for _package in ("leapnbv_planner", "leapnbv_common"):  # the ROS-free cores, straight from the source tree
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "src" / _package))
# reference_planner_kernels: the tests' per-point occlusion kernel and plain line-of-sight walk.
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "src" / "leapnbv_planner" / "test"))

from leapnbv_planner.candidates import check_feasibility, generate_candidates  # noqa: E402
from leapnbv_planner.inputs import CameraInMap, PlanFloor, PlanInputs, PlanTarget  # noqa: E402
from leapnbv_planner.mesh_kernel import mesh_vertex_normals  # noqa: E402
from leapnbv_planner.obstacle_map import (  # noqa: E402
    line_of_sight_clear_fraction,
    voxel_map_from_centres,
    warm_up_obstacle_map,
)
from leapnbv_planner.occlusion_kernel import count_framed_bucketed  # noqa: E402
from leapnbv_planner.params import nbv_params_class  # noqa: E402
from leapnbv_planner.plan import plan_views  # noqa: E402
from leapnbv_planner.requirements import SurfacePoints  # noqa: E402
from leapnbv_planner.score_terms import ScoringContext, get_term  # noqa: E402
from leapnbv_planner.scoring import score_candidates, warm_up_scoring  # noqa: E402

WIDTH, HEIGHT = 640, 480
INTRINSICS = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])
CAMERA_HEIGHT = 1.2
PLANE_NORMAL = np.array([0.0, -1.0, 0.0])
PLANE_OFFSET = CAMERA_HEIGHT  # floor: y = 1.2 in the optical frame
ROOM_HALF_WIDTH, ROOM_DEPTH, CEILING_Y = 3.0, 6.0, CAMERA_HEIGHT - 2.6
PERSON_CENTRE = np.array([0.2, CAMERA_HEIGHT - 0.85, 3.0])
PERSON_RADIUS = 0.2
PERSON_HEIGHT = 1.7
# Axis-aligned boxes (min corner, max corner): an occluder in front of the person, a pillar
# behind it on the right, a cabinet.
BOXES = [
    (np.array([-0.4, 0.3, 2.0]), np.array([0.25, CAMERA_HEIGHT, 2.3])),
    (np.array([0.7, CEILING_Y, 3.6]), np.array([1.0, CAMERA_HEIGHT, 3.9])),
    (np.array([-2.5, -0.2, 3.5]), np.array([-1.5, CAMERA_HEIGHT, 4.5])),
]


def ray_cast_scene(grid_width: int, grid_height: int) -> Tuple[np.ndarray, np.ndarray]:
    """Ray-cast the scene on a grid of pixel centres; return (target, background) points.

    Args:
        grid_width, grid_height: number of sampled columns and rows across the image.

    Returns:
        target (N, 3) and background (K, 3) points in raster order.
    """
    u = (np.arange(grid_width) + 0.5) * WIDTH / grid_width
    v = (np.arange(grid_height) + 0.5) * HEIGHT / grid_height
    uu, vv = np.meshgrid(u, v)
    rays = np.stack(
        [(uu - INTRINSICS[0, 2]) / INTRINSICS[0, 0], (vv - INTRINSICS[1, 2]) / INTRINSICS[1, 1],
         np.ones_like(uu)], axis=-1,
    ).reshape(-1, 3)
    hit = np.full(rays.shape[0], np.inf)
    label = np.zeros(rays.shape[0], dtype=np.int8)  # 0 background, 1 person, 2 floor
    with np.errstate(divide="ignore", invalid="ignore"):
        # Room planes (ray parameter t with ray z = 1, so t is the depth).
        for axis, value, kind in ((2, ROOM_DEPTH, 0), (0, -ROOM_HALF_WIDTH, 0),
                                  (0, ROOM_HALF_WIDTH, 0), (1, CEILING_Y, 0),
                                  (1, CAMERA_HEIGHT, 2)):
            t = value / rays[:, axis]
            closer = (t > 0) & (t < hit)
            hit[closer], label[closer] = t[closer], kind
        for low, high in BOXES:
            t_near = np.max(np.minimum(low / rays, high / rays), axis=1)
            t_far = np.min(np.maximum(low / rays, high / rays), axis=1)
            closer = (t_near <= t_far) & (t_near > 0) & (t_near < hit)
            hit[closer], label[closer] = t_near[closer], 0
        # Vertical person cylinder about the y axis through PERSON_CENTRE.
        ox, oz = -PERSON_CENTRE[0], -PERSON_CENTRE[2]
        a = rays[:, 0] ** 2 + rays[:, 2] ** 2
        b = 2.0 * (ox * rays[:, 0] + oz * rays[:, 2])
        c = ox * ox + oz * oz - PERSON_RADIUS ** 2
        disc = b * b - 4 * a * c
        t = (-b - np.sqrt(disc)) / (2 * a)
        y = t * rays[:, 1]
        inside = (disc >= 0) & (np.abs(y - PERSON_CENTRE[1]) <= PERSON_HEIGHT / 2)
        closer = inside & (t > 0) & (t < hit)
        hit[closer], label[closer] = t[closer], 1
    points = rays * hit[:, None]
    finite = np.isfinite(hit)
    return points[finite & (label == 1)], points[finite & (label == 0)]


def scene_with_counts(num_target: int, num_background: int) -> Tuple[np.ndarray, np.ndarray]:
    """Ray-cast on a grid fine enough for the counts, then keep every k-th point in order."""
    scale = 1.0
    while True:
        target, background = ray_cast_scene(int(WIDTH * scale), int(HEIGHT * scale))
        if target.shape[0] >= num_target and background.shape[0] >= num_background:
            break
        scale *= 1.25
    pick_t = np.linspace(0, target.shape[0] - 1, num_target).astype(np.int64)
    pick_b = np.linspace(0, background.shape[0] - 1, num_background).astype(np.int64)
    return target[pick_t], background[pick_b]


def reference_occlusion(
    target: np.ndarray, background: np.ndarray, rotations: np.ndarray, positions: np.ndarray,
    half_window: int,
) -> np.ndarray:
    """Slow S_o: numpy projection, np.minimum.at min-depth image, per-point window loop."""
    fx, skew, cx = INTRINSICS[0]
    fy, cy = INTRINSICS[1, 1], INTRINSICS[1, 2]
    result = np.zeros(rotations.shape[0])
    pad = half_window
    for c in range(rotations.shape[0]):
        cam_t = (target - positions[c]) @ rotations[c]
        cam_b = (background - positions[c]) @ rotations[c]
        with np.errstate(divide="ignore", invalid="ignore"):
            u_t = fx * (cam_t[:, 0] / cam_t[:, 2]) + skew * (cam_t[:, 1] / cam_t[:, 2]) + cx
            v_t = fy * (cam_t[:, 1] / cam_t[:, 2]) + cy
            u_b = fx * (cam_b[:, 0] / cam_b[:, 2]) + skew * (cam_b[:, 1] / cam_b[:, 2]) + cx
            v_b = fy * (cam_b[:, 1] / cam_b[:, 2]) + cy
        view = (cam_t[:, 2] > 0) & (u_t >= 0) & (u_t < WIDTH) & (v_t >= 0) & (v_t < HEIGHT)
        keep = ((cam_b[:, 2] > 0) & (u_b >= -pad) & (u_b < WIDTH + pad)
                & (v_b >= -pad) & (v_b < HEIGHT + pad))
        image = np.full((HEIGHT + 2 * pad, WIDTH + 2 * pad), np.inf)
        np.minimum.at(
            image,
            (np.floor(v_b[keep]).astype(np.int64) + pad, np.floor(u_b[keep]).astype(np.int64) + pad),
            cam_b[keep, 2],
        )
        cols = np.floor(u_t[view]).astype(np.int64) + pad
        rows = np.floor(v_t[view]).astype(np.int64) + pad
        depths = cam_t[view, 2]
        visible = 0
        for col, row, depth in zip(cols, rows, depths):
            window = image[row - pad:row + pad + 1, col - pad:col + pad + 1]
            visible += depth <= window.min()
        result[c] = visible / len(depths) if len(depths) else 0.0
    return result


def room_voxel_map(resolution: float = 0.1):
    """The benchmark room's boxes and walls as an obstacle map (map frame = the observation frame)."""
    solids = list(BOXES) + [
        (np.array([-ROOM_HALF_WIDTH, CEILING_Y, ROOM_DEPTH]),
         np.array([ROOM_HALF_WIDTH, CAMERA_HEIGHT, ROOM_DEPTH + 0.1])),
        (np.array([-ROOM_HALF_WIDTH - 0.1, CEILING_Y, 0.0]), np.array([-ROOM_HALF_WIDTH, CAMERA_HEIGHT, ROOM_DEPTH])),
        (np.array([ROOM_HALF_WIDTH, CEILING_Y, 0.0]), np.array([ROOM_HALF_WIDTH + 0.1, CAMERA_HEIGHT, ROOM_DEPTH])),
    ]
    centres = []
    for lo, hi in solids:
        axes = [np.arange(np.floor(a / resolution), np.ceil(b / resolution)) for a, b in zip(lo, hi)]
        index = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        centres.append((index + 0.5) * resolution)
    return voxel_map_from_centres(np.concatenate(centres), resolution)


def reference_clear_fraction(grid, cameras: np.ndarray, targets: np.ndarray, margin: float) -> np.ndarray:
    """The obvious way: sample every segment every r/8 and look the samples up in the grid."""
    out = np.empty(len(cameras))
    shape = np.array(grid.occupied.shape)
    for c, camera in enumerate(cameras):
        clear = 0
        for target in targets:
            length = float(np.linalg.norm(target - camera))
            t = np.arange(0.0, 1.0 - margin / length, grid.resolution / 8.0 / length)
            cells = np.floor((camera + t[:, None] * (target - camera)) / grid.resolution).astype(np.int64)
            cells -= grid.lower_index
            cells = cells[np.all((cells >= 0) & (cells < shape), axis=1)]
            clear += not grid.occupied[cells[:, 0], cells[:, 1], cells[:, 2]].any()
        out[c] = clear / len(targets)
    return out


def time_call(function: Callable[[], object], repeats: int) -> Tuple[float, float]:
    """Median and p95 wall time in milliseconds over `repeats` calls (after one warm call)."""
    function()
    samples: List[float] = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        samples.append((time.perf_counter() - start) * 1e3)
    return float(np.median(samples)), float(np.percentile(samples, 95))


def main() -> None:
    """Run the benchmark and print a table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--reference-repeats", type=int, default=3)
    parser.add_argument("--robot-only", action="store_true", help="only the robot's plan (3 rings, reachability, "
                        "mesh S_o)")
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {0})
    warm_up_scoring()

    centroid = np.median(ray_cast_scene(WIDTH, HEIGHT)[0], axis=0)

    params = nbv_params_class()()  # the robot's values
    if args.robot_only:
        warm_up_obstacle_map()
        bench_robot_plan(params, centroid, room_voxel_map(), args.repeats)
        return

    def ring(num_candidates: int):
        return generate_candidates(
            centroid, PLANE_NORMAL, PLANE_OFFSET, nbv_params_class()(num_candidates=num_candidates)
        )

    print(f"image {WIDTH}x{HEIGHT}, delta {params.delta_px:g} px, ring radius {params.radius:g} m,"
          f" terms {', '.join(params.score_terms)}, one core, {args.repeats} repeats (median / p95 ms)")
    print("\nscore_candidates, 20k target / 100k background points:")
    target, background = scene_with_counts(20000, 100000)
    for num_candidates in (16, 32, 64):
        candidates = ring(num_candidates)
        median, p95 = time_call(partial(
            score_candidates, target, background, candidates.rotations, candidates.positions,
            INTRINSICS, WIDTH, HEIGHT), args.repeats)
        print(f"  C = {len(candidates):3d}: {median:7.2f} / {p95:7.2f}")

    print("\nscore_candidates, C = 17 (16 ring + current):")
    candidates = ring(16)
    for num_target, num_background in ((5000, 25000), (20000, 100000), (50000, 250000)):
        target, background = scene_with_counts(num_target, num_background)
        median, p95 = time_call(partial(
            score_candidates, target, background, candidates.rotations, candidates.positions,
            INTRINSICS, WIDTH, HEIGHT), args.repeats)
        print(f"  {num_target // 1000:3d}k / {num_background // 1000:3d}k: {median:7.2f} / {p95:7.2f}")

    print("\nworst case: same 20k/100k points in random order (no spatial coherence):")
    target, background = scene_with_counts(20000, 100000)
    rng = np.random.default_rng(0)
    shuffled_t, shuffled_b = rng.permutation(target), rng.permutation(background)
    median, p95 = time_call(lambda: score_candidates(
        shuffled_t, shuffled_b, candidates.rotations, candidates.positions, INTRINSICS,
        WIDTH, HEIGHT), args.repeats)
    print(f"  C = {len(candidates):3d}: {median:7.2f} / {p95:7.2f}")

    print("\nreference (numpy + np.minimum.at + per-point window loop), 20k/100k, C = 17:")
    fast = score_candidates(target, background, candidates.rotations, candidates.positions,
                            INTRINSICS, WIDTH, HEIGHT)
    slow_result: List[np.ndarray] = []
    ref_median, ref_p95 = time_call(lambda: slow_result.append(reference_occlusion(
        target, background, candidates.rotations, candidates.positions, 4)),
        args.reference_repeats)
    fast_median, _ = time_call(lambda: score_candidates(
        target, background, candidates.rotations, candidates.positions, INTRINSICS,
        WIDTH, HEIGHT), args.repeats)
    # The reference is the paper's S_o over the observed points, which the deployed terms do not score.
    fast_occlusion = score_candidates(target, background, candidates.rotations, candidates.positions, INTRINSICS,
                                      WIDTH, HEIGHT, terms=[("occlusion", 1.0)]).term("occlusion")
    max_diff = float(np.max(np.abs(slow_result[-1] - fast_occlusion)))
    print(f"  reference {ref_median:8.1f} / {ref_p95:8.1f}  fast {fast_median:.2f}"
          f"  ratio {ref_median / fast_median:6.0f}x  max |S_o diff| {max_diff:.1e}")
    print(f"  S_o per candidate: {np.array2string(fast_occlusion, precision=2)}")

    print("\nper term, 20k/100k, C = 17 (each on a fresh context: the first kernel user pays the kernel):")
    for name in params.score_terms:
        median, p95 = time_call(lambda name=name: get_term(name).compute(ScoringContext(
            target, background, candidates.rotations, candidates.positions, INTRINSICS, WIDTH, HEIGHT)),
            args.repeats)
        print(f"  {name:12s}: {median:7.2f} / {p95:7.2f}")

    print("\ncheck_feasibility, 100k background points:")
    for num_candidates in (16, 64):
        candidates = ring(num_candidates)
        median, p95 = time_call(partial(
            check_feasibility, candidates, background, PLANE_NORMAL, PLANE_OFFSET, params), args.repeats)
        print(f"  C = {len(candidates):3d}: {median:7.2f} / {p95:7.2f}")
    median, p95 = time_call(lambda: ring(16), args.repeats)
    print(f"\ngenerate_candidates (16): {median:.3f} / {p95:.3f}")

    warm_up_obstacle_map()
    grid = room_voxel_map()
    candidates = ring(16)
    target, _ = scene_with_counts(20000, 100000)
    print(f"\nline_of_sight_clear_fraction, {grid.voxel_count} voxels of 0.1 m, C = 17, 20k target points:")
    for max_targets in (500, 1500, 5000):
        median, p95 = time_call(partial(line_of_sight_clear_fraction, grid, np.eye(3), np.zeros(3),
                                        candidates.positions, target, max_targets), args.repeats)
        print(f"  {max_targets:5d} walked: {median:7.2f} / {p95:7.2f}")
    stride = int(np.ceil(len(target) / 1500))
    fast = line_of_sight_clear_fraction(grid, np.eye(3), np.zeros(3), candidates.positions, target, 1500)
    slow: List[np.ndarray] = []
    ref_median, _ = time_call(lambda: slow.append(reference_clear_fraction(
        grid, candidates.positions, target[::stride], 0.1)), args.reference_repeats)
    fast_median, _ = time_call(partial(line_of_sight_clear_fraction, grid, np.eye(3), np.zeros(3),
                                       candidates.positions, target, 1500), args.repeats)
    print(f"  reference (numpy samples every r/8) {ref_median:8.1f}  fast {fast_median:.2f}"
          f"  ratio {ref_median / fast_median:6.0f}x  max |diff| {np.max(np.abs(slow[-1] - fast)):.1e}")
    print(f"  clear share per candidate: {np.array2string(fast, precision=2)}")

    print("\nplan_views (ring, feasibility, scoring, choice, base goal), 20k/100k, C = 17:")
    target, background = scene_with_counts(20000, 100000)
    frame = PlanTarget(target_points=target.astype(np.float32), background_points=background.astype(np.float32),
                       centroid=centroid, k=INTRINSICS, width=WIDTH, height=HEIGHT)
    ground = PlanFloor(normal=PLANE_NORMAL, offset=PLANE_OFFSET)
    for label, obstacle_map, camera_pose in (("frame only", None, None),
                                             ("with the obstacle map", grid, CameraInMap(np.eye(3), np.zeros(3)))):
        median, p95 = time_call(partial(plan_views, PlanInputs(frame, ground, params, obstacle_map, camera_pose)),
                                args.repeats)
        print(f"  {label:22s}: {median:7.2f} / {p95:7.2f}")

    bench_robot_plan(params, centroid, grid, args.repeats)


def bench_robot_plan(params, centroid: np.ndarray, grid, repeats: int) -> None:
    """The robot's plan: 3 rings x 16 candidates (1.5-2.5 m), reachability on the floor grid, the mesh S_o over a
    10k-vertex body mesh, 100k background points (20k target points for S_v)."""
    target, background = scene_with_counts(20000, 100000)
    ground = PlanFloor(normal=PLANE_NORMAL, offset=PLANE_OFFSET)
    mesh_vertices, mesh_faces = cylinder_mesh(10000)
    robot = dataclasses.replace(params, num_rings=3, min_radius=1.5, reachability=True,
                                score_terms=["visibility", "area", "body_occlusion", "travel"])
    frame = PlanTarget(target_points=target.astype(np.float32), background_points=background.astype(np.float32),
                       centroid=centroid, k=INTRINSICS, width=WIDTH, height=HEIGHT)
    print(f"\nplan_views, 3 rings x 16 + current, reachability, mesh S_o ({len(mesh_vertices)} vertices), 100k "
          "background:")
    for label, obstacle_map, camera_pose in (("frame only", None, None),
                                             ("with the obstacle map", grid, CameraInMap(np.eye(3), np.zeros(3)))):
        call = partial(plan_views, PlanInputs(frame, ground, robot, obstacle_map, camera_pose,
                                              (mesh_vertices, mesh_faces)))
        median, p95 = time_call(call, repeats)
        # The process's CPU time too: on a shared machine the wall time also holds what others took from the core.
        cpu = []
        for _ in range(max(20, repeats // 4)):
            start = time.process_time()
            call()
            cpu.append((time.process_time() - start) * 1e3)
        print(f"  {label:22s}: {median:7.2f} / {p95:7.2f}   (CPU time p50 {np.median(cpu):.2f})")
    plan = plan_views(PlanInputs(frame, ground, robot, grid, CameraInMap(np.eye(3), np.zeros(3)),
                                 (mesh_vertices, mesh_faces)))
    print(f"  feasible {int(plan.feasibility.feasible.sum())} of {len(plan.candidates)}, unreachable "
          f"{int((plan.feasibility.reasons == 3).sum())}, chosen {plan.chosen_index}, path "
          f"{0 if plan.base_path is None else len(plan.base_path)} cells")
    reference = reference_robot_terms(plan, target, background, mesh_vertices, mesh_faces, grid, robot)
    scored = plan.feasibility.feasible  # infeasible candidates are not scored (score_infeasible off)
    for name, values in reference.items():
        difference = np.max(np.abs(plan.scores.term(name)[scored] - values[scored]))
        print(f"  {name}: max |plan - per-point reference| over the {int(scored.sum())} scored candidates "
              f"{difference:.1e}")
    # S_v over the whole body mesh (visibility_points: body_mesh) against the observed points: the plan with each,
    # and the framing kernel alone over the scored candidates (its bucketed mesh is the mesh S_o's, made once).
    mesh_input = (mesh_vertices, mesh_faces)
    for points in ("observed", "body_mesh"):
        variant = dataclasses.replace(robot, visibility_points=points)
        median, p95 = time_call(partial(plan_views, PlanInputs(frame, ground, variant, body_mesh=mesh_input)), repeats)
        print(f"  S_v over {points + ',':10s} frame only: {median:7.2f} / {p95:7.2f}")
    mesh = SurfacePoints(mesh_vertices, mesh_vertex_normals(mesh_vertices, mesh_faces))
    context = ScoringContext(target, background, plan.candidates.rotations[scored], plan.candidates.positions[scored],
                             INTRINSICS, WIDTH, HEIGHT, params=robot, given={"body_mesh": mesh})
    bucketed, _, *boxes = context.buckets("mesh")
    fx, skew, cx = INTRINSICS[0]
    fy, cy = INTRINSICS[1, 1], INTRINSICS[1, 2]
    median, p95 = time_call(partial(count_framed_bucketed, bucketed, *boxes, context.rotations, context.positions,
                                    fx, skew, cx, fy, cy, WIDTH, HEIGHT, robot.visibility_min_depth,
                                    robot.visibility_max_depth), repeats)
    print(f"  framing kernel alone ({len(context.positions)} candidates x {len(mesh_vertices)} vertices): "
          f"{median:7.3f} / {p95:7.3f}")
    every = dataclasses.replace(robot, score_infeasible=True)
    frame_only = PlanInputs(frame, ground, every, body_mesh=(mesh_vertices, mesh_faces))
    median, p95 = time_call(partial(plan_views, frame_only), repeats)
    print(f"  every candidate scored (score_infeasible), frame only: {median:7.2f} / {p95:7.2f}")


def reference_robot_terms(plan, target: np.ndarray, background: np.ndarray, mesh_vertices: np.ndarray,
                          mesh_faces: np.ndarray, grid, robot) -> dict:
    """S_v and the mesh S_o of the plan's candidates from the per-point kernel (count_visible_targets: every point
    projected, every background point tested; count_framed for S_v over the mesh) and the plain line-of-sight walk
    (segments_clear)."""
    from reference_planner_kernels import count_framed, count_visible_targets, segments_clear

    rotations, positions = plan.candidates.rotations, plan.candidates.positions
    fx, skew, cx = INTRINSICS[0]
    fy, cy = INTRINSICS[1, 1], INTRINSICS[1, 2]
    half_window = int(np.floor(robot.delta_px))
    target = np.ascontiguousarray(target.astype(np.float32), dtype=np.float64)
    background = np.ascontiguousarray(background.astype(np.float32), dtype=np.float64)
    in_view, _ = count_visible_targets(target, np.zeros((0, 3)), rotations, positions, fx, skew, cx, fy, cy, WIDTH,
                                       HEIGHT, half_window, np.zeros((0, 3)))
    normals = mesh_vertex_normals(mesh_vertices, mesh_faces)
    _, not_hidden = count_visible_targets(mesh_vertices, background, rotations, positions, fx, skew, cx, fy, cy,
                                          WIDTH, HEIGHT, half_window, normals)
    facing = np.count_nonzero(positions @ normals.T > np.einsum("vk,vk->v", normals, mesh_vertices), axis=1)
    stride = max(1, int(np.ceil(len(mesh_vertices) / robot.map_max_target_points)))
    clear = segments_clear(grid.occupied, grid.lower_index.astype(np.float64), grid.resolution, positions,
                           np.ascontiguousarray(mesh_vertices[::stride]), robot.map_target_margin).mean(axis=1)
    body = np.where(facing > 0, not_hidden / np.maximum(facing, 1), 0.0) * clear
    visibility = in_view / len(target)
    if robot.visibility_points == "body_mesh":  # S_v over the whole mesh: every vertex projected
        visibility = count_framed(mesh_vertices, rotations, positions, fx, skew, cx, fy, cy, WIDTH, HEIGHT,
                                  robot.visibility_min_depth, robot.visibility_max_depth) / len(mesh_vertices)
    return {"visibility": visibility, "body_occlusion": body}


def cylinder_mesh(count: int) -> Tuple[np.ndarray, np.ndarray]:
    """The scene's person cylinder as a mesh surface (an open tube: its normals point outward) of about ``count``
    vertices, 1 cm outside the ray-cast surface."""
    segments = 100
    rings = max(2, count // segments)
    angles = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    radius = PERSON_RADIUS + 0.01
    heights = PERSON_CENTRE[1] + np.linspace(-PERSON_HEIGHT / 2, PERSON_HEIGHT / 2, rings)
    y, a = np.meshgrid(heights, angles, indexing="ij")
    vertices = np.column_stack([PERSON_CENTRE[0] + radius * np.cos(a).ravel(), y.ravel(),
                                PERSON_CENTRE[2] + radius * np.sin(a).ravel()])
    faces = []
    for r in range(rings - 1):
        for k in range(segments):
            i, j = r * segments + k, r * segments + (k + 1) % segments
            faces.append([i, j, i + segments])
            faces.append([j, j + segments, i + segments])
    return vertices, np.array(faces, dtype=np.int64)


if __name__ == "__main__":
    main()
