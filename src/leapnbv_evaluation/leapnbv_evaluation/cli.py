"""Closed-loop evaluation from the command line: benchmark scenes through the running node graph, one move each.

    python -m leapnbv_evaluation.cli --scenes 50 --out out/eval
    python -m leapnbv_evaluation.cli --scenes 1000 --workers 2 --out out/eval1000
    python -m leapnbv_evaluation.cli --scenes 10 --out out/eval_models --perception onnxruntime \\
        --detector-model yolov8s.onnx --hmr-model smplerx.onnx --body-model SMPLX_NEUTRAL.npz \\
        --scene-body-model SMPLX_NEUTRAL.npz

Continuous episodes (``--continuous``, :mod:`leapnbv_evaluation.continuous`): the robot drives while the
graph plans from every frame, on sim time; outputs continuous.md (the table and one row per episode) and
continuous.json (:class:`~leapnbv_evaluation.continuous_results.ContinuousRun`)::

    python -m leapnbv_evaluation.cli --continuous --room corridor --scenes 40 --out out/continuous_corridor

What runs: :mod:`leapnbv_evaluation.harness` (the graph, the in-process simulator, the closed
loop), :mod:`leapnbv_evaluation.episode` (the methods and how a view is scored); with
``--workers N`` the scenes are split among N processes with a graph each
(:mod:`leapnbv_evaluation.parallel`: ROS domains, log folders, merging).

Outputs in ``--out`` (:func:`leapnbv_evaluation.task_report.write_evaluation_outputs`): results.md /
results.json / plots, chosen_views.json (per scene: stamps, candidates' scores, each method's pick,
world pose and metrics), evaluation.md (raw-coverage table, the graph's own areas, failures, wall
time), run.json (the typed run), and logs/ (one log per node; workers/worker_<k>/ with --workers).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Any, List, Optional, Sequence

from leapnbv_evaluation.benchmark_set import (
    BASE_ROOMS,
    BENCHMARK_SEEDS,
    FAMILY_SEEDS,
    ROOMS,
    checked_seed_count,
    room_seeds,
)
from leapnbv_evaluation.continuous_results import ContinuousRun, continuous_table_markdown, per_episode_markdown
from leapnbv_evaluation.episode import EvaluationError
from leapnbv_evaluation.harness import ClosedLoopEvaluator
from leapnbv_evaluation.options import CLOCK_MODES, EvaluationOptions
from leapnbv_evaluation.parallel import DOMAIN_BASE_ENV, own_domain, run_in_workers
from leapnbv_evaluation.report_files import write_text_atomically
from leapnbv_evaluation.results import EvaluationRun
from leapnbv_evaluation.task_report import task_table_markdown, write_evaluation_outputs
from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_sim.poses import HEAD_MODES, ROBOT_MOTIONS
from leapnbv_stand_ins.files import ensure_stand_in_body_model

#: A scene's frames are 0.1 s apart and scenes 10 s: at most this many moves fit in a scene's stamps.
MAX_MOVES = 50


def seeds_for(count: int, offset: int = 0, room: str = "furnished") -> List[int]:
    """Benchmark seeds [offset, offset + count) of a room or family (the small stand-in checks seeds past the
    committed ones).

    Raises:
        EvaluationError: A count below 1 or a negative offset.
    """
    body = None
    committed = checked_seed_count() if room in BASE_ROOMS else len(FAMILY_SEEDS.get(room, []))
    if offset + count > committed:
        body = SMPLXModel.load(ensure_stand_in_body_model("small"))
    try:
        return room_seeds(room, count, offset, body)
    except ValueError as error:
        raise EvaluationError(f"--scenes {count} --seed-offset {offset}: {error}") from error


def run_evaluation(seeds: Sequence[int], out_dir: str, options: Optional[EvaluationOptions] = None,
                   workers: int = 1, domain_base: Optional[int] = None) -> EvaluationRun:
    """Evaluate the scenes (in this process, or in ``workers`` worker processes), write the outputs.

    Returns:
        The run.
    """
    options = options or EvaluationOptions()
    started = time.monotonic()
    if workers > 1:
        run = run_in_workers(seeds, out_dir, options, workers, domain_base)
    else:
        if options.log_dir is None:
            options.log_dir = os.path.join(out_dir, "logs")
        with own_domain(domain_base) as domain:
            print(f"[evaluation] ROS domain {domain}", flush=True)
            with ClosedLoopEvaluator(options) as evaluator:
                run = evaluator.evaluate(seeds)
    run.total_wall_s = time.monotonic() - started
    write_evaluation_outputs(out_dir, run)
    return run


def run_continuous(seeds: Sequence[int], out_dir: str, options: EvaluationOptions,
                   domain_base: Optional[int] = None) -> ContinuousRun:
    """Continuous episodes of the scenes in this process; writes continuous.md and continuous.json.

    Returns:
        The run.
    """
    started = time.monotonic()
    if options.log_dir is None:
        options.log_dir = os.path.join(out_dir, "logs")
    os.makedirs(out_dir, exist_ok=True)
    with own_domain(domain_base) as domain:
        print(f"[evaluation] ROS domain {domain}, continuous ({options.clock} clock)", flush=True)
        with ClosedLoopEvaluator(options) as evaluator:
            def progress(episode: Any) -> None:
                print(f"[evaluation] seed {episode.seed}: {episode.outcome} in {episode.time_s:.1f} s sim "
                      f"({episode.wall_s:.0f} s wall), coverage {episode.coverage_start:.3f} -> "
                      f"{episode.coverage_end:.3f}, {episode.goal_switches} switches", flush=True)

            run = evaluator.evaluate_continuous(seeds, on_episode=progress)
    run.total_wall_s = round(time.monotonic() - started, 3)
    run.write(os.path.join(out_dir, "continuous.json"))
    write_text_atomically(os.path.join(out_dir, "continuous.md"),
                          continuous_table_markdown(run) + "\n" + per_episode_markdown(run))
    return run


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=50,
                        help=f"how many benchmark scenes (any number; the first {len(BENCHMARK_SEEDS)} seeds are "
                             "the committed ones)")
    parser.add_argument("--seed-offset", type=int, default=0, help="skip this many benchmark seeds first")
    parser.add_argument("--out", default=os.path.join("out", "evaluation"), help="output folder")
    parser.add_argument("--workers", type=int, default=1,
                        help="worker processes, each with its own graph and ROS domain (default 1: this process)")
    parser.add_argument("--domain-base", type=int, default=None,
                        help=f"ROS domain of worker 0 (worker k: base + k) or of the one-process run; default "
                             f"${DOMAIN_BASE_ENV}, else (one process) $ROS_DOMAIN_ID when set, else free domains "
                             "claimed with locks (see leapnbv_evaluation.parallel)")
    parser.add_argument("--perception", choices=["ground_truth", "onnxruntime", "tensorrt"], default="ground_truth")
    parser.add_argument("--detector-backend", choices=["ground_truth", "onnxruntime", "tensorrt"], default=None,
                        help="the detector's backend when it differs from --perception: ground_truth gives a real "
                        "HMR model the simulator's person boxes (no trained detector needed)")
    parser.add_argument("--detector-model", default=None, help="YOLOv8 ONNX file (real perception)")
    parser.add_argument("--hmr-model", default=None, help="SMPLer-X student ONNX file (real perception)")
    parser.add_argument("--body-model", default=None,
                        help="SMPL-X .npz of the HMR node (ground truth default: the small stand-in)")
    parser.add_argument("--scene-body-model", default=None,
                        help="body model of the scenes (default: the small stand-in the seeds were chosen for)")
    parser.add_argument("--params", default=None, help="graph parameter YAML")
    parser.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE",
                        help="override one graph parameter (repeatable)")
    parser.add_argument("--frame-timeout", type=float, default=15.0, help="seconds to wait for a frame's plan")
    parser.add_argument("--room", choices=list(ROOMS), default="furnished",
                        help="benchmark rooms with furniture around the person (default), without, or a family "
                        "(leapnbv_evaluation.benchmark_set.FAMILY_CHANGES: its own seeds and robot)")
    parser.add_argument("--no-obstacle-map", action="store_true",
                        help="the planner gets no map of the room: it knows only what each frame shows")
    parser.add_argument("--robot-motion", choices=list(ROBOT_MOTIONS), default="base",
                        help="base (default): the robot's base drives to a pick and its camera stays at its mounting "
                        "height; free: the camera jumps to the 6-DoF pick")
    parser.add_argument("--robot-head", choices=list(HEAD_MODES), default="pan_tilt",
                        help="pan_tilt (default): the camera tilts toward the pick; fixed: it keeps its pitch")
    parser.add_argument("--max-moves", type=int, default=1,
                        help="leap_nbv's episode continues through the graph up to this many moves (default 1)")
    parser.add_argument("--min-gain", type=float, default=0.02,
                        help="a further move is made only when the graph's pick scores this much above staying")
    parser.add_argument("--continuous", action="store_true",
                        help="continuous episodes: the robot drives while the graph plans from every frame")
    parser.add_argument("--clock", choices=list(CLOCK_MODES), default="lockstep",
                        help="continuous: lockstep (sim time advances once the graph answered: reproducible) or "
                        "real_time (sim time follows the wall clock)")
    parser.add_argument("--camera-rate", type=float, default=10.0, help="continuous: frames per second of sim time")
    parser.add_argument("--time-limit", type=float, default=30.0, help="continuous: sim seconds per episode at most")
    parser.add_argument("--obstacle-memory", action="store_true",
                        help="continuous, with --no-obstacle-map: nbv_node plans with the map it builds on the way "
                        "from the frames (its obstacle_memory parameter; leapnbv_planner.obstacle_memory)")
    parser.add_argument("--commit-hold", type=float, default=1.0,
                        help="continuous: arrival counts at a goal committed at least this many sim seconds")
    args = parser.parse_args(argv)

    options = EvaluationOptions(perception=args.perception, detector_backend=args.detector_backend,
                                detector_model=args.detector_model,
                                hmr_model=args.hmr_model, body_model=args.body_model,
                                scene_body_model=args.scene_body_model, params_file=args.params,
                                set_parameters=list(args.set), frame_timeout_s=args.frame_timeout,
                                room=args.room, obstacle_map=not args.no_obstacle_map,
                                robot_motion=args.robot_motion, robot_head=args.robot_head,
                                max_moves=args.max_moves, min_gain=args.min_gain, continuous=args.continuous,
                                clock=args.clock, camera_rate_hz=args.camera_rate, time_limit_s=args.time_limit,
                                commit_hold_s=args.commit_hold, obstacle_memory=args.obstacle_memory)
    try:
        if args.workers < 1:
            raise EvaluationError(f"--workers must be >= 1, got {args.workers}")
        if not 1 <= args.max_moves <= MAX_MOVES:
            raise EvaluationError(f"--max-moves must be in [1, {MAX_MOVES}], got {args.max_moves}")
        if args.obstacle_memory and not (args.continuous and args.no_obstacle_map):
            raise EvaluationError("--obstacle-memory needs --continuous and --no-obstacle-map")
        if args.continuous and args.workers != 1:
            raise EvaluationError("--continuous runs in one process (--workers 1)")
        if args.continuous and not (0.5 <= args.camera_rate <= 60.0 and 0.0 < args.time_limit <= 600.0
                                    and args.commit_hold >= 0.0):
            raise EvaluationError("--camera-rate must be in [0.5, 60], --time-limit in (0, 600], --commit-hold >= 0")
        seeds = seeds_for(args.scenes, args.seed_offset, args.room)
        if args.continuous:
            continuous = run_continuous(seeds, args.out, options, domain_base=args.domain_base)
            print(continuous_table_markdown(continuous), end="")
            print(f"[evaluation] {len(seeds)} continuous episodes in {continuous.total_wall_s:.1f} s; outputs in "
                  f"{args.out}")
            return 0
        run = run_evaluation(seeds, args.out, options, workers=args.workers, domain_base=args.domain_base)
    except EvaluationError as exc:
        print(f"[evaluation] {exc}", file=sys.stderr)
        return 1
    print(task_table_markdown(run), end="")
    failures = sum(1 for scene in run.scenes if scene.graph_failure)
    print(f"[evaluation] {len(seeds)} scenes ({failures} graph failures) in {run.total_wall_s:.1f} s "
          f"with {run.workers} worker(s); outputs in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
