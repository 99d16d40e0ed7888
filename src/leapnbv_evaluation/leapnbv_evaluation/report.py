"""Demo report and evaluation outputs: person overlays, top-down ring maps, task and latency tables."""

from __future__ import annotations

import json
import logging
import math
import os
from typing import Any, Dict, List, Mapping, NamedTuple, Optional, Sequence, Tuple

import cv2
import numpy as np

from leapnbv_common.atomic_files import write_file_atomically
from leapnbv_evaluation.metrics import latency_summary

LOGGER = logging.getLogger(__name__)

# Success rule of the task table: coverage rises by at least this many points (fraction) ...
SUCCESS_MIN_GAIN = 0.10
# ... or reaches at least this coverage after the move.
SUCCESS_MIN_COVERAGE = 0.90
# Coverages are fractions computed in floating point: 0.60 - 0.50 is 0.0999...98, which must count.
_SUCCESS_TOLERANCE = 1e-9
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
    """A pyplot-free Agg figure: no global figure registry to leak, safe off the main thread."""
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


def _format_value(value: Any) -> str:
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (float, np.floating)):
        number = float(value)
        return "n/a" if not math.isfinite(number) else f"{number:.4g}"
    if value is None:
        return "n/a"
    return str(value).replace("|", "\\|").replace("\n", " ")


def _require(frame: Mapping[str, Any], key: str, position: int) -> Any:
    if key not in frame:
        raise ReportError(f"frames[{position}] has no key {key!r}")
    return frame[key]


def _candidate_arrays(candidates: Mapping[str, Any], position: int) -> Dict[str, Any]:
    """Validate one frame's candidate dict and return it with numpy arrays."""
    keys = ("positions", "scores", "s_visibility", "s_area", "s_occlusion", "feasible", "chosen_index", "ring_center")
    for key in keys:
        if key not in candidates:
            raise ReportError(f"frames[{position}]['candidates'] has no key {key!r}")
    positions = np.asarray(candidates["positions"], dtype=np.float64).reshape(-1, 3)
    count = positions.shape[0]
    arrays: Dict[str, Any] = {"positions": positions}
    for key in ("scores", "s_visibility", "s_area", "s_occlusion"):
        arrays[key] = np.asarray(candidates[key], dtype=np.float64).reshape(-1)
    arrays["feasible"] = np.asarray(candidates["feasible"], dtype=bool).reshape(-1)
    for key in ("scores", "s_visibility", "s_area", "s_occlusion", "feasible"):
        if arrays[key].shape != (count,):
            raise ReportError(f"frames[{position}]['candidates'][{key!r}] must be ({count},), got {arrays[key].shape}")
    chosen = int(candidates["chosen_index"])
    if not -1 <= chosen < count:
        raise ReportError(f"frames[{position}]['candidates']['chosen_index'] {chosen} out of range for {count}")
    arrays["chosen_index"] = chosen
    arrays["ring_center"] = np.asarray(candidates["ring_center"], dtype=np.float64).reshape(3)
    rotations = candidates.get("rotations")
    arrays["rotations"] = None if rotations is None else np.asarray(rotations, dtype=np.float64)
    return arrays


