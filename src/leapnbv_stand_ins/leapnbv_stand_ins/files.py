"""Where the generated stand-ins (body model, contract ONNX models) live, their file names, and making them on demand.

Every tool and test takes the stand-in files from here, so their names exist once.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Tuple

STAND_IN_BODY_FILE = "stand_in_body_{resolution}.npz"
STAND_IN_SMPLX_DENSE_FILE = "stand_in_smplx_dense.npz"  # the SMPL-X npz layout in every key
CONTRACT_DETECTOR_FILE = "contract_yolov8.onnx"
CONTRACT_HMR_FILES = {(512, 384): "contract_smplerx.onnx", (256, 192): "contract_smplerx_256x192.onnx"}


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


def ensure_stand_in_body_model(resolution: str = "small", folder: Optional[Path] = None, force: bool = False) -> str:
    """Path of the stand-in body model .npz of this resolution, generated if absent (deterministic)."""
    from leapnbv_stand_ins.stand_in_body_model import write_stand_in_body_model

    path = Path(folder or stand_in_dir()) / STAND_IN_BODY_FILE.format(resolution=resolution)
    if force or not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        write_stand_in_body_model(str(path), resolution)
    return str(path)


def ensure_stand_in_smplx_dense(folder: Optional[Path] = None, force: bool = False) -> str:
    """Path of "stand_in_smplx_dense" (SMPL-X's npz layout in every key), generated if absent."""
    from leapnbv_stand_ins.stand_in_smplx_dense import write_stand_in_smplx_dense

    path = Path(folder or stand_in_dir()) / STAND_IN_SMPLX_DENSE_FILE
    if force or not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        write_stand_in_smplx_dense(str(path))
    return str(path)


def ensure_contract_models(folder: Optional[Path] = None, force: bool = False,
                           hmr_input: Tuple[int, int] = (512, 384)) -> Tuple[str, str]:
    """Paths of the contract detector and HMR ONNX models (HMR input ``hmr_input``), generated if absent."""
    from leapnbv_stand_ins.contract_models import write_contract_detector, write_contract_hmr

    folder = Path(folder or stand_in_dir())
    folder.mkdir(parents=True, exist_ok=True)
    size = (int(hmr_input[0]), int(hmr_input[1]))
    detector, hmr = folder / CONTRACT_DETECTOR_FILE, folder / CONTRACT_HMR_FILES[size]
    if force or not detector.exists():
        write_contract_detector(str(detector))
    if force or not hmr.exists():
        write_contract_hmr(str(hmr), size)
    return str(detector), str(hmr)
