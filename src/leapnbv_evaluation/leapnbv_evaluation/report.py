"""Reports: the demo report (person overlays, top-down ring maps) and the evaluation outputs (task and latency
tables, plots, chosen views, run summary).

Readers only: they take typed inputs (:class:`DemoFrame`, :class:`~leapnbv_evaluation.results.EvaluationRun`)
and never recompute what the run decided (success comes with each method's result). Every file is
written atomically (a failed write leaves the previous file intact).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from typing import Any, Dict, List, Mapping, NamedTuple, Optional, Sequence, Tuple

import cv2
import numpy as np

from leapnbv_common.atomic_files import write_file_atomically
from leapnbv_common.conversions import GroundPlaneArrays, ViewCandidatesArrays
from leapnbv_evaluation.metrics import SUCCESS_MIN_COVERAGE, SUCCESS_MIN_GAIN, latency_summary
from leapnbv_evaluation.results import EvaluationRun, MethodResult, SceneResult

# Background points this close to the floor are the floor itself, not occluders (m).
FLOOR_CLEARANCE_M = 0.05
# Most background / target points drawn in one map; more only slow the PNG down.
MAX_PLOTTED_POINTS = 20000

MASK_TINT_RGB = (0, 200, 0)
MASK_TINT_ALPHA = 0.45
BOX_COLOUR_RGB = (255, 64, 0)


class ReportError(ValueError):
    """An input to the report writers is malformed (names the field and shape at fault)."""


class GroundFrame(NamedTuple):
    """A 2D map basis on the ground plane (all in the camera optical frame, metres).

    Attributes:
        origin: (3,) the camera's foot point on the plane.
        e1: (3,) unit, the camera's forward direction projected on the plane (map +y, "up").
        e2: (3,) unit, e1 x n: the camera's right on the plane (map +x).
    """

    origin: np.ndarray
    e1: np.ndarray
    e2: np.ndarray


# ---------------------------------------------------------------------------------------------
# Atomic file writing
# ---------------------------------------------------------------------------------------------


def _write_text_atomically(path: str, text: str) -> str:
    def write(temporary: str) -> None:
        with open(temporary, "w", encoding="utf-8") as stream:
            stream.write(text)

    return write_file_atomically(path, write)


def _write_json_atomically(path: str, payload: Any) -> str:
    return _write_text_atomically(path, json.dumps(_to_plain(payload), indent=2, allow_nan=False) + "\n")


def _write_rgb_png_atomically(path: str, rgb: np.ndarray) -> str:
    bgr = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR)

    def write(temporary: str) -> None:
        if not cv2.imwrite(temporary, bgr):
            raise ReportError(f"cv2.imwrite could not write {path}")

    return write_file_atomically(path, write)


def _save_figure_atomically(figure: Any, path: str) -> str:
    return write_file_atomically(path, lambda temporary: figure.savefig(temporary, format="png", dpi=110))


def _to_plain(value: Any) -> Any:
    """numpy scalars/arrays, tuples and NaN/inf -> plain JSON types (non-finite floats -> None)."""
    if isinstance(value, Mapping):
        return {str(key): _to_plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_to_plain(item) for item in value]
    if isinstance(value, np.ndarray):
        return [_to_plain(item) for item in value.tolist()]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        number = float(value)
        return number if math.isfinite(number) else None
    if value is None or isinstance(value, str):
        return value
    return str(value)


def _new_figure(size_in: Tuple[float, float]) -> Any:
    """A pyplot-free Agg figure: no global figure registry to leak, safe off the main thread.

    matplotlib is imported here, on the first plot: it takes about a second to import, and the
    tables and the demo's text need none of it.
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=size_in)
    FigureCanvasAgg(figure)
    return figure


# ---------------------------------------------------------------------------------------------
# 1. Person overlay
# ---------------------------------------------------------------------------------------------


