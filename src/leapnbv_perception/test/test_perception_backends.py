"""Tests for the engine backends: onnxruntime on the contract models, TensorRT logic on fakes."""

from __future__ import annotations

import json
import logging
import os
import re
import sys
import types
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
import onnx
import pytest

from leapnbv_perception.backends import ModelFileNotFoundError, create_backend, tensorrt_backend
from leapnbv_perception.backends.base import BackendError
from leapnbv_perception.backends.precision_plan import (
    PrecisionPlanError,
    load_precision_plan,
    parse_precision_plan,
    write_precision_plan,
)
from leapnbv_perception.backends.tensorrt_backend import (
    CudaMemory,
    TensorRTAdapter,
    TensorRTBackend,
    engine_cache_key,
    engine_cache_path,
)
from leapnbv_perception.detector import PersonDetector
from leapnbv_perception.model_contracts import (
    HMR_OUTPUT_SIZES,
    SMPLERX_CONTRACT,
    YOLOV8_CONTRACT,
    ModelContractError,
    check_backend_contract,
)
from leapnbv_stand_ins.contract_models import write_contract_detector, write_contract_hmr


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> Dict[str, str]:
    folder = tmp_path_factory.mktemp("contract_models")
    return {
        "detector": write_contract_detector(str(folder / "contract_yolov8.onnx")),
        "hmr": write_contract_hmr(str(folder / "contract_smplerx.onnx")),
        "hmr256": write_contract_hmr(str(folder / "contract_smplerx_256.onnx"), (256, 192)),
    }


def test_contract_models_are_small(models: Dict[str, str]) -> None:
    for path in models.values():
        assert os.path.getsize(path) < 2 * 1024 * 1024


def test_onnxruntime_runs_contract_detector(models: Dict[str, str]) -> None:
    backend = create_backend("onnxruntime", models["detector"])
    check_backend_contract(backend, YOLOV8_CONTRACT)
    assert backend.precision == "fp32"
    detector = PersonDetector(backend)
    rgb = np.full((480, 640, 3), 100, dtype=np.uint8)
    assert len(detector.detect(rgb)) == 0
    rgb[120:400, 250:330] = (220, 30, 30)  # the contract model's "person" is saturated red
    boxes = detector.detect(rgb)
    assert len(boxes) == 1
    np.testing.assert_allclose(boxes[0, :4], [250, 120, 330, 400], atol=8.5)
    rgb_moved = np.full((480, 640, 3), 100, dtype=np.uint8)
    rgb_moved[100:300, 400:480] = (220, 30, 30)
    np.testing.assert_allclose(detector.detect(rgb_moved)[0, :4], [400, 100, 480, 300], atol=8.5)


@pytest.mark.parametrize("key, hw", [("hmr", (512, 384)), ("hmr256", (256, 192))])
def test_onnxruntime_runs_contract_hmr(models: Dict[str, str], key: str, hw: tuple) -> None:
    backend = create_backend("onnxruntime", models[key], intra_op_threads=1)
    check_backend_contract(backend, SMPLERX_CONTRACT)
    rng = np.random.default_rng(0)
    first = backend.run({"img": rng.random((1, 3) + hw, dtype=np.float32)})
    second = backend.run({"img": rng.random((1, 3) + hw, dtype=np.float32)})
    for name, size in HMR_OUTPUT_SIZES.items():
        assert first[name].shape == (1, size)
        assert np.all(np.isfinite(first[name]))
        assert not np.allclose(first[name], second[name])
    assert abs(first["cam_param"][0, 2]) <= 0.5


def test_wrong_output_name_is_refused(models: Dict[str, str], tmp_path: Path) -> None:
    model = onnx.load(models["detector"])
    for node in model.graph.node:
        node.output[:] = ["boxes" if name == "output0" else name for name in node.output]
    model.graph.output[0].name = "boxes"
    path = tmp_path / "renamed.onnx"
    onnx.save(model, str(path))
    backend = create_backend("onnxruntime", str(path))
    with pytest.raises(ModelContractError) as error:
        PersonDetector(backend)
    message = str(error.value)
    assert "missing output 'output0'" in message
    assert "boxes(1, 84, 8400)" in message and "renamed.onnx" in message


def test_hmr_model_is_not_a_detector(models: Dict[str, str]) -> None:
    with pytest.raises(ModelContractError, match="images"):
        PersonDetector(create_backend("onnxruntime", models["hmr"]))


def test_missing_model_file_names_path(tmp_path: Path) -> None:
    missing = tmp_path / "models" / "yolov8s.onnx"
    for name in ("onnxruntime", "tensorrt"):
        with pytest.raises(ModelFileNotFoundError, match="models/yolov8s.onnx"):
            create_backend(name, str(missing))
    assert issubclass(ModelFileNotFoundError, FileNotFoundError)


