"""export-hmr: one ONNX graph (encoder + heads) with the engine contract's names and shapes,
checked by onnx.checker, by the project's contract check and by onnxruntime against PyTorch
(within each output's own FP32 rounding noise), with metadata that hmr_node checks against its
parameters (leapnbv_perception.hmr). The file appears at --out only when every check passed.

Exit codes (leapnbv_model_tools.exit_codes.ModelToolExit): 0 written; 1 a check failed (nothing
written at --out, an earlier file there is left as it was); 2 a wrong argument or an unusable input
(missing, truncated, not a checkpoint, another variant or family): one line on stderr naming the file.

Both families export to the same contract: SMPLer-X (s32 ... h32) and SMPLest-X (smplest_x_h). What
SMPLest-X does differently at test time is in the metadata, not in a second tail: its left hand is not
mirrored (``unmirror_left_hand`` false) and its crops are the box x 1.2 (``box_ratio``)."""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from leapnbv_model_tools.checkpoint import (
    VARIANTS,
    CheckpointError,
    Network,
    box_ratio_of,
    family_of,
    load_network,
    unmirrors_left_hand,
    variant_label,
)
from leapnbv_model_tools.exit_codes import ModelToolExit
from leapnbv_model_tools.file_hash import sha256_of

OUTPUT_NAMES = ("root_pose", "body_pose", "lhand_pose", "rhand_pose", "jaw_pose", "betas", "expression", "cam_param")
DEFAULT_OPSET = 16  # RoiAlign/GridSample-free graph; 17 only adds LayerNormalization, which is not used

# Operators an export may use: each is supported by TensorRT 8.4's ONNX parser already (onnx-tensorrt
# docs/operators.md of 8.4, so by 8.5 and later) without a plugin. Not in it on purpose: LayerNormalization
# (parsed from TensorRT 8.6), GridSample, RoiAlign and NonZero (added in 8.5, RoiAlign and GridSample as
# plugins), Einsum (restricted). The networks are written so that their graphs stay inside this set.
TENSORRT_OPERATORS = frozenset({
    "Add", "And", "BatchNormalization", "Cast", "Ceil", "Clip", "Concat", "Constant", "ConstantOfShape", "Conv",
    "ConvTranspose", "Div", "Equal", "Erf", "Exp", "Expand", "Flatten", "Floor", "Gather", "Gemm", "Greater",
    "GreaterOrEqual", "Identity", "Less", "LessOrEqual", "MatMul", "Max", "Min", "Mul", "Neg", "Not", "Or", "Pow",
    "Range", "ReduceMax", "ReduceMean", "ReduceSum", "Relu", "Reshape", "Shape", "Sigmoid", "Slice", "Softmax",
    "Split", "Sqrt", "Squeeze", "Sub", "Tile", "Transpose", "Unsqueeze", "Where",
})

# Parity limit. Two FP32 evaluations of one network (PyTorch's kernels, onnxruntime's) differ by rounding
# in another order, and how far depends on the network and its weights: ~1e-6 on random weights, 1.2e-4 in
# the hand branch of an s32 checkpoint between the same PyTorch network in FP32 and in FP64, where a fixed
# 1e-4 refused a correct export. So the limit is measured per output: the network run in FP64 on the same
# crops gives that output's FP32 noise, max |PyTorch FP32 - PyTorch FP64|, and onnxruntime may differ from
# PyTorch FP32 by at most PARITY_NOISE_FACTOR x that noise + PARITY_FLOOR x max(1, max |output|). The floor
# covers outputs whose FP32 rounding is (nearly) exact (the body-only engine's constant hands). A wrong
# weight, operator or constant moves outputs by far more (tests/test_smplerx_tools.py: one bias element
# off by 1e-3, LayerNorm's eps 1e-6 -> 1e-3).
PARITY_NOISE_FACTOR = 8.0
PARITY_FLOOR = 1e-5


# "leapnbv.hands": whether the engine estimates the hand poses. "not_estimated" (export-hmr --without-hands):
# the hand branch is left out and lhand_pose / rhand_pose are the identity rotation (6D) for every hand joint,
# which the tail decodes to axis-angle 0: the SMPL-X hand mean pose (leapnbv_perception.hmr reads it).
HANDS_KEY = "leapnbv.hands"
HANDS_ESTIMATED, HANDS_NOT_ESTIMATED = "estimated", "not_estimated"


