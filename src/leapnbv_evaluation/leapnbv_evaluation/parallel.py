"""Parallel evaluation: the scenes split among worker processes, each with its own graph on its own ROS domain.

Worker ``k`` runs ``python -m leapnbv_evaluation.parallel SPEC`` on the k-th contiguous share of
the seeds with its own ``ROS_DOMAIN_ID``: its graph, its simulator and its collector talk to each
other only (the stamps of two runs are the same, so two runs on one domain would mix their frames).
The domains:

* ``--domain-base D`` or ``$LEAPNBV_EVAL_DOMAIN_BASE=D``: worker k uses D + k, as given;
* a one-process run uses ``D`` when given, else ``$ROS_DOMAIN_ID`` when it is set, else claims one free
  domain as below (:func:`own_domain`): the simulator publishes camera topics, which must never reach
  another graph on the machine (a robot's, or a second run's) on everyone's default domain 0;
* else the parent claims N free domains for the run: it holds an exclusive lock on
  ``$TMPDIR/leapnbv-ros-domains/<domain>.lock`` (the lock folder the test suite's conftest uses for
  its own domain), searching 1..101 upward from its own ``ROS_DOMAIN_ID`` + 1 and skipping its own
  domain and every locked one; the locks are released when the run ends. 1..101 keeps Fast DDS's
  ports clear of Linux's ephemeral port range.

Everything of worker ``k`` lies in ``<out>/workers/worker_<k>/``: ``spec.json`` (its seeds and
options), ``worker.log`` (its output, one line per finished scene), ``logs/`` (its graph's node
logs) and ``run.json`` (its typed results). Each scene is stamped by its place in the whole run
(the worker passes ``first_index``), so a worker's scene sees exactly the frames a one-process
run would show it; the parent merges the workers' runs in seed order into one
:class:`~leapnbv_evaluation.results.EvaluationRun`, and the tables are those of a one-process run
(latencies aside).
"""
from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import json
import os
import pathlib
import signal
import subprocess
import sys
import time
from typing import IO, Iterable, Iterator, List, Mapping, Optional, Sequence, Tuple

from leapnbv_evaluation.episode import EvaluationError
from leapnbv_evaluation.harness import ClosedLoopEvaluator
from leapnbv_evaluation.options import EvaluationOptions
from leapnbv_evaluation.results import EvaluationRun, ResultsError, SceneResult

DOMAIN_BASE_ENV = "LEAPNBV_EVAL_DOMAIN_BASE"
#: The largest ROS domain id Fast DDS accepts.
MAX_DOMAIN_ID = 232
#: Domains claimed for workers: 1..101 (clear of Linux's ephemeral ports; 0 is everyone's default).
CLAIMABLE_DOMAINS = range(1, 102)
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


def explicit_domain_base(explicit: Optional[int] = None, environ: Optional[Mapping[str, str]] = None) -> Optional[int]:
    """The workers' first ROS domain when one is given: ``explicit``, else $LEAPNBV_EVAL_DOMAIN_BASE, else None.

    Raises:
        EvaluationError: A variable that is not an integer.
    """
    environ = os.environ if environ is None else environ
    if explicit is not None:
        return int(explicit)
    value = environ.get(DOMAIN_BASE_ENV, "").strip()
    if not value:
        return None
    try:
        return int(value)
    except ValueError as error:
        raise EvaluationError(f"${DOMAIN_BASE_ENV} must be an integer, got {value!r}") from error


def lock_folder(environ: Optional[Mapping[str, str]] = None) -> pathlib.Path:
    """Where domain locks live (shared with the test suite's conftest)."""
    environ = os.environ if environ is None else environ
    return pathlib.Path(environ.get("TMPDIR", "/tmp")) / "leapnbv-ros-domains"


def claim_domains(count: int, environ: Optional[Mapping[str, str]] = None) -> Tuple[List[int], List[IO[str]]]:
    """``count`` free ROS domains, locked for as long as the returned handles stay open.

    Raises:
        EvaluationError: Not enough free domains.
    """
    environ = os.environ if environ is None else environ
    try:
        own = int(environ.get("ROS_DOMAIN_ID", "0").strip() or 0)
    except ValueError as error:
        raise EvaluationError(f"$ROS_DOMAIN_ID must be an integer, got {environ.get('ROS_DOMAIN_ID')!r}") from error
    folder = lock_folder(environ)
    folder.mkdir(parents=True, exist_ok=True)
    domains: List[int] = []
    handles: List[IO[str]] = []
    candidates = list(CLAIMABLE_DOMAINS)
    start = next((i for i, domain in enumerate(candidates) if domain > own), 0)
    for domain in candidates[start:] + candidates[:start]:
        if len(domains) == count:
            break
        if domain == own:
            continue
        handle = open(folder / f"{domain}.lock", "w")  # noqa: SIM115 - held open: the lock lasts the run
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        domains.append(domain)
        handles.append(handle)
    if len(domains) < count:
        release_domains(handles)
        raise EvaluationError(f"only {len(domains)} of {count} ROS domains are free in {folder}: "
                              f"set --domain-base or ${DOMAIN_BASE_ENV}")
    return domains, handles