def test_unknown_backend_and_precision(models: Dict[str, str]) -> None:
    with pytest.raises(ValueError, match="unknown engine backend 'openvino'; known: onnxruntime, "
                                         "onnxruntime_last_bit_nudged, tensorrt"):
        create_backend("openvino", models["detector"])
    with pytest.raises(ValueError, match="int8"):
        create_backend("onnxruntime", models["detector"], precision="int8")


def test_a_backend_registered_from_outside_is_created_by_name(tmp_path: Path) -> None:
    from leapnbv_perception.backends import ENGINE_BACKENDS, BackendSettings, register_backend

    model = tmp_path / "m.onnx"
    model.write_bytes(b"not read by this backend")
    made = []
    register_backend("Recorded", lambda path, precision, settings: made.append((path, precision, settings)) or made)
    try:
        assert "recorded" in ENGINE_BACKENDS.names()
        assert create_backend(" RECORDED ", str(model), precision="FP16", intra_op_threads=3, providers=["A"]) is made
        assert made == [(str(model), "fp16", BackendSettings(providers=("A",), intra_op_threads=3))]
        with pytest.raises(ModelFileNotFoundError):
            create_backend("recorded", str(tmp_path / "missing.onnx"))
    finally:
        ENGINE_BACKENDS.unregister("recorded")


def test_run_rejects_wrong_input(models: Dict[str, str]) -> None:
    backend = create_backend("onnxruntime", models["detector"])
    with pytest.raises(BackendError, match="images"):
        backend.run({"img": np.zeros((1, 3, 640, 640), np.float32)})
    with pytest.raises(BackendError, match=r"\(1, 3, 320, 320\)"):
        backend.run({"images": np.zeros((1, 3, 320, 320), np.float32)})


# ---------------------------------------------------------------------------------------
# TensorRT: a fake tensorrt module and fake device memory
# ---------------------------------------------------------------------------------------


class FakeMemory:
    """Device memory as numpy byte buffers keyed by fake pointers."""

    def __init__(self) -> None:
        self.buffers: Dict[int, np.ndarray] = {}
        self.next_pointer = 4096
        self.stream_handle = 77
        self.synchronized = 0

    def gpu_name(self) -> str:
        return "Fake Xavier"

    def allocate(self, nbytes: int) -> int:
        pointer = self.next_pointer
        self.next_pointer += 4096
        self.buffers[pointer] = np.zeros(nbytes, dtype=np.uint8)
        return pointer

    def copy_to_device(self, pointer: int, host: np.ndarray) -> None:
        self.buffers[pointer][:] = np.frombuffer(np.ascontiguousarray(host).tobytes(), dtype=np.uint8)

    def copy_to_host(self, host: np.ndarray, pointer: int) -> None:
        host[...] = np.frombuffer(self.buffers[pointer].tobytes(), dtype=host.dtype).reshape(host.shape)

    def synchronize(self) -> None:
        self.synchronized += 1

    def free_all(self) -> None:
        self.buffers.clear()


def doubled(memory: FakeMemory, source: int, target: int) -> None:
    values = np.frombuffer(memory.buffers[source].tobytes(), dtype=np.float32) * 2.0
    memory.buffers[target][:] = np.frombuffer(values.tobytes(), dtype=np.uint8)


class TensorContext:
    def __init__(self, memory: FakeMemory) -> None:
        self.memory = memory
        self.addresses: Dict[str, int] = {}
        self.streams: List[int] = []

    def set_tensor_address(self, name: str, pointer: int) -> None:
        self.addresses[name] = pointer

    def execute_async_v3(self, stream: int) -> bool:
        self.streams.append(stream)
        doubled(self.memory, self.addresses["x"], self.addresses["y"])
        return True


class BindingContext:
    def __init__(self, memory: FakeMemory) -> None:
        self.memory = memory

    def execute_v2(self, bindings: List[int]) -> bool:
        doubled(self.memory, bindings[0], bindings[1])  # binding order: x, y
        return True


class TensorApiEngine:
    """TensorRT 10 style: tensors by name."""

    def __init__(self, memory: FakeMemory) -> None:
        self.memory = memory
        self.num_io_tensors = 2

    def get_tensor_name(self, index: int) -> str:
        return ["x", "y"][index]

    def get_tensor_mode(self, name: str) -> str:
        return "INPUT" if name == "x" else "OUTPUT"

    def get_tensor_shape(self, name: str) -> tuple:
        return (1, 4)

    def get_tensor_dtype(self, name: str) -> str:
        return "float"

    def create_execution_context(self) -> TensorContext:
        return TensorContext(self.memory)


class BindingApiEngine:
    """TensorRT 8.x style: bindings by index."""

    def __init__(self, memory: FakeMemory) -> None:
        self.memory = memory
        self.num_bindings = 2

    def get_binding_name(self, index: int) -> str:
        return ["x", "y"][index]

    def binding_is_input(self, index: int) -> bool:
        return index == 0

    def get_binding_shape(self, index: int) -> tuple:
        return (1, 4)

    def get_binding_dtype(self, index: int) -> str:
        return "float"

    def create_execution_context(self) -> BindingContext:
        return BindingContext(self.memory)