class _Exported(torch.nn.Module):
    def __init__(self, model: Network, hands: bool = True) -> None:
        super().__init__()
        self.model = model
        self.hands = hands

    def forward(self, img: torch.Tensor):
        outputs = self.model(img, hands=self.hands)
        return tuple(outputs[name] for name in OUTPUT_NAMES)


def export_metadata(variant: str, checkpoint_sha256: str, input_hw: Tuple[int, int],
                    box_ratio: Optional[float] = None, unmirror_left_hand: Optional[bool] = None,
                    hands: bool = True) -> Dict[str, str]:
    """The metadata the export writes (leapnbv_perception.hmr.check_export_metadata reads it). ``box_ratio`` and
    ``unmirror_left_hand`` default to the variant's family's (SMPLer-X 1.25 and true, SMPLest-X 1.2 and false)."""
    box_ratio = box_ratio_of(variant) if box_ratio is None else box_ratio
    unmirror_left_hand = unmirrors_left_hand(variant) if unmirror_left_hand is None else unmirror_left_hand
    return {
        "leapnbv.producer": "leapnbv_model_tools export-hmr",
        "leapnbv.variant": variant_label(variant),
        "leapnbv.checkpoint_sha256": checkpoint_sha256,
        "leapnbv.input_size": f"{input_hw[0]}x{input_hw[1]}",
        "leapnbv.unmirror_left_hand": "true" if unmirror_left_hand else "false",
        "leapnbv.box_ratio": repr(float(box_ratio)),
        HANDS_KEY: HANDS_ESTIMATED if hands else HANDS_NOT_ESTIMATED,
    }


# Above this many bytes of weights the graph is written with its tensors in one external file,
# ``<out>.data`` beside it: one protobuf message cannot exceed 2 GiB (smpler_x_h32 has 2.6 GB, smplest_x_h 2.8 GB).
EXTERNAL_DATA_ABOVE_BYTES = 1_800_000_000


def weight_bytes(model: torch.nn.Module) -> int:
    return sum(t.numel() * t.element_size() for t in list(model.parameters()) + list(model.buffers()))


def export_onnx(model: Network, path: str, input_hw: Tuple[int, int], metadata: Dict[str, str],
                opset: int = DEFAULT_OPSET, hands: bool = True,
                check: Optional[Callable[[str], None]] = None) -> str:
    """Write the ONNX graph to ``path`` (and ``path.data`` when the weights exceed
    EXTERNAL_DATA_ABOVE_BYTES), checked by onnx.checker and then by ``check(staged_path)`` (which
    raises to refuse the file). ``hands=False``: the body-only graph (SMPLerX.forward(hands=False);
    the hand branch's weights are not in it).

    Everything is written and checked in a hidden folder beside ``path`` (same file system, so the
    move is a rename) and moved into place only after every check passed: a failed or interrupted
    export never replaces a good file and leaves no partial one at ``path``.
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
        if check is not None:
            check(staged)  # the data file sits beside the staged graph, where the graph names it
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


def operators_outside_tensorrt(path: str) -> List[str]:
    """The graph's operators that are not in TENSORRT_OPERATORS (empty: the graph parses on TensorRT 8.5)."""
    return [op for op in operator_types(path) if op not in TENSORRT_OPERATORS]


@dataclass(frozen=True)
class OutputParity:
    """One output's parity: onnxruntime against PyTorch FP32, and PyTorch FP32's own noise against FP64."""

    name: str
    difference: float  #: max |onnxruntime - PyTorch FP32| over crops and elements
    noise: float  #: max |PyTorch FP32 - PyTorch FP64|: the network's own FP32 rounding on these crops
    scale: float  #: max |PyTorch FP64|

    @property
    def limit(self) -> float:
        return PARITY_NOISE_FACTOR * self.noise + PARITY_FLOOR * max(1.0, self.scale)

    @property
    def ok(self) -> bool:
        return bool(np.isfinite(self.difference)) and self.difference <= self.limit  # NaN fails


