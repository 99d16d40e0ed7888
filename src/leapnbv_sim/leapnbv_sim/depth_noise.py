"""A RealSense-like depth noise model.

Depth-squared Gaussian noise, edge dropouts, range limits (docs/ALGORITHMS.md §9).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from leapnbv_common.array_types import BoolArray, Float32Array, FloatingArray, UInt16Array


@dataclass(frozen=True)
class DepthNoiseConfig:
    """Parameters of :func:`apply_depth_noise`.

    The axial noise of an active stereo camera grows with the square of the depth:
    ``sigma(z) = sigma_quadratic_per_m * z^2 + sigma_constant_m``. For a D435-class camera
    (subpixel 0.08, baseline 50 mm, focal ~615 px) ``0.08 / (615 * 0.05) ~ 0.0026 / m``, i.e.
    about 2.3 cm at 3 m.

    Attributes:
        sigma_quadratic_per_m: Coefficient a of a * z^2 (1/m).
        sigma_constant_m: Constant noise floor b (m).
        edge_jump_m: A pixel is a depth edge when a 4-neighbour differs by more than this (m),
            or when a neighbour has no return.
        edge_dropout_probability: Chance that an edge pixel returns nothing (stereo matching
            fails at occlusion boundaries).
        random_dropout_probability: Chance that any pixel returns nothing.
        min_depth_m: Nearer returns are dropped (the camera's minimum Z).
        max_depth_m: Farther returns are dropped.
    """

    sigma_quadratic_per_m: float = 0.0026
    sigma_constant_m: float = 0.0005
    edge_jump_m: float = 0.10
    edge_dropout_probability: float = 0.5
    random_dropout_probability: float = 0.002
    min_depth_m: float = 0.28
    max_depth_m: float = 10.0


def depth_edge_mask(depth_m: FloatingArray, jump_m: float) -> BoolArray:
    """Pixels at a depth discontinuity (a 4-neighbour differs by > jump_m, or has no return).

    Args:
        depth_m: (H,W) float depth in metres, 0 = no return.
        jump_m: Discontinuity threshold in metres.

    Returns:
        (H,W) bool mask of edge pixels that themselves have a return.
    """
    depth = np.asarray(depth_m, dtype=np.float32)
    valid = depth > 0
    edges = np.zeros(depth.shape, dtype=bool)
    # Compare each pixel with its right and lower neighbour and mark both sides of a jump.
    horizontal = (np.abs(depth[:, 1:] - depth[:, :-1]) > jump_m) | (valid[:, 1:] != valid[:, :-1])
    vertical = (np.abs(depth[1:, :] - depth[:-1, :]) > jump_m) | (valid[1:, :] != valid[:-1, :])
    edges[:, 1:] |= horizontal
    edges[:, :-1] |= horizontal
    edges[1:, :] |= vertical
    edges[:-1, :] |= vertical
    return edges & valid


def apply_depth_noise(
    depth_m: Float32Array,
    seed: int,
    config: Optional[DepthNoiseConfig] = None,
) -> Float32Array:
    """Corrupt an ideal depth image like an active stereo camera would; deterministic for a seed.

    Args:
        depth_m: (H,W) float ideal depth in metres (camera z), 0 = no return.
        seed: Seed of the noise (same seed and input -> identical output).
        config: Noise parameters; defaults if None.

    Returns:
        (H,W) float32 noisy depth in metres, 0 where the camera returns nothing.

    Raises:
        ValueError: depth_m is not 2-D.
    """
    depth = np.asarray(depth_m, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth_m must be (H,W), got shape {depth.shape}")
    cfg = config if config is not None else DepthNoiseConfig()
    rng = np.random.default_rng(seed)
    valid = depth > 0
    sigma = cfg.sigma_quadratic_per_m * depth * depth + cfg.sigma_constant_m
    noisy = depth + sigma * rng.standard_normal(depth.shape, dtype=np.float32)
    edges = depth_edge_mask(depth, cfg.edge_jump_m)
    uniform = rng.random(depth.shape, dtype=np.float32)
    dropped = (edges & (uniform < cfg.edge_dropout_probability)) | (
        rng.random(depth.shape, dtype=np.float32) < cfg.random_dropout_probability
    )
    keep = valid & ~dropped & (noisy >= cfg.min_depth_m) & (noisy <= cfg.max_depth_m)
    return np.where(keep, noisy, 0.0).astype(np.float32)


def depth_m_to_mm(depth_m: FloatingArray) -> UInt16Array:
    """Convert metres to the camera's uint16 millimetres (rounded; 0 stays 0; clipped to 65535).

    Args:
        depth_m: (H,W) float depth in metres, 0 = no return.

    Returns:
        (H,W) uint16 depth in millimetres.
    """
    millimetres = np.rint(np.asarray(depth_m, dtype=np.float64) * 1000.0)
    depth_mm: UInt16Array = np.clip(millimetres, 0, 65535).astype(np.uint16)
    return depth_mm
