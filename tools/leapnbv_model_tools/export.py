"""export-hmr: one ONNX graph (encoder + heads) with the engine contract's names and shapes,
checked by onnx.checker, by the project's contract check and by onnxruntime against PyTorch,
with metadata that hmr_node checks against its parameters (leapnbv_perception.hmr)."""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from typing import Dict, Optional, Sequence, Tuple

import numpy as np
import torch

from leapnbv_model_tools.checkpoint import CheckpointError, load_smplerx
from leapnbv_model_tools.file_hash import sha256_of
from leapnbv_model_tools.smplerx import VARIANTS, SMPLerX

OUTPUT_NAMES = ("root_pose", "body_pose", "lhand_pose", "rhand_pose", "jaw_pose", "betas", "expression", "cam_param")
DEFAULT_OPSET = 16  # RoiAlign/GridSample-free graph; 17 only adds LayerNormalization, which is not used
PARITY_TOLERANCE = 1e-4


# "leapnbv.hands": whether the engine estimates the hand poses. "not_estimated" (export-hmr --without-hands):
# the hand branch is left out and lhand_pose / rhand_pose are the identity rotation (6D) for every hand joint,
# which the tail decodes to axis-angle 0: the SMPL-X hand mean pose (leapnbv_perception.hmr reads it).
HANDS_KEY = "leapnbv.hands"
HANDS_ESTIMATED, HANDS_NOT_ESTIMATED = "estimated", "not_estimated"


class _Exported(torch.nn.Module):
    def __init__(self, model: SMPLerX, hands: bool = True) -> None:
        super().__init__()
        self.model = model
        self.hands = hands

    def forward(self, img: torch.Tensor):
        outputs = self.model(img, hands=self.hands)
        return tuple(outputs[name] for name in OUTPUT_NAMES)


def export_metadata(variant: str, checkpoint_sha256: str, input_hw: Tuple[int, int], box_ratio: float = 1.25,
                    unmirror_left_hand: bool = True, hands: bool = True) -> Dict[str, str]:
    """The metadata the export writes (leapnbv_perception.hmr.EXPORT_METADATA_KEYS reads it)."""
    return {
        "leapnbv.producer": "leapnbv_model_tools export-hmr",
        "leapnbv.variant": f"smpler_x_{variant}",
        "leapnbv.checkpoint_sha256": checkpoint_sha256,
        "leapnbv.input_size": f"{input_hw[0]}x{input_hw[1]}",
        "leapnbv.unmirror_left_hand": "true" if unmirror_left_hand else "false",
        "leapnbv.box_ratio": repr(float(box_ratio)),
        HANDS_KEY: HANDS_ESTIMATED if hands else HANDS_NOT_ESTIMATED,
    }


# Above this many bytes of weights the graph is written with its tensors in one external file,
# ``<out>.data`` beside it: one protobuf message cannot exceed 2 GiB (smpler_x_h32 has 2.6 GB).
EXTERNAL_DATA_ABOVE_BYTES = 1_800_000_000


def weight_bytes(model: torch.nn.Module) -> int:
    return sum(t.numel() * t.element_size() for t in list(model.parameters()) + list(model.buffers()))


def export_onnx(model: SMPLerX, path: str, input_hw: Tuple[int, int], metadata: Dict[str, str],
                opset: int = DEFAULT_OPSET, hands: bool = True) -> str:
    """Write the ONNX graph to ``path`` (and ``path.data`` when the weights exceed
    EXTERNAL_DATA_ABOVE_BYTES), checked by onnx.checker. ``hands=False``: the body-only graph
    (SMPLerX.forward(hands=False); the hand branch's weights are not in it).

    Everything is written and checked in a folder beside ``path`` first and then moved into place,
    so a failed or interrupted export never replaces a good file.
    """
    import onnx

    final = os.path.abspath(path)
    data_name = os.path.basename(final) + ".data"
    external = weight_bytes(model) > EXTERNAL_DATA_ABOVE_BYTES
    example = torch.zeros(1, 3, *input_hw)
    with tempfile.TemporaryDirectory(dir=os.path.dirname(final), prefix=".export-hmr-") as work:
        raw = os.path.join(work, "traced.onnx")
        with torch.no_grad():
            # The wrapper in eval mode too: the exporter restores the wrapper's mode on every submodule
            # afterwards (a fresh wrapper is in training mode, which would leave BatchNorm on batch statistics).
            # A graph over 2 GiB is written by the exporter with its tensors in files beside `raw`.
            torch.onnx.export(_Exported(model, hands).eval(), (example,), raw, input_names=["img"],
                              output_names=list(OUTPUT_NAMES), opset_version=opset, dynamo=False)
        model.eval()
        proto = onnx.load(raw)  # with any external tensors the exporter wrote
        del proto.metadata_props[:]
        for key, value in metadata.items():
            entry = proto.metadata_props.add()
            entry.key, entry.value = key, value
        staged = os.path.join(work, os.path.basename(final))
        if external:
            onnx.save_model(proto, staged, save_as_external_data=True, all_tensors_to_one_file=True,
                            location=data_name, size_threshold=1024)
        else:
            onnx.save(proto, staged)
        del proto
        onnx.checker.check_model(staged)  # by path: reads external data where there is some
        umask = os.umask(0)
        os.umask(umask)
        for written in (staged, os.path.join(work, data_name)) if external else (staged,):
            os.chmod(written, 0o666 & ~umask)  # as any file the user writes (the writer may make it private)
        if external:
            os.replace(os.path.join(work, data_name), final + ".data")  # the data first: the graph names it
        os.replace(staged, final)
        if not external and os.path.exists(final + ".data"):
            os.remove(final + ".data")  # left by an earlier export with external data at this path
    return final