def write_demo_report(out_dir: str, frames: Sequence[Mapping[str, Any]], summary: Mapping[str, Any]) -> str:
    """Write the demo report: per-frame overlay and ring PNGs, report.md and summary.json.

    Each frame dict holds "index", "stamp_ns", "rgb" (H,W,3 uint8), "box" (xyxy or None),
    "mask" (H,W bool or None), "candidates" (dict with positions (C,3), scores, s_visibility,
    s_area, s_occlusion (C,), feasible (C,) bool, chosen_index, ring_center (3,), optional
    rotations (C,3,3); or None), "target_points" (N,3), "background_points" (K,3), "plane"
    ((normal, offset) or None), "latency_ms" (end to end), optional "label" (box text).
    A frame without candidates, without a plane or with chosen_index -1 produced no goal;
    the report says so. Every file is written atomically.

    Args:
        out_dir: Output folder (created if missing).
        frames: The frames, in order.
        summary: Free-form key -> value rows for the summary table.

    Returns:
        Path of report.md.

    Raises:
        ReportError: A frame misses a key or has inconsistent shapes.
    """
    os.makedirs(out_dir, exist_ok=True)
    lines: List[str] = ["# LEAP-NBV demo report", "", "## Summary", "", "| Item | Value |", "|---|---|"]
    for key, value in summary.items():
        lines.append(f"| {_format_value(key)} | {_format_value(value)} |")
    lines.append("")
    frame_records: List[Dict[str, Any]] = []
    for position, frame in enumerate(frames):
        index = int(_require(frame, "index", position))
        stamp_ns = int(_require(frame, "stamp_ns", position))
        latency_ms = _require(frame, "latency_ms", position)
        name = f"frame_{index:03d}"
        overlay = overlay_person(
            _require(frame, "rgb", position), frame.get("box"), frame.get("mask"), str(frame.get("label", "person"))
        )
        overlay_file = f"{name}_overlay.png"
        _write_rgb_png_atomically(os.path.join(out_dir, overlay_file), overlay)
        record: Dict[str, Any] = {
            "index": index,
            "stamp_ns": stamp_ns,
            "latency_ms": latency_ms,
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
            f"## Frame {index}",
            "",
            f"- stamp: {stamp_ns} ns",
            f"- end-to-end latency: {_format_value(latency_ms)} ms",
        ]
        candidates = frame.get("candidates")
        plane = frame.get("plane")
        ring_file: Optional[str] = None
        if candidates is None:
            lines.append("- **no goal for this frame**: the planner produced no candidates")
        else:
            arrays = _candidate_arrays(candidates, position)
            chosen = arrays["chosen_index"]
            count = len(arrays["scores"])
            record["num_candidates"] = count
            record["num_feasible"] = int(arrays["feasible"].sum())
            record["candidate_scores"] = arrays["scores"]
            lines.append(f"- candidates: {count} ({record['num_feasible']} feasible)")
            if plane is not None:
                ring_file = f"{name}_ring.png"
                plot_ring_top_down(
                    os.path.join(out_dir, ring_file),
                    arrays["positions"],
                    arrays["scores"],
                    arrays["feasible"],
                    chosen,
                    arrays["ring_center"],
                    frame.get("target_points"),
                    frame.get("background_points"),
                    plane[0],
                    float(plane[1]),
                    title=f"frame {index}: candidate ring",
                    candidate_rotations=arrays["rotations"],
                )
                record["ring"] = ring_file
            if chosen < 0:
                lines.append("- **no goal for this frame**: no feasible candidate")
            elif plane is None:
                lines.append("- **no goal for this frame**: no ground plane (scores below are for information)")
            if chosen >= 0:
                x, y, z = arrays["positions"][chosen]
                chosen_scores = {
                    key: float(arrays[key][chosen]) for key in ("s_visibility", "s_area", "s_occlusion", "scores")
                }
                current = float(arrays["scores"][0]) if count else float("nan")
                gain = chosen_scores["scores"] - current
                record.update(
                    goal=plane is not None,
                    chosen_index=chosen,
                    chosen_position_m=[float(x), float(y), float(z)],
                    chosen_scores={
                        "s_visibility": chosen_scores["s_visibility"],
                        "s_area": chosen_scores["s_area"],
                        "s_occlusion": chosen_scores["s_occlusion"],
                        "score": chosen_scores["scores"],
                    },
                    current_score=current,
                    score_gain=gain,
                )
                stay = " (stay: the current view is best)" if chosen == 0 else ""
                lines += [
                    f"- chosen view: {chosen}{stay}",
                    f"- position (x, y, z): ({x:.3f}, {y:.3f}, {z:.3f}) m",
                    f"- S_v {chosen_scores['s_visibility']:.3f} / S_a {chosen_scores['s_area']:.3f} / "
                    f"S_o {chosen_scores['s_occlusion']:.3f} / score {chosen_scores['scores']:.3f}",
                    f"- gain over the current view: {gain:+.3f} (score {current:.3f} -> {chosen_scores['scores']:.3f})",
                ]
        lines += ["", f"![frame {index} overlay]({overlay_file})"]
        if ring_file is not None:
            lines.append(f"![frame {index} ring]({ring_file})")
        lines.append("")
        frame_records.append(record)
    _write_json_atomically(os.path.join(out_dir, "summary.json"), {"summary": dict(summary), "frames": frame_records})
    return _write_text_atomically(os.path.join(out_dir, "report.md"), "\n".join(lines))


# ---------------------------------------------------------------------------------------------
# 5. Evaluation: task table, latency table, plots
# ---------------------------------------------------------------------------------------------


def is_success(coverage_before: float, coverage_after: float) -> bool:
    """The task table's success rule: coverage rises by >= 10 points or reaches >= 90 %.

    Args:
        coverage_before: Body coverage before the move, fraction 0-1.
        coverage_after: Body coverage after the move, fraction 0-1.

    Returns:
        True for a success.
    """
    before, after = float(coverage_before), float(coverage_after)
    rises_enough = after - before >= SUCCESS_MIN_GAIN - _SUCCESS_TOLERANCE
    return rises_enough or after >= SUCCESS_MIN_COVERAGE - _SUCCESS_TOLERANCE


