"""SMPL-X body model in numpy: .npz loader and linear blend skinning (LBS).

The math follows the `smplx` package's lbs.py step by step (shape blend, joint regression,
pose blend, kinematic chain, skinning) for one body, with everything that does not depend
on the pose precomputed at load:

    v_shaped = v_template + S [betas, expression]                      (blend_shapes)
    J        = J_regressor v_shaped = J_template + (J_regressor S) c   (vertices2joints)
    v_posed  = v_shaped + P vec(R_1..54 - I)                           (pose_blend)
    G_k      = G_parent(k) [R_k | J_k - J_parent(k)],  A_k = G_k [I | -J_k] (batch_rigid_transform)
    v        = sum_k w_vk A_k v_posed                                  (skinning)

Conventions as SMPLer-X uses the model: no PCA hands, flat_hand_mean = False (the hand mean
pose is added to the hand axis-angles), eyes at zero, betas = shape columns [:10],
expression = columns [300:310] (or [10:20] for a 20-column model).
"""

from __future__ import annotations

import os
import zipfile
import zlib
from dataclasses import dataclass, field
from typing import Dict, Mapping, Optional, Tuple

import numpy as np

from leapnbv_common.array_types import FloatArray, FloatingArray, GenericArray, Int64Array, IntArray
from leapnbv_perception.rotations import axis_angle_to_matrix, matrix_to_axis_angle

NUM_JOINTS = 55
NUM_BODY_JOINTS = 21
NUM_HAND_JOINTS = 15
NUM_BETAS = 10
NUM_EXPRESSION = 10
# Joint indices in the SMPL-X kinematic tree.
JAW_JOINT = 22
LEFT_EYE_JOINT = 23
RIGHT_EYE_JOINT = 24
LEFT_HAND_FIRST_JOINT = 25
RIGHT_HAND_FIRST_JOINT = 40
# Shape columns where expression starts in the full model (300 shape + 100 expression).
FULL_MODEL_EXPRESSION_OFFSET = 300

REQUIRED_KEYS = (
    "v_template",
    "shapedirs",
    "posedirs",
    "J_regressor",
    "weights",
    "kintree_table",
    "f",
    "hands_meanl",
    "hands_meanr",
)

_CONVERSION_HINT = (
    "convert the official pickle once with a Python that has chumpy/scipy available, e.g.:\n"
    "  import pickle, numpy as np, scipy.sparse as sp\n"
    "  d = pickle.load(open('SMPLX_NEUTRAL.pkl', 'rb'), encoding='latin1')\n"
    "  np.savez('SMPLX_NEUTRAL.npz', **{k: (v.toarray() if sp.issparse(v) else np.asarray(v))\n"
    "           for k, v in d.items() if k in %s})\n"
    "or download SMPLX_NEUTRAL.npz from https://smpl-x.is.tue.mpg.de (the 'npz' release)."
    % (REQUIRED_KEYS + ("hands_componentsl", "hands_componentsr"),)
)


class SMPLXModelError(ValueError):
    """The body model file is not a usable SMPL-X .npz (format, keys or shapes)."""


# What np.load and reading a member raise for a truncated, cut or corrupted .npz (a zip archive).
_CORRUPT_ARCHIVE_ERRORS = (zipfile.BadZipFile, EOFError, zlib.error)


def _corrupt_message(path: str, error: BaseException, key: str = "") -> str:
    where = " (reading key '%s')" % key if key else ""
    return "SMPL-X model '%s' is truncated or corrupt%s: %s: %s; copy the file again (%d bytes on disk)" % (
        path, where, type(error).__name__, error, os.path.getsize(path))


class BodyModelNotFoundError(FileNotFoundError):
    """The body model file does not exist."""


