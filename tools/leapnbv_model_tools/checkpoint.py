"""SMPLer-X checkpoints in the official file structure: strict loading, random ones for tests,
and the key/shape manifest of each variant.

The official files (`smpler_x_{s,b,l,h}32.pth.tar`) are `torch.save`d dicts whose weights are
under 'network', every key prefixed 'module.' (DataParallel), without `smplx_layer.*` keys.
SMPLer-X's own loader renames `backbone` -> `encoder`, `body_rotation_net` -> `body_regressor`,
`hand_rotation_net` -> `hand_regressor` and loads with strict=False (a missing key silently
stays random). Here the same renames apply, and then every key must be used and every
tensor's shape must match: otherwise one error lists what is missing, unexpected and misshaped.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, List, Tuple

import torch

from leapnbv_model_tools.smplerx import OFFICIAL_VARIANTS, VARIANTS, SMPLerX

MANIFEST_DIR = Path(__file__).resolve().parent / "manifests"
_RENAMES = (("backbone.", "encoder."), ("body_rotation_net.", "body_regressor."),
            ("hand_rotation_net.", "hand_regressor."))


class CheckpointError(ValueError):
    """A checkpoint that does not fit the network (keys or shapes), naming every difference."""


def checkpoint_file_name(variant: str) -> str:
    return f"smpler_x_{variant}.pth.tar"


def normalize_key(key: str) -> str:
    """A checkpoint key as the network names it: no 'module.' prefix, SMPLer-X's renames applied."""
    if key.startswith("module."):
        key = key[len("module."):]
    for old, new in _RENAMES:
        if key.startswith(old):
            key = new + key[len(old):]
    return key


def state_dict_of(checkpoint: Dict) -> Dict[str, torch.Tensor]:
    """The network weights of an official checkpoint dict ('network'), keys normalized, smplx_layer dropped."""
    if not isinstance(checkpoint, dict) or "network" not in checkpoint:
        found = sorted(checkpoint)[:10] if isinstance(checkpoint, dict) else type(checkpoint).__name__
        raise CheckpointError(f"not a SMPLer-X checkpoint: no 'network' entry (found {found})")
    return {normalize_key(k): v for k, v in checkpoint["network"].items() if "smplx_layer" not in k}


def check_state_dict(model: SMPLerX, weights: Dict[str, torch.Tensor], source: str = "<weights>") -> None:
    """Raise CheckpointError unless `weights` has exactly the model's keys with its shapes."""
    expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    missing = sorted(set(expected) - set(weights))
    unexpected = sorted(set(weights) - set(expected))
    misshaped = sorted(f"{k}: checkpoint {tuple(weights[k].shape)}, network {expected[k]}"
                       for k in set(expected) & set(weights) if tuple(weights[k].shape) != expected[k])
    if missing or unexpected or misshaped:
        def listed(title: str, items: List[str]) -> str:
            shown = items[:20] + ([f"... {len(items) - 20} more"] if len(items) > 20 else [])
            return f"\n  {title} ({len(items)}): " + ", ".join(shown) if items else ""
        shapes = {k: tuple(v.shape) for k, v in weights.items()}
        fits = [v for v in VARIANTS if (MANIFEST_DIR / f"smpler_x_{v}.json").exists() and read_manifest(v) == shapes]
        hint = f" (its keys and shapes are those of {', '.join(fits)})" if fits else ""
        raise CheckpointError(
            f"{source} does not fit SMPLer-X {model.variant.name} (embed {model.variant.embed_dim}, "
            f"depth {model.variant.depth}): {len(missing)} missing, {len(unexpected)} unexpected, "
            f"{len(misshaped)} of the wrong shape{hint}"
            + listed("missing", missing) + listed("unexpected", unexpected) + listed("wrong shape", misshaped))


def load_smplerx(path: str, variant: str) -> SMPLerX:
    """The network of `variant` with the checkpoint's weights, strictly, in eval mode."""
    checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    weights = state_dict_of(checkpoint)
    model = SMPLerX(variant)
    check_state_dict(model, weights, path)
    model.load_state_dict(weights, strict=True)
    return model.eval()


def random_smplerx(variant: str, seed: int = 0) -> SMPLerX:
    """A randomly initialised network (BatchNorm statistics randomised too, so they matter)."""
    torch.manual_seed(seed)
    model = SMPLerX(variant)
    with torch.no_grad():
        for name, tensor in model.state_dict().items():
            if name.endswith("running_var"):
                tensor.uniform_(0.5, 1.5)
            elif name.endswith("running_mean"):
                tensor.normal_(0.0, 0.1)
            elif name.endswith(("task_tokens", "pos_embed")):
                tensor.normal_(0.0, 0.02)
    return model.eval()


def save_official(model: SMPLerX, path: str, epoch: int = 0) -> str:
    """Save in the official structure: {'epoch', 'network': {'module.' + key: tensor}}."""
    network = {"module." + k: v.detach().clone() for k, v in model.state_dict().items()}
    torch.save({"epoch": epoch, "network": network}, path)
    return path


def manifest(variant: str) -> Dict[str, List[int]]:
    """Key -> shape of the network's state dict (the checkpoint's keys without 'module.')."""
    return {k: list(v.shape) for k, v in SMPLerX(variant).state_dict().items()}


def write_manifests(folder: Path = MANIFEST_DIR) -> List[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for variant in OFFICIAL_VARIANTS:
        keys = manifest(variant)
        count = sum(_numel(shape) for key, shape in keys.items() if not key.endswith("num_batches_tracked"))
        path = folder / f"smpler_x_{variant}.json"
        path.write_text(json.dumps({"variant": variant, "parameters_and_buffers": count, "keys": keys}, indent=1)
                        + "\n")
        paths.append(path)
    return paths


def _numel(shape: List[int]) -> int:
    total = 1
    for size in shape:
        total *= size
    return total


def read_manifest(variant: str) -> Dict[str, Tuple[int, ...]]:
    data = json.loads((MANIFEST_DIR / f"smpler_x_{variant}.json").read_text())
    return {k: tuple(v) for k, v in data["keys"].items()}
