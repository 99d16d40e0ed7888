"""distill: train a SMPLer-X (or SMPLest-X) student on a teacher's meshes (centroid-relative per-vertex loss).

Teacher and student may be of either family (``--teacher-variant smplest_x_h``: SMPLest-X-H beside the
SMPLer-X teachers); each network's mesh is made as its own test-time forward makes it (SMPLer-X's left
hand un-mirrored, SMPLest-X's as predicted). Both see the same crops (the box x 1.25, below), also a
SMPLest-X network, which was trained on the box x 1.2: its meshes are centroid-relative, so the crop's
scale changes what it sees by 4 %, not where the mesh lies.

    python -m leapnbv_model_tools distill --train train.jsonl [--val val.jsonl]
        --teacher T.pth.tar --teacher-variant l32 --student-variant s32 [--student-checkpoint S.pth.tar]
        --body-model SMPLX_NEUTRAL.npz --out DIR [--input 512x384|256x192] [--epochs 10]
        [--batch-size 8] [--lr 1e-4] [--cache DIR] [--max-steps N] [--no-export] [--targets teacher|gt]
        [--init-mean]
    torchrun --nproc_per_node 2 -m leapnbv_model_tools distill ...   (DistributedDataParallel)

Manifest (JSON lines): ``{"image": "a.png", "box": [x1, y1, x2, y2], "params": {...}}``; the
image path relative to the manifest's folder; ``params`` optional ground truth (axis-angle
``root`` 3, ``body`` 63, ``lhand`` 45, ``rhand`` 45, ``jaw`` 3, ``betas`` 10, ``expression`` 10) and
optional ``"camera": {"K": [fx, fy, cx, cy], "translation": [x, y, z]}`` (the image's intrinsics and
the body's translation in the camera frame: camera-frame vertices = SMPL-X(params) + translation).
Every crop is made as inference makes it (leapnbv_perception.hmr_crop: the box enlarged by 1.25
to 3:4, the affine crop to 512 x 384, then ``fit_to_engine_input``).

Teacher meshes: computed once per crop through the teacher and the PyTorch SMPL-X layer, and
stored centroid-relative in ``<cache>/<teacher key>/<crop sha256>.npy``; the teacher key is
the sha256 of the teacher checkpoint's sha256, its variant, the body model file's sha256 and
the input size, so another teacher (or body model) gets another folder, a changed crop
another file; a run that stops while filling the cache resumes it. Each process computes its
share (crop index modulo the number of processes).

Training: AdamW on mean over the global batch of the mean per-vertex distance between the
centroid-relative student and teacher meshes (metres). BatchNorm layers stay in eval mode
(their statistics are the checkpoint's: batches of a few crops would only add noise), and the
network has no dropout, so a step is a deterministic function of the weights and the batch.
The order of the crops in epoch e is a permutation seeded by (seed, e); each global batch of
B crops is split across the P processes (B must be a multiple of P), each process's loss is
its mean, DDP averages the gradients: the same update as one process with batch B.
``checkpoint.pt`` (student, optimizer, step, history) is written at every epoch's end, every
``--save-every`` steps and when ``--max-steps`` stops the run; a run on the same --out resumes
from it (the configuration must match) and continues at the next step, in the same data order.

``--targets gt`` trains on the manifest's ground-truth meshes instead (same loss, no teacher):
the baseline a distilled student is compared with, and how a teacher is trained on synthetic data.

``--projection-weight W`` (default 0: the paper's loss alone) adds W times the mean distance between
the student's mesh projected as the HMR tail projects it (its ``cam_param`` translation, the virtual
camera of the crop) and the ground-truth mesh projected by the real camera, both in units of the crop
box (x / width, y / height of the processed box). The vertex loss is centroid-relative, so it never
teaches the camera head; a network whose mesh the graph places in the image (the raster stage)
needs this signal. It needs ``camera`` on every training sample.

``--init-mean`` (for a network trained from scratch): before the first step, the last linear layer
of every pose, shape and expression head is scaled by 0.01 and its bias set to the training
manifest's mean parameters (rotations as the 6-D the heads output; the hand head, which serves both
hands, the mean of the right hand and the mirrored left), so the network starts at the mean body
instead of at random rotations, the usual start of a body-model regressor. It needs the manifest's
ground-truth parameters.

Validation (each epoch, process 0): PA-MPVPE (mm, Procrustes-aligned mean vertex distance) of
the student to the teacher's mesh, and to the ground-truth mesh where the manifest gives it.
Outputs in --out: checkpoint.pt, history.json, curves.png (loss and PA-MPVPE), and (unless
--no-export) student.pth.tar (the official structure) and student.onnx (export-hmr's exporter,
its checks and metadata: written only when the operators, the engine contract and the parity
pass; a failed export leaves any earlier student.onnx as it was).

Exit codes: 0 trained (and exported); 1 an export check failed (student.onnx not written); 2 bad input (a
manifest, image, box, checkpoint or body model that cannot be used; a --out holding a run of
another configuration; a batch size that the processes do not divide).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import nn

from leapnbv_model_tools.file_hash import sha256_of

PARAM_SIZES = {"root": 3, "body": 63, "lhand": 45, "rhand": 45, "jaw": 3, "betas": 10, "expression": 10}
CONFIG_KEYS = ("train", "targets", "teacher_variant", "student_variant", "student_checkpoint", "input", "batch_size",
               "lr", "seed", "teacher_sha256", "body_model_sha256", "init_mean", "projection_weight")


class DistillError(ValueError):
    """Bad input to distill (one line naming the file or option)."""


@dataclass
class Sample:
    image: str
    box: Tuple[float, float, float, float]
    params: Optional[Dict[str, np.ndarray]]
    camera_k: Optional[np.ndarray] = None  # (fx, fy, cx, cy)
    translation: Optional[np.ndarray] = None  # (3,) camera-frame body translation


def read_manifest(path: str) -> List[Sample]:
    if not os.path.isfile(path):
        raise DistillError(f"manifest not found: '{path}'")
    base = Path(path).resolve().parent
    samples = []
    for number, line in enumerate(Path(path).read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip():
            continue
        try:
            entry = json.loads(line)
            image = str((base / entry["image"]).resolve()) if not os.path.isabs(entry["image"]) else entry["image"]
            box = tuple(float(v) for v in entry["box"])
            if len(box) != 4 or not box[2] > box[0] or not box[3] > box[1]:
                raise ValueError(f"box {list(box)} is not [x1, y1, x2, y2] with x2 > x1, y2 > y1")
            params = None
            if entry.get("params") is not None:
                params = {}
                for key, size in PARAM_SIZES.items():
                    values = np.asarray(entry["params"][key], dtype=np.float64).reshape(-1)
                    if values.size != size:
                        raise ValueError(f"params.{key} has {values.size} values, expected {size}")
                    params[key] = values
            camera_k = translation = None
            if entry.get("camera") is not None:
                camera_k = np.asarray(entry["camera"]["K"], dtype=np.float64).reshape(-1)
                translation = np.asarray(entry["camera"]["translation"], dtype=np.float64).reshape(-1)
                if camera_k.size != 4 or translation.size != 3 or not np.all(np.isfinite(camera_k)) \
                        or not np.all(np.isfinite(translation)) or not np.all(camera_k[:2] > 0):
                    raise ValueError("camera needs K [fx > 0, fy > 0, cx, cy] and translation [x, y, z], finite")
        except (ValueError, KeyError, TypeError) as error:
            raise DistillError(f"manifest '{path}' line {number}: {error}") from error
        if not os.path.isfile(image):
            raise DistillError(f"manifest '{path}' line {number}: image not found: '{image}'")
        samples.append(Sample(image, box, params, camera_k, translation))
    if not samples:
        raise DistillError(f"manifest '{path}' has no samples")
    return samples


def make_crop(sample: Sample, input_hw: Tuple[int, int]) -> np.ndarray:
    """(3, H, W) float32: the inference crop of the person box."""
    return crop_and_box(sample, input_hw)[0]


def crop_and_box(sample: Sample, input_hw: Tuple[int, int]) -> Tuple[np.ndarray, np.ndarray]:
    """(the inference crop (3, H, W) float32, the processed box [x, y, w, h] in image pixels)."""
    import cv2

    from leapnbv_perception.hmr_crop import engine_input_for_box

    bgr = cv2.imread(sample.image, cv2.IMREAD_COLOR)
    if bgr is None:
        raise DistillError(f"image unreadable: '{sample.image}'")
    rgb = np.ascontiguousarray(bgr[:, :, ::-1])
    engine_input, processed, _ = engine_input_for_box(rgb, sample.box, input_hw)
    return engine_input[0], processed


def ground_truth_meshes(layer, samples: List[Sample]) -> torch.Tensor:
    """(B, V, 3) vertices of the samples' ground-truth parameters through the PyTorch SMPL-X layer."""
    from leapnbv_model_tools.torch_smplx import mesh_from_axis_angle

    with torch.no_grad():
        return mesh_from_axis_angle(layer, {k: torch.from_numpy(np.stack([s.params[k] for s in samples])).float()
                                            for k in PARAM_SIZES})