# Layers of the fake network: name -> output data types (what TensorRT's ONNX parser would create).
FAKE_LAYERS = [
    ("/encoder/patch_embed/Conv", ["FLOAT"]),
    ("/encoder/blocks.11/norm1/ReduceMean", ["FLOAT"]),
    ("/encoder/blocks.11/norm1/Pow", ["FLOAT"]),
    ("/encoder/blocks.11/norm1/Sqrt", ["FLOAT"]),
    ("/encoder/blocks.11/norm1/Shape", ["INT32"]),
    ("/encoder/blocks.11/attn/Softmax", ["FLOAT"]),
    ("/head/Gemm", ["FLOAT", "FLOAT"]),
]


class FakeTensor:
    def __init__(self, dtype: str) -> None:
        self.dtype = dtype


class FakeLayer:
    """A network layer that records the precision constraints set on it."""

    def __init__(self, name: str, output_types: List[str]) -> None:
        self.name = name
        self._outputs = [FakeTensor(dtype) for dtype in output_types]
        self.num_outputs = len(self._outputs)
        self.precision = None  # TensorRT: unset until a constraint is given
        self.output_types: Dict[int, str] = {}

    def get_output(self, index: int) -> FakeTensor:
        return self._outputs[index]

    def set_output_type(self, index: int, dtype: str) -> None:
        if self._outputs[index].dtype not in ("FLOAT", "HALF"):
            raise TypeError("cannot set a float type on a non-float output")  # what TensorRT refuses
        self.output_types[index] = dtype


class FakeNetwork:
    def __init__(self, flags: int) -> None:
        self.flags = flags
        self.layers: List[FakeLayer] = []

    @property
    def num_layers(self) -> int:
        return len(self.layers)

    def get_layer(self, index: int) -> FakeLayer:
        return self.layers[index]


def make_fake_tensorrt(memory: FakeMemory, tensor_api: bool, version: str = "10.3.0") -> types.ModuleType:
    trt = types.ModuleType("tensorrt")
    trt.__version__ = version
    trt.builds = []
    trt.deserialized = []
    trt.parsed_paths = []
    trt.layer_constraints = []  # per build: layer name -> (precision, {output: type})

    class Logger:
        WARNING = 2

        def __init__(self, level: int) -> None:
            self.level = level

    class Runtime:
        def __init__(self, logger: Logger) -> None:
            pass

        def deserialize_cuda_engine(self, data: bytes) -> object:
            trt.deserialized.append(data)
            if data.startswith(b"CORRUPT"):
                raise RuntimeError("Serialization assertion failed")
            if not data.startswith(b"ENGINE"):
                return None
            return TensorApiEngine(memory) if tensor_api else BindingApiEngine(memory)

    class Config:
        def __init__(self) -> None:
            self.flags: List[str] = []

        def set_memory_pool_limit(self, pool: str, size: int) -> None:
            self.workspace = size

        def set_flag(self, flag: str) -> None:
            self.flags.append(flag)

    class Builder:
        def __init__(self, logger: Logger) -> None:
            pass

        def create_network(self, flags: int) -> FakeNetwork:
            return FakeNetwork(flags)

        def create_builder_config(self) -> Config:
            return Config()

        def build_serialized_network(self, network: FakeNetwork, config: Config) -> bytes:
            trt.builds.append(list(config.flags))
            trt.layer_constraints.append({
                layer.name: (layer.precision, dict(layer.output_types))
                for layer in network.layers if layer.precision is not None or layer.output_types
            })
            return b"ENGINE" + b"-fp16" * ("FP16" in config.flags)

    class OnnxParser:
        def __init__(self, network: FakeNetwork, logger: Logger) -> None:
            self.network = network
            self.num_errors = 0

        def parse(self, data: bytes, path: Optional[str] = None) -> bool:
            trt.parsed_paths.append(path)
            if not data.startswith(b"ONNX"):
                return False
            self.network.layers = [FakeLayer(name, types_) for name, types_ in FAKE_LAYERS]
            return True

    trt.Logger = Logger
    trt.Runtime = Runtime
    trt.Builder = Builder
    trt.OnnxParser = OnnxParser
    trt.NetworkDefinitionCreationFlag = types.SimpleNamespace(EXPLICIT_BATCH=0)
    trt.MemoryPoolType = types.SimpleNamespace(WORKSPACE="workspace")
    trt.BuilderFlag = types.SimpleNamespace(FP16="FP16", OBEY_PRECISION_CONSTRAINTS="OBEY_PRECISION_CONSTRAINTS")
    trt.DataType = types.SimpleNamespace(FLOAT="FLOAT", HALF="HALF", INT32="INT32", BOOL="BOOL")
    trt.float32 = trt.DataType.FLOAT
    trt.TensorIOMode = types.SimpleNamespace(INPUT="INPUT", OUTPUT="OUTPUT")
    trt.nptype = lambda dtype: np.float32
    return trt