def _mean(values: Sequence[float]) -> float:
    return float(np.mean(values)) if len(values) else float("nan")


def _scene_results(results: Mapping[str, Any]) -> Tuple[List[str], List[Mapping[str, Any]]]:
    for key in ("methods", "scenes"):
        if key not in results:
            raise ReportError(f"results has no key {key!r}")
    methods = [str(method) for method in results["methods"]]
    scenes = list(results["scenes"])
    for position, scene in enumerate(scenes):
        if "per_method" not in scene:
            raise ReportError(f"results['scenes'][{position}] has no key 'per_method'")
        for method, row in scene["per_method"].items():
            for key in ("coverage_before", "coverage_after", "area_before", "area_after"):
                if key not in row:
                    raise ReportError(f"results['scenes'][{position}]['per_method'][{method!r}] has no key {key!r}")
    return methods, scenes


def aggregate_task_results(results: Mapping[str, Any]) -> Dict[str, Any]:
    """Per-method aggregates of the task table, with success recomputed by `is_success`.

    Args:
        results: {"methods": [...], "scenes": [{"seed", "start_occlusion", "per_method": {method:
            {"coverage_before", "coverage_after", "area_before", "area_after", "pa_mpvpe_mm",
            "success", "chosen_index"}}}], "latency_ms": {stage: [ms, ...]}}.

    Returns:
        {"methods", "per_method": {method: {"scenes", "coverage_before_pct", "coverage_after_pct",
        "area_before_kpx", "area_after_kpx", "pa_mpvpe_mm", "pa_mpvpe_scenes", "success_rate_pct",
        "successes"}}, "latency_ms": {stage: latency_summary}, "success_flag_mismatches":
        [{"seed", "method", "given", "computed"}]}. Means over the scenes that ran the method; NaN
        where none did (PA-MPVPE: over the scenes that have one).

    Raises:
        ReportError: Missing keys.
    """
    methods, scenes = _scene_results(results)
    per_method: Dict[str, Dict[str, Any]] = {}
    mismatches: List[Dict[str, Any]] = []
    for method in methods:
        rows = [(scene, scene["per_method"][method]) for scene in scenes if method in scene["per_method"]]
        successes = []
        for scene, row in rows:
            computed = is_success(row["coverage_before"], row["coverage_after"])
            successes.append(computed)
            given = row.get("success")
            if given is not None and bool(given) != computed:
                mismatches.append(
                    {"seed": scene.get("seed"), "method": method, "given": bool(given), "computed": computed}
                )
        errors = [float(row["pa_mpvpe_mm"]) for _, row in rows if row.get("pa_mpvpe_mm") is not None]
        per_method[method] = {
            "scenes": len(rows),
            "coverage_before_pct": 100.0 * _mean([float(row["coverage_before"]) for _, row in rows]),
            "coverage_after_pct": 100.0 * _mean([float(row["coverage_after"]) for _, row in rows]),
            "area_before_kpx": _mean([float(row["area_before"]) for _, row in rows]) / 1000.0,
            "area_after_kpx": _mean([float(row["area_after"]) for _, row in rows]) / 1000.0,
            "pa_mpvpe_mm": _mean(errors),
            "pa_mpvpe_scenes": len(errors),
            "successes": int(sum(successes)),
            "success_rate_pct": 100.0 * _mean([float(flag) for flag in successes]),
        }
    if mismatches:
        LOGGER.warning("success flags disagree with the coverage rule in %d rows; using the rule", len(mismatches))
    latency = {str(stage): latency_summary(samples) for stage, samples in dict(results.get("latency_ms", {})).items()}
    return {"methods": methods, "per_method": per_method, "latency_ms": latency, "success_flag_mismatches": mismatches}


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


def task_table_markdown(results: Mapping[str, Any]) -> str:
    """The headline task table (one row per method) as markdown, for the README.

    Args:
        results: As for `write_task_table`.

    Returns:
        Markdown table text ending in a newline.
    """
    return _headline_table(aggregate_task_results(results))


def _latency_table(latency: Mapping[str, Mapping[str, float]]) -> str:
    lines = ["| Stage | p50 (ms) | p95 (ms) | p99 (ms) | mean (ms) | n |", "|---|---:|---:|---:|---:|---:|"]
    for stage, stats in latency.items():
        lines.append(
            f"| {stage} | {_number(stats['p50'], 1)} | {_number(stats['p95'], 1)} | {_number(stats['p99'], 1)} | "
            f"{_number(stats['mean'], 1)} | {int(stats['n'])} |"
        )
    return "\n".join(lines) + "\n"


