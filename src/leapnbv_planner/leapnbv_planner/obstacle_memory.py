"""A bounded, decaying memory of the obstacles the frames' depth showed, in the fixed frame (a map without a map).

Without the robot's obstacle map the planner knows only what the current frame shows, and a view
behind furniture that the start view could not see looks free (16 % of first picks in furnished
rooms). A robot driving toward such a view sees the furniture on the way. This memory keeps what
the frames saw: each frame's depth, with the person's pixels left out, goes to the fixed frame with
the frame's camera pose (floor-aligned: z up, floor z = 0, as the camera-pose topic promises); the
points between ``floor_clearance_m`` and ``max_height_m`` above the floor and within ``max_range_m``
of the camera are counted into voxels (OctoMap's convention: voxel (i, j, k) spans [i r, (i+1) r) on
each axis, centre ((i, j, k) + 0.5) r; :mod:`leapnbv_planner.obstacle_map`).

* **Evidence**: a voxel gains one unit per frame that has at least ``min_points`` points in it (a
  frame's count saturates at one unit, so a near wall does not outweigh many frames), up to
  ``max_weight``.
* **Decay**: the weight halves every ``half_life_s`` of the frames' stamps (a chair that was moved,
  a person who walked through: what is not seen again fades); a voxel below ``forget_weight`` is
  dropped.
* **Occupied**: a voxel whose weight now is at least ``occupied_weight`` (0.5 by default: seen in one
  frame within the last half-life; what a single frame saw counts, as the current frame's own depth
  does in the plan).
* **Bounded**: at most ``max_voxels`` voxels; over that, the weakest go first (then the oldest).

:meth:`ObstacleMemory.occupied_centres` is a map in the form the obstacle map takes
(:func:`leapnbv_planner.obstacle_map.voxel_map_from_centres`), so the plan uses it where it would use
the robot's map. A stamp older than the last one seen is refused (the decay runs forward only); a
change of fixed frame clears the memory (its voxels are in the old frame).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import numpy as np

from leapnbv_planner.arrays import Array

__all__ = ["ObstacleMemory", "ObstacleMemoryParams", "depth_points_in_fixed_frame", "frame_obstacle_points",
           "PERSON_MARGIN_M"]

#: m: background points this near the person's points (horizontally, by voxel column) are left out of the
#: memory: the mask's edge leaves some of the person in the background, and the person is not an obstacle.
PERSON_MARGIN_M = 0.15


@dataclass(frozen=True)
class ObstacleMemoryParams:
    """The memory's limits (see the module docstring)."""

    resolution: float = 0.1
    floor_clearance_m: float = 0.10
    max_height_m: float = 2.2
    max_range_m: float = 5.0
    min_points: int = 3
    max_weight: float = 8.0
    half_life_s: float = 20.0
    occupied_weight: float = 0.5
    forget_weight: float = 0.2
    max_voxels: int = 50_000

    def __post_init__(self) -> None:
        for name in ("resolution", "max_range_m", "max_weight", "half_life_s", "occupied_weight", "forget_weight"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"obstacle memory {name} must be a finite number > 0, got {value}")
        if not (0.0 <= self.floor_clearance_m < self.max_height_m):
            raise ValueError("obstacle memory needs 0 <= floor_clearance_m < max_height_m")
        if self.min_points < 1 or self.max_voxels < 1:
            raise ValueError("obstacle memory min_points and max_voxels must be >= 1")


