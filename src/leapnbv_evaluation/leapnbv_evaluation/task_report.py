"""The evaluation outputs of a closed-loop run: task and latency tables, per-scene table, plots, the chosen
views, the run summary.

It only reads: it takes the typed :class:`~leapnbv_evaluation.results.EvaluationRun` and never recomputes what
the run decided (success comes with each method's result); files are written atomically (:mod:`report_files`).
"""
from __future__ import annotations

import json
import math
import os
from typing import Any, Dict, List, Mapping, Sequence, Tuple, Union

import numpy as np

from leapnbv_common.array_types import FloatArray
from leapnbv_evaluation.metrics import SUCCESS_MIN_COVERAGE, SUCCESS_MIN_GAIN, latency_summary
from leapnbv_evaluation.report_files import (
    ReportError,
    new_figure,
    save_figure_atomically,
    to_plain,
    write_json_atomically,
    write_text_atomically,
)
from leapnbv_evaluation.results import EvaluationRun, MethodResult, SceneResult

# ---------------------------------------------------------------------------------------------
# 5. Evaluation: task table, latency table, plots, chosen views, run summary
# ---------------------------------------------------------------------------------------------

#: The coverage a table reads: the headline surface coverage, or the raw share of all vertices.
COVERAGES = ("surface", "raw")


def _mean(values: Sequence[float]) -> float:
    return float(np.mean(values)) if len(values) else float("nan")


def _coverage(row: MethodResult, coverage: str) -> Tuple[float, float, bool]:
    """(before, after, success) of a method's move on the surface or the raw coverage."""
    if coverage == "raw":
        return row.before.raw_coverage, row.after.raw_coverage, row.raw_success
    return row.before.surface_coverage, row.after.surface_coverage, row.success


def aggregate_task_results(run: EvaluationRun, coverage: str = "surface") -> Dict[str, Any]:
    """Per-method aggregates of the task table (success as scored, never recomputed).

    Args:
        run: The run.
        coverage: "surface" (the headline) or "raw" (share of all vertices, with its success flag).

    Returns:
        {"methods", "per_method": {method: {"scenes", "coverage_before_pct", "coverage_after_pct",
        "area_before_kpx", "area_after_kpx", "pa_mpvpe_before_mm", "pa_mpvpe_mm", "pa_mpvpe_scenes", "successes",
        "success_rate_pct"}}, "latency_ms": {stage: latency_summary}}. Means over the scenes that
        ran the method; NaN where none did (PA-MPVPE: over the scenes that have one).

    Raises:
        ReportError: An unknown coverage.
    """
    if coverage not in COVERAGES:
        raise ReportError(f"coverage must be one of {COVERAGES}, got {coverage!r}")
    per_method: Dict[str, Dict[str, Any]] = {}
    for method in run.methods:
        rows = [scene.per_method[method] for scene in run.scenes if method in scene.per_method]
        values = [_coverage(row, coverage) for row in rows]
        errors = [float(row.pa_mpvpe_mm) for row in rows if row.pa_mpvpe_mm is not None]
        # The start view's mesh error over the same scenes (real models: the graph's mesh before the move).
        errors_before = [float(scene.pa_mpvpe_before_mm) for scene in run.scenes
                         if method in scene.per_method and scene.per_method[method].pa_mpvpe_mm is not None
                         and scene.pa_mpvpe_before_mm is not None]
        per_method[method] = {
            "scenes": len(rows),
            "coverage_before_pct": 100.0 * _mean([float(before) for before, _, _ in values]),
            "coverage_after_pct": 100.0 * _mean([float(after) for _, after, _ in values]),
            "area_before_kpx": _mean([float(row.before.area_px) for row in rows]) / 1000.0,
            "area_after_kpx": _mean([float(row.after.area_px) for row in rows]) / 1000.0,
            "pa_mpvpe_before_mm": _mean(errors_before),
            "pa_mpvpe_mm": _mean(errors),
            "pa_mpvpe_scenes": len(errors),
            "successes": int(sum(success for _, _, success in values)),
            "success_rate_pct": 100.0 * _mean([float(success) for _, _, success in values]),
        }
    latency = {stage: latency_summary(samples) for stage, samples in run.latency_ms().items()}
    aggregates = {"methods": list(run.methods), "per_method": per_method, "latency_ms": latency}
    if run.energy_j():  # the board's power rails were there (a Jetson)
        aggregates["energy_j_per_frame"] = latency_summary(run.energy_j())
    return aggregates


