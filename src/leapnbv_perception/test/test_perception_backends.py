"""Tests for the engine backends: onnxruntime on the contract models, TensorRT logic on fakes."""

from __future__ import annotations

import os
import types
from pathlib import Path
from typing import Dict, List

import numpy as np
import onnx
import pytest

from leapnbv_perception.backends import ModelFileNotFoundError, create_backend
from leapnbv_perception.backends.base import BackendError
from leapnbv_perception.backends.tensorrt_backend import (
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
    with pytest.raises(ValueError, match="openvino"):
        create_backend("openvino", models["detector"])
    with pytest.raises(ValueError, match="int8"):
        create_backend("onnxruntime", models["detector"], precision="int8")


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


def make_fake_tensorrt(memory: FakeMemory, tensor_api: bool, version: str = "10.3.0") -> types.ModuleType:
    trt = types.ModuleType("tensorrt")
    trt.__version__ = version
    trt.builds = []
    trt.deserialized = []

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

        def create_network(self, flags: int) -> object:
            return types.SimpleNamespace(flags=flags)

        def create_builder_config(self) -> Config:
            return Config()

        def build_serialized_network(self, network: object, config: Config) -> bytes:
            trt.builds.append(list(config.flags))
            return b"ENGINE" + b"-fp16" * ("FP16" in config.flags)

    class OnnxParser:
        def __init__(self, network: object, logger: Logger) -> None:
            self.num_errors = 0

        def parse(self, data: bytes) -> bool:
            return data.startswith(b"ONNX")

    trt.Logger = Logger
    trt.Runtime = Runtime
    trt.Builder = Builder
    trt.OnnxParser = OnnxParser
    trt.NetworkDefinitionCreationFlag = types.SimpleNamespace(EXPLICIT_BATCH=0)
    trt.MemoryPoolType = types.SimpleNamespace(WORKSPACE="workspace")
    trt.BuilderFlag = types.SimpleNamespace(FP16="FP16")
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
