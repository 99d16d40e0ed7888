"""SMPLer-X and SMPLest-X checkpoints in the official file structure: strict loading, random ones for tests,
and the key/shape manifest of each variant.

The official files (`smpler_x_{s,b,l,h}32.pth.tar`, `smplest_x_h.pth.tar`) are `torch.save`d dicts whose
weights are under 'network', every key prefixed 'module.' (DataParallel), without `smplx_layer.*` keys.
Both projects' loaders rename `backbone` -> `encoder`, `body_rotation_net` -> `body_regressor`,
`hand_rotation_net` -> `hand_regressor` and load with strict=False (a missing key silently
stays random). Here the same renames apply, and then every key must be used and every
tensor's shape must match: otherwise one error lists what is missing, unexpected and misshaped, and
names the family whose modules the file holds when it is the other one (a SMPLer-X file given as
SMPLest-X or the reverse).
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Tuple, Union

import torch

from leapnbv_model_tools import smplest_x, smplerx
from leapnbv_model_tools.smplerx import SMPLerX
from leapnbv_model_tools.smplest_x import SMPLestX

Network = Union[SMPLerX, SMPLestX]
# Every variant of both families, by the name --variant takes (SMPLer-X's short names, SMPLest-X's prefixed).
VARIANTS: Dict[str, smplerx.Variant] = {**smplerx.VARIANTS, **smplest_x.VARIANTS}
OFFICIAL_VARIANTS = smplerx.OFFICIAL_VARIANTS + smplest_x.OFFICIAL_VARIANTS
FAMILY_NAMES = {"smpler_x": "SMPLer-X", "smplest_x": "SMPLest-X"}
# Top-level modules that only one family has: what a file of the other family is recognised by.
_FAMILY_MODULES = {"smpler_x": ("body_position_net", "body_regressor", "box_net", "hand_roi_net",
                                "hand_position_net", "hand_regressor", "face_regressor"),
                   "smplest_x": ("decoder",)}


def family_of(variant: str) -> str:
    """'smplest_x' or 'smpler_x' (ValueError for an unknown variant)."""
    if variant in smplest_x.VARIANTS:
        return "smplest_x"
    if variant in smplerx.VARIANTS:
        return "smpler_x"
    raise ValueError(f"unknown variant {variant!r}; known: {sorted(VARIANTS)}")


def variant_label(variant: str) -> str:
    """The variant's full name (export metadata, file names): smpler_x_s32, smplest_x_h."""
    return variant if family_of(variant) == "smplest_x" else f"smpler_x_{variant}"


def build_network(variant: str) -> Network:
    """The network of `variant` (either family), randomly initialised, in training mode as nn.Module makes it."""
    return SMPLestX(variant) if family_of(variant) == "smplest_x" else SMPLerX(variant)


def unmirrors_left_hand(variant: str) -> bool:
    """Whether the tail must un-mirror the left hand: SMPLer-X predicts it on a mirrored patch, SMPLest-X not."""
    return family_of(variant) == "smpler_x"


def box_ratio_of(variant: str) -> float:
    """The crop box enlargement the network was trained with (SMPLer-X 1.25, SMPLest-X 1.2)."""
    return smplest_x.BOX_RATIO if family_of(variant) == "smplest_x" else 1.25


def family_of_keys(keys: Iterable[str]) -> Optional[str]:
    """The family whose modules normalized checkpoint keys hold (None: neither or both)."""
    tops = {key.split(".", 1)[0] for key in keys}
    found = [family for family, modules in _FAMILY_MODULES.items() if tops & set(modules)]
    return found[0] if len(found) == 1 else None