def depth_points_in_fixed_frame(depth_m: Array, K: Array, rotation: Array, position: Array, stride: int = 2,
                                exclude: Optional[Array] = None) -> Tuple[Array, Array]:
    """A depth image's points in the fixed frame (every ``stride``-th pixel, valid depth, not excluded).

    Args:
        depth_m: (H, W) metres, 0 or non-finite for no return.
        K: (3, 3) intrinsics of the depth image.
        rotation: (3, 3) camera optical frame in the fixed frame.
        position: (3,) camera centre in the fixed frame.
        stride: Take every stride-th row and column (>= 1).
        exclude: (H, W) bool pixels to leave out (the person's), or None.

    Returns:
        ((N, 3) points in the fixed frame, (N,) their distance from the camera).
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    step = max(1, int(stride))
    rows, cols = np.mgrid[0:depth.shape[0]:step, 0:depth.shape[1]:step]
    z = depth[rows, cols]
    keep = np.isfinite(z) & (z > 0.0)
    if exclude is not None:
        keep &= ~np.asarray(exclude, dtype=bool)[rows, cols]
    z, u, v = z[keep], cols[keep].astype(np.float64), rows[keep].astype(np.float64)
    k = np.asarray(K, dtype=np.float64)
    camera = np.stack([(u - k[0, 2]) * z / k[0, 0], (v - k[1, 2]) * z / k[1, 1], z], axis=1)
    points = camera @ np.asarray(rotation, dtype=np.float64).T + np.asarray(position, dtype=np.float64)
    return points, np.linalg.norm(camera, axis=1)


def frame_obstacle_points(background: Array, person: Array, rotation: Array, position: Array,
                          resolution: float, margin_m: float = PERSON_MARGIN_M) -> Tuple[Array, Array]:
    """A frame's background points (the camera's optical frame) for the memory: fixed frame, the person left out.

    Args:
        background: (N, 3) the frame's points outside the person's mask, optical frame (TargetGeometry's).
        person: (M, 3) the person's points, optical frame: the voxel columns (x, y cells of ``resolution``)
            they occupy, grown by ``margin_m``, leave the background points in them out.
        rotation: (3, 3) camera optical frame in the fixed frame.
        position: (3,) camera centre in the fixed frame.
        resolution: Voxel edge of the memory (m).
        margin_m: How far around the person's columns the background is left out (m).

    Returns:
        ((K, 3) points in the fixed frame, (K,) their distance from the camera).
    """
    rot = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    pos = np.asarray(position, dtype=np.float64).reshape(3)
    camera = np.asarray(background, dtype=np.float64).reshape(-1, 3)
    camera = camera[np.isfinite(camera).all(axis=1)]
    points = camera @ rot.T + pos
    body = np.asarray(person, dtype=np.float64).reshape(-1, 3)
    body = body[np.isfinite(body).all(axis=1)] @ rot.T + pos
    if len(body) and len(points):
        grow = int(math.ceil(max(0.0, margin_m) / resolution))
        columns = np.unique(np.floor(body[:, :2] / resolution).astype(np.int64), axis=0)
        offsets = np.stack(np.meshgrid(np.arange(-grow, grow + 1), np.arange(-grow, grow + 1)), -1).reshape(-1, 2)
        near = np.unique((columns[:, None, :] + offsets[None, :, :]).reshape(-1, 2), axis=0)
        cells = np.floor(points[:, :2] / resolution).astype(np.int64)
        # Column membership by one integer key per (i, j).
        low = np.minimum(near.min(axis=0), cells.min(axis=0))
        span = int((np.maximum(near.max(axis=0), cells.max(axis=0)) - low).max() + 1)
        keyed_near = (near[:, 0] - low[0]) * span + (near[:, 1] - low[1])
        keyed = (cells[:, 0] - low[0]) * span + (cells[:, 1] - low[1])
        keep = ~np.isin(keyed, keyed_near)
        points, camera = points[keep], camera[keep]
    return points, np.linalg.norm(camera, axis=1)


class ObstacleMemory:
    """The memory (see the module docstring).

    Args:
        params: Its limits.
    """

    def __init__(self, params: Optional[ObstacleMemoryParams] = None) -> None:
        self.params = params or ObstacleMemoryParams()
        self.frame_id = ""
        self.stamp_ns: Optional[int] = None  # the newest frame taken in
        self._weights: Dict[Tuple[int, int, int], Tuple[float, int]] = {}  # voxel -> (weight at stamp, stamp)
        #: Frames taken in since the memory was made or cleared.
        self.frames = 0

    def __len__(self) -> int:
        return len(self._weights)

    def clear(self) -> None:
        """Forget everything (another fixed frame, another room)."""
        self._weights.clear()
        self.frame_id = ""
        self.stamp_ns = None
        self.frames = 0

    def _decayed(self, weight: float, since_ns: int, now_ns: int) -> float:
        return float(weight * 0.5 ** (max(0, now_ns - since_ns) * 1e-9 / self.params.half_life_s))

    def add_points(self, points: Array, distances: Array, stamp_ns: int, frame_id: str) -> int:
        """Take one frame's points (fixed frame; their distance from the camera) in; how many voxels it hit.

        Raises:
            ValueError: A stamp older than the newest one taken in (in the same fixed frame).
        """
        p = self.params
        stamp = int(stamp_ns)
        if frame_id != self.frame_id:
            self.clear()
            self.frame_id = frame_id
        if self.stamp_ns is not None and stamp < self.stamp_ns:
            raise ValueError(f"obstacle memory: frame stamped {stamp} ns is older than the newest taken in "
                             f"({self.stamp_ns} ns)")
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        dist = np.asarray(distances, dtype=np.float64).reshape(-1)
        keep = (np.isfinite(pts).all(axis=1) & (pts[:, 2] >= p.floor_clearance_m) & (pts[:, 2] <= p.max_height_m)
                & (dist <= p.max_range_m))
        cells, counts = np.unique(np.floor(pts[keep] / p.resolution).astype(np.int64), axis=0, return_counts=True)
        hit = 0
        for cell, count in zip(map(tuple, cells), counts):
            if count < p.min_points:
                continue
            weight, since = self._weights.get(cell, (0.0, stamp))
            self._weights[cell] = (min(p.max_weight, self._decayed(weight, since, stamp) + 1.0), stamp)
            hit += 1
        self.stamp_ns = stamp
        self.frames += 1
        self._forget(stamp)
        return hit

    def _forget(self, now_ns: int) -> None:
        """Drop what faded below forget_weight; over max_voxels, the weakest (then the oldest) first."""
        p = self.params
        decayed = {cell: self._decayed(w, since, now_ns) for cell, (w, since) in self._weights.items()}
        for cell, weight in decayed.items():
            if weight < p.forget_weight:
                del self._weights[cell]
        if len(self._weights) > p.max_voxels:
            order = sorted(self._weights, key=lambda c: (decayed[c], self._weights[c][1], c))
            for cell in order[:len(self._weights) - p.max_voxels]:
                del self._weights[cell]

    def weight(self, point: Array, now_ns: Optional[int] = None) -> float:
        """The decayed weight of the voxel holding ``point`` at ``now_ns`` (the newest stamp when None); 0 if none."""
        cell = tuple(np.floor(np.asarray(point, dtype=np.float64) / self.params.resolution).astype(np.int64))
        if cell not in self._weights or self.stamp_ns is None:
            return 0.0
        weight, since = self._weights[cell]
        return self._decayed(weight, since, self.stamp_ns if now_ns is None else int(now_ns))

    def occupied_centres(self, now_ns: Optional[int] = None) -> Array:
        """(M, 3) centres of the voxels occupied at ``now_ns`` (the newest stamp when None), sorted by (i, j, k)."""
        if not self._weights or self.stamp_ns is None:
            return np.zeros((0, 3))
        now = self.stamp_ns if now_ns is None else int(now_ns)
        cells = sorted(cell for cell, (w, since) in self._weights.items()
                       if self._decayed(w, since, now) >= self.params.occupied_weight)
        if not cells:
            return np.zeros((0, 3))
        centres: Array = (np.asarray(cells, dtype=np.float64) + 0.5) * self.params.resolution
        return centres
