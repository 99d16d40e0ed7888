"""The demo report of a bag run: per frame the colour image with the person, the chosen view and its score
terms, and a top-down map of the candidate ring.

It only reads: it takes typed frames (:class:`DemoFrame`) and writes files atomically (:mod:`report_files`).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any, Dict, List, Mapping, NamedTuple, Optional, Sequence, Tuple, Union

import cv2
import numpy as np

from leapnbv_common.array_types import BoolArray, FloatArray, FloatingArray, UInt8Array
from leapnbv_common.conversions import GroundPlaneArrays, ViewCandidatesArrays
from leapnbv_evaluation.report_files import (
    ReportError,
    new_figure,
    save_figure_atomically,
    write_json_atomically,
    write_rgb_png_atomically,
    write_text_atomically,
)

# Background points this close to the floor are the floor itself, not occluders (m).
FLOOR_CLEARANCE_M = 0.05
# Most background / target points drawn in one map; more only slow the PNG down.
MAX_PLOTTED_POINTS = 20000

#: A plane normal: three numbers, as a list or an array.
PlaneNormal = Union[Sequence[float], FloatArray]
MASK_TINT_RGB = (0, 200, 0)
MASK_TINT_ALPHA = 0.45
BOX_COLOUR_RGB = (255, 64, 0)


class GroundFrame(NamedTuple):
    """A 2D map basis on the ground plane (all in the camera optical frame, metres).

    Attributes:
        origin: (3,) the camera's foot point on the plane.
        e1: (3,) unit, the camera's forward direction projected on the plane (map +y, "up").
        e2: (3,) unit, e1 x n: the camera's right on the plane (map +x).
    """

    origin: FloatArray
    e1: FloatArray
    e2: FloatArray


# ---------------------------------------------------------------------------------------------
# 1. Person overlay
# ---------------------------------------------------------------------------------------------


def overlay_person(
    rgb: UInt8Array,
    box_xyxy: Optional[Sequence[float]],
    mask: Optional[BoolArray],
    label: str = "",
) -> UInt8Array:
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


def _draw_label(image: UInt8Array, label: str, x0: int, y0: int, y1: int) -> None:
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


def _unit_plane(normal: PlaneNormal, offset: float) -> Tuple[FloatArray, float]:
    """Normalise n.x + d = 0 so that |n| = 1 (d scales with it)."""
    n = np.asarray(normal, dtype=np.float64).reshape(-1)
    if n.shape != (3,):
        raise ReportError(f"plane normal must be (3,), got {n.shape}")
    length = float(np.linalg.norm(n))
    if not math.isfinite(length) or length < 1e-9 or not math.isfinite(float(offset)):
        raise ReportError(f"plane (normal {n.tolist()}, offset {offset}) is degenerate")
    return n / length, float(offset) / length


def ground_frame(normal: PlaneNormal, offset: float) -> GroundFrame:
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


def to_ground_2d(points: FloatingArray, frame: GroundFrame) -> FloatArray:
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


def _points_array(points: Optional[FloatingArray], name: str) -> FloatArray:
    if points is None:
        return np.zeros((0, 3))
    array = np.asarray(points, dtype=np.float64)
    if array.size == 0:
        return np.zeros((0, 3))
    if array.ndim != 2 or array.shape[1] != 3:
        raise ReportError(f"{name} must be (N,3), got {array.shape}")
    finite: FloatArray = array[np.all(np.isfinite(array), axis=1)]
    return finite


def _subsample(points: FloatArray, limit: int) -> FloatArray:
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
    candidate_positions: FloatArray,
    scores: FloatArray,
    feasible: BoolArray,
    chosen_index: int,
    ring_center: FloatArray,
    target_points: Optional[FloatingArray],
    background_points: Optional[FloatingArray],
    plane_normal: PlaneNormal,
    plane_offset: float,
    title: str = "",
    candidate_rotations: Optional[FloatArray] = None,
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

    figure = new_figure((7.0, 7.0))
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
    return save_figure_atomically(figure, path)


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
    rgb: UInt8Array
    box: Optional[Sequence[float]] = None
    mask: Optional[BoolArray] = None
    candidates: Optional[ViewCandidatesArrays] = None
    ground: Optional[GroundPlaneArrays] = None
    target_points: Optional[FloatingArray] = None
    background_points: Optional[FloatingArray] = None
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
        write_rgb_png_atomically(os.path.join(out_dir, overlay_file), overlay)
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
    write_json_atomically(os.path.join(out_dir, "summary.json"), {"summary": dict(summary), "frames": frame_records})
    return write_text_atomically(os.path.join(out_dir, "report.md"), "\n".join(lines))


