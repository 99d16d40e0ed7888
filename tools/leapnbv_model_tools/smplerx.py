"""The SMPLer-X network (test mode) in PyTorch, written here from the public code's structure.

Module and parameter names follow the official model (so the public checkpoints load by their
state-dict keys): ``encoder`` (ViT with 31 task tokens), ``body_position_net``,
``body_regressor``, ``box_net``, ``hand_roi_net``, ``hand_position_net``, ``hand_regressor``,
``face_regressor``. The forward returns what the engine contract needs (docs/ALGORITHMS.md §3):
raw 6D rotations (the left hand's as predicted on the mirrored patch: the tail un-mirrors it),
betas, expression and cam_param, each (1, n).

Written so that the traced graph uses only operators TensorRT 8.5's ONNX parser takes:
- LayerNorm as mean / variance / sqrt (no LayerNormalization op, which 8.5 may not parse);
- the 512x384 -> 256x192 nearest downsampling as a stride-2 slice (what nearest picks);
- point sampling (grid_sample, align_corners=True, zero padding) and the hand RoIAlign
  (aligned=False, adaptive sampling, average) as products with one-hot bilinear weight
  matrices: MatMul / Equal / Floor / Ceil (no Einsum), no GridSample (opset 16, plugin-free only on newer
  TensorRT), no RoiAlign (a plugin on 8.5), no NonZero / ScatterND (the reference's in-place
  boolean-mask assignment in restore_bbox is written as torch.where).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Tuple

import torch
from torch import nn
from torch.nn import functional as F

# Geometry of the SMPLer-X configs (main/config/config_smpler_x_*.py).
INPUT_IMG_SHAPE = (512, 384)
INPUT_BODY_SHAPE = (256, 192)
OUTPUT_HM_SHAPE = (16, 16, 12)
OUTPUT_HAND_HM_SHAPE = (16, 16, 16)
INPUT_HAND_SHAPE = (256, 256)
INPUT_FACE_SHAPE = (192, 192)
HAND_ROI_UPSCALE = 4
BODY_POS_JOINTS = 25  # smpl_x.pos_joint_part['body']
HAND_POS_JOINTS = 20  # smpl_x.pos_joint_part['rhand']
BODY_ROT_JOINTS = 21  # orig body joints without the root
HAND_ROT_JOINTS = 15
NUM_BETAS = 10
NUM_EXPRESSION = 10
TASK_TOKENS = 31  # shape, cam, expression, jaw, 2 hand, 25 body
LAYER_NORM_EPS = 1e-6
MAX_ROI_SAMPLES = 8  # adaptive RoIAlign samples per bin side covered exactly (RoIs up to 8 bins = 128 px)


@dataclass(frozen=True)
class Variant:
    name: str
    embed_dim: int
    depth: int
    num_heads: int


VARIANTS: Dict[str, Variant] = {
    "s32": Variant("s32", 384, 12, 12),
    "b32": Variant("b32", 768, 12, 12),
    "l32": Variant("l32", 1024, 24, 16),
    "h32": Variant("h32", 1280, 32, 16),
    # Not SMPLer-X releases: narrow members of the same family for the tests and the synthetic
    # compression ladder on a CPU (same heads and contract, width / depth / heads reduced).
    "t32": Variant("t32", 32, 1, 2),
    "t64": Variant("t64", 64, 2, 2),
    "t128": Variant("t128", 128, 3, 4),
}
OFFICIAL_VARIANTS = ("s32", "b32", "l32", "h32")


class LayerNorm(nn.LayerNorm):
    """nn.LayerNorm's parameters, computed with primitive ops (exports without LayerNormalization)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        mean = x.mean(dim=-1, keepdim=True)
        centred = x - mean
        variance = (centred * centred).mean(dim=-1, keepdim=True)
        return centred / torch.sqrt(variance + self.eps) * self.weight + self.bias


class Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))  # exact (erf) GELU