def overlay_person(
    rgb: np.ndarray,
    box_xyxy: Optional[Sequence[float]],
    mask: Optional[np.ndarray],
    label: str = "",
) -> np.ndarray:
    """The colour frame with the person mask tinted and the detection box drawn.

    Mask pixels become (1 - a) rgb + a tint; the box is a 2 px rectangle with `label`
    (e.g. "person 0.87") on a filled strip above it (inside the box when there is no room).

    Args:
        rgb: (H,W,3) uint8 colour frame (RGB order; returned in the same order).
        box_xyxy: (4,) box corners x0, y0, x1, y1 in pixels, or None.
        mask: (H,W) bool person mask, or None.
        label: Text drawn with the box; empty for none.

    Returns:
        (H,W,3) uint8, a new array (the input is not modified).

    Raises:
        ReportError: Bad shapes or dtype.
    """
    image = np.asarray(rgb)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ReportError(f"rgb must be (H,W,3) uint8, got {image.shape} {image.dtype}")
    height, width = image.shape[:2]
    out = image.copy()
    if mask is not None:
        mask_array = np.asarray(mask)
        if mask_array.shape != (height, width):
            raise ReportError(f"mask must be (H,W) = {(height, width)}, got {mask_array.shape}")
        mask_array = mask_array.astype(bool)
        tint = np.asarray(MASK_TINT_RGB, dtype=np.float32)
        blended = (1.0 - MASK_TINT_ALPHA) * out[mask_array].astype(np.float32) + MASK_TINT_ALPHA * tint
        out[mask_array] = np.clip(np.rint(blended), 0, 255).astype(np.uint8)
    if box_xyxy is not None:
        box = np.asarray(box_xyxy, dtype=np.float64).reshape(-1)
        if box.shape != (4,) or not np.all(np.isfinite(box)):
            raise ReportError(f"box_xyxy must be 4 finite numbers, got {box_xyxy!r}")
        x0, y0, x1, y1 = (int(round(value)) for value in box)
        x0, x1 = sorted((int(np.clip(x0, 0, width - 1)), int(np.clip(x1, 0, width - 1))))
        y0, y1 = sorted((int(np.clip(y0, 0, height - 1)), int(np.clip(y1, 0, height - 1))))
        cv2.rectangle(out, (x0, y0), (x1, y1), BOX_COLOUR_RGB, thickness=2)
        if label:
            _draw_label(out, label, x0, y0, y1)
    return out


def _draw_label(image: np.ndarray, label: str, x0: int, y0: int, y1: int) -> None:
    """Draw `label` on a filled strip at the box's top-left corner (in place)."""
    font = cv2.FONT_HERSHEY_SIMPLEX
    scale = max(0.4, min(1.0, image.shape[0] / 900.0))
    (text_width, text_height), baseline = cv2.getTextSize(label, font, scale, 1)
    strip_height = text_height + baseline + 4
    # Above the box when it fits, else just inside its top edge.
    top = y0 - strip_height if y0 - strip_height >= 0 else min(y0, max(0, y1 - strip_height))
    cv2.rectangle(image, (x0, top), (x0 + text_width + 4, top + strip_height), BOX_COLOUR_RGB, thickness=-1)
    cv2.putText(image, label, (x0 + 2, top + text_height + 2), font, scale, (255, 255, 255), 1, lineType=cv2.LINE_AA)


# ---------------------------------------------------------------------------------------------
# 2. Ground-plane map coordinates
# ---------------------------------------------------------------------------------------------


def _unit_plane(normal: Sequence[float], offset: float) -> Tuple[np.ndarray, float]:
    """Normalise n.x + d = 0 so that |n| = 1 (d scales with it)."""
    n = np.asarray(normal, dtype=np.float64).reshape(-1)
    if n.shape != (3,):
        raise ReportError(f"plane normal must be (3,), got {n.shape}")
    length = float(np.linalg.norm(n))
    if not math.isfinite(length) or length < 1e-9 or not math.isfinite(float(offset)):
        raise ReportError(f"plane (normal {n.tolist()}, offset {offset}) is degenerate")
    return n / length, float(offset) / length


