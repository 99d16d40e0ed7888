"""Controlled errors for the ground-truth backends: the error budget's stand-in for a learned model.

An evaluation tool, never for a robot. The ground-truth detector and mesh backends are perfect; a learned
detector and HMR model are not. To measure how much error the closed loop tolerates (README, "Error
budget"), the truth is corrupted by a known amount before the graph sees it:

- **the mesh's 2-D placement** (``shift``): the mesh moved parallel to the image plane so that its
  projection moves by ``shift`` times the box's width and height, in a random direction;
- **its depth and scale** (``depth``): the mesh scaled about the camera centre by 1 + ``depth`` or
  1 - ``depth`` (random sign), so it projects the same but stands nearer or farther and is smaller or
  larger, as a monocular model's error along the line of sight;
- **its pose and shape** (``pa_mpvpe_mm``): Gaussian noise on the body pose and the betas, scaled until
  the mesh is that far from the true one after Procrustes alignment (the PA-MPVPE a model card reports);
- **the person boxes** (:class:`BoxCorruption`): each side moved by Gaussian noise (``jitter``), the box
  grown about its centre (``grow``), or cut on one random side (``truncate``), each a share of the box's
  size; and whole frames without any detection (``miss_share``).

Every random draw comes from the frame's stamp and a seed (:func:`frame_rng`), so two runs of the same
scenes on simulated time corrupt every frame the same way, whatever the machine. Plain numpy, no ROS.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Tuple

import numpy as np

from leapnbv_common.array_types import Float32Array, FloatArray, FloatingArray
from leapnbv_common.procrustes import pa_mpvpe_mm

__all__ = ["MeshCorruption", "NO_MESH_CORRUPTION", "BoxCorruption", "frame_rng", "MESH_STREAM", "BOX_STREAM",
           "noisy_pose_and_shape", "displaced_mesh", "corrupted_boxes", "SHAPE_NOISE_PER_RAD"]

#: The random stream of each node's draws (a frame's mesh and its boxes are corrupted independently).
MESH_STREAM = 1
BOX_STREAM = 2
#: Betas noise (in the betas' unit standard deviations) per radian of body-pose noise: shape errors grow with
#: pose errors, as a model's do, and neither alone makes the PA-MPVPE.
SHAPE_NOISE_PER_RAD = 2.0
_PA_TOLERANCE_MM = 1.0
_PA_ITERATIONS = 30
_MAX_NOISE_SCALE = 4.0  # rad per unit draw: beyond this a pose is no body (the PA-MPVPE levels off)
_MIN_BOX_PX = 2.0


@dataclass(frozen=True)
class MeshCorruption:
    """How the ground-truth mesh is corrupted (all zero: the truth as it is)."""

    shift: float = 0.0
    depth: float = 0.0
    pa_mpvpe_mm: float = 0.0
    seed: int = 0

    @property
    def active(self) -> bool:
        return self.shift > 0.0 or self.depth > 0.0 or self.pa_mpvpe_mm > 0.0

    def describe(self) -> str:
        """One line for the node's diagnostics (``info.truth_corruption``)."""
        if not self.active:
            return "none"
        return (f"mesh shift {self.shift:g} of the box, depth {self.depth:g}, PA-MPVPE {self.pa_mpvpe_mm:g} mm, "
                f"seed {self.seed}")


@dataclass(frozen=True)
class BoxCorruption:
    """How the ground-truth person boxes are corrupted (all zero: the truth as it is)."""

    jitter: float = 0.0
    grow: float = 0.0
    truncate: float = 0.0
    miss_share: float = 0.0
    seed: int = 0

    @property
    def active(self) -> bool:
        return self.jitter > 0.0 or self.grow > 0.0 or self.truncate > 0.0 or self.miss_share > 0.0

    def describe(self) -> str:
        """One line for the node's diagnostics (``info.truth_corruption``)."""
        if not self.active:
            return "none"
        return (f"box jitter {self.jitter:g}, grow {self.grow:g}, truncate {self.truncate:g}, missed frames "
                f"{self.miss_share:g}, seed {self.seed}")


NO_MESH_CORRUPTION = MeshCorruption()


