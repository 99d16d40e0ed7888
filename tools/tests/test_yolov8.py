"""The YOLOv8 architecture (tools/leapnbv_model_tools/yolov8.py): the reference's parameter counts, the
export contract the detector node checks, and onnxruntime against PyTorch."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime
import pytest
import torch
from leapnbv_model_tools.yolov8 import YOLOv8, export_yolov8, random_yolov8

from leapnbv_perception.backends.onnxruntime_backend import OnnxRuntimeBackend
from leapnbv_perception.model_contracts import YOLOV8_CONTRACT, check_backend_contract


@pytest.mark.parametrize(("scale", "parameters"), [("n", 3_157_200), ("s", 11_166_560), ("m", 25_902_640)])
def test_parameter_count_is_the_references(scale: str, parameters: int) -> None:
    # The figures ultralytics prints for yolov8{n,s,m}.yaml with 80 classes.
    assert sum(p.numel() for p in YOLOv8(scale).parameters()) == parameters


def test_export_meets_the_detector_contract_and_matches_pytorch(tmp_path: Path) -> None:
    torch.set_num_threads(1)
    model = random_yolov8("n", seed=1)
    path = export_yolov8(model, str(tmp_path / "yolov8n_random.onnx"))
    check_backend_contract(OnnxRuntimeBackend(path), YOLOV8_CONTRACT)
    image = np.random.default_rng(0).uniform(0, 1, size=(1, 3, 640, 640)).astype(np.float32)
    with torch.no_grad():
        expected = model(torch.from_numpy(image)).numpy()
    session = onnxruntime.InferenceSession(path, providers=["CPUExecutionProvider"])
    got = session.run(["output0"], {"images": image})[0]
    assert got.shape == (1, 84, 8400)
    np.testing.assert_allclose(got, expected, atol=2e-3, rtol=1e-4)
    # Anchor points at the cell centres of strides 8, 16, 32, in that order: the first cell of each
    # level is centred at stride / 2. Untrained, the background prior keeps every class score low.
    centres_x = expected[0, 0]
    starts = (0, 80 * 80, 80 * 80 + 40 * 40)
    spread = [np.abs(expected[0, 0, start] - stride / 2) for start, stride in zip(starts, (8, 16, 32))]
    assert np.all(np.asarray(spread) < 4 * np.asarray((8, 16, 32))), spread
    assert centres_x.shape == (8400,) and float(expected[0, 4:].max()) < 0.05


def test_a_320_export_meets_the_contract_at_its_own_size(tmp_path: Path) -> None:
    # (the detector's letterbox at the model's size is tested in the runtime's tests: cv2 is not here)
    from leapnbv_perception.model_contracts import yolo_anchor_count

    path = export_yolov8(random_yolov8("n", seed=2, image_size=320), str(tmp_path / "yolov8n_320.onnx"), 320)
    backend = OnnxRuntimeBackend(path)
    check_backend_contract(backend, YOLOV8_CONTRACT)
    assert dict(backend.output_specs)["output0"].shape == (1, 84, yolo_anchor_count(320)) == (1, 84, 2100)