def ground_frame(normal: Sequence[float], offset: float) -> GroundFrame:
    """A 2D map basis on the ground plane n.x + d = 0, seen from the camera at the origin.

    origin = -d n is the camera's foot point; e1 = the optical axis z projected on the plane
    (the image's up direction -y when the camera looks straight down); e2 = e1 x n, the camera's
    right on the plane. With `to_ground_2d` the map has the camera at (0, 0) looking toward +y.

    Args:
        normal: (3,) plane normal pointing up (need not be unit length).
        offset: d of n.x + d = 0.

    Returns:
        GroundFrame(origin (3,), e1 (3,), e2 (3,)).

    Raises:
        ReportError: A zero or non-finite normal.
    """
    n, d = _unit_plane(normal, offset)
    origin = -d * n
    e1 = np.zeros(3)
    for axis in (np.array([0.0, 0.0, 1.0]), np.array([0.0, -1.0, 0.0]), np.array([1.0, 0.0, 0.0])):
        projected = axis - float(axis @ n) * n
        length = float(np.linalg.norm(projected))
        if length > 1e-6:
            e1 = projected / length
            break
    e2 = np.cross(e1, n)
    return GroundFrame(origin=origin, e1=e1, e2=e2 / np.linalg.norm(e2))


def to_ground_2d(points: np.ndarray, frame: GroundFrame) -> np.ndarray:
    """Map coordinates of points (their orthogonal projection on the plane).

    Args:
        points: (N,3) points in the optical frame (or (3,)).
        frame: From `ground_frame`.

    Returns:
        (N,2): column 0 along e2 (right, map x), column 1 along e1 (forward, map y), metres.

    Raises:
        ReportError: Points not (N,3).
    """
    array = np.asarray(points, dtype=np.float64)
    if array.ndim == 1 and array.shape[0] == 3:
        array = array[None, :]
    if array.ndim != 2 or array.shape[1] != 3:
        raise ReportError(f"points must be (N,3), got {array.shape}")
    relative = array - np.asarray(frame.origin, dtype=np.float64)[None, :]
    return np.stack([relative @ frame.e2, relative @ frame.e1], axis=1)


def _points_array(points: Optional[np.ndarray], name: str) -> np.ndarray:
    if points is None:
        return np.zeros((0, 3))
    array = np.asarray(points, dtype=np.float64)
    if array.size == 0:
        return np.zeros((0, 3))
    if array.ndim != 2 or array.shape[1] != 3:
        raise ReportError(f"{name} must be (N,3), got {array.shape}")
    return array[np.all(np.isfinite(array), axis=1)]


def _subsample(points: np.ndarray, limit: int) -> np.ndarray:
    """At most `limit` rows, chosen with a fixed seed so the same input draws the same map."""
    if len(points) <= limit:
        return points
    keep = np.random.default_rng(0).choice(len(points), size=limit, replace=False)
    return points[np.sort(keep)]


# ---------------------------------------------------------------------------------------------
# 3. Top-down ring map
# ---------------------------------------------------------------------------------------------


