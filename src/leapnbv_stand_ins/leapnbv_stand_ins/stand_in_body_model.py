"""STAND-IN body model: a procedural humanoid written in the exact SMPL-X .npz layout.

This is NOT SMPL-X and makes no accuracy claim. It exists so that the real SMPL-X loader,
LBS, rasterizer and simulator run without the licensed SMPL-X files. It has the same keys,
the same 55 joints and kinematic tree, and (at resolution "full") exactly the vertex and face
counts of SMPLX_NEUTRAL.npz.

Geometry (metres, y up, facing +z, pelvis at the origin, T-pose, about 1.75 m tall): ten
closed triangle surfaces, each skinned along its chain of joints:

- torso: an elliptic tube from below the pelvis up through the spine joints and the neck;
- head: an ellipsoid (its lower front blends to the jaw joint), two eyeballs;
- legs: tubes from inside the pelvis through hip, knee, ankle, bending forward into a foot;
- arms: tubes from inside the chest through collar, shoulder, elbow, wrist, flattening into
  a palm whose end splits into four finger tubes (one closed surface per arm and hand);
- thumbs: closed tubes from inside the palm.

Every surface is closed and consistently oriented (outward normals). Ten closed genus-0
surfaces give V - F/2 = 20; the real counts (10,475 and 20,908) have V - F/2 = 21, so one
extra vertex (the last one) sits at the pelvis joint and is used by no face.

Other arrays:
- weights: piecewise by bone along each chain, blended with a smoothstep across each joint;
- J_regressor: per joint, Gaussian weights on the nearest vertices of the parts it moves,
  corrected (least squares) so rows sum to 1 and reproduce the rest joint exactly; so the
  joints follow the betas;
- shapedirs: 10 shape directions (height, girth, leg length, shoulder width, belly, arm
  length, head size, hip width, chest depth, upper-body length) and 10 expression
  directions (smooth bumps on the face: mouth open, smile, cheeks, brows, ...);
- posedirs: a small corrective bulge. For each joint only the diagonal entries of (R - I)
  are used: vertices in the joint's blend zone move outward from the bone axis by
  0.15 * blend * r * (1 - cos angle) / 2, i.e. at most 7.5 % of the local radius at 90 deg;
- hands_meanl/r: a gentle finger curl (mirrored between hands); hands_componentsl/r:
  identity (the PCA hand space is unused, SMPLer-X predicts full hand poses).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
from numpy.typing import NDArray

from leapnbv_common.array_types import BoolArray, FloatArray, GenericArray, Int64Array, IntArray
from leapnbv_common.atomic_files import write_file_atomically

# Per-vertex part names ("torso", "arm", ...): numpy object arrays of str.
ObjectArray = NDArray[np.object_]

NUM_JOINTS = 55
SMPLX_PARENTS = (
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15,
    20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38,
    21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53,
)
JOINT_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "jaw", "left_eye", "right_eye",
    "left_index1", "left_index2", "left_index3", "left_middle1", "left_middle2", "left_middle3",
    "left_pinky1", "left_pinky2", "left_pinky3", "left_ring1", "left_ring2", "left_ring3",
    "left_thumb1", "left_thumb2", "left_thumb3",
    "right_index1", "right_index2", "right_index3", "right_middle1", "right_middle2",
    "right_middle3", "right_pinky1", "right_pinky2", "right_pinky3", "right_ring1",
    "right_ring2", "right_ring3", "right_thumb1", "right_thumb2", "right_thumb3",
)
ROOT_PARENT_UINT32 = 4294967295
FULL_NUM_VERTICES = 10475  # the real SMPL-X counts, matched at resolution "full"
FULL_NUM_FACES = 20908

# Finger chains per hand in SMPL-X joint order (first joint of each finger, relative).
_LEFT_FINGER_FIRST = {"index": 25, "middle": 28, "pinky": 31, "ring": 34}
_LEFT_THUMB_FIRST = 37
_RIGHT_OFFSET = 15  # right-hand joint = left-hand joint + 15
# Fingers across the palm from the thumb side; segment lengths (m) 1->2, 2->3, 3->tip.
_FINGER_ORDER = ("index", "middle", "ring", "pinky")
_FINGER_SEGMENTS = {
    "index": (0.040, 0.025, 0.022),
    "middle": (0.045, 0.028, 0.024),
    "ring": (0.042, 0.026, 0.022),
    "pinky": (0.032, 0.020, 0.020),
}
_FINGER_SETBACK = {"index": 0.0, "middle": 0.003, "ring": 0.0, "pinky": -0.008}


@dataclass
class _Resolution:
    """Segments around (S) and rings along (R) each part."""

    palm_split: int  # m: each finger loop has 2m + 2 vertices, arm rings 8m + 2
    arm_rings: int
    finger_rings: int
    leg_segments: int
    leg_rings: int
    thumb_segments: int
    thumb_rings: int
    eye_segments: int
    eye_rings: int
    torso_segments: int
    torso_rings: int
    head_segments: int
    head_rings: int


_SMALL = _Resolution(3, 16, 4, 16, 20, 8, 5, 8, 4, 24, 22, 20, 14)
_FULL_BASE = _Resolution(4, 30, 8, 32, 45, 10, 10, 12, 6, 48, 50, 48, 44)


def _smoothstep(values: FloatArray) -> FloatArray:
    clipped = np.clip(values, 0.0, 1.0)
    return clipped * clipped * (3.0 - 2.0 * clipped)


def _normalize(vector: FloatArray) -> FloatArray:
    unit: FloatArray = vector / np.linalg.norm(vector, axis=-1, keepdims=True)
    return unit


@dataclass
class _Chain:
    """A polyline through joints with the joint owning each segment.

    Attributes:
        points: (P, 3) polyline.
        owners: (P-1,) joint index moving each segment.
        radii: (P, 2) half-widths (along e1, e2) at each point, interpolated by arc length.
        up: reference vector fixing the ring frame (e1 = up made orthogonal to the tangent).
        blend: half-width (m) of the weight blend across a point where the owner changes.
    """

    points: FloatArray
    owners: Sequence[int]
    radii: FloatArray
    up: FloatArray
    blend: float = 0.03
    arc: FloatArray = field(init=False)

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float64)
        self.radii = np.asarray(self.radii, dtype=np.float64)
        lengths = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        self.arc = np.concatenate([[0.0], np.cumsum(lengths)])

    @property
    def length(self) -> float:
        return float(self.arc[-1])

    def _blend_fractions(self, s: FloatArray) -> FloatArray:
        """(N, P-1) share of each segment at arc lengths s (smooth across interior points)."""
        segments = len(self.points) - 1
        lengths = np.diff(self.arc)
        # sigma_k: how far past interior point k the sample is, smoothly, 0..1.
        sigma = np.ones((s.shape[0], segments + 1))
        sigma[:, segments] = 0.0
        for k in range(1, segments):
            half = max(min(self.blend, 0.45 * lengths[k - 1], 0.45 * lengths[k]), 1e-6)
            sigma[:, k] = _smoothstep((s - self.arc[k] + half) / (2.0 * half))
        return sigma[:, :-1] - sigma[:, 1:]

    def centre_and_tangent(self, s: FloatArray) -> Tuple[FloatArray, FloatArray]:
        """Centres (N, 3) on the polyline and smoothed tangents (N, 3) at arc lengths s."""
        s = np.clip(s, 0.0, self.length)
        centres = np.stack([np.interp(s, self.arc, self.points[:, axis]) for axis in range(3)], axis=1)
        directions = _normalize(np.diff(self.points, axis=0))
        tangents = _normalize(self._blend_fractions(s) @ directions)
        return centres, tangents

    def half_widths(self, s: FloatArray) -> FloatArray:
        return np.stack([np.interp(s, self.arc, self.radii[:, axis]) for axis in range(2)], axis=1)

    def frames(self, tangents: FloatArray) -> Tuple[FloatArray, FloatArray]:
        e1 = _normalize(self.up[None] - (tangents @ self.up)[:, None] * tangents)
        e2 = np.cross(tangents, e1)
        return e1, e2

    def weights(self, s: FloatArray) -> FloatArray:
        """(N, 55) skinning weights at arc lengths s."""
        fractions = self._blend_fractions(np.clip(s, 0.0, self.length))
        result = np.zeros((s.shape[0], NUM_JOINTS))
        for segment, owner in enumerate(self.owners):
            result[:, owner] += fractions[:, segment]
        return result


class _MeshBuilder:
    """Accumulates vertices, faces, weights and per-vertex bookkeeping of all parts."""

    def __init__(self) -> None:
        self.vertices: List[FloatArray] = []
        self.faces: List[Int64Array] = []
        self.weights: List[FloatArray] = []
        self.axis_points: List[FloatArray] = []
        self.parts: List[ObjectArray] = []
        self.count = 0
        self.component_faces: List[Tuple[int, int]] = []

    def add_vertices(self, vertices: FloatArray, weights: FloatArray, axis_points: FloatArray, part: str) -> Int64Array:
        indices = np.arange(self.count, self.count + len(vertices))
        self.vertices.append(vertices)
        self.weights.append(weights)
        self.axis_points.append(axis_points)
        self.parts.append(np.array([part] * len(vertices), dtype=object))
        self.count += len(vertices)
        return indices

    def add_faces(self, faces: IntArray) -> None:
        self.faces.append(np.asarray(faces, dtype=np.int64).reshape(-1, 3))

    def arrays(self) -> Tuple[FloatArray, Int64Array, FloatArray, FloatArray, ObjectArray]:
        return (
            np.concatenate(self.vertices),
            np.concatenate(self.faces),
            np.concatenate(self.weights),
            np.concatenate(self.axis_points),
            np.concatenate(self.parts),
        )


def _strip(ring_a: Int64Array, ring_b: Int64Array) -> Int64Array:
    """Two triangles per quad between two rings of equal size (a -> b along the tube)."""
    a0 = ring_a
    a1 = np.roll(ring_a, -1)
    b0 = ring_b
    b1 = np.roll(ring_b, -1)
    return np.concatenate([np.stack([a0, a1, b1], axis=1), np.stack([a0, b1, b0], axis=1)])


def _fan(ring: Int64Array, pole: int, at_start: bool) -> Int64Array:
    """Triangles closing a ring with a pole (outward for a CCW ring)."""
    nxt = np.roll(ring, -1)
    poles = np.full_like(ring, pole)
    if at_start:
        return np.stack([poles, nxt, ring], axis=1)
    return np.stack([ring, nxt, poles], axis=1)


def _ring_angles(segments: int) -> FloatArray:
    return (np.arange(segments) + 0.5) * 2.0 * np.pi / segments


def _cap_taper(s: FloatArray, length: float, cap_start: float, cap_end: float) -> FloatArray:
    """Radius factor rounding the ends into hemispheres of the given lengths."""
    factor = np.ones_like(s)
    if cap_start > 0.0:
        d = np.clip(s / cap_start, 0.0, 1.0)
        factor = np.minimum(factor, np.sqrt(np.clip(1.0 - (1.0 - d) ** 2, 0.0, 1.0)))
    if cap_end > 0.0:
        d = np.clip((length - s) / cap_end, 0.0, 1.0)
        factor = np.minimum(factor, np.sqrt(np.clip(1.0 - (1.0 - d) ** 2, 0.0, 1.0)))
    return factor


def _add_closed_tube(
    builder: _MeshBuilder,
    chain: _Chain,
    segments: int,
    rings: int,
    part: str,
    cap_fraction: float = 1.0,
) -> None:
    """A tube along the chain with pole caps at both ends (closed, genus 0)."""
    s = chain.length * (np.arange(rings) + 0.5) / rings
    centres, tangents = chain.centre_and_tangent(s)
    e1, e2 = chain.frames(tangents)
    radii = chain.half_widths(s)
    taper = _cap_taper(s, chain.length, cap_fraction * radii[0].max(), cap_fraction * radii[-1].max())
    angles = _ring_angles(segments)
    offsets_1 = (radii[:, 0] * taper)[:, None] * np.cos(angles)[None]
    offsets_2 = (radii[:, 1] * taper)[:, None] * np.sin(angles)[None]
    ring_points = centres[:, None] + offsets_1[..., None] * e1[:, None] + offsets_2[..., None] * e2[:, None]
    weights = np.repeat(chain.weights(s), segments, axis=0)
    ring_ids = builder.add_vertices(
        ring_points.reshape(-1, 3), weights, np.repeat(centres, segments, axis=0), part
    ).reshape(rings, segments)
    poles_s = np.array([0.0, chain.length])
    pole_points = chain.points[[0, -1]]
    pole_ids = builder.add_vertices(pole_points, chain.weights(poles_s), pole_points, part)
    faces = [_fan(ring_ids[0], pole_ids[0], True)]
    faces += [_strip(ring_ids[i], ring_ids[i + 1]) for i in range(rings - 1)]
    faces.append(_fan(ring_ids[-1], pole_ids[1], False))
    builder.add_faces(np.concatenate(faces))


def _add_ellipsoid(
    builder: _MeshBuilder,
    centre: FloatArray,
    radii: FloatArray,
    segments: int,
    rings: int,
    weight_fn: Callable[[FloatArray], FloatArray],
    part: str,
) -> None:
    """A UV ellipsoid (poles on the y axis), skinned by weight_fn(points) -> (N, 55)."""
    chain = _Chain(
        points=np.array([centre - [0.0, radii[1], 0.0], centre + [0.0, radii[1], 0.0]]),
        owners=[0],
        radii=np.array([[radii[0], radii[2]], [radii[0], radii[2]]]),
        up=np.array([1.0, 0.0, 0.0]),
    )
    polar = np.pi * (np.arange(rings) + 0.5) / rings  # from the bottom pole up
    s = chain.length * (1.0 - np.cos(polar)) / 2.0
    centres, tangents = chain.centre_and_tangent(s)
    e1, e2 = chain.frames(tangents)
    angles = _ring_angles(segments)
    sin_polar = np.sin(polar)
    ring_points = (
        centres[:, None]
        + (radii[0] * sin_polar)[:, None, None] * np.cos(angles)[None, :, None] * e1[:, None]
        + (radii[2] * sin_polar)[:, None, None] * np.sin(angles)[None, :, None] * e2[:, None]
    ).reshape(-1, 3)
    pole_points = chain.points.copy()
    points = np.concatenate([ring_points, pole_points])
    ids = builder.add_vertices(points, weight_fn(points), np.repeat(centre[None], len(points), axis=0), part)
    ring_ids = ids[: rings * segments].reshape(rings, segments)
    faces = [_fan(ring_ids[0], ids[-2], True)]
    faces += [_strip(ring_ids[i], ring_ids[i + 1]) for i in range(rings - 1)]
    faces.append(_fan(ring_ids[-1], ids[-1], False))
    builder.add_faces(np.concatenate(faces))


def _mirror(point: Union[Sequence[float], FloatArray]) -> FloatArray:
    return np.array([-point[0], point[1], point[2]], dtype=np.float64)


def _side(point: Sequence[float], left: bool) -> FloatArray:
    array = np.asarray(point, dtype=np.float64)
    return array if left else _mirror(array)


def _add_arm_with_hand(
    builder: _MeshBuilder, joints: FloatArray, left: bool, resolution: _Resolution, part_suffix: str
) -> None:
    """Arm tube (cap in the chest) flattening into a palm whose end splits into 4 fingers.

    Finger joints (index/middle/ring/pinky 1..3) are written into `joints` from the
    geometry of the palm end.
    """
    wrist = joints[20 if left else 21]
    collar = joints[13 if left else 14]
    shoulder = joints[16 if left else 17]
    elbow = joints[18 if left else 19]
    palm_end = _side([0.765, 0.425, 0.0], left)
    start = _side([0.03, 0.415, -0.01], left)
    chain = _Chain(
        points=np.array([start, collar, shoulder, elbow, wrist, palm_end]),
        owners=[9, 13 if left else 14, 16 if left else 17, 18 if left else 19, 20 if left else 21],
        radii=np.array([[0.05, 0.05], [0.055, 0.055], [0.052, 0.05], [0.038, 0.036], [0.028, 0.022], [0.044, 0.013]]),
        up=np.array([0.0, 0.0, 1.0]),
        blend=0.03,
    )
    m = resolution.palm_split
    n = 4 * m
    segments = 2 * n + 2
    rings = resolution.arm_rings
    s = chain.length * (np.arange(rings) + 0.5) / (rings - 0.5)  # last ring exactly at the palm end
    centres, tangents = chain.centre_and_tangent(s)
    e1, e2 = chain.frames(tangents)
    radii = chain.half_widths(s)
    angles = _ring_angles(segments)
    round_offsets = np.stack([np.cos(angles), np.sin(angles)], axis=1)  # (S, 2) unit circle
    # Flat palm section: rows evenly spaced across the width, rounded edges.
    u_top = 1.0 - 2.0 * np.arange(n + 1) / n
    u_bottom = -u_top
    flat = np.concatenate(
        [
            np.stack([u_top, np.sqrt(1.0 - 0.6 * u_top**2)], axis=1),
            np.stack([u_bottom, -np.sqrt(1.0 - 0.6 * u_bottom**2)], axis=1),
        ]
    )
    wrist_s = chain.arc[4]
    flatness = _smoothstep((s - wrist_s) / (0.45 * (chain.length - wrist_s)))
    taper = _cap_taper(s, chain.length, radii[0].max(), 0.0)
    unit = (1.0 - flatness)[:, None, None] * round_offsets[None] + flatness[:, None, None] * flat[None]
    offsets = unit * (radii * taper[:, None])[:, None, :]
    ring_points = centres[:, None] + offsets[..., 0:1] * e1[:, None] + offsets[..., 1:2] * e2[:, None]
    weights = np.repeat(chain.weights(s), segments, axis=0)
    part = "arm" + part_suffix
    ring_ids = builder.add_vertices(
        ring_points.reshape(-1, 3), weights, np.repeat(centres, segments, axis=0), part
    ).reshape(rings, segments)
    pole_ids = builder.add_vertices(chain.points[:1], chain.weights(np.array([0.0])), chain.points[:1], part)
    faces = [_fan(ring_ids[0], pole_ids[0], True)]
    faces += [_strip(ring_ids[i], ring_ids[i + 1]) for i in range(rings - 1)]
    builder.add_faces(np.concatenate(faces))

    end_ring = ring_ids[-1]
    end_points = ring_points[-1]
    axis = tangents[-1]
    wrist_joint = 20 if left else 21
    for k, finger in enumerate(_FINGER_ORDER):
        loop_local = list(range(k * m, (k + 1) * m + 1)) + list(range(2 * n + 1 - (k + 1) * m, 2 * n + 2 - k * m))
        loop_ids = end_ring[loop_local]
        loop_points = end_points[loop_local]
        base = loop_points.mean(axis=0)
        first = _LEFT_FINGER_FIRST[finger] + (0 if left else _RIGHT_OFFSET)
        lengths = _FINGER_SEGMENTS[finger]
        knuckle = base + axis * (0.012 + _FINGER_SETBACK[finger])
        finger_points = [base, knuckle]
        for length in lengths:
            finger_points.append(finger_points[-1] + axis * length)
        joints[first] = finger_points[1]
        joints[first + 1] = finger_points[2]
        joints[first + 2] = finger_points[3]
        finger_chain = _Chain(
            points=np.array(finger_points),
            owners=[wrist_joint, first, first + 1, first + 2],
            radii=np.array([[0.0095, 0.0095], [0.0092, 0.0092], [0.0085, 0.0085], [0.0078, 0.0078], [0.0072, 0.0072]]),
            up=chain.up,
            blend=0.008,
        )
        _add_finger(builder, finger_chain, loop_ids, loop_points, resolution.finger_rings, part)


def _add_finger(
    builder: _MeshBuilder,
    chain: _Chain,
    loop_ids: Int64Array,
    loop_points: FloatArray,
    rings: int,
    part: str,
) -> None:
    """A finger tube growing out of a loop of palm-end vertices, closed by a tip pole."""
    s0 = 0.6 * chain.arc[1]
    s = s0 + (chain.length - s0) * (np.arange(rings) + 1.0) / (rings + 0.5)
    centres, tangents = chain.centre_and_tangent(s)
    radii = chain.half_widths(s)[:, 0] * _cap_taper(s, chain.length, 0.0, 0.8 * chain.radii[-1, 0])
    # Each ring vertex keeps the direction its loop vertex has from the loop centre.
    directions = loop_points - loop_points.mean(axis=0)
    points = []
    for centre, tangent, radius in zip(centres, tangents, radii):
        projected = directions - (directions @ tangent)[:, None] * tangent
        points.append(centre + radius * _normalize(projected))
    points_array = np.concatenate(points)
    segments = len(loop_ids)
    ring_ids = builder.add_vertices(
        points_array, np.repeat(chain.weights(s), segments, axis=0), np.repeat(centres, segments, axis=0), part
    ).reshape(rings, segments)
    tip = chain.points[-1:]
    tip_id = builder.add_vertices(tip, chain.weights(np.array([chain.length])), tip, part)[0]
    faces = [_strip(loop_ids, ring_ids[0])]
    faces += [_strip(ring_ids[i], ring_ids[i + 1]) for i in range(rings - 1)]
    faces.append(_fan(ring_ids[-1], tip_id, False))
    builder.add_faces(np.concatenate(faces))


def _rest_joints() -> FloatArray:
    """Rest joint locations of the body joints (fingers are set from the palm geometry)."""
    joints = np.zeros((NUM_JOINTS, 3))
    body = {
        0: [0.0, 0.0, 0.0],
        3: [0.0, 0.11, -0.015],
        6: [0.0, 0.24, -0.005],
        9: [0.0, 0.30, 0.0],
        12: [0.0, 0.50, -0.02],
        15: [0.0, 0.58, 0.005],
        22: [0.0, 0.615, 0.03],
    }
    sides = {
        1: [0.085, -0.09, 0.0],
        4: [0.10, -0.50, 0.01],
        7: [0.105, -0.90, -0.03],
        10: [0.115, -0.955, 0.09],
        13: [0.075, 0.42, -0.01],
        16: [0.18, 0.44, -0.02],
        18: [0.44, 0.43, -0.03],
        20: [0.69, 0.43, -0.02],
        23: [0.032, 0.675, 0.088],
    }
    for index, point in body.items():
        joints[index] = point
    for index, point in sides.items():
        joints[index] = point
        joints[index + 1] = _mirror(point)
    thumb = [[0.71, 0.42, 0.025], [0.735, 0.415, 0.05], [0.76, 0.412, 0.065]]
    for offset, point in enumerate(thumb):
        joints[_LEFT_THUMB_FIRST + offset] = point
        joints[_LEFT_THUMB_FIRST + _RIGHT_OFFSET + offset] = _mirror(point)
    return joints


HEAD_CENTRE = np.array([0.0, 0.665, 0.015])
HEAD_RADII = np.array([0.078, 0.1, 0.095])


def _build_surfaces(resolution: _Resolution) -> Tuple[_MeshBuilder, FloatArray]:
    joints = _rest_joints()
    builder = _MeshBuilder()

    torso = _Chain(
        points=np.array(
            [[0.0, -0.15, 0.0], joints[0], joints[3], joints[6], joints[9], [0.0, 0.43, -0.015], joints[12], joints[15]]
        ),
        owners=[0, 0, 3, 6, 9, 9, 12],
        radii=np.array(
            [[0.13, 0.10], [0.165, 0.11], [0.15, 0.10], [0.155, 0.105], [0.17, 0.11], [0.16, 0.095],
             [0.055, 0.055], [0.05, 0.05]]
        ),
        up=np.array([1.0, 0.0, 0.0]),
        blend=0.05,
    )
    _add_closed_tube(builder, torso, resolution.torso_segments, resolution.torso_rings, "torso", cap_fraction=0.5)

    def head_weights(points: FloatArray) -> FloatArray:
        weights = np.zeros((len(points), NUM_JOINTS))
        jaw = _smoothstep((0.64 - points[:, 1]) / 0.04) * _smoothstep((points[:, 2] - 0.0) / 0.04)
        weights[:, 22] = jaw
        weights[:, 15] = 1.0 - jaw
        return weights

    _add_ellipsoid(
        builder, HEAD_CENTRE, HEAD_RADII, resolution.head_segments, resolution.head_rings, head_weights, "head"
    )
    for eye in (23, 24):
        def eye_weights(points: FloatArray, joint: int = eye) -> FloatArray:
            weights = np.zeros((len(points), NUM_JOINTS))
            weights[:, joint] = 1.0
            return weights

        _add_ellipsoid(
            builder, joints[eye], np.full(3, 0.0125), resolution.eye_segments, resolution.eye_rings, eye_weights, "eye"
        )

    for left in (True, False):
        offset = 0 if left else 1
        leg = _Chain(
            points=np.array(
                [_side([0.085, 0.0, 0.0], left), joints[1 + offset], joints[4 + offset], joints[7 + offset],
                 joints[10 + offset], _side([0.12, -0.96, 0.16], left)]
            ),
            owners=[0, 1 + offset, 4 + offset, 7 + offset, 10 + offset],
            radii=np.array([[0.08, 0.08], [0.085, 0.085], [0.05, 0.052], [0.036, 0.04], [0.045, 0.028], [0.038, 0.02]]),
            up=np.array([1.0, 0.0, 0.0]),
            blend=0.04,
        )
        _add_closed_tube(builder, leg, resolution.leg_segments, resolution.leg_rings, "leg", cap_fraction=0.6)

    for left in (True, False):
        _add_arm_with_hand(builder, joints, left, resolution, "")
        first = _LEFT_THUMB_FIRST + (0 if left else _RIGHT_OFFSET)
        thumb = _Chain(
            points=np.array(
                [_side([0.70, 0.425, 0.0], left), joints[first], joints[first + 1], joints[first + 2],
                 _side([0.782, 0.41, 0.075], left)]
            ),
            owners=[20 if left else 21, first, first + 1, first + 2],
            radii=np.array([[0.013, 0.012], [0.0125, 0.0115], [0.0105, 0.0095], [0.0092, 0.0085], [0.008, 0.0075]]),
            up=np.array([0.0, 1.0, 0.0]),
            blend=0.008,
        )
        _add_closed_tube(builder, thumb, resolution.thumb_segments, resolution.thumb_rings, "thumb", cap_fraction=0.8)
    return builder, joints


def _face_count(resolution: _Resolution) -> int:
    """Faces the surfaces will have at this resolution (see the module docstring)."""
    m = resolution.palm_split
    arm_segments = 8 * m + 2
    loop = 2 * m + 2
    arm = arm_segments * (2 * resolution.arm_rings - 1) + 4 * loop * (2 * resolution.finger_rings + 1)
    closed = (
        resolution.torso_segments * resolution.torso_rings
        + resolution.head_segments * resolution.head_rings
        + 2 * resolution.leg_segments * resolution.leg_rings
        + 2 * resolution.thumb_segments * resolution.thumb_rings
        + 2 * resolution.eye_segments * resolution.eye_rings
    )
    return 2 * (closed + arm)


def _full_resolution() -> _Resolution:
    """Adjust torso and head ring counts so the faces are exactly 20,908."""
    base = _FULL_BASE
    others = _face_count(replace(base, torso_rings=0, head_rings=0))
    remainder = FULL_NUM_FACES // 2 - others // 2
    best: Optional[Tuple[int, int, int]] = None
    for torso_rings in range(base.torso_rings - 15, base.torso_rings + 16):
        for head_segments in range(base.head_segments - 8, base.head_segments + 9):
            rest = remainder - base.torso_segments * torso_rings
            if rest > 0 and rest % head_segments == 0:
                head_rings = rest // head_segments
                cost = abs(torso_rings - base.torso_rings) + abs(head_rings - base.head_rings)
                if 20 <= head_rings <= 80 and (best is None or cost < best[0]):
                    best = (cost, torso_rings, head_segments * 1000 + head_rings)
    if best is None:
        raise RuntimeError("no torso/head ring counts give %d faces" % FULL_NUM_FACES)
    head_segments, head_rings = divmod(best[2], 1000)
    return replace(base, torso_rings=best[1], head_segments=head_segments, head_rings=head_rings)


def _joint_regressor(vertices: FloatArray, weights: FloatArray, joints: FloatArray, usable: BoolArray) -> FloatArray:
    """(55, V): rows sum to 1 and reproduce the rest joints from nearby vertices."""
    regressor = np.zeros((NUM_JOINTS, len(vertices)))
    for joint in range(NUM_JOINTS):
        parent = SMPLX_PARENTS[joint]
        related = weights[:, joint] > 0.05
        if parent >= 0:
            related |= weights[:, parent] > 0.05
        candidates = np.nonzero(related & usable)[0]
        distances = np.linalg.norm(vertices[candidates] - joints[joint], axis=1)
        order = candidates[np.argsort(distances)]
        best_row: Optional[FloatArray] = None
        best_nearest = order[:0]
        # Grow the neighbourhood until the joint sits inside it (no strongly negative weight).
        for count in (48, 96, 192, 384, 768, 1536):
            nearest = order[:count]
            near_distances = np.linalg.norm(vertices[nearest] - joints[joint], axis=1)
            sigma = max(float(np.median(near_distances)), 1e-4)
            prior = np.exp(-0.5 * (near_distances / sigma) ** 2)
            prior /= prior.sum()
            # Smallest change to the prior with sum w = 1 and sum w_i v_i = joint (exact).
            constraints = np.vstack([np.ones(len(nearest)), vertices[nearest].T])
            target = np.concatenate([[1.0], joints[joint]])
            row = prior + np.linalg.pinv(constraints) @ (target - constraints @ prior)
            if best_row is None or row.min() > best_row.min():
                best_row, best_nearest = row, nearest
            if row.min() > -0.02 or count >= len(order):
                break
        regressor[joint, best_nearest] = best_row
    return regressor


def _shape_directions(vertices: FloatArray, axis_points: FloatArray, parts: ObjectArray) -> FloatArray:
    """(V, 3, 20): 10 shape then 10 expression directions (metres per unit coefficient)."""
    x, y, z = vertices[:, 0], vertices[:, 1], vertices[:, 2]
    radial = vertices - axis_points
    dirs = np.zeros((len(vertices), 3, 20))
    is_arm = np.isin(parts, ["arm", "thumb"])
    is_head = np.isin(parts, ["head", "eye"])
    is_torso = parts == "torso"
    dirs[:, 1, 0] = 0.06 * y  # height: vertical stretch about the pelvis
    dirs[:, :, 1] = 0.12 * radial  # girth
    dirs[:, 1, 2] = 0.06 * np.minimum(y, 0.0)  # leg length
    upper = _smoothstep((y - 0.3) / 0.1)
    dirs[:, 0, 3] = 0.03 * np.sign(x) * _smoothstep((np.abs(x) - 0.05) / 0.13) * upper  # shoulder width
    belly = np.exp(-0.5 * ((y - 0.12) / 0.1) ** 2) * _smoothstep(z / 0.05) * is_torso
    dirs[:, 2, 4] = 0.03 * belly  # belly
    dirs[:, 0, 5] = 0.06 * np.sign(x) * np.maximum(np.abs(x) - 0.18, 0.0) * is_arm  # arm length
    dirs[:, :, 6] = 0.08 * (vertices - HEAD_CENTRE) * is_head[:, None]  # head size
    hips = np.exp(-0.5 * ((y + 0.08) / 0.12) ** 2) * ~is_arm
    dirs[:, 0, 7] = 0.025 * np.sign(x) * _smoothstep(np.abs(x) / 0.05) * hips  # hip width
    chest = np.exp(-0.5 * ((y - 0.32) / 0.08) ** 2) * is_torso
    dirs[:, 2, 8] = 0.02 * np.sign(z) * chest  # chest depth
    dirs[:, 1, 9] = 0.03 * _smoothstep((y - 0.25) / 0.2)  # upper-body length

    # Expressions: smooth bumps on the front of the head, (centre, direction) per column.
    face = (parts == "head") & (z > HEAD_CENTRE[2])
    bumps = [
        ([0.0, 0.605, 0.10], [0.0, -1.0, 0.0], 0.02),  # mouth open
        ([0.025, 0.62, 0.095], [0.5, 1.0, 0.0], 0.015),  # smile (left corner; mirrored below)
        ([0.045, 0.645, 0.085], [1.0, 0.0, 0.5], 0.02),  # cheeks (mirrored)
        ([0.03, 0.71, 0.095], [0.0, 1.0, 0.0], 0.018),  # brows up (mirrored)
        ([0.015, 0.705, 0.1], [-1.0, -0.5, 0.0], 0.012),  # brow furrow (mirrored)
        ([0.0, 0.62, 0.105], [0.0, 0.0, 1.0], 0.015),  # lips forward
        ([0.0, 0.665, 0.11], [0.0, 1.0, 0.3], 0.012),  # nose wrinkle
        ([0.032, 0.685, 0.095], [0.0, -1.0, 0.0], 0.01),  # left eyelid
        ([-0.032, 0.685, 0.095], [0.0, -1.0, 0.0], 0.01),  # right eyelid
        ([0.0, 0.585, 0.09], [0.0, -0.3, 1.0], 0.025),  # chin forward
    ]
    mirrored = {1, 2, 3, 4}
    for column, (centre, direction, width) in enumerate(bumps):
        centre_array = np.asarray(centre)
        direction_array = _normalize(np.asarray(direction, dtype=np.float64))
        for sign in ((1.0, -1.0) if column in mirrored else (1.0,)):
            c = centre_array * [sign, 1.0, 1.0]
            d = direction_array * [sign, 1.0, 1.0]
            bump = np.exp(-0.5 * np.sum((vertices - c) ** 2, axis=1) / width**2) * face
            dirs[:, :, 10 + column] += 0.01 * bump[:, None] * d[None]
    return dirs


def _pose_directions(weights: FloatArray, radial: FloatArray) -> FloatArray:
    """(V, 3, 486) small corrective bulge driven by the diagonal of (R_k - I)."""
    posedirs = np.zeros((len(weights), 3, (NUM_JOINTS - 1) * 9))
    for joint in range(1, NUM_JOINTS):
        parent = SMPLX_PARENTS[joint]
        blend = 4.0 * weights[:, joint] * weights[:, parent]
        if not np.any(blend > 0.0):
            continue
        # offset = 0.15 * blend * r * (3 - tr R) / 4 = -0.15/4 * blend * r * sum diag(R - I)
        column = -0.15 / 4.0 * blend[:, None] * radial
        for diagonal in (0, 4, 8):
            posedirs[:, :, 9 * (joint - 1) + diagonal] = column
    return posedirs


def _hand_means() -> Tuple[FloatArray, FloatArray]:
    """Gentle finger curl (left hand; the right is its mirror: axis-angle (x, -y, -z))."""
    left = np.zeros((15, 3))
    for finger_start in (0, 3, 6, 9):  # index, middle, pinky, ring (relative to joint 25)
        left[finger_start : finger_start + 3, 2] = [-0.15, -0.2, -0.1]
    left[12:15] = [[0.1, 0.1, 0.0], [0.0, 0.05, 0.0], [0.0, 0.05, 0.0]]
    right = left * [1.0, -1.0, -1.0]
    return left.reshape(-1), right.reshape(-1)


def build_stand_in_body_model(resolution: str = "small") -> Dict[str, GenericArray]:
    """Build the STAND-IN body model arrays in the SMPL-X .npz layout.

    Args:
        resolution: "small" (about 2.7k vertices, for tests) or "full" (exactly 10,475
            vertices and 20,908 faces, like SMPLX_NEUTRAL.npz, for benchmarks).

    Returns:
        name -> array with keys v_template (V,3), shapedirs (V,3,20), posedirs (V,3,486),
        J_regressor (55,V), weights (V,55), kintree_table (2,55), f (F,3),
        hands_meanl/r (45,), hands_componentsl/r (45,45), joint_names (55,) str,
        stand_in (a marker: "stand-in body model, not SMPL-X").

    Raises:
        ValueError: for an unknown resolution.
    """
    return _build(resolution)[0]


def _build(resolution: str) -> Tuple[Dict[str, GenericArray], FloatArray, ObjectArray]:
    """The arrays of `build_stand_in_body_model`, plus per vertex its bone-axis point (V, 3)
    and part name (V,), which the dense SMPL-X stand-in builds on."""
    if resolution == "small":
        settings = _SMALL
    elif resolution == "full":
        settings = _full_resolution()
    else:
        raise ValueError("resolution must be 'small' or 'full', got '%s'" % resolution)
    builder, joints = _build_surfaces(settings)
    # The extra interior vertex (at the pelvis, no faces): see the module docstring.
    pelvis_weight = np.zeros((1, NUM_JOINTS))
    pelvis_weight[0, 0] = 1.0
    builder.add_vertices(joints[:1].copy(), pelvis_weight, joints[:1].copy(), "interior")
    vertices, faces, weights, axis_points, parts = builder.arrays()
    weights = weights / weights.sum(axis=1, keepdims=True)
    usable = parts != "interior"
    regressor = _joint_regressor(vertices, weights, joints, usable)
    radial = (vertices - axis_points) * usable[:, None]
    hands_meanl, hands_meanr = _hand_means()
    kintree = np.stack([np.array(SMPLX_PARENTS, dtype=np.int64), np.arange(NUM_JOINTS, dtype=np.int64)])
    kintree[0, 0] = ROOT_PARENT_UINT32
    arrays = {
        "v_template": vertices.astype(np.float64),
        "shapedirs": _shape_directions(vertices, axis_points, parts),
        "posedirs": _pose_directions(weights, radial),
        "J_regressor": regressor,
        "weights": weights,
        "kintree_table": kintree,
        "f": faces.astype(np.int32),
        "hands_meanl": hands_meanl,
        "hands_meanr": hands_meanr,
        "hands_componentsl": np.eye(45),
        "hands_componentsr": np.eye(45),
        "joint_names": np.array(JOINT_NAMES),
        "stand_in": np.array("stand-in body model (procedural humanoid), not SMPL-X; no accuracy claim"),
    }
    return arrays, axis_points, parts


def write_stand_in_body_model(path: str, resolution: str = "small") -> str:
    """Write the stand-in model with np.savez_compressed (no pickle), atomically.

    Compressed because posedirs is mostly zeros (the small model shrinks from ~34 MB to
    ~2 MB); np.load reads it the same way.

    Args:
        path: target .npz file (its folder is created).
        resolution: "small" or "full".

    Returns:
        The path written.
    """
    arrays = build_stand_in_body_model(resolution)
    return write_file_atomically(path, lambda temporary: np.savez_compressed(temporary, **arrays))
