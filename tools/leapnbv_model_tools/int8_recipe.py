"""The INT8 recipe of quantize-int8: which integer format for which CPU, and the graph it is applied to.

onnxruntime's CPU kernels (MLAS) for a QDQ model's integer convolutions and matrix products:

- x86-64 with VNNI (AVX512-VNNI, AVX-VNNI) or AMX: the fast path is **U8S8** (activations uint8,
  weights int8): VPDPBUSD multiplies unsigned by signed bytes. S8S8 has no such instruction and
  runs slower than FP32 there (YOLOv8s: 0.6-0.7x FP32; U8S8 2.6-3.0x; docs/INT8.md).
- x86-64 with AVX2 or AVX-512 but no VNNI: U8S8 too (VPMADDUBSW), with **reduce_range** (7-bit
  weights): onnxruntime's documentation (Quantize ONNX models, "When to use reduce-range") gives it
  for U8S8 on these CPUs to avoid VPMADDUBSW's 16-bit saturation, "not needed on machines supporting
  VNNI", and per-channel weights "generally" need it there. Argued from that documentation, not
  measured (no such CPU here).
- ARM64 (the Jetson's cores): **S8S8 with symmetric activations** (zero point 0). onnxruntime's
  documentation has no U8S8 saturation issue on ARM and gives S8S8 QDQ as the default; on the Jetson
  the engine is TensorRT, whose INT8 takes only symmetric signed QDQ (zero point 0), so this is the
  file that also serves TensorRT. Argued, not measured.

Everything else the same for each: static QDQ, per-channel weights, MinMax calibration on rendered
frames, after onnxruntime's pre-processing (``quant_pre_process``: symbolic shape inference, graph
optimization, ONNX shape inference), and before it the transposed convolutions rewritten as
convolutions (``int8_graph.conv_transpose_to_conv``: onnxruntime has no integer ConvTranspose).

The operators quantized differ per engine (``OP_SETS``, measured): the detector all that onnxruntime
can quantize; the HMR engine only the products (Conv, MatMul, Gemm) and the data movement between
them (``PRODUCT_OPS``), its residual additions, LayerNorms and GELUs float.
"""

from __future__ import annotations

import platform
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple

#: CPU kinds and the recipe each gets (``auto``)
CPU_KINDS = ("x86-vnni", "x86-avx2", "arm64", "other")

#: the recipes a user can ask for (``--recipe``)
RECIPES = ("u8s8", "u8s8-reduce-range", "s8s8")

RECIPE_FOR_CPU = {"x86-vnni": "u8s8", "x86-avx2": "u8s8-reduce-range", "arm64": "s8s8", "other": "u8s8"}

#: operators quantized when only the products and the data movement between them are (the "products" op set)
PRODUCT_OPS = ("Conv", "MatMul", "Gemm", "Relu", "Clip", "MaxPool", "Resize", "Concat", "Slice", "Split",
               "Reshape", "Transpose", "Squeeze", "Unsqueeze", "Flatten", "DepthToSpace")

#: op set per engine (measured: scripts/experiments/int8_recipes.py, docs/INT8.md): the detector gains from
#: every operator onnxruntime can quantize (SiLU's Sigmoid and Mul stay uint8 between the convolutions: 113 ms
#: against 158 ms with the products only); the HMR engine is as fast with the products only (120 ms against
#: 123-128 ms) and keeps its residual additions, normalizations and GELUs in float
OP_SETS = {"detector": "all", "hmr": "products"}

#: operator types whose outputs stay float per engine: the HMR engine's MatMuls (onnxruntime then runs them as
#: MatMulIntegerToFloat); a quantized attention-score output makes onnxruntime fuse the Softmax into a
#: QLinearSoftmax, slower than the float Softmax it replaces (s32: 34 ms against 6 ms)
FLOAT_OUTPUTS = {"detector": (), "hmr": ("MatMul",)}


def quantized_ops(op_set: str) -> Optional[List[str]]:
    """The op_types_to_quantize of an op set.

    "all" (None: onnxruntime's whole registry), "no-softmax" (all but Softmax, whose QLinear kernel is
    slower than the float one), "products" (PRODUCT_OPS).
    """
    if op_set == "all":
        return None
    if op_set == "products":
        return list(PRODUCT_OPS)
    if op_set == "no-softmax":
        from onnxruntime.quantization.registry import QDQRegistry, QLinearOpsRegistry

        return sorted((set(QDQRegistry) | set(QLinearOpsRegistry)) - {"Softmax"})
    raise ValueError(f"unknown op set '{op_set}'")


#: the metadata keys quantize-int8 writes (beside the export's own leapnbv.* keys, kept)
METADATA_PREFIX = "leapnbv.int8."