@pytest.fixture
def onnx_file(tmp_path: Path) -> str:
    path = tmp_path / "model.onnx"
    path.write_bytes(b"ONNX fake model bytes")
    return str(path)


def test_cache_key_depends_on_every_part() -> None:
    base = engine_cache_key(b"abc", "8.5.2", "Xavier", "fp16")
    assert len(base) == 64 and base == engine_cache_key(b"abc", "8.5.2", "Xavier", "FP16")
    others = {
        engine_cache_key(b"abd", "8.5.2", "Xavier", "fp16"),
        engine_cache_key(b"abc", "10.3.0", "Xavier", "fp16"),
        engine_cache_key(b"abc", "8.5.2", "Orin", "fp16"),
        engine_cache_key(b"abc", "8.5.2", "Xavier", "fp32"),
    }
    assert base not in others and len(others) == 4


def test_cache_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    key = "f" * 64
    path = engine_cache_path(str(tmp_path), "/models/smplerx_h32.onnx", "fp16", key)
    assert path == str(tmp_path / ("smplerx_h32.fp16.%s.engine" % ("f" * 20)))
    monkeypatch.setenv("LEAPNBV_ENGINE_CACHE", str(tmp_path / "env"))
    assert engine_cache_path(None, "a.onnx", "fp32", key).startswith(str(tmp_path / "env"))


@pytest.mark.parametrize("tensor_api", [True, False])
def test_tensorrt_backend_builds_caches_and_runs(onnx_file: str, tmp_path: Path, tensor_api: bool) -> None:
    memory = FakeMemory()
    trt = make_fake_tensorrt(memory, tensor_api)
    cache = tmp_path / "cache"
    backend = TensorRTBackend(onnx_file, "fp16", str(cache), trt=trt, memory=memory)
    assert backend.engine_was_built and trt.builds == [["FP16"]]
    assert os.path.isfile(backend.engine_path) and backend.engine_path.startswith(str(cache))
    assert backend.uses_tensor_api == tensor_api
    assert dict(backend.input_specs)["x"].shape == (1, 4) and list(backend.output_specs) == ["y"]
    x = np.array([[1.0, -2.0, 3.5, 0.25]], dtype=np.float32)
    np.testing.assert_allclose(backend.run({"x": x})["y"], 2.0 * x)
    assert memory.synchronized == 1
    if tensor_api:
        assert backend._context.streams == [memory.stream_handle]

    again = TensorRTBackend(onnx_file, "fp16", str(cache), trt=trt, memory=FakeMemory())
    assert not again.engine_was_built and len(trt.builds) == 1
    assert again.engine_path == backend.engine_path


@pytest.mark.parametrize("bad_cache", [b"CORRUPT engine", b"stale engine from TensorRT 8.4"])
def test_tensorrt_rebuilds_unusable_cache(onnx_file: str, tmp_path: Path, bad_cache: bytes) -> None:
    memory = FakeMemory()
    trt = make_fake_tensorrt(memory, tensor_api=True)
    first = TensorRTBackend(onnx_file, "fp32", str(tmp_path), trt=trt, memory=memory)
    Path(first.engine_path).write_bytes(bad_cache)
    second = TensorRTBackend(onnx_file, "fp32", str(tmp_path), trt=trt, memory=FakeMemory())
    assert second.engine_was_built and trt.builds == [[], []]
    assert Path(second.engine_path).read_bytes() == b"ENGINE"


def test_tensorrt_precision_and_version_change_the_cache(onnx_file: str, tmp_path: Path) -> None:
    memory = FakeMemory()
    fp32 = TensorRTBackend(onnx_file, "fp32", str(tmp_path), trt=make_fake_tensorrt(memory, True), memory=memory)
    fp16 = TensorRTBackend(onnx_file, "fp16", str(tmp_path), trt=make_fake_tensorrt(memory, True), memory=memory)
    old_trt = make_fake_tensorrt(memory, False, "8.5.2")
    old = TensorRTBackend(onnx_file, "fp32", str(tmp_path), trt=old_trt, memory=memory)
    assert len({fp32.engine_path, fp16.engine_path, old.engine_path}) == 3
    assert all(b.engine_was_built for b in (fp32, fp16, old))


def test_tensorrt_parse_failure_is_reported(tmp_path: Path) -> None:
    path = tmp_path / "broken.onnx"
    path.write_bytes(b"not an onnx file")
    memory = FakeMemory()
    with pytest.raises(BackendError, match="broken.onnx"):
        TensorRTBackend(str(path), "fp32", str(tmp_path), trt=make_fake_tensorrt(memory, True), memory=memory)


def test_tensorrt_missing_module_is_a_clear_error() -> None:
    try:
        import tensorrt  # noqa: F401
    except ImportError:
        with pytest.raises(BackendError, match="onnxruntime"):
            TensorRTAdapter()
    else:
        pytest.skip("tensorrt is installed here")


# ---------------------------------------------------------------------------------------
# The FP16 precision plan
# ---------------------------------------------------------------------------------------