class Attention(nn.Module):
    def __init__(self, dim: int, num_heads: int) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.scale = (dim // num_heads) ** -0.5
        self.qkv = nn.Linear(dim, dim * 3, bias=True)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        batch, tokens, channels = x.shape
        qkv = self.qkv(x).reshape(batch, tokens, 3, self.num_heads, -1).permute(2, 0, 3, 1, 4)
        q, k, v = qkv[0] * self.scale, qkv[1], qkv[2]
        attention = (q @ k.transpose(-2, -1)).softmax(dim=-1)
        return self.proj((attention @ v).transpose(1, 2).reshape(batch, tokens, channels))


class Block(nn.Module):
    def __init__(self, dim: int, num_heads: int) -> None:
        super().__init__()
        self.norm1 = LayerNorm(dim, eps=LAYER_NORM_EPS)
        self.attn = Attention(dim, num_heads)
        self.norm2 = LayerNorm(dim, eps=LAYER_NORM_EPS)
        self.mlp = Mlp(dim, dim * 4)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.attn(self.norm1(x))
        return x + self.mlp(self.norm2(x))


class PatchEmbed(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        # Padding 2 (the reference's 4 + 2 (ratio // 2 - 1) for ratio 1): same 16 x 12 grid as
        # padding 0 would give, different values.
        self.proj = nn.Conv2d(3, dim, kernel_size=16, stride=16, padding=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x)


class ViTEncoder(nn.Module):
    """ViT over the 256 x 192 body image; returns (feature map (1, C, 16, 12), task tokens (1, T, C)).

    T is 31 for SMPLer-X (TASK_TOKENS); SMPLest-X's encoder is the same ViT with 80 tokens."""

    def __init__(self, variant: Variant, task_tokens: int = TASK_TOKENS) -> None:
        super().__init__()
        dim = variant.embed_dim
        self.num_task_tokens = task_tokens
        self.patch_embed = PatchEmbed(dim)
        self.task_tokens = nn.Parameter(torch.zeros(1, task_tokens, dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, 16 * 12 + 1, dim))
        self.blocks = nn.ModuleList([Block(dim, variant.num_heads) for _ in range(variant.depth)])
        self.last_norm = LayerNorm(dim, eps=LAYER_NORM_EPS)

    def forward(self, image: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        grid = self.patch_embed(image)
        batch, channels, height, width = grid.shape
        patches = grid.flatten(2).transpose(1, 2)
        patches = patches + self.pos_embed[:, 1:] + self.pos_embed[:, :1]  # tokens get no position embedding
        x = torch.cat([self.task_tokens.expand(batch, -1, -1), patches], dim=1)
        for block in self.blocks:
            x = block(x)
        x = self.last_norm(x)
        tokens = x[:, :self.num_task_tokens]
        feature_map = x[:, self.num_task_tokens:].transpose(1, 2).reshape(batch, channels, height, width)
        return feature_map, tokens


def _linear_layers(dims, relu_final: bool = False) -> nn.Sequential:
    layers = []
    for index in range(len(dims) - 1):
        layers.append(nn.Linear(dims[index], dims[index + 1]))
        if index < len(dims) - 2 or relu_final:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


def _conv_layers(dims, bnrelu_final: bool = True) -> nn.Sequential:
    layers = []
    for index in range(len(dims) - 1):
        layers.append(nn.Conv2d(dims[index], dims[index + 1], kernel_size=1))
        if index < len(dims) - 2 or bnrelu_final:
            layers += [nn.BatchNorm2d(dims[index + 1]), nn.ReLU()]
    return nn.Sequential(*layers)


def _deconv_layers(dims) -> nn.Sequential:
    layers = []
    for index in range(len(dims) - 1):
        layers += [nn.ConvTranspose2d(dims[index], dims[index + 1], kernel_size=4, stride=2, padding=1, bias=False),
                   nn.BatchNorm2d(dims[index + 1]), nn.ReLU()]
    return nn.Sequential(*layers)


def _softmax_volume(heatmaps: torch.Tensor) -> torch.Tensor:
    shape = heatmaps.shape
    return F.softmax(heatmaps.reshape(shape[0], shape[1], -1), dim=2).reshape(shape)


def soft_argmax_3d(heatmaps: torch.Tensor) -> torch.Tensor:
    """(B, J, D, H, W) logits -> (B, J, 3) expected (x, y, z) in heatmap cells."""
    probabilities = _softmax_volume(heatmaps)
    depth, height, width = heatmaps.shape[2:]
    x = (probabilities.sum(dim=(2, 3)) * torch.arange(width, dtype=heatmaps.dtype)).sum(dim=2, keepdim=True)
    y = (probabilities.sum(dim=(2, 4)) * torch.arange(height, dtype=heatmaps.dtype)).sum(dim=2, keepdim=True)
    z = (probabilities.sum(dim=(3, 4)) * torch.arange(depth, dtype=heatmaps.dtype)).sum(dim=2, keepdim=True)
    return torch.cat([x, y, z], dim=2)


def soft_argmax_2d(heatmaps: torch.Tensor) -> torch.Tensor:
    """(B, J, H, W) logits -> (B, J, 2) expected (x, y) in pixels."""
    probabilities = _softmax_volume(heatmaps)
    height, width = heatmaps.shape[2:]
    x = (probabilities.sum(dim=2) * torch.arange(width, dtype=heatmaps.dtype)).sum(dim=2, keepdim=True)
    y = (probabilities.sum(dim=3) * torch.arange(height, dtype=heatmaps.dtype)).sum(dim=2, keepdim=True)
    return torch.cat([x, y], dim=2)


def _one_hot(index: torch.Tensor, size: int) -> torch.Tensor:
    """index (...) float integral -> (..., size) 1.0 where arange == index (all zero out of range)."""
    return (index.unsqueeze(-1) == torch.arange(size, dtype=index.dtype)).to(index.dtype)


def sample_points(feature: torch.Tensor, points_xy: torch.Tensor) -> torch.Tensor:
    """Bilinear features at pixel points, as grid_sample(align_corners=True, zeros padding).

    feature (B, C, H, W); points_xy (B, P, 2) in pixels -> (B, P, C).
    """
    height, width = feature.shape[2:]
    x, y = points_xy[..., 0], points_xy[..., 1]
    x0, y0 = torch.floor(x), torch.floor(y)
    lx, ly = x - x0, y - y0
    weight_x = (1 - lx).unsqueeze(-1) * _one_hot(x0, width) + lx.unsqueeze(-1) * _one_hot(x0 + 1, width)
    weight_y = (1 - ly).unsqueeze(-1) * _one_hot(y0, height) + ly.unsqueeze(-1) * _one_hot(y0 + 1, height)
    # (B, P, H) @ (B, H, C W) -> (B, P, C, W), then weighted by (B, P, 1, W) and summed: (B, P, C).
    batch, channels = feature.shape[:2]
    rows = torch.matmul(weight_y, feature.permute(0, 2, 1, 3).reshape(batch, height, channels * width))
    rows = rows.reshape(batch, -1, channels, width)
    return (rows * weight_x.unsqueeze(2)).sum(dim=3)


def _roi_axis_weights(
    start: torch.Tensor, end: torch.Tensor, bins: int, size: int
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Per RoI (R,), the (R, bins, size) weights summing RoIAlign's samples along one axis, and
    the sample count per bin (R,). RoIAlign aligned=False, sampling_ratio 0 (adaptive)."""
    length = torch.clamp(end - start, min=1.0)
    bin_size = length / bins
    count = torch.clamp(torch.ceil(length / bins), min=1.0, max=float(MAX_ROI_SAMPLES))
    sample = torch.arange(MAX_ROI_SAMPLES, dtype=start.dtype)
    index = torch.arange(bins, dtype=start.dtype)
    # (R, bins, S) sample coordinates
    coordinate = (start[:, None, None] + index[None, :, None] * bin_size[:, None, None]
                  + (sample[None, None, :] + 0.5) * (bin_size / count)[:, None, None])
    used = (sample[None, None, :] < count[:, None, None]) & (coordinate >= -1.0) & (coordinate <= float(size))
    clamped = torch.clamp(coordinate, min=0.0)
    low = torch.floor(clamped)
    at_edge = low >= size - 1
    low = torch.where(at_edge, torch.full_like(low, size - 1), low)
    clamped = torch.where(at_edge, low, clamped)
    high = torch.where(at_edge, low, low + 1)
    frac = clamped - low
    weights = ((1 - frac).unsqueeze(-1) * _one_hot(low, size) + frac.unsqueeze(-1) * _one_hot(high, size))
    weights = (weights * used.unsqueeze(-1).to(weights.dtype)).sum(dim=2)
    return weights, count


def roi_align(feature: torch.Tensor, rois_xyxy: torch.Tensor, output_hw: Tuple[int, int]) -> torch.Tensor:
    """RoIAlign (average, aligned=False, spatial scale 1, adaptive sampling) of one image's
    feature (1, C, H, W) over RoIs (R, 4) in feature pixels -> (R, C, out_h, out_w).

    Separable: the mean over a bin's samples of the bilinear value equals Wy V Wx^T / count with
    per-axis weight matrices (a sample outside [-1, size] contributes zero, as the reference).
    """
    height, width = feature.shape[2:]
    weight_y, count_y = _roi_axis_weights(rois_xyxy[:, 1], rois_xyxy[:, 3], output_hw[0], height)
    weight_x, count_x = _roi_axis_weights(rois_xyxy[:, 0], rois_xyxy[:, 2], output_hw[1], width)
    channels = feature.shape[1]
    # (R, out_h, H) @ (H, C W) -> (R, out_h, C, W) -> (R, C, out_h, W) @ (R, 1, W, out_w) -> (R, C, out_h, out_w)
    rows = torch.matmul(weight_y, feature[0].permute(1, 0, 2).reshape(height, channels * width))
    rows = rows.reshape(rows.shape[0], output_hw[0], channels, width).permute(0, 2, 1, 3)
    pooled = torch.matmul(rows, weight_x.transpose(1, 2).unsqueeze(1))
    return pooled / (count_y * count_x)[:, None, None, None]


def restore_box(center: torch.Tensor, size: torch.Tensor, aspect: float, extension: float) -> torch.Tensor:
    """Hand/face box (B, 4) xyxy in the 256 x 192 body image from a centre and size in heatmap
    cells: grown to `aspect` (w / h) about its centre, then scaled by `extension`."""
    scale = torch.tensor([INPUT_BODY_SHAPE[1] / OUTPUT_HM_SHAPE[2], INPUT_BODY_SHAPE[0] / OUTPUT_HM_SHAPE[1]],
                         dtype=center.dtype)
    low = (center - size / 2) * scale
    high = (center + size / 2) * scale
    w, h = high[:, 0] - low[:, 0], high[:, 1] - low[:, 1]
    c_x, c_y = low[:, 0] + w / 2, low[:, 1] + h / 2
    new_h = torch.where(w > aspect * h, w / aspect, h)
    new_w = torch.where(w < aspect * h, h * aspect, w)
    new_w, new_h = new_w * extension, new_h * extension
    return torch.stack([c_x - new_w / 2, c_y - new_h / 2, c_x + new_w / 2, c_y + new_h / 2], dim=1)


class PositionNet(nn.Module):
    def __init__(self, joints: int, hm_shape: Tuple[int, int, int], dim: int) -> None:
        super().__init__()
        self.joints, self.hm_shape = joints, hm_shape
        self.conv = _conv_layers([dim, joints * hm_shape[0]], bnrelu_final=False)

    def forward(self, feature: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        heatmaps = self.conv(feature).reshape(-1, self.joints, *self.hm_shape)
        return _softmax_volume(heatmaps), soft_argmax_3d(heatmaps)


class BodyRotationNet(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.body_conv = _linear_layers([dim, 512])
        self.root_pose_out = _linear_layers([BODY_POS_JOINTS * 515, 6])
        self.body_pose_out = _linear_layers([BODY_POS_JOINTS * 515, BODY_ROT_JOINTS * 6])
        self.shape_out = _linear_layers([dim, NUM_BETAS])
        self.cam_out = _linear_layers([dim, 3])

    def forward(self, body_tokens, shape_token, cam_token, body_joints):
        features = torch.cat([self.body_conv(body_tokens), body_joints], dim=2).flatten(1)
        return (self.root_pose_out(features), self.body_pose_out(features), self.shape_out(shape_token),
                self.cam_out(cam_token))


class BoxNet(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.deconv = _deconv_layers([dim + BODY_POS_JOINTS * OUTPUT_HM_SHAPE[0], 256, 256, 256])
        self.bbox_center = _conv_layers([256, 3], bnrelu_final=False)
        self.lhand_size = _linear_layers([256, 256, 2])
        self.rhand_size = _linear_layers([256, 256, 2])
        self.face_size = _linear_layers([256, 256, 2])

    def forward(self, feature: torch.Tensor, joint_heatmaps: torch.Tensor):
        batch = feature.shape[0]
        volume = joint_heatmaps.reshape(batch, -1, OUTPUT_HM_SHAPE[1], OUTPUT_HM_SHAPE[2])
        upsampled = self.deconv(torch.cat([feature, volume], dim=1))  # (B, 256, 128, 96)
        centers = soft_argmax_2d(self.bbox_center(upsampled))  # (B, 3, 2) in 128 x 96 pixels
        sampled = sample_points(upsampled, centers)  # (B, 3, 256)
        sizes = (self.lhand_size(sampled[:, 0]), self.rhand_size(sampled[:, 1]), self.face_size(sampled[:, 2]))
        centers = centers / 8  # to the 16 x 12 heatmap cells
        return centers[:, 0], sizes[0], centers[:, 1], sizes[1], centers[:, 2], sizes[2]


class HandRoI(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.deconv = _deconv_layers([dim, dim // 2, dim // 4])
        self.conv = _conv_layers([dim // 4, dim], bnrelu_final=False)

    def forward(self, feature: torch.Tensor, lhand_box: torch.Tensor, rhand_box: torch.Tensor) -> torch.Tensor:
        upsampled = self.deconv(feature)  # (1, C/4, 64, 48)
        to_feature = torch.tensor(
            [OUTPUT_HM_SHAPE[2] * HAND_ROI_UPSCALE / INPUT_BODY_SHAPE[1],
             OUTPUT_HM_SHAPE[1] * HAND_ROI_UPSCALE / INPUT_BODY_SHAPE[0]] * 2, dtype=feature.dtype)
        size = OUTPUT_HAND_HM_SHAPE[1:]
        left = roi_align(upsampled, lhand_box * to_feature, size).flip(3)  # mirrored: a right hand
        right = roi_align(upsampled, rhand_box * to_feature, size)
        return self.conv(torch.cat([left, right], dim=0))


class HandRotationNet(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.hand_conv = _conv_layers([dim, 512])
        self.hand_pose_out = _linear_layers([HAND_POS_JOINTS * 515, HAND_ROT_JOINTS * 6])

    def forward(self, feature: torch.Tensor, joints: torch.Tensor) -> torch.Tensor:
        sampled = sample_points(self.hand_conv(feature), joints[:, :, :2])
        return self.hand_pose_out(torch.cat([sampled, joints], dim=2).flatten(1))


class FaceRegressor(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.expr_out = _linear_layers([dim, NUM_EXPRESSION])
        self.jaw_pose_out = _linear_layers([dim, 6])

    def forward(self, expression_token, jaw_token):
        return self.expr_out(expression_token), self.jaw_pose_out(jaw_token)


# The identity rotation in the 6D representation (columns a1 = x[0::2] = (1, 0, 0), a2 = x[1::2] = (0, 1, 0)),
# for each of the 15 hand joints: the hand pose a body-only export writes.
HAND_IDENTITY_6D = torch.tensor([1.0, 0.0, 0.0, 1.0, 0.0, 0.0] * HAND_ROT_JOINTS).reshape(1, -1)


class SMPLerX(nn.Module):
    """SMPLer-X in test mode; input (1, 3, 512, 384) or (1, 3, 256, 192) RGB / 255."""

    def __init__(self, variant: str) -> None:
        super().__init__()
        if variant not in VARIANTS:
            raise ValueError(f"unknown SMPLer-X variant {variant!r}; known: {sorted(VARIANTS)}")
        self.variant = VARIANTS[variant]
        dim = self.variant.embed_dim
        self.encoder = ViTEncoder(self.variant)
        self.body_position_net = PositionNet(BODY_POS_JOINTS, OUTPUT_HM_SHAPE, dim)
        self.body_regressor = BodyRotationNet(dim)
        self.box_net = BoxNet(dim)
        self.hand_roi_net = HandRoI(dim)
        self.hand_position_net = PositionNet(HAND_POS_JOINTS, OUTPUT_HAND_HM_SHAPE, dim)
        self.hand_regressor = HandRotationNet(dim)
        self.face_regressor = FaceRegressor(dim)

    def forward(self, img: torch.Tensor, hands: bool = True) -> Dict[str, torch.Tensor]:
        """The eight contract outputs. ``hands=False``: the hand branch (box net, hand RoI, hand
        position and rotation nets) is not run and both hand poses are the identity rotation in 6D
        (``HAND_IDENTITY_6D``: the tail decodes it to axis-angle 0, the SMPL-X hand mean pose); the
        other six outputs do not depend on that branch and are the same."""
        if img.shape[2:] == INPUT_IMG_SHAPE:
            img = img[:, :, ::2, ::2]  # F.interpolate(nearest) to 256 x 192 takes every other pixel
        feature, tokens = self.encoder(img)
        shape_token, cam_token, expression_token, jaw_token = tokens[:, 0], tokens[:, 1], tokens[:, 2], tokens[:, 3]
        body_tokens = tokens[:, 6:]
        joint_heatmaps, body_joints = self.body_position_net(feature)
        root, body, betas, cam = self.body_regressor(body_tokens, shape_token, cam_token, body_joints)
        if not hands:
            expression, jaw = self.face_regressor(expression_token, jaw_token)
            # Tied to the graph's input by a product with zero so that the outputs are computed tensors,
            # not graph constants (an engine builder may refuse a constant as a network output).
            identity = HAND_IDENTITY_6D.to(root.dtype).expand(root.shape[0], -1) + 0.0 * root[:, :1]
            return {"root_pose": root, "body_pose": body, "lhand_pose": identity, "rhand_pose": identity,
                    "jaw_pose": jaw, "betas": betas, "expression": expression, "cam_param": cam}
        l_center, l_size, r_center, r_size, _, _ = self.box_net(feature, joint_heatmaps)
        hand_aspect = INPUT_HAND_SHAPE[1] / INPUT_HAND_SHAPE[0]
        lhand_box = restore_box(l_center, l_size, hand_aspect, 2.0)
        rhand_box = restore_box(r_center, r_size, hand_aspect, 2.0)
        hand_feature = self.hand_roi_net(feature, lhand_box, rhand_box)
        _, hand_joints = self.hand_position_net(hand_feature)
        hand_poses = self.hand_regressor(hand_feature, hand_joints)
        expression, jaw = self.face_regressor(expression_token, jaw_token)
        return {"root_pose": root, "body_pose": body, "lhand_pose": hand_poses[0:1], "rhand_pose": hand_poses[1:2],
                "jaw_pose": jaw, "betas": betas, "expression": expression, "cam_param": cam}


def camera_depth_scale() -> float:
    """k of t_z = k sigmoid(cam[2]) for the virtual focal 5000 and a 2.5 m camera space."""
    return math.sqrt(5000.0 * 5000.0 * 2.5 * 2.5 / (INPUT_BODY_SHAPE[0] * INPUT_BODY_SHAPE[1]))