def operator_types(path: str) -> Sequence[str]:
    import onnx

    return sorted({node.op_type for node in onnx.load(path, load_external_data=False).graph.node})


def parity(model: SMPLerX, path: str, crops: np.ndarray, threads: int = 1, hands: bool = True) -> float:
    """Largest |onnxruntime - PyTorch| over all outputs and crops (N, 3, H, W) float32."""
    import onnxruntime

    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = threads
    session = onnxruntime.InferenceSession(path, options, providers=["CPUExecutionProvider"])
    worst = 0.0
    for crop in crops:
        batch = crop[None].astype(np.float32)
        with torch.no_grad():
            expected = model(torch.from_numpy(batch), hands=hands)
        got = dict(zip(OUTPUT_NAMES, session.run(list(OUTPUT_NAMES), {"img": batch})))
        for name in OUTPUT_NAMES:
            worst = max(worst, float(np.abs(got[name] - expected[name].numpy()).max()))
    return worst


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m leapnbv_model_tools export-hmr", description=__doc__)
    parser.add_argument("--checkpoint", required=True, help="smpler_x_{s,b,l,h}32.pth.tar (official structure)")
    parser.add_argument("--variant", required=True, choices=sorted(VARIANTS))
    parser.add_argument("--out", required=True)
    parser.add_argument("--input", default="512x384", choices=["512x384", "256x192"])
    parser.add_argument("--opset", type=int, default=DEFAULT_OPSET)
    parser.add_argument("--box-ratio", type=float, default=1.25)
    parser.add_argument("--parity-crops", type=int, default=2, help="random crops compared with onnxruntime")
    parser.add_argument("--without-hands", action="store_true",
                        help="body-only engine: the hand branch is not computed, lhand_pose / rhand_pose are the "
                             "identity rotation (the SMPL-X hand mean pose); metadata leapnbv.hands=not_estimated")
    args = parser.parse_args(argv)
    input_hw = tuple(int(v) for v in args.input.split("x"))
    try:
        model = load_smplerx(args.checkpoint, args.variant)
    except CheckpointError as error:
        print(f"export-hmr: {error}", file=sys.stderr)
        return 2
    hands = not args.without_hands
    metadata = export_metadata(args.variant, sha256_of(args.checkpoint), input_hw, args.box_ratio, hands=hands)
    export_onnx(model, args.out, input_hw, metadata, args.opset, hands=hands)
    from leapnbv_perception.backends.onnxruntime_backend import OnnxRuntimeBackend
    from leapnbv_perception.model_contracts import SMPLERX_CONTRACT, check_backend_contract

    check_backend_contract(OnnxRuntimeBackend(args.out), SMPLERX_CONTRACT)
    crops = np.random.default_rng(0).uniform(0.0, 1.0, size=(args.parity_crops, 3) + input_hw).astype(np.float32)
    difference = parity(model, args.out, crops, hands=hands)
    print(f"{args.out}: opset {args.opset}, hands {metadata[HANDS_KEY]}, "
          f"operators {', '.join(operator_types(args.out))}")
    print(f"parity onnxruntime vs PyTorch: max |diff| = {difference:.3g} (tolerance {PARITY_TOLERANCE})")
    return 0 if difference <= PARITY_TOLERANCE else 1
