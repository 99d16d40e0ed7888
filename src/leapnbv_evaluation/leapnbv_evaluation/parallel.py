"""Parallel evaluation: the scenes split among worker processes, each with its own graph on its own ROS domain.

Worker ``k`` runs ``python -m leapnbv_evaluation.parallel SPEC`` on the k-th contiguous share of
the seeds, with ``ROS_DOMAIN_ID = base + k``: its graph, its simulator and its collector talk to
each other only. The base is ``--domain-base``, else the environment variable
``LEAPNBV_EVAL_DOMAIN_BASE``, else the parent's own ``ROS_DOMAIN_ID`` (0 when unset): the parent
joins no DDS graph while its workers run, so worker 0 may take its domain, and a run started with
its own ``ROS_DOMAIN_ID`` d uses d .. d + N - 1. Domains must lie in 0..232 (Fast DDS derives its
ports from them; 0..101 is the range that stays clear of Linux's ephemeral ports).

Everything of worker ``k`` lies in ``<out>/workers/worker_<k>/``: ``spec.json`` (its seeds and
options), ``worker.log`` (its output, one line per finished scene), ``logs/`` (its graph's node
logs) and ``run.json`` (its typed results). Each scene is stamped by its place in the whole run
(the worker passes ``first_index``), so a worker's scene sees exactly the frames a one-process
run would show it; the parent merges the workers' runs in seed order into one
:class:`~leapnbv_evaluation.results.EvaluationRun`, and the tables are those of a one-process run
(latencies aside).
"""
from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from typing import Dict, List, Optional, Sequence, Tuple

from leapnbv_evaluation.episode import EvaluationError
from leapnbv_evaluation.harness import ClosedLoopEvaluator, EvaluationOptions
from leapnbv_evaluation.results import EvaluationRun, ResultsError, SceneResult

DOMAIN_BASE_ENV = "LEAPNBV_EVAL_DOMAIN_BASE"
#: The largest ROS domain id Fast DDS accepts.
MAX_DOMAIN_ID = 232
#: Seconds a stopping worker gets to stop its graph before it is killed.
STOP_GRACE_S = 20.0


def shares(seeds: Sequence[int], workers: int) -> List[Tuple[int, List[int]]]:
    """The seeds cut into at most ``workers`` contiguous shares of near-equal size: (first index, seeds)."""
    count = len(seeds)
    workers = max(1, min(int(workers), count))
    out = []
    start = 0
    for k in range(workers):
        size = count // workers + (1 if k < count % workers else 0)
        out.append((start, [int(seed) for seed in seeds[start:start + size]]))
        start += size
    return out


def domain_base(explicit: Optional[int] = None, environ: Optional[Dict[str, str]] = None) -> int:
    """The workers' first ROS domain: ``explicit``, else $LEAPNBV_EVAL_DOMAIN_BASE, else $ROS_DOMAIN_ID, else 0.

    Raises:
        EvaluationError: A value that is not an integer.
    """
    environ = os.environ if environ is None else environ
    if explicit is not None:
        return int(explicit)
    for name in (DOMAIN_BASE_ENV, "ROS_DOMAIN_ID"):
        value = environ.get(name, "").strip()
        if value:
            try:
                return int(value)
            except ValueError as error:
                raise EvaluationError(f"${name} must be an integer, got {value!r}") from error
    return 0


def worker_dir(out_dir: str, index: int) -> str:
    return os.path.join(out_dir, "workers", f"worker_{index}")


