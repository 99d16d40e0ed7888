"""Human mesh estimation: crop, HMR engine (read by output name), FP32 SMPL-X tail."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Dict, Mapping, Optional, Sequence, Tuple

import numpy as np

from leapnbv_common.array_types import FloatArray, FloatingArray, IntArray, UInt8Array
from leapnbv_perception.backends.base import EngineBackend
from leapnbv_perception.hmr_crop import DEFAULT_BOX_SCALE, engine_input_for_box
from leapnbv_perception.hmr_tail import camera_translation, unmirror_left_hand, virtual_intrinsics
from leapnbv_perception.model_contracts import (
    HMR_INPUT_NAME,
    HMR_OUTPUT_SIZES,
    SMPLERX_CONTRACT,
    check_backend_contract,
)
from leapnbv_perception.rotations import matrix_to_axis_angle, rot6d_to_matrix
from leapnbv_perception.smplx_layer import NUM_BODY_JOINTS, NUM_HAND_JOINTS, SMPLXModel, SMPLXParams


class HMROutputError(ValueError):
    """The HMR engine returned non-finite or wrongly sized values."""


class ExportMetadataError(ValueError):
    """The HMR model's export metadata disagrees with the node's parameters or its own input."""


# Written by `leapnbv_model_tools export-hmr` (tools/): keys under this prefix in the ONNX metadata.
EXPORT_METADATA_PREFIX = "leapnbv."
# Whether the engine estimates the hand poses: "estimated", or "not_estimated" for a body-only export
# (`export-hmr --without-hands`), whose lhand_pose / rhand_pose are the identity rotation for every hand
# joint: axis-angle 0 after the tail, i.e. the SMPL-X hand mean pose. An engine without the key (a contract
# model, an older export, an engine from elsewhere) is taken to estimate them.
HANDS_KEY = EXPORT_METADATA_PREFIX + "hands"
HANDS_ESTIMATED = "estimated"
HANDS_NOT_ESTIMATED = "not_estimated"


def hands_estimated(metadata: Mapping[str, str]) -> bool:
    """False only for an engine whose export metadata says that it does not estimate the hands."""
    return metadata.get(HANDS_KEY, HANDS_ESTIMATED) != HANDS_NOT_ESTIMATED


def read_export_metadata(model_path: Optional[str]) -> Dict[str, str]:
    """The export's ``leapnbv.*`` metadata of an ONNX file ({} for another or absent file, or without onnx).

    Reads the model proto without external data (the weights stay on disk when stored outside).
    """
    if not model_path or not str(model_path).lower().endswith(".onnx") or not os.path.isfile(model_path):
        return {}
    try:
        import onnx
    except ImportError:  # the runtime without the onnx package: nothing to check against
        return {}
    proto = onnx.load(str(model_path), load_external_data=False)
    return {entry.key: entry.value for entry in proto.metadata_props if entry.key.startswith(EXPORT_METADATA_PREFIX)}


def check_export_metadata(metadata: Mapping[str, str], input_hw: Tuple[int, int], box_scale: float,
                          unmirror_left_hand: bool, source: str = "the HMR model") -> None:
    """Check an export's metadata against the parameters the tail will use.

    No ``leapnbv.*`` metadata (a contract model, an export from elsewhere): nothing to check.

    Raises:
        ExportMetadataError: naming each disagreement (input size, un-mirror flag, box ratio) and an
            unknown ``leapnbv.hands`` value.
    """
    if not metadata:
        return
    problems = []
    size = metadata.get(EXPORT_METADATA_PREFIX + "input_size")
    if size is not None and size != "%dx%d" % tuple(input_hw):
        problems.append(f"metadata input_size {size} but the graph's input is {int(input_hw[0])}x{int(input_hw[1])}")
    flag = metadata.get(EXPORT_METADATA_PREFIX + "unmirror_left_hand")
    if flag is not None and (flag == "true") != bool(unmirror_left_hand):
        problems.append("exported with unmirror_left_hand=%s but the parameter is %s"
                        % (flag, str(bool(unmirror_left_hand)).lower()))
    ratio = metadata.get(EXPORT_METADATA_PREFIX + "box_ratio")
    if ratio is not None and abs(float(ratio) - float(box_scale)) > 1e-6:
        problems.append("exported for box ratio %s but box_scale is %g" % (ratio, box_scale))
    hands = metadata.get(HANDS_KEY)
    if hands is not None and hands not in (HANDS_ESTIMATED, HANDS_NOT_ESTIMATED):
        problems.append("metadata hands %r is neither %r nor %r" % (hands, HANDS_ESTIMATED, HANDS_NOT_ESTIMATED))
    if problems:
        raise ExportMetadataError(
            "%s (%s, checkpoint sha256 %s) does not match the parameters: %s"
            % (source, metadata.get(EXPORT_METADATA_PREFIX + "variant", "?"),
               metadata.get(EXPORT_METADATA_PREFIX + "checkpoint_sha256", "?")[:12], "; ".join(problems)))


@dataclass
class HumanMeshEstimate:
    """One person's mesh in the virtual crop camera, with what is needed to use it.

    Attributes:
        vertices: (V, 3) float32, model vertices + cam_translation (virtual crop camera,
            optical axes: x right, y down, z forward).
        faces: (F, 3) uint32.
        joints: (55, 3) float32 posed joints in the same frame.
        fx, fy, cx, cy: virtual intrinsics that project `vertices` onto the source image.
        processed_box: (4,) [x, y, w, h] crop box in source pixels.
        crop_affine: (2, 3) source -> crop (512x384) pixels.
        root, body, left_hand, right_hand, jaw: axis-angle (3,), (63,), (45,), (45,), (3,)
            (left hand already un-mirrored; hand poses relative to the hand mean).
        betas: (10,).
        expression: (10,).
        cam_translation: (3,) metres in the virtual crop camera.
    """

    vertices: FloatArray
    faces: IntArray
    joints: FloatArray
    fx: float
    fy: float
    cx: float
    cy: float
    processed_box: FloatArray
    crop_affine: FloatArray
    root: FloatArray
    body: FloatArray
    left_hand: FloatArray
    right_hand: FloatArray
    jaw: FloatArray
    betas: FloatArray
    expression: FloatArray
    cam_translation: FloatArray


class HumanMeshEstimator:
    """SMPLer-X-style HMR on any EngineBackend plus the numpy SMPL-X tail.

    Args:
        backend: engine with the SMPLer-X encoder + heads contract (input `img`).
        body_model: loaded SMPL-X (or stand-in) model.
        box_scale: crop enlargement about the box centre (SMPLer-X 1.25).
        unmirror_left_hand: apply R_L = S R S to the left-hand rotations.

    Attributes:
        export_metadata: the model's ``leapnbv.*`` export metadata ({} when it has none).
        hands_estimated: False for a body-only export (``leapnbv.hands`` = ``not_estimated``): its hand
            poses are always axis-angle 0 (the SMPL-X hand mean pose), not an estimate.

    Raises:
        ModelContractError: when the backend does not declare the contract's names/shapes.
        ExportMetadataError: when the model is an export-hmr ONNX whose metadata (input size,
            un-mirror flag, box ratio) disagrees with these arguments.
    """

    def __init__(
        self,
        backend: EngineBackend,
        body_model: SMPLXModel,
        box_scale: float = DEFAULT_BOX_SCALE,
        unmirror_left_hand: bool = True,
    ) -> None:
        check_backend_contract(backend, SMPLERX_CONTRACT)
        self.backend = backend
        self.body_model = body_model
        self.box_scale = float(box_scale)
        self.unmirror_left_hand = bool(unmirror_left_hand)
        input_shape = backend.input_specs[HMR_INPUT_NAME].shape
        height, width = input_shape[2], input_shape[3]
        if not isinstance(height, int) or not isinstance(width, int):
            raise ValueError(f"the HMR model's input must have a static height and width, got {input_shape}")
        self.input_hw: Tuple[int, int] = (height, width)
        model_path = getattr(backend, "model_path", None)
        self.export_metadata = read_export_metadata(model_path if isinstance(model_path, str) else None)
        check_export_metadata(self.export_metadata, self.input_hw, self.box_scale, self.unmirror_left_hand,
                              str(model_path))
        # A body-only engine (export-hmr --without-hands): every estimate's hands are the SMPL-X hand mean pose.
        self.hands_estimated = hands_estimated(self.export_metadata)

    def _read_outputs(self, outputs: Mapping[str, FloatingArray]) -> Dict[str, FloatArray]:
        """Flatten each named output to its per-item length and reject non-finite values."""
        values = {}
        for name, size in HMR_OUTPUT_SIZES.items():
            if name not in outputs:
                raise HMROutputError("HMR engine output '%s' missing (got %s)" % (name, sorted(outputs)))
            array = np.asarray(outputs[name], dtype=np.float64).reshape(-1)
            if array.size != size:
                raise HMROutputError("HMR output '%s' has %d values, expected %d" % (name, array.size, size))
            if not np.all(np.isfinite(array)):
                raise HMROutputError("HMR output '%s' has non-finite values" % name)
            values[name] = array
        return values

    def estimate(self, rgb: UInt8Array, box_xyxy: Sequence[float]) -> HumanMeshEstimate:
        """Estimate the mesh of the person in one box.

        Args:
            rgb: (H, W, 3) uint8 RGB image.
            box_xyxy: [x_min, y_min, x_max, y_max, ...] person box in source pixels.

        Returns:
            HumanMeshEstimate.

        Raises:
            InvalidBoxError: when the box has no area inside the image.
            HMROutputError: when the engine returns non-finite or missing outputs.
        """
        engine_input, processed_box, affine = engine_input_for_box(rgb, box_xyxy, self.input_hw, self.box_scale)
        outputs = self.backend.run({HMR_INPUT_NAME: engine_input})
        values = self._read_outputs(outputs)

        root = rot6d_to_matrix(values["root_pose"].reshape(1, 6))[0]
        body = rot6d_to_matrix(values["body_pose"].reshape(NUM_BODY_JOINTS, 6))
        left_hand = rot6d_to_matrix(values["lhand_pose"].reshape(NUM_HAND_JOINTS, 6))
        right_hand = rot6d_to_matrix(values["rhand_pose"].reshape(NUM_HAND_JOINTS, 6))
        jaw = rot6d_to_matrix(values["jaw_pose"].reshape(1, 6))[0]
        if self.unmirror_left_hand:
            left_hand = unmirror_left_hand(left_hand)
        params = SMPLXParams(
            root_rotation=root,
            body_rotations=body,
            jaw_rotation=jaw,
            left_hand_rotations=left_hand,
            right_hand_rotations=right_hand,
            betas=values["betas"],
            expression=values["expression"],
        )
        posed = self.body_model.forward(params, add_hand_mean=True)
        translation = camera_translation(values["cam_param"])
        offset = translation.astype(np.float32)
        fx, fy, cx, cy = virtual_intrinsics(processed_box)
        axis_angles = matrix_to_axis_angle(
            np.concatenate([root[None], body, left_hand, right_hand, jaw[None]], axis=0)
        )
        hands_end = 1 + NUM_BODY_JOINTS + 2 * NUM_HAND_JOINTS
        return HumanMeshEstimate(
            vertices=posed.vertices + offset,
            faces=self.body_model.faces,
            joints=posed.joints + offset,
            fx=fx,
            fy=fy,
            cx=cx,
            cy=cy,
            processed_box=processed_box,
            crop_affine=affine,
            root=axis_angles[0],
            body=axis_angles[1 : 1 + NUM_BODY_JOINTS].reshape(-1),
            left_hand=axis_angles[1 + NUM_BODY_JOINTS : 1 + NUM_BODY_JOINTS + NUM_HAND_JOINTS].reshape(-1),
            right_hand=axis_angles[1 + NUM_BODY_JOINTS + NUM_HAND_JOINTS : hands_end].reshape(-1),
            jaw=axis_angles[hands_end],
            betas=values["betas"].copy(),
            expression=values["expression"].copy(),
            cam_translation=translation,
        )