MANIFEST_DIR = Path(__file__).resolve().parent / "manifests"
_RENAMES = (("backbone.", "encoder."), ("body_rotation_net.", "body_regressor."),
            ("hand_rotation_net.", "hand_regressor."))


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: unreadable, not a SMPLer-X / SMPLest-X checkpoint, or one that does not fit the
    network (keys or shapes, naming every difference). The first line of the message names the file."""

    def __init__(self, message: str, line: str = "") -> None:
        super().__init__(message)
        self.line = line or message.splitlines()[0]

    def one_line(self) -> str:
        """The message as one line (the CLI contract)."""
        return self.line


def checkpoint_file_name(variant: str) -> str:
    return f"{variant_label(variant)}.pth.tar"


def manifest_path(variant: str, folder: Path = MANIFEST_DIR) -> Path:
    return folder / f"{variant_label(variant)}.json"


def normalize_key(key: str) -> str:
    """A checkpoint key as the network names it: no 'module.' prefix, SMPLer-X's renames applied."""
    if key.startswith("module."):
        key = key[len("module."):]
    for old, new in _RENAMES:
        if key.startswith(old):
            key = new + key[len(old):]
    return key


def state_dict_of(checkpoint: Dict, source: str = "<checkpoint>") -> Dict[str, torch.Tensor]:
    """The network weights of an official checkpoint dict ('network'), keys normalized, smplx_layer dropped."""
    if not isinstance(checkpoint, dict) or "network" not in checkpoint:
        found = sorted(map(str, checkpoint))[:10] if isinstance(checkpoint, dict) else type(checkpoint).__name__
        raise CheckpointError(f"{source} is not a SMPLer-X checkpoint: no 'network' entry (found {found})")
    network = checkpoint["network"]
    if not isinstance(network, dict):
        raise CheckpointError(f"{source} is not a SMPLer-X checkpoint: its 'network' is a {type(network).__name__}, "
                              "not a dict of tensors")
    for key, value in network.items():
        if not isinstance(key, str) or not isinstance(value, torch.Tensor):
            raise CheckpointError(f"{source} is not a SMPLer-X checkpoint: 'network' entry {key!r} is a "
                                  f"{type(value).__name__}, not a tensor")
    return {normalize_key(k): v for k, v in network.items() if "smplx_layer" not in k}


_ZIP_MAGIC = b"PK\x03\x04"


def read_checkpoint(path: str) -> Dict:
    """``torch.load(path, weights_only=True)``, every failure a CheckpointError of one line naming the file
    (missing, a folder, unreadable, empty, truncated, not a PyTorch file, or holding more than tensors)."""
    if not os.path.exists(path):
        raise CheckpointError(f"checkpoint not found: '{path}'")
    if os.path.isdir(path):
        raise CheckpointError(f"checkpoint '{path}' is a folder, not a file")
    try:
        with open(path, "rb") as stream:
            head = stream.read(8)
        size = os.path.getsize(path)
    except OSError as error:
        raise CheckpointError(f"checkpoint '{path}' is unreadable: {error.strerror or error}") from error
    if size == 0:
        raise CheckpointError(f"checkpoint '{path}' is empty")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # noqa: BLE001 - torch.load raises many kinds (RuntimeError, UnpicklingError, ...)
        text = str(error)
        first = text.splitlines()[0] if text else type(error).__name__
        unpickler = re.search(r"WeightsUnpickler error:\s*([^\n]+)", text)
        detail = unpickler.group(1) if unpickler else first
        # weights_only refuses a pickle that holds more than tensors (a class, a function); on bytes that are
        # no pickle at all it says the same, so the header (zip archive, pickle protocol >= 2) tells them apart.
        refused = "Weights only load failed" in text
        if head[:1] == b"\x08" and head[2:3] == b"\x12" or path.endswith(".onnx"):  # ir_version, producer_name
            reason = "not a PyTorch checkpoint (it looks like an ONNX model)"
        elif refused and (head.startswith(_ZIP_MAGIC) or head[:1] == b"\x80"):
            reason = f"not a plain-tensor checkpoint (torch.load with weights_only refuses it: {detail[:100]})"
        elif head.startswith(_ZIP_MAGIC):
            found = re.search(r"zip archive: ([^.]*)", first)
            reason = f"truncated or damaged (torch.load: {found.group(1) if found else first[:100]})"
        else:
            reason = f"not a PyTorch checkpoint, or truncated (torch.load: {type(error).__name__}: {detail[:100]})"
        raise CheckpointError(f"checkpoint '{path}' is {reason}") from error