def release_domains(handles: Sequence[IO[str]]) -> None:
    for handle in handles:
        handle.close()  # closing the file releases its lock


@contextlib.contextmanager
def own_domain(explicit: Optional[int] = None) -> Iterator[int]:
    """Run a one-process graph on a ROS domain of its own; yields the domain.

    ``explicit`` (or $LEAPNBV_EVAL_DOMAIN_BASE) when given, else $ROS_DOMAIN_ID when it is set (the caller chose),
    else a free domain claimed with a lock (claim_domains) and set in ``os.environ["ROS_DOMAIN_ID"]`` (what
    rclpy and the graph's node processes read) until the block ends.

    Raises:
        EvaluationError: A bad domain value, or no free domain.
    """
    first = explicit_domain_base(explicit)
    previous = os.environ.get("ROS_DOMAIN_ID")
    handles: List[IO[str]] = []
    if first is not None:
        if not 0 <= first <= MAX_DOMAIN_ID:
            raise EvaluationError(f"ROS domain {first} is outside 0..{MAX_DOMAIN_ID}")
        domain = first
    elif previous is not None and previous.strip():
        try:
            domain = int(previous)
        except ValueError as error:
            raise EvaluationError(f"$ROS_DOMAIN_ID must be an integer, got {previous!r}") from error
    else:
        (domain,), handles = claim_domains(1)
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    try:
        yield domain
    finally:
        release_domains(handles)
        if previous is None:
            os.environ.pop("ROS_DOMAIN_ID", None)
        else:
            os.environ["ROS_DOMAIN_ID"] = previous


def worker_dir(out_dir: str, index: int) -> str:
    return os.path.join(out_dir, "workers", f"worker_{index}")


def run_in_workers(seeds: Sequence[int], out_dir: str, options: EvaluationOptions, workers: int,
                   base: Optional[int] = None) -> EvaluationRun:
    """Evaluate the seeds in ``workers`` processes and merge their runs in seed order.

    Args:
        seeds: The seeds, in order.
        out_dir: The run's output folder (the workers' folders go under it).
        options: How the graphs run (each worker's log_dir is its own).
        workers: How many processes (at most one per seed).
        base: First ROS domain (worker k: base + k); None: $LEAPNBV_EVAL_DOMAIN_BASE, else free
            domains claimed with locks.

    Raises:
        EvaluationError: The domains do not fit, or a worker failed (its log's tail says why).
    """
    parts = shares(seeds, workers)
    first = explicit_domain_base(base)
    handles: List[IO[str]] = []
    if first is None:
        domains, handles = claim_domains(len(parts))
    else:
        domains = list(range(first, first + len(parts)))
        if first < 0 or domains[-1] > MAX_DOMAIN_ID:
            raise EvaluationError(f"ROS domains {first}..{domains[-1]} for {len(parts)} workers are outside "
                                  f"0..{MAX_DOMAIN_ID}")
    processes: List[Tuple[int, subprocess.Popen[bytes]]] = []
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
            env = dict(os.environ, ROS_DOMAIN_ID=str(domains[index]))
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
                    raise EvaluationError(f"worker {index} (ROS domain {domains[index]}) exited with code "
                                          f"{code}:\n{_tail(os.path.join(worker_dir(out_dir, index), 'worker.log'))}")
            time.sleep(0.5)
    finally:
        _stop(process for _, process in processes)
        release_domains(handles)
    try:
        return EvaluationRun.merge([EvaluationRun.read(os.path.join(worker_dir(out_dir, index), "run.json"))
                                    for index in range(len(parts))])
    except (OSError, ResultsError) as error:
        raise EvaluationError(f"the workers' results cannot be merged: {error}") from error


def _stop(processes: Iterable[subprocess.Popen[bytes]]) -> None:
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