@dataclass
class SMPLXParams:
    """SMPL-X pose and shape of one body, rotations as matrices.

    Attributes:
        root_rotation: (3, 3) global orientation.
        body_rotations: (21, 3, 3) body joints 1..21.
        jaw_rotation: (3, 3).
        left_hand_rotations: (15, 3, 3) joints 25..39, relative to the hand mean pose.
        right_hand_rotations: (15, 3, 3) joints 40..54, relative to the hand mean pose.
        betas: (10,) shape coefficients.
        expression: (10,) expression coefficients.
    """

    root_rotation: FloatArray = field(default_factory=lambda: np.eye(3))
    body_rotations: FloatArray = field(default_factory=lambda: np.tile(np.eye(3), (NUM_BODY_JOINTS, 1, 1)))
    jaw_rotation: FloatArray = field(default_factory=lambda: np.eye(3))
    left_hand_rotations: FloatArray = field(default_factory=lambda: np.tile(np.eye(3), (NUM_HAND_JOINTS, 1, 1)))
    right_hand_rotations: FloatArray = field(default_factory=lambda: np.tile(np.eye(3), (NUM_HAND_JOINTS, 1, 1)))
    betas: FloatArray = field(default_factory=lambda: np.zeros(NUM_BETAS))
    expression: FloatArray = field(default_factory=lambda: np.zeros(NUM_EXPRESSION))

    @classmethod
    def zeros(cls) -> SMPLXParams:
        """Rest pose (identity rotations), zero shape and expression."""
        return cls()

    @classmethod
    def from_axis_angle(
        cls,
        root: FloatArray,
        body: FloatArray,
        left_hand: FloatArray,
        right_hand: FloatArray,
        jaw: FloatArray,
        betas: Optional[FloatArray] = None,
        expression: Optional[FloatArray] = None,
    ) -> SMPLXParams:
        """Build from axis-angle vectors.

        Args:
            root: (3,).
            body: (63,) or (21, 3).
            left_hand: (45,) or (15, 3).
            right_hand: (45,) or (15, 3).
            jaw: (3,).
            betas: (10,) or None for zeros.
            expression: (10,) or None for zeros.

        Returns:
            SMPLXParams with rotation matrices.

        Raises:
            ValueError: naming the argument with a wrong size.
        """

        def rotations(name: str, values: FloatArray, count: int) -> FloatArray:
            array = np.asarray(values, dtype=np.float64)
            if array.size != count * 3:
                raise ValueError(
                    "%s must have %d values (axis-angle x %d), got %d" % (name, count * 3, count, array.size)
                )
            return axis_angle_to_matrix(array.reshape(count, 3))

        def coefficients(name: str, values: Optional[FloatArray], count: int) -> FloatArray:
            if values is None:
                return np.zeros(count)
            array = np.asarray(values, dtype=np.float64).reshape(-1)
            if array.size != count:
                raise ValueError("%s must have %d values, got %d" % (name, count, array.size))
            return array

        return cls(
            root_rotation=rotations("root", root, 1)[0],
            body_rotations=rotations("body", body, NUM_BODY_JOINTS),
            jaw_rotation=rotations("jaw", jaw, 1)[0],
            left_hand_rotations=rotations("left_hand", left_hand, NUM_HAND_JOINTS),
            right_hand_rotations=rotations("right_hand", right_hand, NUM_HAND_JOINTS),
            betas=coefficients("betas", betas, NUM_BETAS),
            expression=coefficients("expression", expression, NUM_EXPRESSION),
        )


@dataclass
class SMPLXOutput:
    """Posed body in the model frame (no camera translation).

    Attributes:
        vertices: (V, 3) float32.
        joints: (55, 3) float32 posed joint locations.
    """

    vertices: FloatArray
    joints: FloatArray


# ----------------------------------------------------------------------------------------
# LBS steps, one function per equation (shapes as in smplx's lbs.py, without the batch)
# ----------------------------------------------------------------------------------------


def blend_shapes(coefficients: FloatArray, shape_dirs_flat: FloatArray) -> FloatArray:
    """Shape (and expression) offsets: S c.

    Args:
        coefficients: (K,) betas and/or expression.
        shape_dirs_flat: (V*3, K) blend shape directions.

    Returns:
        (V, 3) vertex offsets.
    """
    return (shape_dirs_flat @ coefficients).reshape(-1, 3)


