"""Carrying a person box from one frame to a later one with the person's mesh.

The detector then need not run on every frame (ROS-free; the detector node's
``detect_every_n_frames`` uses it).

The box of frame A (a detection: the visible part of the person) is moved into frame B by the image
motion of the mesh estimated in frame A: each vertex is projected into A, moved by the camera's
motion from A to B (the camera poses of both frames; identity without them) and projected into B;
a scale and a translation fitted to those point pairs (least squares) map the box's corners. The
person's own motion between A and B is not known here: it is what limits how many frames a box can
be carried (docs/ALGORITHMS.md, "Detect less often").

Shapes: vertices (V, 3) in A's camera optical frame (x right, y down, z forward, metres); K (3, 3);
poses as (R (3, 3), t (3,)) of T_world_camera; boxes (x_min, y_min, x_max, y_max) in pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence, Tuple, Union

import numpy as np

from leapnbv_common.array_types import BoolArray, FloatArray, FloatingArray

MIN_DEPTH_M = 0.1
MIN_POINTS = 8


@dataclass(frozen=True)
class CarriedBox:
    """A box moved from frame A to frame B.

    Attributes:
        box: (4,) float64 in B's pixels, clipped to the image.
        confidence: in [0, 1]: the share of the mesh's points that project into B's image in front of
            the camera, times the share of the carried box that stays inside the image.
        scale: the fitted image scale from A to B (1 = same apparent size).
    """

    box: FloatArray
    confidence: float
    scale: float


def camera_motion(pose_a: Optional[Tuple[FloatArray, FloatArray]],
                  pose_b: Optional[Tuple[FloatArray, FloatArray]]) -> Tuple[FloatArray, FloatArray]:
    """(R, t) taking points from A's camera frame to B's: T_B_world T_world_A; identity without poses."""
    if pose_a is None or pose_b is None:
        return np.eye(3), np.zeros(3)
    (ra, ta), (rb, tb) = pose_a, pose_b
    rotation = rb.T @ ra
    return rotation, rb.T @ (np.asarray(ta, np.float64) - np.asarray(tb, np.float64))


def project(points: FloatArray, K: FloatArray) -> Tuple[FloatArray, BoolArray]:
    """(uv (N, 2), in front (N,) bool) of camera-frame points."""
    z = points[:, 2]
    front = z > MIN_DEPTH_M
    safe = np.where(front, z, 1.0)
    uv: FloatArray = np.stack(
        (K[0, 0] * points[:, 0] / safe + K[0, 2], K[1, 1] * points[:, 1] / safe + K[1, 2]), axis=1)
    return uv, front


def carry_box(box_a: Union[Sequence[float], FloatingArray], vertices_a: FloatArray, K_a: FloatArray,
              K_b: FloatArray, image_size_b: Tuple[int, int],
              motion: Tuple[FloatArray, FloatArray]) -> Optional[CarriedBox]:
    """Move ``box_a`` into frame B with the mesh's image motion (None: too few points to fit).

    Args:
        box_a: (x_min, y_min, x_max, y_max) in A.
        vertices_a: (V, 3) the person's mesh in A's camera frame.
        K_a: (3, 3) intrinsics of A.
        K_b: (3, 3) intrinsics of B.
        image_size_b: (width, height) of B.
        motion: (R, t) from A's camera frame to B's (camera_motion).
    """
    vertices_a = np.asarray(vertices_a, np.float64)
    rotation, translation = motion
    uv_a, front_a = project(vertices_a, np.asarray(K_a, np.float64))
    uv_b, front_b = project(vertices_a @ rotation.T + translation, np.asarray(K_b, np.float64))
    x0, y0, x1, y1 = (float(v) for v in box_a[:4])
    width, height = image_size_b
    inside_box_a = front_a & (uv_a[:, 0] >= x0) & (uv_a[:, 0] <= x1) & (uv_a[:, 1] >= y0) & (uv_a[:, 1] <= y1)
    used = inside_box_a & front_b  # the part of the mesh the box showed
    if used.sum() < MIN_POINTS:
        used = front_a & front_b
    if used.sum() < MIN_POINTS:
        return None
    a, b = uv_a[used], uv_b[used]
    # b = s a + c: least squares on the centred points (s > 0)
    a_mean, b_mean = a.mean(axis=0), b.mean(axis=0)
    da, db = a - a_mean, b - b_mean
    scale = float((da * db).sum() / max((da * da).sum(), 1e-12))
    if not np.isfinite(scale) or scale <= 0.0:
        return None
    offset = b_mean - scale * a_mean
    moved = np.array([x0, y0, x1, y1]) * scale + np.tile(offset, 2)
    clipped = np.array([np.clip(moved[0], 0, width), np.clip(moved[1], 0, height),
                        np.clip(moved[2], 0, width), np.clip(moved[3], 0, height)])
    area = max((moved[2] - moved[0]) * (moved[3] - moved[1]), 1e-9)
    kept = max(clipped[2] - clipped[0], 0.0) * max(clipped[3] - clipped[1], 0.0) / area
    in_image = front_b & (uv_b[:, 0] >= 0) & (uv_b[:, 0] < width) & (uv_b[:, 1] >= 0) & (uv_b[:, 1] < height)
    confidence = float(in_image.mean()) * float(kept)
    return CarriedBox(clipped, confidence, scale)


@dataclass
class DetectionSchedule:
    """When to run the detector: every ``every_n`` frames, and whenever the carried box is not trusted.

    every_n = 1 runs it on every frame (no carrying).
    """

    every_n: int = 1
    min_confidence: float = 0.8
    frames_since_detection: Optional[int] = None

    def due(self) -> bool:
        """Whether the next frame is one the detector runs on anyway (the first, or the N-th)."""
        return (self.frames_since_detection is None or self.every_n <= 1
                or self.frames_since_detection + 1 >= self.every_n)

    def should_detect(self, carried: Optional[CarriedBox]) -> bool:
        """Decide for the next frame, given the box carried into it (None: none could be)."""
        return self.due() or carried is None or carried.confidence < self.min_confidence

    def record(self, detected: bool) -> None:
        self.frames_since_detection = 0 if detected else (self.frames_since_detection or 0) + 1