NORM1 = "/encoder/blocks.11/norm1/*"
SOFTMAX = "/encoder/blocks.11/attn/Softmax"


def test_precision_plan_parsing_and_digest(tmp_path: Path) -> None:
    path = write_precision_plan(str(tmp_path / "plan.json"), [NORM1, SOFTMAX, NORM1], tool="fp16_check 0.1")
    plan = load_precision_plan(path)
    assert plan.keep_fp32 == (NORM1, SOFTMAX) and plan.path == path
    assert plan.matches("/encoder/blocks.11/norm1/Pow") and plan.matches(SOFTMAX)
    assert not plan.matches("/encoder/blocks.1/norm1/Pow") and not plan.matches(SOFTMAX + "_1")
    reordered = tmp_path / "reordered.json"
    reordered.write_text(json.dumps({"keep_fp32": [SOFTMAX, NORM1], "version": 1, "notes": "same layers"}))
    assert load_precision_plan(str(reordered)).digest == plan.digest
    other = parse_precision_plan({"version": 1, "keep_fp32": [NORM1]})
    assert other.digest != plan.digest
    assert load_precision_plan("") is None and load_precision_plan(None) is None


@pytest.mark.parametrize("content, message", [
    ("{not json", "not readable JSON"),
    ('{"version": 2, "keep_fp32": []}', "version 2 is not supported"),
    ('{"version": 1, "keep_fp32": "/head/*"}', "'keep_fp32' must be a list"),
    ('{"version": 1, "keep_fp32": [""]}', "'keep_fp32' must be a list"),
    ('[1, 2]', "expected a JSON object"),
])
def test_precision_plan_errors_name_the_file(tmp_path: Path, content: str, message: str) -> None:
    path = tmp_path / "bad_plan.json"
    path.write_text(content)
    with pytest.raises(PrecisionPlanError, match=message) as error:
        load_precision_plan(str(path))
    assert "bad_plan.json" in str(error.value)
    with pytest.raises(PrecisionPlanError, match="not found.*missing.json"):
        load_precision_plan(str(tmp_path / "missing.json"))


def test_engine_params_have_the_plan_field() -> None:
    from leapnbv_perception.params import EngineParams, HmrParams

    assert EngineParams().precision_plan_path == "" and HmrParams().precision_plan_path == ""


def test_node_loader_passes_the_plan(monkeypatch: pytest.MonkeyPatch) -> None:
    from leapnbv_perception import backends
    from leapnbv_perception.nodes.engine_loading import create_engine_backend
    from leapnbv_perception.params import HmrParams

    seen = {}
    monkeypatch.setattr(backends, "create_backend", lambda *args, **kwargs: seen.update(kwargs) or "backend")
    params = HmrParams(backend="tensorrt", model_file_path="/m/s32.onnx", precision_plan_path="/m/s32.plan.json")
    assert create_engine_backend(params) == "backend"
    assert seen["precision_plan_path"] == "/m/s32.plan.json"


def test_fp16_engine_keeps_planned_layers_in_fp32(onnx_file: str, tmp_path: Path,
                                                  caplog: pytest.LogCaptureFixture) -> None:
    plan = write_precision_plan(str(tmp_path / "plan.json"), [NORM1, SOFTMAX])
    memory = FakeMemory()
    trt = make_fake_tensorrt(memory, tensor_api=False, version="8.5.2.2")
    with caplog.at_level(logging.INFO, logger="leapnbv_perception.backends.tensorrt_backend"):
        backend = TensorRTBackend(onnx_file, "fp16", str(tmp_path / "cache"), trt=trt, memory=memory,
                                  precision_plan_path=plan)
    kept = ["/encoder/blocks.11/norm1/ReduceMean", "/encoder/blocks.11/norm1/Pow", "/encoder/blocks.11/norm1/Sqrt",
            SOFTMAX]
    assert backend.kept_fp32_layers == kept
    assert trt.builds == [["FP16", "OBEY_PRECISION_CONSTRAINTS"]]
    constraints = trt.layer_constraints[0]
    assert sorted(constraints) == sorted(kept)  # the shape layer (int32 output) and the others untouched
    assert all(value == ("FLOAT", {0: "FLOAT"}) for value in constraints.values())
    line = [r.getMessage() for r in caplog.records if "keeps 4 layers in FP32" in r.getMessage()]
    assert len(line) == 1 and all(name in line[0] for name in kept) and "plan.json" in line[0]
    assert "skipped (outputs not floating point): /encoder/blocks.11/norm1/Shape" in line[0]
    np.testing.assert_allclose(backend.run({"x": np.ones((1, 4), np.float32)})["y"], 2.0)

    caplog.clear()
    with caplog.at_level(logging.INFO, logger="leapnbv_perception.backends.tensorrt_backend"):
        cached = TensorRTBackend(onnx_file, "fp16", str(tmp_path / "cache"), trt=trt, memory=FakeMemory(),
                                 precision_plan_path=plan)
    assert not cached.engine_was_built and cached.kept_fp32_layers == kept and len(trt.builds) == 1
    assert any("cached, built from" in r.getMessage() and SOFTMAX in r.getMessage() for r in caplog.records)


