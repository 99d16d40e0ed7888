"""STAND-IN body model in the layout of SMPLX_NEUTRAL.npz in every key: "stand_in_smplx_dense".

This is NOT SMPL-X and makes no accuracy claim. It is the procedural humanoid of
`stand_in_body_model` at resolution "full" (10,475 vertices, 20,908 faces), with the arrays
widened to the real file's layout, so that a loader or an LBS that is right only on the small
stand-in (20 shape columns, diagonal-only pose correctives) fails on it:

- shapedirs (V, 3, 400): columns 0:10 the stand-in's shape directions, 300:310 its expression
  directions; every other column a smooth local bump (a few millimetres) at a different place,
  so that reading the expression from columns 10:20 (or any wrong offset) moves the face.
- posedirs (V, 3, 486): dense in the sense of the real model: every one of the 9 entries of
  (R_k - I) of every joint k = 1..54 drives vertices. Joint k moves its vertices by
  0.1 * w_vk * (R_k - I) r_v, r_v the vertex's offset from its bone axis (the real model's
  correctives are learnt; these are only structured, non-symmetric in (R - I), so a transposed
  pose feature gives a different mesh).
- lmk_faces_idx (51,) / lmk_bary_coords (51, 3): 51 static face landmarks, on faces of the front
  of the head; dynamic_lmk_faces_idx (79, 17) / dynamic_lmk_bary_coords (79, 17, 3): the 17
  contour landmarks for each of the 79 head-yaw bins of `smplx`'s lookup (0..39 degrees one way,
  40..78 the other), on faces along the lower head contour turned by that yaw.
- v_template, f, J_regressor, weights, kintree_table, hands_mean{l,r}, hands_components{l,r}
  as `stand_in_body_model`, plus joint_names and a "stand_in" marker.

The shapes and dtypes of the keys `smplx.create(..., model_type="smplx", ext="npz")` reads
follow `smplx/body_models.py` (SMPL, SMPLH and SMPLX constructors) and the real file.
"""

from __future__ import annotations

from typing import Dict, Tuple

import numpy as np

from leapnbv_common.array_types import FloatArray, GenericArray, Int64Array
from leapnbv_common.atomic_files import write_file_atomically
from leapnbv_stand_ins.stand_in_body_model import HEAD_CENTRE, NUM_JOINTS, ObjectArray, _build

NUM_SHAPE_COLUMNS = 400  # 300 shape + 100 expression, as SMPLX_NEUTRAL.npz
EXPRESSION_OFFSET = 300
NUM_STATIC_LANDMARKS = 51
NUM_DYNAMIC_BINS = 79
NUM_CONTOUR_LANDMARKS = 17
POSE_CORRECTIVE_GAIN = 0.1
STAND_IN_MARKER = "stand-in body model (procedural humanoid) in the SMPL-X npz layout, not SMPL-X; no accuracy claim"


def _bump_columns(vertices: FloatArray, count: int, rng: np.random.Generator) -> FloatArray:
    """(V, 3, count): each column a Gaussian bump (sigma 4 cm, peak 4 mm) at a random vertex."""
    columns = np.zeros((len(vertices), 3, count))
    centres = rng.integers(0, len(vertices) - 1, size=count)
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    for column in range(count):
        distance2 = np.sum((vertices - vertices[centres[column]]) ** 2, axis=1)
        bump = 0.004 * np.exp(-0.5 * distance2 / 0.04**2)
        bump[bump < 1e-5] = 0.0  # local: keeps the file compressible
        columns[:, :, column] = bump[:, None] * directions[column][None]
    return columns


def _dense_pose_directions(weights: FloatArray, radial: FloatArray) -> FloatArray:
    """(V, 3, 486): offset_v = gain * sum_k w_vk (R_k - I) r_v, all nine entries per joint.

    The pose feature is vec(R_k - I) row-major: entry 9 (k - 1) + 3 i + j is (R_k - I)[i, j],
    which adds gain * w_vk * r_v[j] to component i of the offset.
    """
    posedirs = np.zeros((len(weights), 3, (NUM_JOINTS - 1) * 9))
    for joint in range(1, NUM_JOINTS):
        share = POSE_CORRECTIVE_GAIN * weights[:, joint]
        for row in range(3):
            for col in range(3):
                posedirs[:, row, 9 * (joint - 1) + 3 * row + col] = share * radial[:, col]
    return posedirs


def _nearest_faces(face_centres: FloatArray, candidates: Int64Array, points: FloatArray) -> Int64Array:
    distances = np.linalg.norm(face_centres[candidates][None] - points[:, None], axis=2)
    nearest: Int64Array = candidates[np.argmin(distances, axis=1)]
    return nearest