def plot_ring_top_down(
    path: str,
    candidate_positions: np.ndarray,
    scores: np.ndarray,
    feasible: np.ndarray,
    chosen_index: int,
    ring_center: np.ndarray,
    target_points: Optional[np.ndarray],
    background_points: Optional[np.ndarray],
    plane_normal: Sequence[float],
    plane_offset: float,
    title: str = "",
    candidate_rotations: Optional[np.ndarray] = None,
) -> str:
    """Write a top-down PNG map of the candidate ring in ground coordinates (atomically).

    Draws background points higher than FLOOR_CLEARANCE_M above the floor (grey), the target
    points, the candidates coloured by score (viridis + colour bar), an x on infeasible ones,
    candidate 0 (the current view) as a square, the chosen view as a big star with an arrow
    along its optical axis projected on the ground, and the ring centre.

    Args:
        path: PNG file to write.
        candidate_positions: (C,3) camera positions, optical frame, metres.
        scores: (C,) total scores.
        feasible: (C,) bool.
        chosen_index: Index of the chosen view, -1 for none.
        ring_center: (3,) ring centre on the ground.
        target_points: (N,3) person points, or None.
        background_points: (K,3) scene points other than the person, or None.
        plane_normal: (3,) ground normal pointing up.
        plane_offset: d of n.x + d = 0.
        title: Figure title.
        candidate_rotations: Optional (C,3,3) with the camera axes as columns; without it the
            chosen view's arrow points at the ring centre (candidates look at the target).

    Returns:
        `path`.

    Raises:
        ReportError: Inconsistent shapes or a chosen index out of range.
    """
    positions = np.asarray(candidate_positions, dtype=np.float64)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ReportError(f"candidate_positions must be (C,3), got {positions.shape}")
    count = positions.shape[0]
    score_array = np.asarray(scores, dtype=np.float64).reshape(-1)
    feasible_array = np.asarray(feasible, dtype=bool).reshape(-1)
    if score_array.shape != (count,) or feasible_array.shape != (count,):
        raise ReportError(
            f"scores {score_array.shape} and feasible {feasible_array.shape} must be ({count},) like the positions"
        )
    chosen = int(chosen_index)
    if not -1 <= chosen < count:
        raise ReportError(f"chosen_index {chosen} out of range for {count} candidates")
    rotations = None
    if candidate_rotations is not None:
        rotations = np.asarray(candidate_rotations, dtype=np.float64)
        if rotations.shape != (count, 3, 3):
            raise ReportError(f"candidate_rotations must be ({count},3,3), got {rotations.shape}")

    n, d = _unit_plane(plane_normal, plane_offset)
    frame = ground_frame(n, d)
    background = _points_array(background_points, "background_points")
    background = background[background @ n + d > FLOOR_CLEARANCE_M]
    background_2d = to_ground_2d(_subsample(background, MAX_PLOTTED_POINTS), frame)
    target_2d = to_ground_2d(_subsample(_points_array(target_points, "target_points"), MAX_PLOTTED_POINTS), frame)
    candidates_2d = to_ground_2d(positions, frame) if count else np.zeros((0, 2))
    center_2d = to_ground_2d(np.asarray(ring_center, dtype=np.float64).reshape(3), frame)[0]

    figure = _new_figure((7.0, 7.0))
    axes = figure.add_subplot(1, 1, 1)
    if len(background_2d):
        axes.scatter(
            background_2d[:, 0],
            background_2d[:, 1],
            s=1.0,
            c="0.6",
            alpha=0.5,
            linewidths=0,
            label=f"occluders > {FLOOR_CLEARANCE_M * 100:.0f} cm",
            zorder=1,
        )
    if len(target_2d):
        axes.scatter(
            target_2d[:, 0],
            target_2d[:, 1],
            s=3.0,
            c="tab:orange",
            alpha=0.6,
            linewidths=0,
            label="person",
            zorder=2,
        )
    if count:
        finite_scores = score_array[np.isfinite(score_array)]
        low = float(finite_scores.min()) if finite_scores.size else 0.0
        high = float(finite_scores.max()) if finite_scores.size else 1.0
        if high - low < 1e-9:
            low, high = low - 0.5, high + 0.5
        rings = axes.scatter(
            candidates_2d[:, 0],
            candidates_2d[:, 1],
            s=90,
            c=np.nan_to_num(score_array, nan=low),
            cmap="viridis",
            vmin=low,
            vmax=high,
            edgecolors="k",
            linewidths=0.6,
            label="candidates",
            zorder=3,
        )
        figure.colorbar(rings, ax=axes, shrink=0.8, label="score")
        if not np.all(feasible_array):
            blocked = candidates_2d[~feasible_array]
            axes.scatter(
                blocked[:, 0],
                blocked[:, 1],
                marker="x",
                s=110,
                c="crimson",
                linewidths=2.0,
                label="infeasible",
                zorder=4,
            )
        axes.scatter(
            candidates_2d[:1, 0],
            candidates_2d[:1, 1],
            marker="s",
            s=220,
            facecolors="none",
            edgecolors="tab:blue",
            linewidths=2.0,
            label="current view (0)",
            zorder=5,
        )
    axes.scatter(
        [center_2d[0]], [center_2d[1]], marker="+", s=160, c="k", linewidths=2.0, label="ring centre", zorder=5
    )
    if chosen >= 0:
        start = candidates_2d[chosen]
        if rotations is not None:
            axis_2d = to_ground_2d(positions[chosen] + rotations[chosen][:, 2], frame)[0] - start
        else:
            axis_2d = center_2d - start
        length = float(np.linalg.norm(axis_2d))
        axes.scatter(
            [start[0]],
            [start[1]],
            marker="*",
            s=480,
            c="red",
            edgecolors="k",
            linewidths=1.0,
            label=f"chosen ({chosen})",
            zorder=6,
        )
        if length > 1e-6:
            reach = 0.5 * max(float(np.linalg.norm(center_2d - start)), 0.4)
            tip = start + axis_2d / length * reach
            axes.annotate(
                "",
                xy=(tip[0], tip[1]),
                xytext=(start[0], start[1]),
                arrowprops={"arrowstyle": "-|>", "color": "red", "lw": 2.0},
                zorder=6,
            )
    for index in range(count):
        axes.annotate(
            str(index),
            (candidates_2d[index, 0], candidates_2d[index, 1]),
            textcoords="offset points",
            xytext=(6, 6),
            fontsize=7,
            color="0.2",
        )
    axes.set_aspect("equal", adjustable="datalim")
    axes.set_xlabel("right of camera [m]")
    axes.set_ylabel("ahead of camera [m]")
    axes.grid(True, alpha=0.3)
    # Below the axes: inside, it would hide candidates on the ring.
    axes.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=4, fontsize=7, markerscale=0.7)
    if title:
        axes.set_title(title)
    figure.tight_layout()
    return _save_figure_atomically(figure, path)


