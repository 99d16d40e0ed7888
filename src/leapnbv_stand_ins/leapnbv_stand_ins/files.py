"""Where the generated stand-ins (body model, contract ONNX models) live, and making them on demand."""
from __future__ import annotations

import os
from pathlib import Path


def models_dir() -> Path:
    """$LEAPNBV_MODELS_DIR, else <repository>/models when running from a checkout, else ~/.cache/leapnbv/models."""
    env = os.environ.get("LEAPNBV_MODELS_DIR")
    if env:
        return Path(env)
    here = Path(__file__).resolve()
    for parent in here.parents:
        if (parent / "scripts" / "setup.sh").exists() and (parent / "src").is_dir():
            return parent / "models"
    return Path.home() / ".cache" / "leapnbv" / "models"


def stand_in_dir() -> Path:
    return models_dir() / "stand_in"


def ensure_stand_in_body_model(resolution: str = "small") -> str:
    """Path of the stand-in body model .npz of this resolution, generated if absent (deterministic)."""
    from leapnbv_stand_ins.stand_in_body_model import write_stand_in_body_model

    path = stand_in_dir() / f"stand_in_body_{resolution}.npz"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        write_stand_in_body_model(str(path), resolution)
    return str(path)


def ensure_contract_models() -> tuple:
    """Paths of the contract detector and HMR ONNX models, generated if absent."""
    from leapnbv_stand_ins.contract_models import write_contract_detector, write_contract_hmr

    folder = stand_in_dir()
    folder.mkdir(parents=True, exist_ok=True)
    detector, hmr = folder / "contract_yolov8.onnx", folder / "contract_smplerx.onnx"
    if not detector.exists():
        write_contract_detector(str(detector))
    if not hmr.exists():
        write_contract_hmr(str(hmr))
    return str(detector), str(hmr)