def test_the_plan_is_part_of_the_fp16_cache_key(onnx_file: str, tmp_path: Path) -> None:
    memory = FakeMemory()
    trt = make_fake_tensorrt(memory, tensor_api=True)
    cache = str(tmp_path / "cache")
    plan_a = write_precision_plan(str(tmp_path / "a.json"), [NORM1])
    plan_a2 = tmp_path / "a_reformatted.json"
    plan_a2.write_text('{"keep_fp32": ["%s"],\n\n "version": 1}' % NORM1)
    plan_b = write_precision_plan(str(tmp_path / "b.json"), [NORM1, SOFTMAX])

    def build(precision: str, plan: str = None) -> TensorRTBackend:
        return TensorRTBackend(onnx_file, precision, cache, trt=trt, memory=memory, precision_plan_path=plan)

    plain, with_a = build("fp16"), build("fp16", plan_a)
    assert plain.kept_fp32_layers is None and "OBEY_PRECISION_CONSTRAINTS" not in trt.builds[0]
    assert with_a.engine_path != plain.engine_path and with_a.engine_was_built
    again = build("fp16", str(plan_a2))
    assert again.engine_path == with_a.engine_path and not again.engine_was_built
    with_b = build("fp16", plan_b)
    assert with_b.engine_was_built and with_b.engine_path not in (plain.engine_path, with_a.engine_path)
    assert len(trt.builds) == 3
    # An FP32 engine runs every layer in FP32: the plan neither changes its key nor its build.
    fp32, fp32_planned = build("fp32"), build("fp32", plan_b)
    assert fp32_planned.engine_path == fp32.engine_path and not fp32_planned.engine_was_built
    assert fp32_planned.kept_fp32_layers is None and trt.layer_constraints[-1] == {}
    key = engine_cache_key(b"abc", "8.5.2", "Xavier", "fp16")
    assert key != engine_cache_key(b"abc", "8.5.2", "Xavier", "fp16", load_precision_plan(plan_a).digest)


def test_a_plan_for_another_model_fails_the_build(onnx_file: str, tmp_path: Path) -> None:
    plan = write_precision_plan(str(tmp_path / "other.json"), [NORM1, "/decoder/blocks.3/*"],
                                model_sha256="0" * 64)
    memory = FakeMemory()
    trt = make_fake_tensorrt(memory, tensor_api=True)
    with pytest.raises(BackendError, match=r"other.json.*1 entry name no layer: /decoder/blocks.3/\*"):
        TensorRTBackend(onnx_file, "fp16", str(tmp_path), trt=trt, memory=memory, precision_plan_path=plan)
    assert trt.builds == [] and not list(tmp_path.glob("*.engine"))
    with pytest.raises(BackendError, match="precision plan not found"):
        TensorRTBackend(onnx_file, "fp16", str(tmp_path), trt=trt, memory=memory,
                        precision_plan_path=str(tmp_path / "nope.json"))


# ---------------------------------------------------------------------------------------
# CUDA memory: cuda-python first, pycuda when cuda-python is missing or does not fit the driver
# ---------------------------------------------------------------------------------------


class FakeCudart:
    """cuda-python's runtime module: (error, value) tuples; `fail` makes calls fail like a CUDA 12
    cuda-python on a CUDA 11.4 driver."""

    cudaMemcpyKind = types.SimpleNamespace(cudaMemcpyHostToDevice=1, cudaMemcpyDeviceToHost=2)

    def __init__(self, fail: str = "") -> None:
        self.fail = fail
        self.memory: Dict[int, bytearray] = {}
        self.next_pointer = 1 << 20
        self.calls: List[str] = []

    def cudaSetDevice(self, device: int) -> tuple:
        self.calls.append("cudaSetDevice")
        return (35,) if self.fail == "insufficient_driver" else (0,)

    def cudaStreamCreate(self) -> tuple:
        return 0, 1234

    def cudaGetDeviceProperties(self, device: int) -> tuple:
        return 0, types.SimpleNamespace(name=b"Xavier\x00\x00")

    def cudaMalloc(self, nbytes: int) -> tuple:
        if self.fail == "missing_function":
            raise RuntimeError('Function "cuMemAlloc_v2" not found')
        pointer = self.next_pointer
        self.next_pointer += 1 << 16
        self.memory[pointer] = bytearray(nbytes)
        return 0, pointer

    def cudaFree(self, pointer: int) -> tuple:
        self.memory.pop(pointer, None)
        return (0,)

    def cudaMemcpy(self, dst: int, src: int, nbytes: int, kind: int) -> tuple:
        import ctypes

        if kind == 1:
            self.memory[dst][:nbytes] = ctypes.string_at(src, nbytes)
        else:
            ctypes.memmove(dst, bytes(self.memory[src][:nbytes]), nbytes)
        return (0,)

    def cudaStreamSynchronize(self, stream: int) -> tuple:
        return (0,) if self.fail != "sync" else (700,)