# ---------------------------------------------------------------------------------------------
# 4. Demo report
# ---------------------------------------------------------------------------------------------


@dataclass
class DemoFrame:
    """One frame of the demo: what the camera saw and what the graph made of it.

    Attributes:
        index: Frame number in the bag.
        stamp_ns: Header stamp.
        rgb: (H,W,3) uint8 colour frame.
        box: Detection box (x0, y0, x1, y1) in pixels, or None.
        mask: (H,W) bool person mask, or None.
        candidates: The graph's scored candidates, or None (the planner produced none).
        ground: The graph's ground plane, or None (it is used only when valid).
        target_points: (N,3) person points (optical frame), or None.
        background_points: (K,3) other scene points, or None.
        latency_ms: End-to-end latency of the frame, or None.
        label: Text drawn with the box.
    """

    index: int
    stamp_ns: int
    rgb: np.ndarray
    box: Optional[Sequence[float]] = None
    mask: Optional[np.ndarray] = None
    candidates: Optional[ViewCandidatesArrays] = None
    ground: Optional[GroundPlaneArrays] = None
    target_points: Optional[np.ndarray] = None
    background_points: Optional[np.ndarray] = None
    latency_ms: Optional[float] = None
    label: str = "person"

    @property
    def plane(self) -> Optional[GroundPlaneArrays]:
        """The ground plane when the graph found one."""
        return self.ground if self.ground is not None and self.ground.valid else None

    @property
    def has_goal(self) -> bool:
        """The graph chose a view for this frame."""
        return self.candidates is not None and self.candidates.chosen_index >= 0


def _format_value(value: Any) -> str:
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (float, np.floating)):
        number = float(value)
        return "n/a" if not math.isfinite(number) else f"{number:.4g}"
    if value is None:
        return "n/a"
    return str(value).replace("|", "\\|").replace("\n", " ")


def chosen_view_scores(candidates: ViewCandidatesArrays, index: int) -> Dict[str, float]:
    """"s_<term>" for every score term of candidate ``index``, then its total "score"."""
    scores = {f"s_{name}": float(candidates.term(name)[index]) for name in candidates.term_names}
    scores["score"] = float(candidates.score[index])
    return scores


