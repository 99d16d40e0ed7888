"""The fp16-check's inputs: the FP32 ONNX model and the calibration crops, refused in one line naming
the file when unusable."""

from __future__ import annotations

import os
from pathlib import Path
from typing import List, Sequence

import numpy as np


class Fp16CheckError(ValueError):
    """Bad input to the FP16 check (one line, naming the file)."""


def load_model(path: str):
    import onnx

    if not os.path.isfile(path):
        raise Fp16CheckError(f"model not found: '{path}'")
    try:
        model = onnx.load(path)
    except Exception as error:  # noqa: BLE001 - protobuf raises several kinds
        raise Fp16CheckError(f"model '{path}' is not a readable ONNX file: {error}") from error
    # protobuf reads an empty file (and some other bytes) as an empty message: no graph is no model
    if not model.graph.input or not model.graph.output or not model.graph.node:
        raise Fp16CheckError(f"model '{path}' is not an ONNX model: no graph inputs, outputs or nodes")
    return model


def load_crops(path: str, input_shape: Sequence[int]) -> np.ndarray:
    """Calibration crops as (N, C, H, W) float32: a .npy/.npz array, or a folder of .npy/.png/.jpg files.

    Images are resized to the input size and scaled to RGB / 255 (the HMR input).
    """
    source = Path(path)
    if not source.exists():
        raise Fp16CheckError(f"calibration crops not found: '{path}'")
    arrays: List[np.ndarray] = []
    channels, height, width = (int(v) for v in input_shape[1:])
    files = sorted(p for p in source.iterdir() if p.is_file()) if source.is_dir() else [source]
    for file in files:
        suffix = file.suffix.lower()
        try:
            if suffix == ".npy":
                arrays.append(np.load(file))
            elif suffix == ".npz":
                with np.load(file) as archive:
                    arrays.extend(archive[key] for key in archive.files)
            elif suffix in (".png", ".jpg", ".jpeg"):
                from PIL import Image

                image = Image.open(file).convert("RGB").resize((width, height), Image.BILINEAR)
                arrays.append(np.asarray(image, dtype=np.float32).transpose(2, 0, 1) / 255.0)
        except (OSError, ValueError) as error:
            raise Fp16CheckError(f"calibration crops '{file}' unreadable: {error}") from error
    if not arrays:
        raise Fp16CheckError(f"calibration crops '{path}': no .npy/.npz/.png/.jpg crops found")
    crops = []
    for array in arrays:
        array = np.asarray(array, dtype=np.float32)
        array = array[None] if array.ndim == 3 else array
        if array.ndim != 4 or tuple(array.shape[1:]) != (channels, height, width):
            raise Fp16CheckError(f"calibration crops '{path}': shape {tuple(array.shape)} does not fit the model "
                                 f"input (N, {channels}, {height}, {width})")
        crops.append(array)
    return np.concatenate(crops)