def _per_scene_table(methods: Sequence[str], scenes: Sequence[Mapping[str, Any]]) -> str:
    header = "| Seed | Start occlusion (%) | " + " | ".join(f"{method}: coverage (%)" for method in methods) + " |"
    lines = [header, "|---:|---:|" + "---:|" * len(methods)]
    for scene in scenes:
        occlusion = scene.get("start_occlusion")
        cells = [str(scene.get("seed", "?")), "n/a" if occlusion is None else _number(100.0 * float(occlusion), 0)]
        for method in methods:
            row = scene["per_method"].get(method)
            if row is None:
                cells.append("-")
                continue
            mark = " ok" if is_success(row["coverage_before"], row["coverage_after"]) else ""
            before, after = 100.0 * float(row["coverage_before"]), 100.0 * float(row["coverage_after"])
            cells.append(f"{before:.1f} -> {after:.1f}{mark}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_task_table(out_dir: str, results: Mapping[str, Any]) -> str:
    """Write results.md, results.json and the coverage / success / latency plots (atomically).

    Success is recomputed with `is_success` (coverage +10 points or >= 90 %); input flags that
    disagree are listed in both outputs and logged, never used.

    Args:
        out_dir: Output folder (created if missing).
        results: See `aggregate_task_results`; optional "default_method" picks the method of the
            per-scene coverage plot (else the first method).

    Returns:
        Path of results.md.

    Raises:
        ReportError: Missing keys or an unknown default method.
    """
    os.makedirs(out_dir, exist_ok=True)
    aggregates = aggregate_task_results(results)
    methods, scenes = _scene_results(results)
    default_method = str(results.get("default_method", methods[0] if methods else ""))
    if methods and default_method not in methods:
        raise ReportError(f"results['default_method'] {default_method!r} is not one of {methods}")

    plot_files = {
        "coverage_per_scene": "coverage_per_scene.png",
        "success_rate": "success_rate.png",
        "latency": "latency.png",
    }
    if methods:
        _plot_coverage_per_scene(os.path.join(out_dir, plot_files["coverage_per_scene"]), scenes, default_method)
        _plot_success_rate(os.path.join(out_dir, plot_files["success_rate"]), aggregates)
    _plot_latency(os.path.join(out_dir, plot_files["latency"]), results.get("latency_ms", {}), aggregates["latency_ms"])

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
    if aggregates["success_flag_mismatches"]:
        lines += [
            f"Note: {len(aggregates['success_flag_mismatches'])} input success flags disagreed with the rule "
            "and were recomputed (see results.json).",
            "",
        ]
    lines += ["## Latency", "", _latency_table(aggregates["latency_ms"])]
    lines += ["## Per scene", "", _per_scene_table(methods, scenes)]
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
            "seed": scene.get("seed"),
            "start_occlusion": scene.get("start_occlusion"),
            "per_method": {
                method: {
                    "coverage_before": row["coverage_before"],
                    "coverage_after": row["coverage_after"],
                    "area_before": row["area_before"],
                    "area_after": row["area_after"],
                    "pa_mpvpe_mm": row.get("pa_mpvpe_mm"),
                    "chosen_index": row.get("chosen_index"),
                    "success": is_success(row["coverage_before"], row["coverage_after"]),
                }
                for method, row in scene["per_method"].items()
            },
        }
        for scene in scenes
    ]
    _write_json_atomically(os.path.join(out_dir, "results.json"), payload)
    return _write_text_atomically(os.path.join(out_dir, "results.md"), "\n".join(lines))


def _plot_coverage_per_scene(path: str, scenes: Sequence[Mapping[str, Any]], method: str) -> str:
    """Dumbbell plot: coverage before (grey) -> after (green success / red not) per scene, sorted by before."""
    rows = [(scene.get("seed"), scene["per_method"][method]) for scene in scenes if method in scene["per_method"]]
    rows.sort(key=lambda item: float(item[1]["coverage_before"]))
    before = np.array([100.0 * float(row["coverage_before"]) for _, row in rows])
    after = np.array([100.0 * float(row["coverage_after"]) for _, row in rows])
    success = np.array([is_success(row["coverage_before"], row["coverage_after"]) for _, row in rows], dtype=bool)
    positions = np.arange(len(rows))
    figure = _new_figure((max(6.0, 0.25 * len(rows) + 2.0), 4.5))
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