@dataclass(frozen=True)
class ParityReport:
    outputs: Tuple[OutputParity, ...]

    @property
    def ok(self) -> bool:
        return all(output.ok for output in self.outputs)

    @property
    def worst_difference(self) -> float:
        return max(output.difference for output in self.outputs)

    def lines(self) -> List[str]:
        rule = f"limit = {PARITY_NOISE_FACTOR:g} x FP32 noise + {PARITY_FLOOR:g} x max(1, |output|)"
        rows = [f"parity onnxruntime vs PyTorch FP32 per output ({rule}; FP32 noise = |PyTorch FP32 - FP64|):"]
        for o in self.outputs:
            rows.append(f"  {o.name:<11} |diff| {o.difference:.3g}  FP32 noise {o.noise:.3g}  limit {o.limit:.3g}"
                        f"{'' if o.ok else '  FAILED'}")
        return rows


def _outputs(model: torch.nn.Module, batch: np.ndarray, hands: bool, dtype: torch.dtype) -> Dict[str, np.ndarray]:
    with torch.no_grad():
        got = model(torch.from_numpy(batch).to(dtype), hands=hands)
    return {name: got[name].double().numpy() for name in OUTPUT_NAMES}


def parity_report(model: Network, path: str, crops: np.ndarray, threads: int = 1, hands: bool = True) -> ParityReport:
    """Per output: |onnxruntime - PyTorch FP32| and PyTorch's FP32 noise (against the same network in FP64)
    over crops (N, 3, H, W). The network is converted to FP64 and back in place (exact: every FP32 value is an
    FP64 value), so no second copy of its weights is held."""
    import onnxruntime

    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = threads
    session = onnxruntime.InferenceSession(path, options, providers=["CPUExecutionProvider"])
    batches = [crop[None].astype(np.float32) for crop in crops]
    got = [dict(zip(OUTPUT_NAMES, session.run(list(OUTPUT_NAMES), {"img": b}))) for b in batches]
    del session
    fp32 = [_outputs(model, b, hands, torch.float32) for b in batches]
    model.double()
    try:
        fp64 = [_outputs(model, b, hands, torch.float64) for b in batches]
    finally:
        model.float()
    outputs = []
    for name in OUTPUT_NAMES:
        outputs.append(OutputParity(
            name,
            difference=max(float(np.abs(g[name].astype(np.float64) - e[name]).max()) for g, e in zip(got, fp32)),
            noise=max(float(np.abs(e[name] - r[name]).max()) for e, r in zip(fp32, fp64)),
            scale=max(float(np.abs(r[name]).max()) for r in fp64)))
    return ParityReport(tuple(outputs))


def parity(model: Network, path: str, crops: np.ndarray, threads: int = 1, hands: bool = True) -> float:
    """Largest |onnxruntime - PyTorch FP32| over all outputs and crops (N, 3, H, W) float32."""
    return parity_report(model, path, crops, threads, hands).worst_difference


class ExportCheckError(RuntimeError):
    """A check of the staged export failed (the file is not moved to --out); ``report``: the parity report."""

    def __init__(self, message: str, report: Optional[ParityReport] = None) -> None:
        super().__init__(message)
        self.report = report


def checked_export(model: Network, path: str, input_hw: Tuple[int, int], metadata: Dict[str, str],
                   opset: int = DEFAULT_OPSET, hands: bool = True, parity_crops: int = 2,
                   seed: int = 0) -> ParityReport:
    """export_onnx with the operator check (TENSORRT_OPERATORS), the engine contract check and the parity check
    on the staged file: the file is moved to ``path`` only when all pass; otherwise ExportCheckError (with the
    parity report, if one was made) and ``path`` is as it was."""
    from leapnbv_perception.backends.onnxruntime_backend import OnnxRuntimeBackend
    from leapnbv_perception.model_contracts import SMPLERX_CONTRACT, ModelContractError, check_backend_contract

    crops = np.random.default_rng(seed).uniform(0.0, 1.0, size=(parity_crops, 3) + tuple(input_hw))
    reports: List[ParityReport] = []

    def check(staged: str) -> None:
        outside = operators_outside_tensorrt(staged)
        if outside:
            raise ExportCheckError(f"operators TensorRT 8.5 does not parse without a plugin: {', '.join(outside)}")
        try:
            check_backend_contract(OnnxRuntimeBackend(staged), SMPLERX_CONTRACT, source=path)
        except ModelContractError as error:
            raise ExportCheckError(f"engine contract: {str(error).splitlines()[0]}") from error
        report = parity_report(model, staged, crops.astype(np.float32), hands=hands)
        reports.append(report)
        if not report.ok:
            failed = [o.name for o in report.outputs if not o.ok]
            raise ExportCheckError(f"parity onnxruntime vs PyTorch over the limit in {', '.join(failed)}", report)

    export_onnx(model, path, input_hw, metadata, opset, hands=hands, check=check)
    return reports[-1]


