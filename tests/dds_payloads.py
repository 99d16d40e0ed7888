"""Deterministic payloads for the DDS transport test (both processes build the same ones)."""
from __future__ import annotations

import numpy as np

NUM_VERTICES = 10475
NUM_FACES = 20908


def make_payloads(seed: int = 7):
    rng = np.random.default_rng(seed)
    depth = rng.integers(0, 65535, size=(480, 640), dtype=np.uint16)
    rgb = rng.integers(0, 255, size=(480, 640, 3), dtype=np.uint8)
    vertices = rng.normal(size=(NUM_VERTICES, 3)).astype(np.float32)
    faces = rng.integers(0, NUM_VERTICES, size=(NUM_FACES, 3)).astype(np.uint32)
    return depth, rgb, vertices, faces