def _number(value: float, digits: int) -> str:
    return "n/a" if not math.isfinite(value) else f"{value:.{digits}f}"


def _pair(before: float, after: float) -> str:
    """"before -> after", or "n/a" when neither is known (ground-truth perception has no mesh error)."""
    if not math.isfinite(before) and not math.isfinite(after):
        return "n/a"
    return f"{_number(before, 1)} -> {_number(after, 1)}"


def _headline_table(aggregates: Mapping[str, Any]) -> str:
    lines = [
        "| Method | Scenes | Coverage before -> after (%) | Area before -> after (k px) | PA-MPVPE before -> after "
        "(mm) | Success (%) |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for method in aggregates["methods"]:
        row = aggregates["per_method"][method]
        lines.append(
            f"| {method} | {row['scenes']} | {_number(row['coverage_before_pct'], 1)} -> "
            f"{_number(row['coverage_after_pct'], 1)} | {_number(row['area_before_kpx'], 1)} -> "
            f"{_number(row['area_after_kpx'], 1)} | {_pair(row['pa_mpvpe_before_mm'], row['pa_mpvpe_mm'])} | "
            f"{_number(row['success_rate_pct'], 1)} |"
        )
    return "\n".join(lines) + "\n"


def task_table_markdown(run: EvaluationRun, coverage: str = "surface") -> str:
    """The task table (one row per method) as markdown, for the README.

    Args:
        run: The run.
        coverage: "surface" (the headline) or "raw".

    Returns:
        Markdown table text ending in a newline.
    """
    return _headline_table(aggregate_task_results(run, coverage))


def _latency_table(latency: Mapping[str, Mapping[str, float]]) -> str:
    lines = ["| Stage | p50 (ms) | p95 (ms) | p99 (ms) | mean (ms) | n |", "|---|---:|---:|---:|---:|---:|"]
    for stage, stats in latency.items():
        lines.append(
            f"| {stage} | {_number(stats['p50'], 1)} | {_number(stats['p95'], 1)} | {_number(stats['p99'], 1)} | "
            f"{_number(stats['mean'], 1)} | {int(stats['n'])} |"
        )
    return "\n".join(lines) + "\n"


def _per_scene_table(run: EvaluationRun) -> str:
    methods = run.methods
    header = "| Seed | Start occlusion (%) | " + " | ".join(f"{method}: coverage (%)" for method in methods) + " |"
    lines = [header, "|---:|---:|" + "---:|" * len(methods)]
    for scene in run.scenes:
        cells = [str(scene.seed), _number(100.0 * float(scene.start_occlusion), 0)]
        for method in methods:
            row = scene.per_method.get(method)
            if row is None:
                cells.append("-")
                continue
            mark = " ok" if row.success else ""
            before, after = 100.0 * row.before.surface_coverage, 100.0 * row.after.surface_coverage
            cells.append(f"{before:.1f} -> {after:.1f}{mark}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_task_table(out_dir: str, run: EvaluationRun) -> str:
    """Write results.md, results.json and the coverage / success / latency plots (atomically).

    Args:
        out_dir: Output folder (created if missing).
        run: The run; its default method is the method of the per-scene coverage plot.

    Returns:
        Path of results.md.

    Raises:
        ReportError: The default method is not one of the run's methods.
    """
    os.makedirs(out_dir, exist_ok=True)
    aggregates = aggregate_task_results(run)
    methods = list(run.methods)
    default_method = run.default_method
    if methods and default_method not in methods:
        raise ReportError(f"the default method {default_method!r} is not one of {methods}")

    plot_files = {
        "coverage_per_scene": "coverage_per_scene.png",
        "success_rate": "success_rate.png",
        "latency": "latency.png",
    }
    if methods:
        _plot_coverage_per_scene(os.path.join(out_dir, plot_files["coverage_per_scene"]), run, default_method)
        _plot_success_rate(os.path.join(out_dir, plot_files["success_rate"]), aggregates)
    _plot_latency(os.path.join(out_dir, plot_files["latency"]), run.latency_ms(), aggregates["latency_ms"])

    lines = [
        "# LEAP-NBV task results",
        "",
        f"Success: coverage rises by >= {SUCCESS_MIN_GAIN * 100:.0f} points or reaches >= "
        f"{SUCCESS_MIN_COVERAGE * 100:.0f} % after one move.",
        "",
        "## Task table",
        "",
        _headline_table(aggregates),
    ]
    lines += ["## Latency", "", _latency_table(aggregates["latency_ms"])]
    energy = aggregates.get("energy_j_per_frame")
    if energy:
        lines += [f"Energy per frame (VDD_IN, from a frame's publication to its view candidates): median "
                  f"{_number(energy['p50'], 3)} J, mean {_number(energy['mean'], 3)} J, "
                  f"p95 {_number(energy['p95'], 3)} J over {energy['n']} frames.", ""]
    lines += ["## Per scene", "", _per_scene_table(run)]
    lines += ["## Plots", ""]
    if methods:
        lines += [
            f"![coverage per scene ({default_method})]({plot_files['coverage_per_scene']})",
            f"![success rate]({plot_files['success_rate']})",
        ]
    lines += [f"![latency]({plot_files['latency']})", ""]

    payload = dict(aggregates)
    payload["default_method"] = default_method
    payload["plots"] = plot_files
    payload["scenes"] = [
        {
            "seed": scene.seed,
            "start_occlusion": scene.start_occlusion,
            "per_method": {
                method: {
                    "coverage_before": row.before.surface_coverage,
                    "coverage_after": row.after.surface_coverage,
                    "area_before": row.before.area_px,
                    "area_after": row.after.area_px,
                    "pa_mpvpe_mm": row.pa_mpvpe_mm,
                    "chosen_index": row.chosen_index,
                    "success": row.success,
                }
                for method, row in scene.per_method.items()
            },
        }
        for scene in run.scenes
    ]
    write_json_atomically(os.path.join(out_dir, "results.json"), payload)
    return write_text_atomically(os.path.join(out_dir, "results.md"), "\n".join(lines))


def _rounded(values: Union[Sequence[float], FloatArray], digits: int = 6) -> List[float]:
    return [round(float(v), digits) for v in values]


def chosen_views_record(scene: SceneResult) -> Dict[str, Any]:
    """chosen_views.json's entry of a scene: stamps, the candidates' scores (6 decimals), each method's pick."""
    record: Dict[str, Any] = {
        "seed": scene.seed,
        "stamp_ns": scene.stamp_ns,
        "start_occlusion": scene.start_occlusion,
        "start_pose": scene.start_pose.to_json(),
        "graph_failure": scene.graph_failure,
        "graph_area_before_px": scene.graph_area_before_px,
        "before": scene.before.to_json(),
        "pa_mpvpe_before_mm": scene.pa_mpvpe_before_mm,
        "graph_vs_truth": scene.graph_vs_truth.to_json(),
    }
    candidates = scene.candidates
    if candidates is not None:
        record["candidates"] = {
            "count": len(candidates),
            "chosen_index": int(candidates.chosen_index),
            "feasible": [bool(v) for v in candidates.feasible],
            "score": _rounded(candidates.score),
        }
        for name in candidates.term_names:
            record["candidates"][f"s_{name}"] = _rounded(candidates.term(name))
        record["candidates"]["positions_obs_m"] = [_rounded(p) for p in candidates.positions]
        if scene.candidate_views is not None:
            record["candidates"]["surface_coverage"] = _rounded([v.surface_coverage for v in scene.candidate_views])
            record["candidates"]["raw_coverage"] = _rounded([v.raw_coverage for v in scene.candidate_views])
    per_method: Dict[str, Dict[str, Any]] = {}
    for method, row in scene.per_method.items():
        entry: Dict[str, Any] = {"chosen_index": row.chosen_index, "pose": row.pose.to_json(),
                                 "after": row.after.to_json()}
        loop = row.closed_loop
        if loop is not None:
            entry.update(goal_received=loop.goal_received, goal_position_error_m=loop.goal_position_error_m,
                         graph_area_after_px=loop.graph_area_after_px, after_stamp_ns=loop.after_stamp_ns,
                         after_graph_failure=loop.after_graph_failure,
                         after_graph_chosen_index=loop.after_graph_chosen_index,
                         closed_loop_matches_render=loop.closed_loop_matches_render)
        entry["success"] = row.success
        per_method[method] = entry
    record["per_method"] = per_method
    return record


def evaluation_summary_markdown(run: EvaluationRun) -> str:
    """evaluation.md: what ran, the raw-coverage table, the graph's own areas, failures, wall time."""
    failures = [(scene.seed, scene.graph_failure) for scene in run.scenes if scene.graph_failure]
    graph_before = [scene.graph_area_before_px for scene in run.scenes if scene.graph_area_before_px is not None]
    areas_after = [scene.per_method[run.default_method].graph_area_after for scene in run.scenes
                   if run.default_method in scene.per_method]
    graph_after = [area for area in areas_after if area is not None]
    ready = _number(run.ready_s, 1) if run.ready_s is not None else "n/a"
    workers = f"; {run.workers} worker processes (one graph each)" if run.workers > 1 else ""
    lines = [
        "# LEAP-NBV closed-loop evaluation",
        "",
        f"Scenes: {len(run.scenes)} (seeds {', '.join(str(seed) for seed in run.seeds)}); rooms: "
        f"{run.room}; obstacle map: {'used' if run.obstacle_map else 'not used'}; perception: "
        f"{run.perception}; wall time {run.total_wall_s:.1f} s (graph ready in {ready} s, "
        f"scenes {run.scenes_wall_s:.1f} s){workers}.",
        "",
        "Headline coverage (results.md) is the surface coverage: the share of the body surface the "
        "viewpoint could show (self-visible vertices, image bounds ignored) that the view does show. "
        "The raw body coverage below divides by all vertices (its ceiling is ~50-55 %: the back of "
        "a body is always hidden); success there uses the same rule, so read it with that in mind.",
        "",
        "## Raw body coverage (share of all vertices)",
        "",
        task_table_markdown(run, coverage="raw"),
        "## Reconstructed area measured by the graph (leap_nbv, mask pixels with depth)",
        "",
        f"before {np.mean(graph_before) / 1000.0:.1f} k px -> after {np.mean(graph_after) / 1000.0:.1f} k px "
        f"over {len(graph_after)} scenes" if graph_after and graph_before else "n/a",
        "",
        "## Graph failures",
        "",
    ]
    lines += [f"- seed {seed}: {reason}" for seed, reason in failures] or ["none"]
    lines.append("")
    return "\n".join(lines)


def write_evaluation_outputs(out_dir: str, run: EvaluationRun) -> str:
    """Write every output of a run: results.md/.json and plots, chosen_views.json, evaluation.md, run.json.

    run.json is the typed run itself (``EvaluationRun.read`` reads it back).

    Returns:
        Path of results.md.
    """
    os.makedirs(out_dir, exist_ok=True)
    path = write_task_table(out_dir, run)
    records = [chosen_views_record(scene) for scene in run.scenes]
    write_text_atomically(os.path.join(out_dir, "chosen_views.json"),
                           json.dumps(to_plain(records), indent=1, allow_nan=False) + "\n")
    write_text_atomically(os.path.join(out_dir, "evaluation.md"), evaluation_summary_markdown(run))
    run.write(os.path.join(out_dir, "run.json"))
    return path


def _plot_coverage_per_scene(path: str, run: EvaluationRun, method: str) -> str:
    """Dumbbell plot: coverage before (grey) -> after (green success / red not) per scene, sorted by before."""
    rows = [(scene.seed, scene.per_method[method]) for scene in run.scenes if method in scene.per_method]
    rows.sort(key=lambda item: item[1].before.surface_coverage)
    before = np.array([100.0 * row.before.surface_coverage for _, row in rows])
    after = np.array([100.0 * row.after.surface_coverage for _, row in rows])
    success = np.array([row.success for _, row in rows], dtype=bool)
    positions = np.arange(len(rows))
    # Wider with more scenes, up to 16 in (about 1800 px): beyond, the scenes share the width.
    figure = new_figure((min(16.0, max(6.0, 0.25 * len(rows) + 2.0)), 4.5))
    axes = figure.add_subplot(1, 1, 1)
    if len(rows):
        axes.vlines(positions, np.minimum(before, after), np.maximum(before, after), colors="0.7", linewidths=2.0)
        axes.scatter(positions, before, c="0.4", s=25, label="before", zorder=3)
        axes.scatter(positions[success], after[success], c="tab:green", s=30, label="after (success)", zorder=4)
        axes.scatter(positions[~success], after[~success], c="tab:red", s=30, label="after (no success)", zorder=4)
    axes.axhline(100.0 * SUCCESS_MIN_COVERAGE, color="tab:green", linestyle="--", linewidth=1.0, alpha=0.6)
    if len(rows) <= 40:
        axes.set_xticks(positions)
        axes.set_xticklabels([str(seed) for seed, _ in rows], rotation=90, fontsize=7)
    axes.set_xlabel("scene (seed), sorted by coverage before")
    axes.set_ylabel("body coverage [%]")
    axes.set_ylim(0.0, 102.0)
    axes.set_title(f"Coverage before -> after one move ({method})")
    axes.grid(True, axis="y", alpha=0.3)
    axes.legend(loc="lower right", fontsize=8)
    figure.tight_layout()
    return save_figure_atomically(figure, path)


def _plot_success_rate(path: str, aggregates: Mapping[str, Any]) -> str:
    """One bar per method: success rate (%), labelled with successes / scenes."""
    methods = list(aggregates["methods"])
    rates = [aggregates["per_method"][method]["success_rate_pct"] for method in methods]
    figure = new_figure((max(4.0, 1.2 * len(methods) + 2.0), 4.0))
    axes = figure.add_subplot(1, 1, 1)
    heights = [rate if math.isfinite(rate) else 0.0 for rate in rates]
    bars = axes.bar(np.arange(len(methods)), heights, color="tab:blue")
    for bar, method in zip(bars, methods):
        row = aggregates["per_method"][method]
        axes.annotate(
            f"{row['successes']}/{row['scenes']}",
            (bar.get_x() + bar.get_width() / 2.0, bar.get_height()),
            textcoords="offset points",
            xytext=(0, 3),
            ha="center",
            fontsize=8,
        )
    axes.set_xticks(np.arange(len(methods)))
    axes.set_xticklabels(methods, rotation=20)
    axes.set_ylim(0.0, 110.0)
    axes.set_ylabel("success rate [%]")
    axes.set_title("Success: +10 points or >= 90 % coverage")
    axes.grid(True, axis="y", alpha=0.3)
    figure.tight_layout()
    return save_figure_atomically(figure, path)


def _plot_latency(path: str, samples: Mapping[str, Sequence[float]], stats: Mapping[str, Mapping[str, float]]) -> str:
    """Horizontal box plot per stage (whiskers 5-95 %), p50 and p95 written beside each box."""
    stages = [stage for stage in stats if stats[stage]["n"] > 0]
    figure = new_figure((7.5, max(2.5, 0.55 * len(stages) + 1.5)))
    axes = figure.add_subplot(1, 1, 1)
    if stages:
        data = [np.asarray(list(samples[stage]), dtype=np.float64) for stage in stages]
        axes.boxplot(data, vert=False, whis=(5, 95), showfliers=True, flierprops={"markersize": 2})
        axes.set_yticks(np.arange(1, len(stages) + 1))
        axes.set_yticklabels(stages)
        for row, stage in enumerate(stages, start=1):
            axes.scatter([stats[stage]["p95"]], [row], marker="|", s=200, c="tab:red", zorder=3)
            axes.annotate(
                f"p50 {stats[stage]['p50']:.1f} / p95 {stats[stage]['p95']:.1f} ms",
                (stats[stage]["max"], row),
                textcoords="offset points",
                xytext=(6, -3),
                fontsize=7,
            )
        axes.margins(x=0.25)
    else:
        axes.text(0.5, 0.5, "no latency samples", ha="center", va="center", transform=axes.transAxes)
    axes.set_xlabel("latency [ms] (box 25-75 %, whiskers 5-95 %, red bar p95)")
    axes.set_title("Latency per stage")
    axes.grid(True, axis="x", alpha=0.3)
    figure.tight_layout()
    return save_figure_atomically(figure, path)