def frame_rng(seed: int, stamp_ns: int, stream: int) -> np.random.Generator:
    """The random generator of one frame: from the seed, the frame's stamp and the stream, nothing else."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, int(stamp_ns) & 0xFFFFFFFFFFFFFFFF, int(stream)])


def noisy_pose_and_shape(body_pose: FloatArray, betas: FloatArray, vertices_of: Callable[[FloatArray, FloatArray],
                         FloatArray], target_mm: float, rng: np.random.Generator
                         ) -> Tuple[FloatArray, FloatArray, float]:
    """Body pose and betas with noise that puts the mesh ``target_mm`` from the true one (PA-MPVPE).

    One Gaussian draw fixes the noise's direction (every body-pose component, and the betas with
    :data:`SHAPE_NOISE_PER_RAD`); its size is found by bisection to within 1 mm of the target. A target
    the noise cannot reach (a pose past any body) gets the largest noise tried.

    Args:
        body_pose: (63,) axis-angle body pose.
        betas: (B,) shape coefficients.
        vertices_of: (body_pose, betas) -> (V, 3) posed vertices (the rest of the body as it is).
        target_mm: the PA-MPVPE to reach; 0 returns the inputs.
        rng: the frame's generator.

    Returns:
        (body_pose, betas, the PA-MPVPE reached in mm).
    """
    body_pose = np.asarray(body_pose, np.float64)
    betas = np.asarray(betas, np.float64)
    if target_mm <= 0.0:
        return body_pose, betas, 0.0
    truth = vertices_of(body_pose, betas)
    pose_noise = rng.standard_normal(body_pose.shape)
    shape_noise = rng.standard_normal(betas.shape) * SHAPE_NOISE_PER_RAD

    def error(scale: float) -> Tuple[float, FloatArray, FloatArray]:
        pose, shape = body_pose + scale * pose_noise, betas + scale * shape_noise
        return pa_mpvpe_mm(vertices_of(pose, shape), truth), pose, shape

    low, high = 0.0, 0.05
    reached, pose, shape = error(high)
    while reached < target_mm and high < _MAX_NOISE_SCALE:
        low, high = high, min(2.0 * high, _MAX_NOISE_SCALE)
        reached, pose, shape = error(high)
    for _ in range(_PA_ITERATIONS):
        if abs(reached - target_mm) <= _PA_TOLERANCE_MM or reached < target_mm:
            break  # close enough, or the largest noise cannot reach it
        middle = 0.5 * (low + high)
        value, middle_pose, middle_shape = error(middle)
        if value >= target_mm:
            high, reached, pose, shape = middle, value, middle_pose, middle_shape
        else:
            low = middle
            if target_mm - value <= _PA_TOLERANCE_MM:
                reached, pose, shape = value, middle_pose, middle_shape
                break
    return pose, shape, float(reached)


def displaced_mesh(vertices: FloatArray, translation: FloatArray, box: FloatArray, k: FloatArray, shift: float,
                   depth: float, rng: np.random.Generator) -> Tuple[FloatArray, FloatArray]:
    """The camera-frame mesh moved along the line of sight (``depth``) and across the image (``shift``).

    The depth error scales the mesh about the camera centre (its projection does not change); then the
    mesh moves parallel to the image plane by the pixel offset shift * (box width cos a, box height sin a)
    at its centroid's depth, for a random angle a. The translation (included in the vertices) moves with
    the mesh.

    Args:
        vertices: (V, 3) vertices in the camera optical frame (metres, z forward).
        translation: (3,) the translation included in ``vertices``.
        box: (>= 4,) the person box x1, y1, x2, y2 the mesh was made for (pixels).
        k: (3, 3) camera matrix.
        shift: placement error as a share of the box.
        depth: depth error as a share of the distance.
        rng: the frame's generator.

    Returns:
        (vertices, translation), float64.
    """
    vertices = np.asarray(vertices, np.float64)
    translation = np.asarray(translation, np.float64)
    if depth > 0.0:
        factor = 1.0 + depth if rng.random() < 0.5 else 1.0 - depth
        vertices, translation = vertices * factor, translation * factor
    if shift > 0.0:
        angle = rng.uniform(0.0, 2.0 * np.pi)
        width, height = float(box[2] - box[0]), float(box[3] - box[1])
        z = float(np.mean(vertices[:, 2]))
        offset = np.array([shift * width * np.cos(angle) * z / k[0, 0],
                           shift * height * np.sin(angle) * z / k[1, 1], 0.0])
        vertices, translation = vertices + offset, translation + offset
    return vertices, translation


def corrupted_boxes(boxes: FloatingArray, image_size: Tuple[int, int], corruption: BoxCorruption,
                    rng: np.random.Generator) -> Float32Array:
    """(N, 5) boxes as a worse detector would give them: missed frames, jitter, grown, truncated, in the image.

    A frame is missed (no box at all) with probability ``miss_share``. Each box is then grown about its centre
    by ``grow`` of its width and height, each side moved by Gaussian noise of ``jitter`` times the box's width
    (left, right) or height (top, bottom), one random side cut by ``truncate`` of the box's size, and clipped
    to the image; a box left smaller than 2 px is dropped. Scores are kept.
    """
    boxes = np.asarray(boxes, np.float32)
    if rng.random() < corruption.miss_share:
        return np.zeros((0, 5), np.float32)
    out = []
    width_px, height_px = image_size
    for row in boxes.astype(np.float64):
        x1, y1, x2, y2 = row[:4]
        w, h = x2 - x1, y2 - y1
        x1, x2 = x1 - 0.5 * corruption.grow * w, x2 + 0.5 * corruption.grow * w
        y1, y2 = y1 - 0.5 * corruption.grow * h, y2 + 0.5 * corruption.grow * h
        w, h = x2 - x1, y2 - y1
        if corruption.jitter > 0.0:
            noise = rng.standard_normal(4) * corruption.jitter
            x1, y1, x2, y2 = x1 + noise[0] * w, y1 + noise[1] * h, x2 + noise[2] * w, y2 + noise[3] * h
        if corruption.truncate > 0.0:
            side = int(rng.integers(4))
            if side == 0:
                x1 += corruption.truncate * w
            elif side == 1:
                x2 -= corruption.truncate * w
            elif side == 2:
                y1 += corruption.truncate * h
            else:
                y2 -= corruption.truncate * h
        x1, x2 = np.clip([min(x1, x2), max(x1, x2)], 0.0, width_px)
        y1, y2 = np.clip([min(y1, y2), max(y1, y2)], 0.0, height_px)
        if x2 - x1 >= _MIN_BOX_PX and y2 - y1 >= _MIN_BOX_PX:
            out.append([x1, y1, x2, y2, row[4]])
    return np.array(out, np.float32).reshape(-1, 5)