def vertices2joints(joint_regressor: FloatArray, vertices: FloatArray) -> FloatArray:
    """Joint locations regressed from vertices: J = J_regressor v.

    Args:
        joint_regressor: (J, V).
        vertices: (V, 3).

    Returns:
        (J, 3).
    """
    return joint_regressor @ vertices


def pose_blend(rotations: FloatArray, pose_dirs_flat: FloatArray) -> FloatArray:
    """Pose-corrective offsets: P vec(R_k - I) over joints 1..J-1.

    Args:
        rotations: (J, 3, 3) joint rotations (joint 0, the root, does not contribute).
        pose_dirs_flat: ((J-1)*9, V*3) pose blend directions.

    Returns:
        (V, 3) vertex offsets.
    """
    pose_feature = (rotations[1:] - np.eye(3)).reshape(-1).astype(pose_dirs_flat.dtype)
    return (pose_feature @ pose_dirs_flat).reshape(-1, 3)


def batch_rigid_transform(
    rotations: FloatArray, joints: FloatArray, parents: IntArray
) -> Tuple[FloatArray, FloatArray]:
    """Kinematic chain: world transforms of every joint and the skinning transforms.

    G_k = G_parent(k) [R_k | J_k - J_parent(k)]; the skinning transform A_k = G_k [I | -J_k]
    moves a rest-pose point attached to joint k to its posed location.

    Args:
        rotations: (J, 3, 3) local joint rotations.
        joints: (J, 3) rest joint locations.
        parents: (J,) parent index per joint, -1 for the root; parents[k] < k.

    Returns:
        (posed joints (J, 3), skinning transforms A (J, 4, 4)), float64.
    """
    num_joints = rotations.shape[0]
    joints = np.asarray(joints, dtype=np.float64)
    relative = joints.copy()
    relative[1:] -= joints[parents[1:]]
    local = np.zeros((num_joints, 4, 4))
    local[:, :3, :3] = rotations
    local[:, :3, 3] = relative
    local[:, 3, 3] = 1.0
    world = np.empty_like(local)
    world[0] = local[0]
    for joint in range(1, num_joints):
        world[joint] = world[parents[joint]] @ local[joint]
    posed_joints = world[:, :3, 3].copy()
    skinning_transforms = world.copy()
    # A_k = G_k [I | -J_k]: subtract the rotated rest joint location from the translation.
    skinning_transforms[:, :3, 3] -= np.einsum("kij,kj->ki", world[:, :3, :3], joints)
    return posed_joints, skinning_transforms


def skinning(vertices: FloatingArray, skinning_transforms: FloatingArray, weights: FloatingArray) -> FloatArray:
    """Linear blend skinning: v'_i = (sum_k w_ik A_k) v_i.

    Args:
        vertices: (V, 3) posed-blend-shaped rest vertices.
        skinning_transforms: (J, 4, 4) A_k from `batch_rigid_transform`.
        weights: (V, J) skinning weights (rows sum to 1).

    Returns:
        (V, 3) skinned vertices, dtype of `weights`.
    """
    top_rows = skinning_transforms[:, :3, :].reshape(skinning_transforms.shape[0], 12).astype(weights.dtype)
    blended = (weights @ top_rows).reshape(-1, 3, 4)  # (V, 3, 4) per-vertex transforms
    x = vertices[:, 0:1]
    y = vertices[:, 1:2]
    z = vertices[:, 2:3]
    # Row-by-row product of each 3x4 transform with [x, y, z, 1], as four fused multiply-adds.
    return blended[:, :, 0] * x + blended[:, :, 1] * y + blended[:, :, 2] * z + blended[:, :, 3]


