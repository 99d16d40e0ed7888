"""Procrustes alignment and PA-MPVPE: a body mesh's error once scale, rotation and translation are out.

The body-mesh error the evaluation reports, and the one the ground truth's pose-and-shape corruption aims at.
"""

from __future__ import annotations

import numpy as np

from leapnbv_common.array_types import FloatArray

__all__ = ["procrustes_align", "pa_mpvpe_mm"]


def procrustes_align(pred: FloatArray, gt: FloatArray) -> FloatArray:
    """Similarity-align pred to gt: argmin over s, R, t of sum |s R pred_i + t - gt_i|^2.

    Umeyama's closed form: with centred X = pred - mean, Y = gt - mean and
    ``U S V^T = svd(X^T Y)``, ``R = V D U^T`` where ``D = diag(1, 1, sign(det(V U^T)))``
    keeps R a proper rotation (no reflection), ``s = trace(S D) / |X|^2`` and
    ``t = mean_gt - s R mean_pred``.

    Args:
        pred: (V,3) predicted vertices.
        gt: (V,3) ground-truth vertices (same order).

    Returns:
        (V,3) aligned prediction.

    Raises:
        ValueError: Shapes differ or are not (V,3), or pred is degenerate (all one point).
    """
    X = np.asarray(pred, dtype=np.float64)
    Y = np.asarray(gt, dtype=np.float64)
    if X.shape != Y.shape or X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"pred {X.shape} and gt {Y.shape} must both be (V,3)")
    mean_x = X.mean(axis=0)
    mean_y = Y.mean(axis=0)
    Xc = X - mean_x
    Yc = Y - mean_y
    variance_x = float(np.sum(Xc * Xc))
    if variance_x <= 0.0:
        raise ValueError("pred is degenerate (all vertices coincide)")
    U, S, Vt = np.linalg.svd(Xc.T @ Yc)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ D @ U.T
    scale = float(np.sum(S * np.diag(D))) / variance_x
    t = mean_y - scale * (R @ mean_x)
    aligned: FloatArray = scale * (X @ R.T) + t
    return aligned


def pa_mpvpe_mm(pred: FloatArray, gt: FloatArray) -> float:
    """PA-MPVPE: mean per-vertex distance after Procrustes alignment (scale, rotation, translation).

    Args:
        pred: (V,3) predicted vertices, metres.
        gt: (V,3) ground-truth vertices, metres, same vertex order.

    Returns:
        Millimetres.
    """
    aligned = procrustes_align(pred, gt)
    return float(np.mean(np.linalg.norm(aligned - np.asarray(gt, dtype=np.float64), axis=1)) * 1000.0)