class FakePyCuda:
    """pycuda.driver with host byte buffers as device memory (`buffers`, like FakeMemory's)."""

    def __init__(self, fail: bool = False) -> None:
        self.fail = fail
        self.buffers: Dict[int, np.ndarray] = {}
        self.freed: List[int] = []
        driver = self

        class Allocation:
            def __init__(self, pointer: int) -> None:
                self.pointer = pointer

            def __int__(self) -> int:
                return self.pointer

            def free(self) -> None:
                driver.freed.append(self.pointer)

        class Device:
            def __init__(self, index: int) -> None:
                self.index = index

            def retain_primary_context(self) -> object:
                return types.SimpleNamespace(push=lambda: None)

            def name(self) -> str:
                return "Xavier (pycuda)"

        class Stream:
            handle = 99

            def synchronize(self) -> None:
                pass

        self.Allocation, self.Device, self.Stream = Allocation, Device, Stream

    def init(self) -> None:
        if self.fail:
            raise RuntimeError("cuInit failed: no CUDA-capable device is detected")

    def mem_alloc(self, nbytes: int) -> object:
        pointer = (len(self.buffers) + 1) * 4096
        self.buffers[pointer] = np.zeros(nbytes, dtype=np.uint8)
        return self.Allocation(pointer)

    def memcpy_htod(self, allocation: object, host: np.ndarray) -> None:
        self.buffers[int(allocation)][:] = np.frombuffer(host.tobytes(), dtype=np.uint8)

    def memcpy_dtoh(self, host: np.ndarray, allocation: object) -> None:
        host[...] = np.frombuffer(self.buffers[int(allocation)].tobytes(), dtype=host.dtype).reshape(host.shape)


def use_cuda_libraries(monkeypatch: pytest.MonkeyPatch, cudart: object, pycuda: object) -> None:
    """Make the backend's imports of cuda-python and pycuda return these (None: ImportError)."""

    def importer(module: object, name: str):
        def do_import() -> object:
            if module is None:
                raise ImportError("No module named '%s'" % name)
            return module
        return do_import

    monkeypatch.setattr(tensorrt_backend, "_import_cudart", importer(cudart, "cuda"))
    monkeypatch.setattr(tensorrt_backend, "_import_pycuda", importer(pycuda, "pycuda"))


def test_cuda_python_is_used_when_it_works(monkeypatch: pytest.MonkeyPatch) -> None:
    cudart = FakeCudart()
    use_cuda_libraries(monkeypatch, cudart, FakePyCuda())
    memory = CudaMemory()
    assert memory.library == "cuda-python" and memory.gpu_name() == "Xavier" and memory.stream_handle == 1234
    pointer = memory.allocate(16)
    memory.copy_to_device(pointer, np.arange(4, dtype=np.float32))
    out = np.empty(4, np.float32)
    memory.copy_to_host(out, pointer)
    np.testing.assert_array_equal(out, np.arange(4, dtype=np.float32))
    memory.free_all()
    assert cudart.memory == {}


@pytest.mark.parametrize("cudart, reason", [
    (None, "cuda-python is not importable"),
    (FakeCudart("insufficient_driver"), r"cudaSetDevice failed: cudaErrorInsufficientDriver \(35\)"),
    (FakeCudart("missing_function"), 'Function "cuMemAlloc_v2" not found'),
])
def test_pycuda_is_used_when_cuda_python_does_not_fit(monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture,
                                                      onnx_file: str, tmp_path: Path, cudart: object,
                                                      reason: str) -> None:
    pycuda = FakePyCuda()
    use_cuda_libraries(monkeypatch, cudart, pycuda)
    with caplog.at_level(logging.WARNING, logger="leapnbv_perception.backends.tensorrt_backend"):
        memory = CudaMemory()
    assert memory.library == "pycuda" and memory.gpu_name() == "Xavier (pycuda)"
    assert any(re.search(reason, r.getMessage()) and "uses pycuda" in r.getMessage() for r in caplog.records)
    # The whole backend runs on the fallback: the fake engine reads and writes pycuda's buffers.
    backend = TensorRTBackend(onnx_file, "fp16", str(tmp_path), trt=make_fake_tensorrt(pycuda, tensor_api=True))
    x = np.array([[0.5, 1.0, -3.0, 8.0]], np.float32)
    np.testing.assert_allclose(backend.run({"x": x})["y"], 2.0 * x)
    assert backend._context.streams == [99]
    backend.close()
    assert len(pycuda.freed) == 2