def parents_from_kintree(kintree_table: GenericArray, source: str = "") -> Int64Array:
    """Parent indices from kintree_table[0], the root's parent as -1.

    The official files store the root's parent as 4294967295 (uint32 -1); both it and -1
    are accepted.

    Raises:
        SMPLXModelError: when the tree is not a valid 55-joint tree with parents[k] < k.
    """
    table = np.asarray(kintree_table)
    if table.ndim != 2 or table.shape[0] != 2:
        raise SMPLXModelError("kintree_table in %s must be (2, J), got %s" % (source, table.shape))
    raw: Int64Array = table[0].astype(np.int64)
    raw[raw >= 2**31] = -1  # uint32 0xFFFFFFFF stored for the root
    parents = raw
    if parents[0] != -1:
        raise SMPLXModelError("kintree_table in %s: root parent is %d, expected -1/4294967295" % (source, parents[0]))
    for joint in range(1, parents.shape[0]):
        if not 0 <= parents[joint] < joint:
            raise SMPLXModelError(
                "kintree_table in %s: joint %d has parent %d; parents must precede children"
                % (source, joint, parents[joint])
            )
    return parents


class SMPLXModel:
    """SMPL-X model arrays plus the precomputed forms the fast LBS uses.

    Args:
        arrays: name -> array with the REQUIRED_KEYS (SMPL-X .npz layout).
        source: file the arrays came from (named in errors).

    Raises:
        SMPLXModelError: for missing keys or inconsistent shapes.
    """

    def __init__(self, arrays: Mapping[str, GenericArray], source: str = "<arrays>") -> None:
        missing = [key for key in REQUIRED_KEYS if key not in arrays]
        if missing:
            raise SMPLXModelError(
                "SMPL-X model %s lacks key(s): %s (has: %s)" % (source, ", ".join(missing), ", ".join(sorted(arrays)))
            )
        self.source = source
        v_template = np.asarray(arrays["v_template"], dtype=np.float64)
        if v_template.ndim != 2 or v_template.shape[1] != 3:
            raise SMPLXModelError("v_template in %s must be (V, 3), got %s" % (source, v_template.shape))
        num_vertices = v_template.shape[0]
        self._check_shape("shapedirs", arrays, (num_vertices, 3, None))
        self._check_shape("posedirs", arrays, (num_vertices, 3, (NUM_JOINTS - 1) * 9))
        self._check_shape("J_regressor", arrays, (NUM_JOINTS, num_vertices))
        self._check_shape("weights", arrays, (num_vertices, NUM_JOINTS))
        self._check_shape("kintree_table", arrays, (2, NUM_JOINTS))
        self._check_shape("f", arrays, (None, 3))
        self._check_shape("hands_meanl", arrays, (NUM_HAND_JOINTS * 3,))
        self._check_shape("hands_meanr", arrays, (NUM_HAND_JOINTS * 3,))

        shapedirs = np.asarray(arrays["shapedirs"], dtype=np.float64)
        num_dirs = shapedirs.shape[2]
        if num_dirs >= FULL_MODEL_EXPRESSION_OFFSET + NUM_EXPRESSION:
            expression_start = FULL_MODEL_EXPRESSION_OFFSET
        elif num_dirs >= NUM_BETAS + NUM_EXPRESSION:
            expression_start = NUM_BETAS
        else:
            raise SMPLXModelError(
                "shapedirs in %s has %d columns; need 400 (300 shape + 100 expression) or 20" % (source, num_dirs)
            )
        self.expression_start = expression_start
        faces = np.asarray(arrays["f"])
        if faces.size and (faces.min() < 0 or faces.max() >= num_vertices):
            raise SMPLXModelError("faces in %s index outside [0, %d)" % (source, num_vertices))

        self.parents = parents_from_kintree(arrays["kintree_table"], source)
        self.v_template = v_template.astype(np.float32)
        self.faces = faces.astype(np.uint32)
        self.joint_regressor = np.asarray(arrays["J_regressor"], dtype=np.float64)
        self.weights = np.ascontiguousarray(np.asarray(arrays["weights"], dtype=np.float32))
        self.left_hand_mean = np.asarray(arrays["hands_meanl"], dtype=np.float64).reshape(NUM_HAND_JOINTS, 3)
        self.right_hand_mean = np.asarray(arrays["hands_meanr"], dtype=np.float64).reshape(NUM_HAND_JOINTS, 3)

        # [betas | expression] directions as one (V*3, 20) matrix: one matmul per frame.
        selected = np.concatenate(
            [shapedirs[:, :, :NUM_BETAS], shapedirs[:, :, expression_start : expression_start + NUM_EXPRESSION]],
            axis=2,
        )
        self.shape_dirs_flat = np.ascontiguousarray(selected.reshape(num_vertices * 3, -1).astype(np.float32))
        # Joints are linear in the coefficients: J = J_reg v_template + (J_reg S) c.
        self.joint_template = self.joint_regressor @ v_template
        self.joint_shape_dirs = np.einsum("jv,vkl->jkl", self.joint_regressor, selected).reshape(NUM_JOINTS * 3, -1)
        # posedirs (V, 3, 486) -> (486, V*3), so the pose blend is one vector-matrix product.
        posedirs = np.asarray(arrays["posedirs"], dtype=np.float32)
        self.pose_dirs_flat = np.ascontiguousarray(posedirs.reshape(num_vertices * 3, -1).T)

    @staticmethod
    def _check_shape(key: str, arrays: Mapping[str, GenericArray], expected: Tuple[Optional[int], ...]) -> None:
        shape = np.shape(arrays[key])
        if len(shape) != len(expected) or any(e is not None and e != s for e, s in zip(expected, shape)):
            wanted = tuple("*" if e is None else e for e in expected)
            raise SMPLXModelError("key '%s' has shape %s, expected %s" % (key, shape, wanted))

    @classmethod
    def load(cls, path: str) -> SMPLXModel:
        """Load SMPLX_NEUTRAL.npz (or any file in its layout) without pickle.

        Args:
            path: the .npz file.

        Returns:
            SMPLXModel.

        Raises:
            BodyModelNotFoundError: naming the path when it does not exist.
            SMPLXModelError: for a .pkl file, a file needing pickle, a truncated or corrupt archive
                (BadZipFile, EOFError, a bad CRC: named with the path), missing keys or bad shapes.
        """
        path = os.fspath(path)
        if path.lower().endswith(".pkl"):
            raise SMPLXModelError(
                "'%s' is a pickle; this loader reads only .npz (no pickle, no chumpy). %s" % (path, _CONVERSION_HINT)
            )
        if not os.path.isfile(path):
            raise BodyModelNotFoundError(
                "SMPL-X model file not found: '%s' (absolute: '%s')" % (path, os.path.abspath(path))
            )
        if os.path.getsize(path) == 0:
            raise SMPLXModelError("SMPL-X model '%s' is empty (0 bytes); copy the file again" % path)
        try:
            archive = np.load(path, allow_pickle=False)
        except ValueError as error:
            with open(path, "rb") as handle:
                looks_pickled = handle.read(1) == b"\x80"  # a pickle's protocol opcode
            if "pickle" not in str(error) or not looks_pickled:  # older numpy calls any unknown format a pickle
                raise SMPLXModelError("'%s' is not a readable .npz (truncated or corrupt?): %s" % (path, error)) \
                    from error
            raise SMPLXModelError("'%s' needs pickle to load (%s). %s" % (path, error, _CONVERSION_HINT)) from error
        except _CORRUPT_ARCHIVE_ERRORS as error:
            raise SMPLXModelError(_corrupt_message(path, error)) from error
        except OSError as error:
            raise SMPLXModelError("'%s' is not a readable .npz: %s" % (path, error)) from error
        if not hasattr(archive, "files"):
            raise SMPLXModelError("'%s' holds a single array, not an .npz archive of SMPL-X keys" % path)
        with archive:
            missing = [key for key in REQUIRED_KEYS if key not in archive.files]
            if missing:
                raise SMPLXModelError(
                    "SMPL-X model '%s' lacks key(s): %s (has: %s)"
                    % (path, ", ".join(missing), ", ".join(archive.files))
                )
            arrays: Dict[str, FloatArray] = {}
            for key in REQUIRED_KEYS:
                try:
                    arrays[key] = archive[key]
                except ValueError as error:
                    if "pickle" not in str(error):  # a truncated or garbled array inside the archive
                        raise SMPLXModelError(_corrupt_message(path, error, key)) from error
                    raise SMPLXModelError(  # object array: would need pickle
                        "key '%s' in '%s' is stored as a pickled object (%s). %s" % (key, path, error, _CONVERSION_HINT)
                    ) from error
                except _CORRUPT_ARCHIVE_ERRORS as error:
                    raise SMPLXModelError(_corrupt_message(path, error, key)) from error
        return cls(arrays, source=path)

    @property
    def num_vertices(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    def full_pose_rotations(self, params: SMPLXParams, add_hand_mean: bool = True) -> FloatArray:
        """The 55 local joint rotations in SMPL-X order.

        Order: global, body (21), jaw, left eye (identity), right eye (identity),
        left hand (15), right hand (15). With add_hand_mean the hand mean pose is added to
        the hand axis-angles, as smplx does for flat_hand_mean = False.

        Returns:
            (55, 3, 3) float64.
        """
        rotations = np.empty((NUM_JOINTS, 3, 3))
        rotations[0] = params.root_rotation
        rotations[1 : 1 + NUM_BODY_JOINTS] = params.body_rotations
        rotations[JAW_JOINT] = params.jaw_rotation
        rotations[LEFT_EYE_JOINT] = np.eye(3)
        rotations[RIGHT_EYE_JOINT] = np.eye(3)
        left = np.asarray(params.left_hand_rotations, dtype=np.float64)
        right = np.asarray(params.right_hand_rotations, dtype=np.float64)
        if add_hand_mean:
            hands_axis_angle = matrix_to_axis_angle(np.concatenate([left, right], axis=0))
            hands_axis_angle[:NUM_HAND_JOINTS] += self.left_hand_mean
            hands_axis_angle[NUM_HAND_JOINTS:] += self.right_hand_mean
            hands = axis_angle_to_matrix(hands_axis_angle)
            left, right = hands[:NUM_HAND_JOINTS], hands[NUM_HAND_JOINTS:]
        rotations[LEFT_HAND_FIRST_JOINT : LEFT_HAND_FIRST_JOINT + NUM_HAND_JOINTS] = left
        rotations[RIGHT_HAND_FIRST_JOINT : RIGHT_HAND_FIRST_JOINT + NUM_HAND_JOINTS] = right
        return rotations

    def shape_coefficients(self, params: SMPLXParams) -> FloatArray:
        """[betas (10), expression (10)] as float32 (20,)."""
        return np.concatenate(
            [np.asarray(params.betas, dtype=np.float32).reshape(NUM_BETAS),
             np.asarray(params.expression, dtype=np.float32).reshape(NUM_EXPRESSION)]
        )

    def forward(self, params: SMPLXParams, add_hand_mean: bool = True) -> SMPLXOutput:
        """Pose and shape the body.

        Args:
            params: pose (rotation matrices), betas and expression.
            add_hand_mean: add the hand mean pose (SMPLer-X: True).

        Returns:
            SMPLXOutput with vertices (V, 3) and joints (55, 3), float32, model frame.
        """
        rotations = self.full_pose_rotations(params, add_hand_mean)
        coefficients = self.shape_coefficients(params)
        v_shaped = self.v_template + blend_shapes(coefficients, self.shape_dirs_flat)
        joints = self.joint_template + (self.joint_shape_dirs @ coefficients.astype(np.float64)).reshape(NUM_JOINTS, 3)
        v_posed = v_shaped + pose_blend(rotations, self.pose_dirs_flat)
        posed_joints, transforms = batch_rigid_transform(rotations, joints, self.parents)
        vertices = skinning(v_posed, transforms, self.weights)
        return SMPLXOutput(vertices=vertices.astype(np.float32, copy=False), joints=posed_joints.astype(np.float32))