def write_demo_report(out_dir: str, frames: Sequence[DemoFrame], summary: Mapping[str, Any]) -> str:
    """Write the demo report: per-frame overlay and ring PNGs, report.md and summary.json.

    A frame without candidates, without a valid ground plane or with chosen_index -1 produced
    no goal; the report says so. Every file is written atomically.

    Args:
        out_dir: Output folder (created if missing).
        frames: The frames, in order.
        summary: Free-form key -> value rows for the summary table.

    Returns:
        Path of report.md.

    Raises:
        ReportError: A frame has inconsistent shapes.
    """
    os.makedirs(out_dir, exist_ok=True)
    lines: List[str] = ["# LEAP-NBV demo report", "", "## Summary", "", "| Item | Value |", "|---|---|"]
    for key, value in summary.items():
        lines.append(f"| {_format_value(key)} | {_format_value(value)} |")
    lines.append("")
    frame_records: List[Dict[str, Any]] = []
    for frame in frames:
        name = f"frame_{frame.index:03d}"
        overlay = overlay_person(frame.rgb, frame.box, frame.mask, frame.label)
        overlay_file = f"{name}_overlay.png"
        _write_rgb_png_atomically(os.path.join(out_dir, overlay_file), overlay)
        record: Dict[str, Any] = {
            "index": frame.index,
            "stamp_ns": frame.stamp_ns,
            "latency_ms": frame.latency_ms,
            "overlay": overlay_file,
            "goal": False,
            "chosen_index": None,
            "chosen_position_m": None,
            "chosen_scores": None,
            "current_score": None,
            "score_gain": None,
            "ring": None,
            "num_candidates": 0,
            "num_feasible": 0,
        }
        lines += [
            f"## Frame {frame.index}",
            "",
            f"- stamp: {frame.stamp_ns} ns",
            f"- end-to-end latency: {_format_value(frame.latency_ms)} ms",
        ]
        candidates = frame.candidates
        plane = frame.plane
        ring_file: Optional[str] = None
        if candidates is None:
            lines.append("- **no goal for this frame**: the planner produced no candidates")
        else:
            chosen = candidates.chosen_index
            count = len(candidates)
            record["num_candidates"] = count
            record["num_feasible"] = int(np.count_nonzero(candidates.feasible))
            record["candidate_scores"] = candidates.score
            lines.append(f"- candidates: {count} ({record['num_feasible']} feasible)")
            if plane is not None:
                ring_file = f"{name}_ring.png"
                plot_ring_top_down(
                    os.path.join(out_dir, ring_file),
                    candidates.positions,
                    candidates.score,
                    candidates.feasible,
                    chosen,
                    candidates.ring_center,
                    frame.target_points,
                    frame.background_points,
                    plane.normal,
                    float(plane.offset),
                    title=f"frame {frame.index}: candidate ring",
                    candidate_rotations=candidates.rotations,
                )
                record["ring"] = ring_file
            if not -1 <= chosen < count:
                raise ReportError(f"frame {frame.index}: chosen_index {chosen} out of range for {count} candidates")
            if chosen < 0:
                lines.append("- **no goal for this frame**: no feasible candidate")
            elif plane is None:
                lines.append("- **no goal for this frame**: no ground plane (scores below are for information)")
            if chosen >= 0:
                x, y, z = candidates.positions[chosen]
                scores = chosen_view_scores(candidates, chosen)
                current = float(candidates.score[0]) if count else float("nan")
                gain = scores["score"] - current
                record.update(
                    goal=plane is not None,
                    chosen_index=chosen,
                    chosen_position_m=[float(x), float(y), float(z)],
                    chosen_scores=scores,
                    current_score=current,
                    score_gain=gain,
                )
                stay = " (stay: the current view is best)" if chosen == 0 else ""
                terms = " / ".join(f"{name} {scores['s_' + name]:.3f}" for name in candidates.term_names)
                lines += [
                    f"- chosen view: {chosen}{stay}",
                    f"- position (x, y, z): ({x:.3f}, {y:.3f}, {z:.3f}) m",
                    f"- {terms} / score {scores['score']:.3f}",
                    f"- gain over the current view: {gain:+.3f} (score {current:.3f} -> {scores['score']:.3f})",
                ]
        lines += ["", f"![frame {frame.index} overlay]({overlay_file})"]
        if ring_file is not None:
            lines.append(f"![frame {frame.index} ring]({ring_file})")
        lines.append("")
        frame_records.append(record)
    _write_json_atomically(os.path.join(out_dir, "summary.json"), {"summary": dict(summary), "frames": frame_records})
    return _write_text_atomically(os.path.join(out_dir, "report.md"), "\n".join(lines))


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
        "area_before_kpx", "area_after_kpx", "pa_mpvpe_mm", "pa_mpvpe_scenes", "successes",
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
        per_method[method] = {
            "scenes": len(rows),
            "coverage_before_pct": 100.0 * _mean([float(before) for before, _, _ in values]),
            "coverage_after_pct": 100.0 * _mean([float(after) for _, after, _ in values]),
            "area_before_kpx": _mean([float(row.before.area_px) for row in rows]) / 1000.0,
            "area_after_kpx": _mean([float(row.after.area_px) for row in rows]) / 1000.0,
            "pa_mpvpe_mm": _mean(errors),
            "pa_mpvpe_scenes": len(errors),
            "successes": int(sum(success for _, _, success in values)),
            "success_rate_pct": 100.0 * _mean([float(success) for _, _, success in values]),
        }
    latency = {stage: latency_summary(samples) for stage, samples in run.latency_ms().items()}
    return {"methods": list(run.methods), "per_method": per_method, "latency_ms": latency}