def test_no_cuda_library_names_every_reason(monkeypatch: pytest.MonkeyPatch) -> None:
    use_cuda_libraries(monkeypatch, FakeCudart("insufficient_driver"), FakePyCuda(fail=True))
    with pytest.raises(BackendError) as error:
        CudaMemory()
    message = str(error.value)
    assert "cudaErrorInsufficientDriver" in message and "pycuda failed to initialise" in message
    assert "cuda-python 11.x on JetPack 5" in message
    use_cuda_libraries(monkeypatch, None, None)
    with pytest.raises(BackendError, match="cuda-python is not importable.*pycuda is not importable"):
        CudaMemory()


def test_the_real_imports_fail_cleanly_without_the_libraries(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("cuda", "cuda.bindings", "cuda.bindings.runtime", "cuda.cudart", "pycuda", "pycuda.driver"):
        monkeypatch.setitem(sys.modules, name, None)  # None in sys.modules makes `import` raise ImportError
    with pytest.raises(BackendError, match="cuda-python is not importable.*pycuda is not importable"):
        CudaMemory()


def test_errors_after_start_up_are_not_swallowed(monkeypatch: pytest.MonkeyPatch) -> None:
    cudart = FakeCudart()
    use_cuda_libraries(monkeypatch, cudart, FakePyCuda())
    memory = CudaMemory()
    cudart.fail = "sync"
    with pytest.raises(BackendError, match=r"cudaStreamSynchronize failed: .*\(700\)"):
        memory.synchronize()


def test_engine_cache_key_covers_weights_stored_outside_the_graph(tmp_path: Path) -> None:
    # A graph with its weights in model.onnx.data (how a model over 2 GiB is exported): changing only
    # the weights changes the key; the parser is given the path so that it finds them.
    from onnx import helper, numpy_helper

    from leapnbv_perception.backends.tensorrt_backend import external_data_digests

    weight = numpy_helper.from_array(np.arange(4096, dtype=np.float32).reshape(64, 64), "w")
    graph = helper.make_graph([helper.make_node("MatMul", ["x", "w"], ["y"])], "g",
                              [helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1, 64])],
                              [helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1, 64])], [weight])
    path = tmp_path / "model.onnx"
    onnx.save_model(helper.make_model(graph), str(path), save_as_external_data=True,
                    all_tensors_to_one_file=True, location="model.onnx.data", size_threshold=0)
    graph_bytes = path.read_bytes()
    first = external_data_digests(str(path))
    assert len(first) == 1 and first[0].startswith("model.onnx.data:")
    data = bytearray((tmp_path / "model.onnx.data").read_bytes())
    data[100] ^= 1
    (tmp_path / "model.onnx.data").write_bytes(bytes(data))
    second = external_data_digests(str(path))
    assert path.read_bytes() == graph_bytes and second != first
    assert (engine_cache_key(graph_bytes, "8.5.2", "Xavier", "fp16", external_digests=first)
            != engine_cache_key(graph_bytes, "8.5.2", "Xavier", "fp16", external_digests=second))
    assert engine_cache_key(graph_bytes, "8.5.2", "Xavier", "fp16", external_digests=()) == \
        engine_cache_key(graph_bytes, "8.5.2", "Xavier", "fp16")
    (tmp_path / "model.onnx.data").unlink()
    with pytest.raises(ModelFileNotFoundError, match="model.onnx.data"):
        external_data_digests(str(path))


def test_tensorrt_parser_is_given_the_model_path(onnx_file: str, tmp_path: Path) -> None:
    trt = make_fake_tensorrt(FakeMemory(), tensor_api=True)
    TensorRTBackend(onnx_file, "fp32", str(tmp_path / "cache"), trt=trt, memory=FakeMemory())
    assert trt.parsed_paths == [onnx_file]


def test_onnxruntime_session_settings_change_speed_not_results(models) -> None:
    # Every graph optimization level, sequential or parallel execution: the same outputs.
    from leapnbv_perception.backends.onnxruntime_backend import GRAPH_OPTIMIZATIONS, OnnxRuntimeBackend

    path = models["hmr"]
    reference = OnnxRuntimeBackend(path, intra_op_threads=1)
    feed = {name: np.random.default_rng(0).uniform(0, 1, spec.shape).astype(spec.dtype)
            for name, spec in reference.input_specs.items()}
    expected = reference.run(feed)
    for level in GRAPH_OPTIMIZATIONS:
        for parallel in (False, True):
            backend = create_backend("onnxruntime", path, intra_op_threads=1, graph_optimization=level,
                                     parallel_execution=parallel, inter_op_threads=2)
            got = backend.run(feed)
            for name, value in expected.items():
                np.testing.assert_allclose(got[name], value, rtol=1e-5, atol=1e-5)
    # Sleeping worker threads: set in the session, the same outputs.
    sleeping = create_backend("onnxruntime", path, intra_op_threads=2, thread_spinning=False)
    assert sleeping._session.get_session_options().get_session_config_entry("session.intra_op.allow_spinning") == "0"
    for name, value in sleeping.run(feed).items():
        np.testing.assert_allclose(value, expected[name], rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="graph_optimization 'fastest' is not one of"):
        OnnxRuntimeBackend(path, graph_optimization="fastest")