def _landmarks(
    vertices: FloatArray, faces: Int64Array, parts: ObjectArray, rng: np.random.Generator
) -> Dict[str, GenericArray]:
    """Static and dynamic (per yaw bin) face landmarks on faces of the head."""
    face_centres = vertices[faces].mean(axis=1)
    on_head = np.nonzero(np.all(parts[faces] == "head", axis=1))[0]
    front = on_head[face_centres[on_head, 2] > HEAD_CENTRE[2] + 0.04]
    # Static: a 51-point grid over the front of the face (brows, eyes, nose, mouth region).
    grid_x, grid_y = np.meshgrid(np.linspace(-0.045, 0.045, 17), np.linspace(0.6, 0.71, 3))
    targets = np.stack([grid_x.ravel(), grid_y.ravel(), np.full(grid_x.size, HEAD_CENTRE[2] + 0.1)], axis=1)
    static = _nearest_faces(face_centres, front, targets)
    # Dynamic: 17 points on an arc of the lower head (the jaw line), the arc turned by the bin's yaw.
    angles = np.deg2rad(np.linspace(-80.0, 80.0, NUM_CONTOUR_LANDMARKS))
    lower = on_head[face_centres[on_head, 1] < HEAD_CENTRE[1]]
    dynamic = np.zeros((NUM_DYNAMIC_BINS, NUM_CONTOUR_LANDMARKS), dtype=np.int64)
    for row in range(NUM_DYNAMIC_BINS):
        yaw = np.deg2rad(row if row <= 39 else -(row - 39))
        turned = angles + yaw
        arc = np.stack([HEAD_CENTRE[0] + 0.08 * np.sin(turned), np.full(turned.shape, HEAD_CENTRE[1] - 0.06),
                        HEAD_CENTRE[2] + 0.09 * np.cos(turned)], axis=1)
        dynamic[row] = _nearest_faces(face_centres, lower, arc)

    def barycentric(shape: Tuple[int, ...]) -> FloatArray:
        raw = rng.uniform(0.1, 1.0, size=shape + (3,))
        coords: FloatArray = raw / raw.sum(axis=-1, keepdims=True)
        return coords

    return {
        "lmk_faces_idx": static.astype(np.int64),
        "lmk_bary_coords": barycentric((NUM_STATIC_LANDMARKS,)),
        "dynamic_lmk_faces_idx": dynamic,
        "dynamic_lmk_bary_coords": barycentric((NUM_DYNAMIC_BINS, NUM_CONTOUR_LANDMARKS)),
    }


def build_stand_in_smplx_dense() -> Dict[str, GenericArray]:
    """The "stand_in_smplx_dense" arrays (deterministic): every key of SMPLX_NEUTRAL.npz that
    `smplx.create` reads, in its shapes (see the module docstring).

    Returns:
        name -> array: v_template (10475, 3), f (20908, 3), shapedirs (V, 3, 400),
        posedirs (V, 3, 486), J_regressor (55, V), weights (V, 55), kintree_table (2, 55),
        hands_mean{l,r} (45,), hands_components{l,r} (45, 45), lmk_faces_idx (51,),
        lmk_bary_coords (51, 3), dynamic_lmk_faces_idx (79, 17), dynamic_lmk_bary_coords
        (79, 17, 3), joint_names (55,), stand_in (marker).
    """
    arrays, axis_points, parts = _build("full")
    rng = np.random.default_rng(20908)
    vertices = np.asarray(arrays["v_template"], dtype=np.float64)
    usable = (parts != "interior")[:, None]
    radial = (vertices - axis_points) * usable
    small = arrays["shapedirs"]  # (V, 3, 20): 10 shape, 10 expression
    shapedirs = _bump_columns(vertices, NUM_SHAPE_COLUMNS, rng)
    shapedirs[:, :, :10] = small[:, :, :10]
    shapedirs[:, :, EXPRESSION_OFFSET:EXPRESSION_OFFSET + 10] = small[:, :, 10:20]
    dense = dict(arrays)
    # float32 like the loaders use them (half the file; the real file's float64 adds nothing here).
    dense["shapedirs"] = shapedirs.astype(np.float32)
    weights = np.asarray(arrays["weights"], dtype=np.float64)
    dense["posedirs"] = _dense_pose_directions(weights, radial).astype(np.float32)
    dense.update(_landmarks(vertices, arrays["f"].astype(np.int64), parts, rng))
    dense["stand_in"] = np.array(STAND_IN_MARKER)
    return dense


def write_stand_in_smplx_dense(path: str) -> str:
    """Write "stand_in_smplx_dense" with np.savez_compressed (no pickle), atomically; returns path."""
    arrays = build_stand_in_smplx_dense()
    return write_file_atomically(path, lambda temporary: np.savez_compressed(temporary, **arrays))