def _number(value: float, digits: int) -> str:
    return "n/a" if not math.isfinite(value) else f"{value:.{digits}f}"


def _headline_table(aggregates: Mapping[str, Any]) -> str:
    lines = [
        "| Method | Scenes | Coverage before -> after (%) | Area before -> after (k px) | PA-MPVPE (mm) "
        "| Success (%) |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for method in aggregates["methods"]:
        row = aggregates["per_method"][method]
        lines.append(
            f"| {method} | {row['scenes']} | {_number(row['coverage_before_pct'], 1)} -> "
            f"{_number(row['coverage_after_pct'], 1)} | {_number(row['area_before_kpx'], 1)} -> "
            f"{_number(row['area_after_kpx'], 1)} | {_number(row['pa_mpvpe_mm'], 1)} | "
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
    _write_json_atomically(os.path.join(out_dir, "results.json"), payload)
    return _write_text_atomically(os.path.join(out_dir, "results.md"), "\n".join(lines))


def _rounded(values: Sequence[float], digits: int = 6) -> List[float]:
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
    graph_after = [scene.per_method[run.default_method].graph_area_after for scene in run.scenes
                   if run.default_method in scene.per_method
                   and scene.per_method[run.default_method].graph_area_after is not None]
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
    _write_text_atomically(os.path.join(out_dir, "chosen_views.json"),
                           json.dumps(_to_plain(records), indent=1, allow_nan=False) + "\n")
    _write_text_atomically(os.path.join(out_dir, "evaluation.md"), evaluation_summary_markdown(run))
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
    figure = _new_figure((min(16.0, max(6.0, 0.25 * len(rows) + 2.0)), 4.5))
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
    return _save_figure_atomically(figure, path)


def _plot_success_rate(path: str, aggregates: Mapping[str, Any]) -> str:
    """One bar per method: success rate (%), labelled with successes / scenes."""
    methods = list(aggregates["methods"])
    rates = [aggregates["per_method"][method]["success_rate_pct"] for method in methods]
    figure = _new_figure((max(4.0, 1.2 * len(methods) + 2.0), 4.0))
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
    return _save_figure_atomically(figure, path)


def _plot_latency(path: str, samples: Mapping[str, Sequence[float]], stats: Mapping[str, Mapping[str, float]]) -> str:
    """Horizontal box plot per stage (whiskers 5-95 %), p50 and p95 written beside each box."""
    stages = [stage for stage in stats if stats[stage]["n"] > 0]
    figure = _new_figure((7.5, max(2.5, 0.55 * len(stages) + 1.5)))
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
    return _save_figure_atomically(figure, path)