def run_in_workers(seeds: Sequence[int], out_dir: str, options: EvaluationOptions, workers: int,
                   base: Optional[int] = None) -> EvaluationRun:
    """Evaluate the seeds in ``workers`` processes and merge their runs in seed order.

    Raises:
        EvaluationError: The domains do not fit, or a worker failed (its log's tail says why).
    """
    parts = shares(seeds, workers)
    first_domain = domain_base(base)
    if first_domain < 0 or first_domain + len(parts) - 1 > MAX_DOMAIN_ID:
        raise EvaluationError(f"ROS domains {first_domain}..{first_domain + len(parts) - 1} for {len(parts)} "
                              f"workers are outside 0..{MAX_DOMAIN_ID}: set --domain-base or ${DOMAIN_BASE_ENV}")
    processes: List[Tuple[int, subprocess.Popen]] = []
    try:
        for index, (first_index, share) in enumerate(parts):
            folder = worker_dir(out_dir, index)
            os.makedirs(folder, exist_ok=True)
            worker_options = dataclasses.replace(options, log_dir=os.path.join(folder, "logs"))
            spec = {"seeds": share, "first_index": first_index, "worker": index,
                    "options": dataclasses.asdict(worker_options)}
            spec_path = os.path.join(folder, "spec.json")
            with open(spec_path, "w", encoding="utf-8") as stream:
                json.dump(spec, stream, indent=1)
            run_path = os.path.join(folder, "run.json")
            if os.path.exists(run_path):
                os.remove(run_path)  # never merge a previous run's results
            env = dict(os.environ, ROS_DOMAIN_ID=str(first_domain + index))
            with open(os.path.join(folder, "worker.log"), "w", encoding="utf-8") as log:
                processes.append((index, subprocess.Popen(
                    [sys.executable, "-m", "leapnbv_evaluation.parallel", spec_path], env=env, stdout=log,
                    stderr=subprocess.STDOUT, start_new_session=True)))
        running = dict(processes)
        while running:
            for index, process in list(running.items()):
                code = process.poll()
                if code is None:
                    continue
                del running[index]
                if code != 0:
                    raise EvaluationError(f"worker {index} (ROS domain {first_domain + index}) exited with code "
                                          f"{code}:\n{_tail(os.path.join(worker_dir(out_dir, index), 'worker.log'))}")
            time.sleep(0.5)
    finally:
        _stop(process for _, process in processes)
    try:
        return EvaluationRun.merge([EvaluationRun.read(os.path.join(worker_dir(out_dir, index), "run.json"))
                                    for index in range(len(parts))])
    except (OSError, ResultsError) as error:
        raise EvaluationError(f"the workers' results cannot be merged: {error}") from error


def _stop(processes) -> None:
    """SIGINT to every running worker (it stops its graph), then SIGKILL after the grace time."""
    waiting = [process for process in processes if process.poll() is None]
    for process in waiting:
        process.send_signal(signal.SIGINT)
    deadline = time.monotonic() + STOP_GRACE_S
    for process in waiting:
        try:
            process.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def _tail(path: str, lines: int = 30) -> str:
    try:
        with open(path, encoding="utf-8", errors="replace") as stream:
            return "".join(stream.readlines()[-lines:])
    except OSError:
        return "(no log)"


def worker_main(argv: Optional[List[str]] = None) -> int:
    """One worker: evaluate the spec's seeds at their places in the run, write run.json beside the spec."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m leapnbv_evaluation.parallel SPEC.json", file=sys.stderr)
        return 2
    with open(args[0], encoding="utf-8") as stream:
        spec = json.load(stream)
    options = EvaluationOptions(**spec["options"])
    seeds = [int(seed) for seed in spec["seeds"]]
    name = f"[worker {spec['worker']}, ROS domain {os.environ.get('ROS_DOMAIN_ID', '0')}]"
    print(f"{name} {len(seeds)} scenes from place {spec['first_index']}", flush=True)

    def progress(scene: SceneResult) -> None:
        print(f"{name} seed {scene.seed} done ({scene.scene_index - spec['first_index'] + 1}/{len(seeds)})"
              + (f": graph failure: {scene.graph_failure}" if scene.graph_failure else ""), flush=True)

    try:
        with ClosedLoopEvaluator(options) as evaluator:
            run = evaluator.evaluate(seeds, first_index=int(spec["first_index"]), on_scene=progress)
    except EvaluationError as error:
        print(f"{name} {error}", file=sys.stderr, flush=True)
        return 1
    run.write(os.path.join(os.path.dirname(os.path.abspath(args[0])), "run.json"))
    print(f"{name} done in {run.scenes_wall_s:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(worker_main())