def _output_problem(path: str) -> Optional[str]:
    final = os.path.abspath(path)
    folder = os.path.dirname(final)
    if os.path.isdir(final):
        return f"--out '{path}' is a folder"
    if not os.path.isdir(folder):
        return f"--out '{path}': folder '{folder}' does not exist"
    if not os.access(folder, os.W_OK | os.X_OK):
        return f"--out '{path}': folder '{folder}' is not writable"
    return None


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m leapnbv_model_tools export-hmr", description=__doc__)
    parser.add_argument("--checkpoint", required=True,
                        help="smpler_x_{s,b,l,h}32.pth.tar or smplest_x_h.pth.tar (official structure)")
    parser.add_argument("--variant", required=True, choices=sorted(VARIANTS),
                        help="s32, b32, l32, h32 (SMPLer-X), smplest_x_h (SMPLest-X); t*: test-only narrow members")
    parser.add_argument("--out", required=True)
    parser.add_argument("--input", default="512x384", choices=["512x384", "256x192"])
    parser.add_argument("--opset", type=int, default=DEFAULT_OPSET)
    parser.add_argument("--box-ratio", type=float, default=None,
                        help="crop box ratio written to the metadata (default: the family's, 1.25 or 1.2)")
    parser.add_argument("--parity-crops", type=int, default=2, help="random crops compared with onnxruntime")
    parser.add_argument("--without-hands", action="store_true",
                        help="body-only engine: the hand branch is not computed, lhand_pose / rhand_pose are the "
                             "identity rotation (the SMPL-X hand mean pose); metadata leapnbv.hands=not_estimated")
    args = parser.parse_args(argv)
    input_hw = tuple(int(v) for v in args.input.split("x"))
    problem = _output_problem(args.out)
    if problem is None and args.parity_crops < 1:
        problem = f"--parity-crops {args.parity_crops}: at least 1"
    if problem is None and args.without_hands and family_of(args.variant) == "smplest_x":
        problem = (f"--without-hands: {args.variant} has no separate hand branch (its hands come from the body's "
                   "decoder), so a body-only engine would save nothing")
    if problem is not None:
        print(f"export-hmr: {problem}", file=sys.stderr)
        return ModelToolExit.BAD_INPUT
    try:
        model = load_network(args.checkpoint, args.variant)
    except CheckpointError as error:
        print(f"export-hmr: {error.one_line()}", file=sys.stderr)
        return ModelToolExit.BAD_INPUT
    hands = not args.without_hands
    metadata = export_metadata(args.variant, sha256_of(args.checkpoint), input_hw, args.box_ratio, hands=hands)
    try:
        report = checked_export(model, args.out, input_hw, metadata, args.opset, hands=hands,
                                parity_crops=args.parity_crops)
    except ExportCheckError as error:
        for line in error.report.lines() if error.report is not None else []:
            print(line)
        kept = "the earlier file there is unchanged" if os.path.exists(args.out) else "nothing written"
        print(f"export-hmr: {error}; {kept} at '{args.out}'", file=sys.stderr)
        return ModelToolExit.CHECK_FAILED
    print(f"{args.out}: opset {args.opset}, hands {metadata[HANDS_KEY]}, "
          f"operators {', '.join(operator_types(args.out))}")
    for line in report.lines():
        print(line)
    return ModelToolExit.OK