#: the HMR engine's last layers: the encoder's final LayerNorm and every regression head (what --keep-fp32 heads
#: leaves in FP32); node-name prefixes of the export-hmr graph
HMR_HEAD_PREFIXES = ("/model/encoder/last_norm/", "/model/body_regressor/", "/model/face_regressor/",
                     "/model/hand_regressor/", "/model/body_position_net/", "/model/hand_position_net/",
                     "/model/box_net/bbox_center", "/model/box_net/lhand_size", "/model/box_net/rhand_size")


@dataclass(frozen=True)
class CpuInfo:
    """What quantize-int8 knows of the CPU: its kind and the flags that decided it."""

    kind: str
    machine: str
    flags: Tuple[str, ...] = field(default_factory=tuple)
    model_name: str = ""

    def describe(self) -> str:
        """One line: the kind, the model name and the integer-relevant flags."""
        shown = " ".join(self.flags) if self.flags else "none"
        return f"{self.kind} ({self.model_name or self.machine}; flags: {shown})"


#: the cpuinfo flags that matter for the integer kernels, in the order they are printed
INTEGER_FLAGS = ("avx2", "avx512f", "avx512bw", "avx512_vnni", "avx_vnni", "amx_tile", "amx_int8", "asimddp", "i8mm")


def classify_cpu(machine: str, flags: Sequence[str], model_name: str = "") -> CpuInfo:
    """The CPU kind from the machine name (platform.machine()) and the cpuinfo flags."""
    present = set(flags)
    shown = tuple(f for f in INTEGER_FLAGS if f in present)
    arch = machine.lower()
    if arch in ("x86_64", "amd64", "i686", "i386"):
        if present & {"avx512_vnni", "avx_vnni", "amx_int8"}:
            return CpuInfo("x86-vnni", machine, shown, model_name)
        if "avx2" in present:
            return CpuInfo("x86-avx2", machine, shown, model_name)
        return CpuInfo("other", machine, shown, model_name)
    if arch in ("aarch64", "arm64"):
        return CpuInfo("arm64", machine, shown, model_name)
    return CpuInfo("other", machine, shown, model_name)


def read_cpuinfo(path: str = "/proc/cpuinfo") -> Tuple[List[str], str]:
    """(flags, model name) of the first processor in /proc/cpuinfo; ([], "") where there is none."""
    flags: List[str] = []
    model_name = ""
    try:
        with open(path) as handle:
            for line in handle:
                key, _, value = line.partition(":")
                key = key.strip().lower()
                if key in ("flags", "features") and not flags:
                    flags = value.split()
                elif key in ("model name", "cpu model") and not model_name:
                    model_name = value.strip()
    except OSError:
        pass
    return flags, model_name


def this_cpu() -> CpuInfo:
    """The CPU this process runs on."""
    flags, model_name = read_cpuinfo()
    return classify_cpu(platform.machine(), flags, model_name)


@dataclass(frozen=True)
class Recipe:
    """The quantize_static settings of one recipe."""

    name: str
    activation_type: str  # "uint8" or "int8"
    weight_type: str
    reduce_range: bool
    symmetric_activations: bool
    per_channel: bool = True

    def quantize_kwargs(self) -> Dict[str, Any]:
        """Keyword arguments for onnxruntime.quantization.quantize_static."""
        from onnxruntime.quantization import QuantFormat, QuantType

        types = {"uint8": QuantType.QUInt8, "int8": QuantType.QInt8}
        return {"quant_format": QuantFormat.QDQ, "per_channel": self.per_channel, "reduce_range": self.reduce_range,
                "activation_type": types[self.activation_type], "weight_type": types[self.weight_type],
                "extra_options": {"ActivationSymmetric": self.symmetric_activations, "WeightSymmetric": True}}


def recipe(name: str) -> Recipe:
    """The recipe called ``name`` (one of RECIPES)."""
    if name == "u8s8":
        return Recipe("u8s8", "uint8", "int8", reduce_range=False, symmetric_activations=False)
    if name == "u8s8-reduce-range":
        return Recipe("u8s8-reduce-range", "uint8", "int8", reduce_range=True, symmetric_activations=False)
    if name == "s8s8":
        return Recipe("s8s8", "int8", "int8", reduce_range=False, symmetric_activations=True)
    raise ValueError(f"unknown recipe '{name}'; known: {', '.join(RECIPES)}")


def choose_recipe(requested: str, cpu: CpuInfo) -> Tuple[Recipe, str]:
    """(recipe, why) for ``--recipe requested`` ("auto" or one of RECIPES) on ``cpu``."""
    if requested == "auto":
        chosen = RECIPE_FOR_CPU[cpu.kind]
        return recipe(chosen), f"auto for {cpu.kind}"
    return recipe(requested), "asked for"


