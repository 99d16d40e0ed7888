"""Whether two continuous evaluations hold the same episodes: two runs of the same seeds on sim time should.

A and B are each a ``continuous.json`` or a folder of ``<run>/continuous.json`` (as continuous_families.sh
writes; runs are then matched by folder name, and a run in one folder only is a difference). Prints one line
per run compared (``corridor: same, 40 episodes`` or ``corridor: 3 differences in 2 of 40 episodes``), then
its differences (``seed 10: target_track[3][5]: 1.2 != 1.3``, A's value first), compared by
:func:`leapnbv_evaluation.continuous_results.compare_runs`: floats within its tolerance, and the fields that
depend on the machine's speed (wall time, frames ticked) left out.

Usage: ``scripts/env.sh python scripts/experiments/continuous_compare.py A B``

Exit codes: 0 every run the same; 1 something differs (a setting, an episode, a seed or a run in one only);
2 a usage error (not two arguments, a file against a folder, a folder with no run), or a missing,
unreadable or wrong-format JSON file (one line on stderr naming it).
"""
from __future__ import annotations

import json
import os
import sys
from typing import Dict, List, Tuple

from leapnbv_evaluation.continuous_results import ContinuousRun, run_differences

RUN_FILE = "continuous.json"


class InputError(Exception):
    """An argument or a file that cannot be compared (exit code 2); the message names it."""


def load_run(path: str) -> ContinuousRun:
    """The run in ``path``; InputError naming the file when it is missing, unreadable or not a continuous run."""
    try:
        with open(path, encoding="utf-8") as handle:
            data = json.load(handle)
    except OSError as error:
        raise InputError(f"{path}: cannot read it ({error.strerror or error})") from error
    except ValueError as error:  # JSONDecodeError, UnicodeDecodeError
        raise InputError(f"{path}: not JSON ({error})") from error
    if not isinstance(data, dict):
        raise InputError(f"{path}: not a continuous run (a JSON {type(data).__name__}, not an object)")
    try:
        return ContinuousRun.from_json(data)
    except (KeyError, TypeError, ValueError, AttributeError) as error:
        raise InputError(f"{path}: not a continuous run ({type(error).__name__}: {error})") from error


def runs_in(folder: str) -> Dict[str, str]:
    """Run name -> its continuous.json, for each <run>/continuous.json in ``folder``."""
    found = {name: os.path.join(folder, name, RUN_FILE) for name in sorted(os.listdir(folder))
             if os.path.isfile(os.path.join(folder, name, RUN_FILE))}
    if not found:
        raise InputError(f"{folder}: no <run>/{RUN_FILE} in this folder")
    return found


def _plural(n: int, word: str) -> str:
    return f"{n} {word}{'' if n == 1 else 's'}"


def summary(name: str, run_a: ContinuousRun, run_b: ContinuousRun) -> Tuple[str, List[str]]:
    """The run's line (``corridor: 3 differences in 2 of 40 episodes``) and its difference lines."""
    found = run_differences(run_a, run_b)
    if not found.count:
        return f"{name}: same, {found.seeds} episodes", []
    parts = []
    in_episodes = found.count - len(found.settings)
    if in_episodes:
        parts.append(f"{_plural(in_episodes, 'difference')} in {len(found.episodes)} of {found.seeds} episodes")
    if found.settings:
        parts.append(f"{_plural(len(found.settings), 'setting')} different")
    return f"{name}: {', '.join(parts)}", found.lines()


def main(argv: List[str]) -> int:
    """Compare the runs of argv[0] and argv[1], print the result; the exit code (module docstring)."""
    if len(argv) != 2 or any(arg.startswith("-") for arg in argv):
        print("usage: continuous_compare.py A B (each a continuous.json or a folder of <run>/continuous.json)",
              file=sys.stderr)
        return 2
    path_a, path_b = argv
    only: Dict[str, str] = {}  # run name -> the one side it is in
    try:
        if os.path.isdir(path_a) != os.path.isdir(path_b):
            raise InputError(f"{path_a} and {path_b}: compare a file with a file, or a folder with a folder")
        if os.path.isdir(path_a):
            runs_a, runs_b = runs_in(path_a), runs_in(path_b)
            pairs = {name: (runs_a[name], runs_b[name]) for name in set(runs_a) & set(runs_b)}
            only.update({name: "A" for name in set(runs_a) - set(runs_b)})
            only.update({name: "B" for name in set(runs_b) - set(runs_a)})
        else:
            # Two files: one run, named by A's folder (out/continuous/corridor/continuous.json: corridor).
            name = os.path.basename(os.path.dirname(os.path.abspath(path_a))) or path_a
            pairs = {name: (path_a, path_b)}
        loaded = {name: (load_run(a), load_run(b)) for name, (a, b) in sorted(pairs.items())}
    except InputError as error:
        print(f"continuous_compare.py: {error}", file=sys.stderr)
        return 2
    differs = bool(only)
    for name in sorted(set(loaded) | set(only)):
        if name in only:
            print(f"{name}: only in {only[name]}")
            continue
        line, lines = summary(name, *loaded[name])
        print(line)
        for difference in lines:
            print(f"  {difference}")
        differs = differs or bool(lines)
    return 1 if differs else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