def box_projection(vertices_camera: torch.Tensor, camera_k: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """(B, V, 2) camera-frame vertices projected with K (B, 4: fx, fy, cx, cy), in units of the processed
    boxes (B, 4: x, y, w, h): (u - x) / w, (v - y) / h."""
    z = vertices_camera[..., 2].clamp(min=1e-3)
    u = camera_k[:, None, 0] * vertices_camera[..., 0] / z + camera_k[:, None, 2]
    v = camera_k[:, None, 1] * vertices_camera[..., 1] / z + camera_k[:, None, 3]
    return torch.stack([(u - boxes[:, None, 0]) / boxes[:, None, 2], (v - boxes[:, None, 1]) / boxes[:, None, 3]],
                       dim=-1)


def student_box_projection(vertices_model: torch.Tensor, cam_param: torch.Tensor) -> torch.Tensor:
    """(B, V, 2): the student's mesh as the HMR tail places it (translation from ``cam_param``, the crop's
    virtual camera; leapnbv_perception.hmr_tail), in units of the processed box."""
    from leapnbv_perception.hmr_tail import BODY_INPUT_SHAPE, VIRTUAL_FOCAL, depth_scale

    height, width = BODY_INPUT_SHAPE
    t = torch.stack([cam_param[:, 0], cam_param[:, 1], depth_scale() * torch.sigmoid(cam_param[:, 2])], dim=1)
    placed = vertices_model + t[:, None, :]
    z = placed[..., 2].clamp(min=1e-3)
    return torch.stack([VIRTUAL_FOCAL[0] / width * placed[..., 0] / z + 0.5,
                        VIRTUAL_FOCAL[1] / height * placed[..., 1] / z + 0.5], dim=-1)


def crop_sha256(crop: np.ndarray) -> str:
    array = np.ascontiguousarray(crop, dtype=np.float32)
    return hashlib.sha256(repr(array.shape).encode() + array.tobytes()).hexdigest()


# ----------------------------------------------------------------------------------------
# Teacher cache


class TeacherCache:
    """Centroid-relative teacher meshes on disk, keyed by the teacher's identity and each crop's sha256."""

    def __init__(self, root: str, teacher_sha256: str, teacher_variant: str, body_sha256: str,
                 input_hw: Tuple[int, int], unmirror_left: bool = True) -> None:
        # The variant names the family too (smplest_x_h, s32), so the two families' meshes never share a folder.
        hand = "left hand un-mirrored" if unmirror_left else "left hand as predicted (not mirrored)"
        identity = {"teacher_sha256": teacher_sha256, "teacher_variant": teacher_variant,
                    "body_model_sha256": body_sha256, "input": f"{input_hw[0]}x{input_hw[1]}",
                    "mesh": f"centroid-relative vertices, float32, add_hand_mean, {hand}"}
        self.unmirror_left = unmirror_left
        self.key = hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()
        self.folder = Path(root) / self.key[:24]
        self.folder.mkdir(parents=True, exist_ok=True)
        (self.folder / "teacher.json").write_text(json.dumps(identity, indent=1) + "\n")
        self.computed = 0
        self.reused = 0

    def path(self, crop_hash: str) -> Path:
        return self.folder / f"{crop_hash}.npy"

    def fill(self, teacher: nn.Module, layer, crops: np.ndarray, hashes: List[str], rank: int = 0,
             world: int = 1) -> None:
        from leapnbv_model_tools.torch_smplx import centroid_relative, mesh_from_outputs

        for index in range(rank, len(crops), world):
            target = self.path(hashes[index])
            if target.exists():
                self.reused += 1
                continue
            with torch.no_grad():
                outputs = teacher(torch.from_numpy(crops[index][None]))
                mesh = centroid_relative(mesh_from_outputs(layer, outputs, self.unmirror_left))[0]
            temporary = target.with_suffix(f".{os.getpid()}.tmp.npy")
            np.save(temporary, mesh.numpy().astype(np.float32))
            os.replace(temporary, target)
            self.computed += 1

    def load(self, hashes: List[str]) -> np.ndarray:
        return np.stack([np.load(self.path(h)) for h in hashes])


# ----------------------------------------------------------------------------------------
# Metrics


def procrustes_align(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Similarity alignment of pred to gt (Umeyama, no reflection); as leapnbv_evaluation.metrics."""
    x, y = pred.astype(np.float64), gt.astype(np.float64)
    mx, my = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mx, y - my
    u, s, vt = np.linalg.svd(xc.T @ yc)
    d = np.eye(3)
    d[2, 2] = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rotation = vt.T @ d @ u.T
    scale = float(np.sum(s * np.diag(d))) / max(float(np.sum(xc * xc)), 1e-20)
    return scale * (x @ rotation.T) + (my - scale * (rotation @ mx))


def pa_mpvpe_mm(pred: np.ndarray, gt: np.ndarray) -> float:
    return float(np.linalg.norm(procrustes_align(pred, gt) - gt, axis=1).mean() * 1000.0)


# ----------------------------------------------------------------------------------------
# Training


class _Batched(nn.Module):
    """Runs the batch-1 SMPLer-X on each crop of a batch: one forward per step for DDP."""

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, crops: torch.Tensor) -> Dict[str, torch.Tensor]:
        outputs = [self.model(crop[None]) for crop in crops]
        return {name: torch.cat([o[name] for o in outputs]) for name in outputs[0]}


def freeze_batchnorm(model: nn.Module) -> None:
    for module in model.modules():
        if isinstance(module, nn.modules.batchnorm._BatchNorm):
            module.eval()


def _progress(step: int, total: int, epoch: int, epochs: int, loss: float, started: float) -> None:
    done = int(30 * step / max(total, 1))
    rate = (time.perf_counter() - started) / max(step, 1)
    text = (f"distill epoch {epoch + 1}/{epochs} [{'#' * done}{'.' * (30 - done)}] step {step}/{total} "
            f"loss {loss * 1000:.2f} mm  {rate:.2f} s/step")
    if sys.stderr.isatty():
        print("\r" + text, end="", file=sys.stderr, flush=True)
    else:
        print(text, file=sys.stderr, flush=True)


def write_curves(history: Dict[str, list], path: str) -> str:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    figure, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    if history["loss"]:
        steps, losses = zip(*history["loss"])
        left.plot(steps, np.asarray(losses) * 1000.0)
    left.set_xlabel("step")
    left.set_ylabel("training loss (mean vertex distance, mm)")
    left.set_yscale("log")
    for key, label in (("val_teacher", "PA-MPVPE to teacher"), ("val_gt", "PA-MPVPE to ground truth")):
        points = [(row["step"], row[key]) for row in history["val"] if row.get(key) is not None]
        if points:
            right.plot(*zip(*points), marker="o", label=label)
    right.set_xlabel("step")
    right.set_ylabel("mm")
    if history["val"]:
        right.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)
    return path


@dataclass
class DistillConfig:
    train: str
    teacher: str
    teacher_variant: str
    student_variant: str
    body_model: str
    out: str
    val: str = ""
    student_checkpoint: str = ""
    input: str = "256x192"
    epochs: int = 1
    batch_size: int = 4
    lr: float = 1e-4
    seed: int = 0
    cache: str = ""
    max_steps: int = 0
    save_every: int = 0
    export: bool = True
    targets: str = "teacher"
    teacher_sha256: str = ""
    body_model_sha256: str = ""
    init_mean: bool = False
    projection_weight: float = 0.0


INIT_OUTPUT_WEIGHT_SCALE = 0.01


def init_from_mean(student: nn.Module, samples: List[Sample]) -> Dict[str, np.ndarray]:
    """Start the student's output heads at the samples' mean parameters (see ``--init-mean``).

    Returns:
        The biases set, by head ("root", "body", "hand", "jaw", "betas", "expression").
    """
    from leapnbv_model_tools.torch_smplx import axis_angle_to_matrix, unmirror

    if not samples or any(s.params is None for s in samples):
        raise DistillError("--init-mean needs the training manifest's ground-truth params on every sample")
    mean = {k: torch.from_numpy(np.mean([s.params[k] for s in samples], axis=0)).float().reshape(-1, 3)
            for k in ("root", "body", "lhand", "rhand", "jaw")}

    def six_d(axis_angle: torch.Tensor) -> torch.Tensor:
        # The heads' 6-D layout: x[0::2] the first column, x[1::2] the second (torch_smplx.rot6d_to_matrix).
        return axis_angle_to_matrix(axis_angle)[..., :2].reshape(-1)

    biases = {
        "root": six_d(mean["root"]), "body": six_d(mean["body"]), "jaw": six_d(mean["jaw"]),
        "betas": torch.from_numpy(np.mean([s.params["betas"] for s in samples], axis=0)).float(),
        "expression": torch.from_numpy(np.mean([s.params["expression"] for s in samples], axis=0)).float(),
    }
    if getattr(student, "family", "smpler_x") == "smplest_x":
        # One head for both hands, left (not mirrored) then right; the decoder's linear heads.
        biases["hand"] = torch.cat([six_d(mean["lhand"]), six_d(mean["rhand"])])
        decoder = student.decoder
        heads = {"root": decoder.dec_body_root_pose, "body": decoder.dec_body_pose, "betas": decoder.dec_body_shape,
                 "hand": decoder.dec_hand_pose, "jaw": decoder.dec_face_jaw_pose,
                 "expression": decoder.dec_face_expression}
    else:
        left_as_output = unmirror(axis_angle_to_matrix(mean["lhand"]))[..., :2].reshape(-1)  # the head sees it mirrored
        biases["hand"] = 0.5 * (six_d(mean["rhand"]) + left_as_output)
        heads = {"root": student.body_regressor.root_pose_out, "body": student.body_regressor.body_pose_out,
                 "betas": student.body_regressor.shape_out, "hand": student.hand_regressor.hand_pose_out,
                 "jaw": student.face_regressor.jaw_pose_out, "expression": student.face_regressor.expr_out}
    with torch.no_grad():
        for name, head in heads.items():
            last = head[-1] if isinstance(head, nn.Sequential) else head
            if last.bias.shape != biases[name].shape:
                raise DistillError(f"--init-mean: head {name} has {tuple(last.bias.shape)} outputs, the mean "
                                   f"{tuple(biases[name].shape)}")
            last.weight.mul_(INIT_OUTPUT_WEIGHT_SCALE)
            last.bias.copy_(biases[name])
    return {name: bias.numpy() for name, bias in biases.items()}


def _distributed() -> Tuple[int, int]:
    import torch.distributed as dist

    if "WORLD_SIZE" in os.environ and int(os.environ["WORLD_SIZE"]) > 1 and not dist.is_initialized():
        dist.init_process_group("gloo")
    if dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def _barrier(world: int) -> None:
    if world > 1:
        import torch.distributed as dist

        dist.barrier()


def _mean_over_processes(value: float, world: int) -> float:
    if world == 1:
        return value
    import torch.distributed as dist

    tensor = torch.tensor([value], dtype=torch.float64)
    dist.all_reduce(tensor)
    return float(tensor.item()) / world


def distill(config: DistillConfig) -> Dict[str, object]:
    from leapnbv_model_tools.checkpoint import (
        VARIANTS,
        CheckpointError,
        load_network,
        random_network,
        unmirrors_left_hand,
    )
    from leapnbv_model_tools.torch_smplx import (
        TorchSMPLX,
        centroid_relative,
        mesh_from_outputs,
        vertex_loss,
    )
    from leapnbv_perception.smplx_layer import SMPLXModel

    rank, world = _distributed()
    torch.manual_seed(config.seed)
    for name in ("teacher_variant", "student_variant") if config.targets == "teacher" else ("student_variant",):
        if getattr(config, name) not in VARIANTS:
            raise DistillError(f"--{name.replace('_', '-')} {getattr(config, name)!r}: known {sorted(VARIANTS)}")
    if config.batch_size % world:
        raise DistillError(f"--batch-size {config.batch_size} is not a multiple of the {world} processes")
    try:
        input_hw = tuple(int(v) for v in config.input.split("x"))
    except ValueError as error:
        raise DistillError(f"--input {config.input!r} is not HxW") from error
    if config.targets not in ("teacher", "gt"):
        raise DistillError(f"--targets {config.targets!r}: 'teacher' or 'gt'")
    use_teacher = config.targets == "teacher"
    checks = [(config.body_model, "body model")] + ([(config.teacher, "teacher checkpoint")] if use_teacher else [])
    for path, what in checks:
        if not os.path.isfile(path):
            raise DistillError(f"{what} not found: '{path}'")
    config.teacher_sha256 = sha256_of(config.teacher) if use_teacher else ""
    config.body_model_sha256 = sha256_of(config.body_model)
    try:
        body = SMPLXModel.load(config.body_model)
    except (ValueError, OSError, KeyError) as error:
        raise DistillError(f"body model '{config.body_model}' is unusable: {str(error).splitlines()[0]}") from error
    try:  # every unusable checkpoint (missing, truncated, not a checkpoint, another variant): one line naming it
        teacher = load_network(config.teacher, config.teacher_variant) if use_teacher else None
        student = (load_network(config.student_checkpoint, config.student_variant) if config.student_checkpoint
                   else random_network(config.student_variant, config.seed))
    except CheckpointError as error:
        raise DistillError(error.one_line()) from error
    layer = TorchSMPLX(body)
    student_unmirror = unmirrors_left_hand(config.student_variant)
    train = read_manifest(config.train)
    val = read_manifest(config.val) if config.val else []
    if config.projection_weight > 0 and any(s.params is None or s.camera_k is None for s in train):
        raise DistillError(f"--projection-weight: manifest '{config.train}' has samples without params or camera")
    if not use_teacher and any(s.params is None for s in train):
        raise DistillError(f"--targets gt: manifest '{config.train}' has samples without params")
    if len(train) < config.batch_size:
        raise DistillError(f"manifest '{config.train}' has {len(train)} samples, fewer than --batch-size "
                           f"{config.batch_size}")
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)

    train_cropped = [crop_and_box(s, input_hw) for s in train]
    train_crops = np.stack([crop for crop, _ in train_cropped])
    val_crops = np.stack([make_crop(s, input_hw) for s in val]) if val else np.zeros((0, 3) + input_hw, np.float32)
    train_hashes = [crop_sha256(c) for c in train_crops]
    val_hashes = [crop_sha256(c) for c in val_crops]
    val_targets = None
    train_gt = None  # the ground-truth meshes of the training crops, when a loss needs them
    cache = None
    if use_teacher:
        cache = TeacherCache(config.cache or str(out / "teacher_cache"), config.teacher_sha256,
                             config.teacher_variant, config.body_model_sha256, input_hw,
                             unmirrors_left_hand(config.teacher_variant))
        cache.fill(teacher, layer, np.concatenate([train_crops, val_crops]), train_hashes + val_hashes, rank, world)
        _barrier(world)
        train_targets = torch.from_numpy(cache.load(train_hashes))
        val_targets = cache.load(val_hashes) if val else None
    else:
        train_gt = ground_truth_meshes(layer, train)
        train_targets = centroid_relative(train_gt)
    val_gt = ground_truth_meshes(layer, val).numpy() if val and all(s.params is not None for s in val) else None
    del teacher

    if config.init_mean:
        init_from_mean(student, train)
    train_projection = None
    if config.projection_weight > 0:
        with torch.no_grad():
            camera_vertices = (train_gt if train_gt is not None else ground_truth_meshes(layer, train)) \
                + torch.from_numpy(np.stack([s.translation for s in train])).float()[:, None, :]
            intrinsics = torch.from_numpy(np.stack([s.camera_k for s in train])).float()
            boxes = torch.from_numpy(np.stack([box for _, box in train_cropped])).float()
            train_projection = box_projection(camera_vertices, intrinsics, boxes)
    model = _Batched(student)
    optimizer = torch.optim.AdamW(student.parameters(), lr=config.lr)
    history: Dict[str, list] = {"loss": [], "val": []}
    step = 0
    checkpoint_path = out / "checkpoint.pt"
    config_record = {k: getattr(config, k) for k in CONFIG_KEYS}
    if checkpoint_path.exists():
        try:  # the run's own resume state (optimizer and history too, so not weights_only)
            state = torch.load(checkpoint_path, map_location="cpu", weights_only=False)
            if not isinstance(state, dict) or not {"config", "student", "optimizer", "step", "history"} <= set(state):
                raise ValueError("not a distill resume state")
        except Exception as error:  # noqa: BLE001 - torch.load raises many kinds
            reason = (str(error).splitlines() or [type(error).__name__])[0][:120]
            raise DistillError(f"'{checkpoint_path}' (the run's resume state) is unreadable ({reason}); remove it "
                               "to start again, or use another --out") from error
        if state["config"] != config_record:
            changed = [k for k in CONFIG_KEYS if state["config"].get(k) != config_record[k]]
            raise DistillError(f"'{checkpoint_path}' is a run with another configuration ({', '.join(changed)} "
                               "differ); use another --out")
        student.load_state_dict(state["student"])
        optimizer.load_state_dict(state["optimizer"])
        step, history = int(state["step"]), state["history"]
    if world > 1:
        from torch.nn.parallel import DistributedDataParallel

        model = DistributedDataParallel(model, find_unused_parameters=True)

    steps_per_epoch = len(train) // config.batch_size
    total_steps = steps_per_epoch * config.epochs
    stop_at = min(total_steps, config.max_steps) if config.max_steps else total_steps
    started = time.perf_counter()
    first_step = step

    def save() -> None:
        if rank == 0:
            state = {"config": config_record, "student": student.state_dict(), "optimizer": optimizer.state_dict(),
                     "step": step, "history": history}
            torch.save(state, str(checkpoint_path) + ".tmp")
            os.replace(str(checkpoint_path) + ".tmp", checkpoint_path)
            (out / "history.json").write_text(json.dumps(history, indent=1) + "\n")

    def validate() -> None:
        if rank != 0 or not val:
            return
        student.eval()
        with torch.no_grad():
            meshes = [mesh_from_outputs(layer, student(torch.from_numpy(c[None])), student_unmirror)[0].numpy()
                      for c in val_crops]
        row: Dict[str, float] = {"step": step}
        if val_targets is not None:
            row["val_teacher"] = float(np.mean([pa_mpvpe_mm(m, t) for m, t in zip(meshes, val_targets)]))
        if val_gt is not None:
            row["val_gt"] = float(np.mean([pa_mpvpe_mm(m, g) for m, g in zip(meshes, val_gt)]))
        history["val"].append(row)

    while step < stop_at:
        epoch, offset = divmod(step, steps_per_epoch)
        order = np.random.default_rng([config.seed, epoch]).permutation(len(train))
        batch = order[offset * config.batch_size:(offset + 1) * config.batch_size]
        mine = torch.from_numpy(batch[rank::world].copy())
        model.train()
        freeze_batchnorm(student)
        outputs = model(torch.from_numpy(train_crops[mine.numpy()]))
        meshes = mesh_from_outputs(layer, outputs, student_unmirror)
        loss = vertex_loss(meshes, train_targets[mine]).mean()
        if train_projection is not None:
            projected = student_box_projection(meshes, outputs["cam_param"])
            loss = loss + config.projection_weight * (projected - train_projection[mine]).norm(dim=-1).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        step += 1
        global_loss = _mean_over_processes(float(loss.item()), world)
        history["loss"].append((step, global_loss))
        if rank == 0:
            _progress(step - first_step, stop_at - first_step, epoch, config.epochs, global_loss, started)
        if step % steps_per_epoch == 0:
            validate()
            save()
        elif config.save_every and step % config.save_every == 0:
            save()
    if step % steps_per_epoch:
        save()
    if rank == 0 and sys.stderr.isatty():
        print(file=sys.stderr)
    result: Dict[str, object] = {"step": step, "history": history,
                                 "teacher_cache": str(cache.folder) if cache else "",
                                 "teacher_computed": cache.computed if cache else 0,
                                 "teacher_reused": cache.reused if cache else 0}
    if rank == 0:
        result["curves"] = write_curves(history, str(out / "curves.png"))
        if config.export and step >= total_steps:
            result.update(export_student(student, config, out, input_hw))
    _barrier(world)
    return result


def export_student(student: nn.Module, config: DistillConfig, out: Path, input_hw: Tuple[int, int]) -> Dict:
    from leapnbv_model_tools.checkpoint import save_official
    from leapnbv_model_tools.export import ExportCheckError, checked_export, export_metadata
    from leapnbv_perception.hmr_crop import DEFAULT_BOX_SCALE

    student.eval()
    checkpoint = save_official(student, str(out / "student.pth.tar"))
    onnx_path = str(out / "student.onnx")
    # The box ratio it was trained on (distill's crops), whatever its family's own; the un-mirroring is the family's.
    metadata = export_metadata(config.student_variant, sha256_of(checkpoint), input_hw, box_ratio=DEFAULT_BOX_SCALE)
    # export-hmr's checks (operators, engine contract, parity within each output's own FP32 noise) on the staged
    # file: student.onnx is written only when they pass, so a failed export never leaves an engine to deploy.
    try:
        report = checked_export(student, onnx_path, input_hw, metadata, parity_crops=1)
    except ExportCheckError as error:
        print(f"distill: student.onnx not written: {error}", file=sys.stderr)
        worst = error.report.worst_difference if error.report is not None else float("nan")
        return {"onnx": None, "checkpoint": checkpoint, "parity": worst, "parity_ok": False}
    return {"onnx": onnx_path, "checkpoint": checkpoint, "parity": report.worst_difference, "parity_ok": True}


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m leapnbv_model_tools distill",
                                     description="distill a SMPLer-X student from a teacher's meshes (exit 0 done, "
                                                 "1 export parity failed, 2 bad input)")
    parser.add_argument("--train", required=True, help="manifest (JSON lines: image, box, optional params)")
    parser.add_argument("--val", default="")
    parser.add_argument("--targets", default="teacher", choices=["teacher", "gt"],
                        help="train on the teacher's meshes, or on the manifest's ground-truth meshes")
    parser.add_argument("--teacher", default="", help="teacher checkpoint (official structure)")
    parser.add_argument("--teacher-variant", default="")
    parser.add_argument("--student-variant", required=True)
    parser.add_argument("--student-checkpoint", default="", help="start from this checkpoint (default: random)")
    parser.add_argument("--body-model", required=True, help="SMPL-X .npz (or a stand-in in its layout)")
    parser.add_argument("--out", required=True)
    parser.add_argument("--input", default="256x192", choices=["512x384", "256x192"])
    parser.add_argument("--epochs", type=int, default=1)
    parser.add_argument("--batch-size", type=int, default=4, help="global batch (all processes together)")
    parser.add_argument("--lr", type=float, default=1e-4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cache", default="", help="teacher mesh cache folder (default: OUT/teacher_cache)")
    parser.add_argument("--max-steps", type=int, default=0, help="stop after this global step (resumable)")
    parser.add_argument("--save-every", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch threads per process")
    parser.add_argument("--no-export", action="store_true")
    parser.add_argument("--projection-weight", type=float, default=0.0,
                        help="weight of the projected-mesh loss that trains the camera head (needs camera in the "
                        "manifest; default 0)")
    parser.add_argument("--init-mean", action="store_true",
                        help="start the output heads at the training manifest's mean parameters (from scratch)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    config = DistillConfig(train=args.train, val=args.val, teacher=args.teacher, teacher_variant=args.teacher_variant,
                           student_variant=args.student_variant, student_checkpoint=args.student_checkpoint,
                           body_model=args.body_model, out=args.out, input=args.input, epochs=args.epochs,
                           batch_size=args.batch_size, lr=args.lr, seed=args.seed, cache=args.cache,
                           max_steps=args.max_steps, save_every=args.save_every, export=not args.no_export,
                           targets=args.targets, init_mean=args.init_mean, projection_weight=args.projection_weight)
    try:
        result = distill(config)
    except DistillError as error:
        print(f"distill: {error}", file=sys.stderr)
        return 2
    if _distributed()[0] == 0:
        summary = {k: v for k, v in result.items() if k != "history"}
        summary["last_loss_mm"] = result["history"]["loss"][-1][1] * 1000.0 if result["history"]["loss"] else None
        summary["val"] = result["history"]["val"][-1] if result["history"]["val"] else None
        print(json.dumps(summary))
    import torch.distributed as dist

    if dist.is_initialized():
        dist.destroy_process_group()
    if "parity_ok" in result and not result["parity_ok"]:
        return 1
    return 0