def excluded_nodes(model, keep_fp32: str) -> List[str]:
    """Node names that stay FP32 for ``--keep-fp32`` ("none" or "heads": HMR_HEAD_PREFIXES)."""
    if keep_fp32 == "none":
        return []
    if keep_fp32 != "heads":
        raise ValueError(f"unknown --keep-fp32 '{keep_fp32}'")
    return [n.name for n in model.graph.node if n.name.startswith(HMR_HEAD_PREFIXES)]


def metadata(recipe_: Recipe, why: str, cpu: CpuInfo, rewritten: int, kept_fp32: int, keep_fp32: str,
             calibration_frames: int, op_set: str, float_outputs: Sequence[str] = ()) -> Dict[str, str]:
    """The leapnbv.int8.* metadata of a written model."""
    return {
        f"{METADATA_PREFIX}recipe": recipe_.name,
        f"{METADATA_PREFIX}activations": recipe_.activation_type + (" symmetric" if recipe_.symmetric_activations
                                                                    else " asymmetric"),
        f"{METADATA_PREFIX}weights": f"{recipe_.weight_type} symmetric per-channel"
                                     + (" reduce-range (7 bit)" if recipe_.reduce_range else ""),
        f"{METADATA_PREFIX}chosen": why,
        f"{METADATA_PREFIX}cpu": cpu.describe(),
        f"{METADATA_PREFIX}preprocess": f"conv_transpose_to_conv ({rewritten} rewritten); quant_pre_process",
        f"{METADATA_PREFIX}keep_fp32": f"{keep_fp32} ({kept_fp32} nodes)",
        f"{METADATA_PREFIX}calibration": f"MinMax on {calibration_frames} rendered frames",
        f"{METADATA_PREFIX}quantized_ops": op_set,
        f"{METADATA_PREFIX}float_outputs": ",".join(float_outputs) or "none",
    }


def read_int8_metadata(path: str) -> Dict[str, str]:
    """The leapnbv.int8.* metadata of an ONNX file ({} when it has none)."""
    import onnx

    proto = onnx.load(path, load_external_data=False)
    return {p.key: p.value for p in proto.metadata_props if p.key.startswith(METADATA_PREFIX)}


def prepare(model_path: str, out_path: str) -> int:
    """The FP32 model quantize_static reads: transposed convolutions rewritten, then quant_pre_process.

    Returns how many transposed convolutions were rewritten.
    """
    import os

    import onnx
    from onnxruntime.quantization.shape_inference import quant_pre_process

    model = onnx.load(model_path)
    rewritten = conv_transpose_to_conv_checked(model)
    staged = out_path + ".rewritten.onnx"
    onnx.save(model, staged)
    try:
        quant_pre_process(staged, out_path)
    finally:
        os.remove(staged)
    return rewritten


def conv_transpose_to_conv_checked(model) -> int:
    """int8_graph.conv_transpose_to_conv, then ONNX shape inference and the checker."""
    import onnx

    from leapnbv_model_tools.int8_graph import conv_transpose_to_conv

    rewritten = conv_transpose_to_conv(model)
    if rewritten:
        inferred = onnx.shape_inference.infer_shapes(model)
        model.CopyFrom(inferred)
        onnx.checker.check_model(model)
    return rewritten


def quantize(model_path: str, out_path: str, reader, recipe_: Recipe, nodes_to_exclude: Optional[List[str]] = None,
             op_types: Optional[Sequence[str]] = None, float_outputs: Sequence[str] = ()) -> None:
    """quantize_static of an already prepared model (``prepare``) with ``recipe_``.

    ``float_outputs``: operator types whose outputs are not quantized (onnxruntime's
    OpTypesToExcludeOutputQuantization).
    """
    from onnxruntime.quantization import quantize_static

    kwargs = recipe_.quantize_kwargs()
    if float_outputs:
        kwargs["extra_options"] = dict(kwargs["extra_options"], OpTypesToExcludeOutputQuantization=list(float_outputs))
    quantize_static(model_path, out_path, reader, op_types_to_quantize=list(op_types) if op_types else None,
                    nodes_to_exclude=nodes_to_exclude or None, **kwargs)


def write_metadata(path: str, entries: Dict[str, str], keep_from: Optional[str] = None) -> None:
    """Add ``entries`` (and the leapnbv.* metadata of ``keep_from``, the source model) to the ONNX file at path."""
    import onnx

    model = onnx.load(path)
    present = {p.key: p for p in model.metadata_props}
    values: Dict[str, str] = {}
    if keep_from is not None:
        source = onnx.load(keep_from, load_external_data=False)
        values.update({p.key: p.value for p in source.metadata_props if p.key.startswith("leapnbv.")})
    values.update(entries)
    for key, value in values.items():
        if key in present:
            present[key].value = value
        else:
            entry = model.metadata_props.add()
            entry.key, entry.value = key, value
    onnx.save(model, path)
