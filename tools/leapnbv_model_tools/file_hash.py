"""The sha256 of a file, read in blocks (checkpoints and body models are hundreds of MB): torch-free, so
the ONNX-only tools (fp16-check) use it without importing torch."""

from __future__ import annotations

import hashlib


def sha256_of(path: str) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()