def check_state_dict(model: Network, weights: Dict[str, torch.Tensor], source: str = "<weights>") -> None:
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
        fits = [v for v in VARIANTS if manifest_path(v).exists() and read_manifest(v) == shapes]
        hint = f" (its keys and shapes are those of {', '.join(fits)})" if fits else ""
        family = family_of(model.variant.name)
        found = family_of_keys(weights)
        modules = ", ".join(sorted({k.split(".", 1)[0] for k in weights}))
        other = (f"{source} is a {FAMILY_NAMES[found]} checkpoint, not {FAMILY_NAMES[family]} (its modules: "
                 f"{modules}); " if found not in (None, family) else "")
        first = (f"{other}{source if not other else 'it'} does not fit {FAMILY_NAMES[family]} {model.variant.name} "
                 f"(embed {model.variant.embed_dim}, depth {model.variant.depth}): {len(missing)} missing, "
                 f"{len(unexpected)} unexpected, {len(misshaped)} of the wrong shape{hint}")
        examples = [f"{title} {items[0]}" for title, items in (("missing", missing), ("unexpected", unexpected),
                                                                ("wrong shape", misshaped)) if items]
        raise CheckpointError(
            first + listed("missing", missing) + listed("unexpected", unexpected) + listed("wrong shape", misshaped),
            line=f"{first}; first {'; first '.join(examples)}")


def load_network(path: str, variant: str) -> Network:
    """The network of `variant` (either family) with the checkpoint's weights, strictly, in eval mode."""
    if variant not in VARIANTS:
        raise CheckpointError(f"unknown variant {variant!r} for '{path}': known {sorted(VARIANTS)}")
    weights = state_dict_of(read_checkpoint(path), f"checkpoint '{path}'")
    with torch.device("meta"):  # shapes only: the checkpoint's tensors are assigned, nothing is initialised twice
        model = build_network(variant)
    check_state_dict(model, weights, f"checkpoint '{path}'")
    model.load_state_dict(weights, strict=True, assign=True)
    return model.eval()


load_smplerx = load_network  # the earlier name: it loads either family


def random_network(variant: str, seed: int = 0) -> Network:
    """A randomly initialised network of either family (BatchNorm statistics randomised too, so they matter)."""
    torch.manual_seed(seed)
    model = build_network(variant)
    with torch.no_grad():
        for name, tensor in model.state_dict().items():
            if name.endswith("running_var"):
                tensor.uniform_(0.5, 1.5)
            elif name.endswith("running_mean"):
                tensor.normal_(0.0, 0.1)
            elif name.endswith(("task_tokens", "pos_embed")):
                tensor.normal_(0.0, 0.02)
    return model.eval()


random_smplerx = random_network


def save_official(model: Network, path: str, epoch: int = 0) -> str:
    """Save in the official structure: {'epoch', 'network': {'module.' + key: tensor}}."""
    network = {"module." + k: v.detach().clone() for k, v in model.state_dict().items()}
    torch.save({"epoch": epoch, "network": network}, path)
    return path


def parameter_count(variant: str) -> int:
    """Parameters of the network (no buffers), counted on the meta device (nothing allocated)."""
    with torch.device("meta"):
        return sum(p.numel() for p in build_network(variant).parameters())


def manifest(variant: str) -> Dict[str, List[int]]:
    """Key -> shape of the network's state dict (the checkpoint's keys without 'module.')."""
    with torch.device("meta"):  # shapes only: no weights allocated or initialised (h32: 2.6 GB, seconds)
        return {k: list(v.shape) for k, v in build_network(variant).state_dict().items()}


def write_manifests(folder: Path = MANIFEST_DIR) -> List[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for variant in OFFICIAL_VARIANTS:
        keys = manifest(variant)
        count = sum(_numel(shape) for key, shape in keys.items() if not key.endswith("num_batches_tracked"))
        path = manifest_path(variant, folder)
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
    data = json.loads(manifest_path(variant).read_text())
    return {k: tuple(v) for k, v in data["keys"].items()}
