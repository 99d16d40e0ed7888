"""The SMPLest-X network (test mode) in PyTorch, written here from the public code's structure.

SMPLest-X (SMPLCap/SMPLest-X: models/SMPLest_X.py, models/module.py, configs/config_smplest_x_h.py)
keeps SMPLer-X's encoder and replaces every head after it by one transformer decoder:

- ``encoder``: the same ViT as SMPLer-X's (patch embedding with padding 2, ``pos_embed[:, 1:] +
  pos_embed[:, :1]``, pre-norm blocks with qkv bias, LayerNorm eps 1e-6, exact GELU, ``last_norm``),
  with 80 task tokens instead of 31; ViT-H: width 1280, 32 blocks, 16 heads.
- ``decoder`` (``TransformerDecoderHead``): the 80 tokens and the 192 patch features, concatenated,
  plus one learned ``pos_embedding`` vector (1, 1, C) added to every one of the 272 rows, through 6
  layers of [self-attention over the 272 rows, cross-attention to the 192 patch features (the
  encoder's, without the added vector), feed-forward of width C], each pre-normed (LayerNorm
  eps 1e-5, PyTorch's default) and residual; 8 heads of 64 (inner width 512, no qkv bias);
  ``token_conv`` (C -> 512) on the first 80 rows; then linear heads read fixed token ranges:
  body root (token 0), body pose (1-21), shape (22-31), body camera (32), hand roots (33-34),
  hand poses (35-64: left 15 then right 15), hand cameras (65-66), face root (67), expression
  (68-77), jaw (78), face camera (79). Rotations are 6D, in the same convention as SMPLer-X's
  (x.view(3, 2): columns x[0::2], x[1::2]), which is the project's tail's.
- ``decoder.transformer.to_token_embedding`` (Linear(80, C)) exists in the reference (and so in
  its checkpoint) but its forward never calls it; it is kept for strict loading and is not in
  the exported graph.

What the test-time forward uses (``Model.forward`` with mode 'test'): the mesh is the SMPL-X
layer of root, body pose, left and right hand poses, jaw, shape, expression and the body camera's
translation (the same ``get_camera_trans`` as SMPLer-X: focal 5000, 2.5 m, 256 x 192). The hand
roots, hand cameras, face root and face camera are training-only outputs. The left hand is
predicted on the unmirrored image: no un-mirroring (SMPLer-X's hand RoI branch flips the left
patch; SMPLest-X has no such branch). Its crop box is the detector's box x 1.2 (``bbox_ratio``),
not 1.25. Both go into the export's metadata (``unmirror_left_hand=false``, ``box_ratio=1.2``),
which the HMR node checks against its ``unmirror_left_hand`` / ``box_scale`` parameters.

The forward returns the engine contract's eight outputs (raw 6D, as SMPLer-X's export), and the
graph uses only operators TensorRT 8.5's ONNX parser takes: MatMul, Softmax, primitive LayerNorm
(no LayerNormalization), Erf GELU, Slice / Reshape / Transpose / Concat.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Tuple

import torch
from torch import nn

from leapnbv_model_tools.smplerx import (
    BODY_ROT_JOINTS,
    HAND_ROT_JOINTS,
    INPUT_IMG_SHAPE,
    NUM_BETAS,
    NUM_EXPRESSION,
    LayerNorm,
    Variant,
    ViTEncoder,
)

TASK_TOKENS = 80  # config encoder_config.task_tokens_num / decoder_config.task_tokens_num
DECODER_LAYER_NORM_EPS = 1e-5  # the decoder's torch.nn.LayerNorm(dim): PyTorch's default eps
BOX_RATIO = 1.2  # config data.bbox_ratio (SMPLer-X: 1.25)
CHECKPOINT_FAMILY = "smplest_x"

# The decoder's readout: token ranges [start, end) of each head (TransformerDecoderHead.forward).
TOKEN_RANGES = {
    "dec_body_root_pose": (0, 1), "dec_body_pose": (1, 22), "dec_body_shape": (22, 32), "dec_body_cam": (32, 33),
    "dec_hand_root_pose": (33, 35), "dec_hand_pose": (35, 65), "dec_hand_cam": (65, 67),
    "dec_face_root_pose": (67, 68), "dec_face_expression": (68, 78), "dec_face_jaw_pose": (78, 79),
    "dec_face_cam": (79, 80),
}
HEAD_OUTPUTS = {
    "dec_body_root_pose": 6, "dec_body_pose": BODY_ROT_JOINTS * 6, "dec_body_shape": NUM_BETAS, "dec_body_cam": 3,
    "dec_hand_root_pose": 2 * 6, "dec_hand_pose": 2 * HAND_ROT_JOINTS * 6, "dec_hand_cam": 2 * 3,
    "dec_face_root_pose": 6, "dec_face_expression": NUM_EXPRESSION, "dec_face_jaw_pose": 6, "dec_face_cam": 3,
}


@dataclass(frozen=True)
class SmplestVariant(Variant):
    """Encoder (width, depth, heads) and decoder (depth, heads x head width, readout width) sizes."""

    decoder_depth: int = 6
    decoder_heads: int = 8
    decoder_head_dim: int = 64
    decoder_out: int = 512  # token_conv's width (decoder_config.dim_out)


VARIANTS: Dict[str, SmplestVariant] = {
    "smplest_x_h": SmplestVariant("smplest_x_h", 1280, 32, 16),
    # Not releases: narrow members of the same architecture (every module, key and readout of the
    # real one, smaller widths and depths) for the tests and CPU experiments.
    "smplest_x_t32": SmplestVariant("smplest_x_t32", 32, 1, 2, decoder_depth=1, decoder_heads=2,
                                    decoder_head_dim=16, decoder_out=16),
    "smplest_x_t128": SmplestVariant("smplest_x_t128", 128, 3, 4, decoder_depth=2, decoder_heads=4,
                                     decoder_head_dim=32, decoder_out=64),
}
OFFICIAL_VARIANTS = ("smplest_x_h",)


def _split_heads(x: torch.Tensor, heads: int) -> torch.Tensor:
    batch, rows, _ = x.shape
    return x.reshape(batch, rows, heads, -1).transpose(1, 2)  # b n (h d) -> b h n d


def _merge_heads(x: torch.Tensor) -> torch.Tensor:
    batch, heads, rows, width = x.shape
    return x.transpose(1, 2).reshape(batch, rows, heads * width)  # b h n d -> b n (h d)


def _attend(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, scale: float) -> torch.Tensor:
    return torch.matmul(torch.softmax(torch.matmul(q, k.transpose(-1, -2)) * scale, dim=-1), v)


class Attention(nn.Module):
    """Self-attention of the decoder (``to_qkv`` without bias, ``to_out.0``)."""

    def __init__(self, dim: int, heads: int, head_dim: int) -> None:
        super().__init__()
        self.heads, self.scale = heads, head_dim ** -0.5
        self.to_qkv = nn.Linear(dim, heads * head_dim * 3, bias=False)
        self.to_out = nn.Sequential(nn.Linear(heads * head_dim, dim))  # [1] is a Dropout(0) in the reference

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        q, k, v = (_split_heads(t, self.heads) for t in self.to_qkv(x).chunk(3, dim=-1))
        return self.to_out(_merge_heads(_attend(q, k, v, self.scale)))


class CrossAttention(nn.Module):
    """Queries from the decoder's rows, keys and values from the image features (``to_q``, ``to_kv``)."""

    def __init__(self, dim: int, heads: int, head_dim: int) -> None:
        super().__init__()
        self.heads, self.scale = heads, head_dim ** -0.5
        self.to_kv = nn.Linear(dim, heads * head_dim * 2, bias=False)
        self.to_q = nn.Linear(dim, heads * head_dim, bias=False)
        self.to_out = nn.Sequential(nn.Linear(heads * head_dim, dim))

    def forward(self, x: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        k, v = (_split_heads(t, self.heads) for t in self.to_kv(context).chunk(2, dim=-1))
        q = _split_heads(self.to_q(x), self.heads)
        return self.to_out(_merge_heads(_attend(q, k, v, self.scale)))


class FeedForward(nn.Module):
    """The decoder's feed-forward (width = feat_dim), indices as the reference's Sequential."""

    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        # net.0 Linear, net.1 GELU, net.2 Dropout, net.3 Linear, net.4 Dropout (identities in test mode)
        self.net = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Identity(), nn.Linear(hidden, dim),
                                 nn.Identity())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class PreNorm(nn.Module):
    """LayerNorm (eps 1e-5) before the wrapped attention or feed-forward."""

    def __init__(self, dim: int, fn: nn.Module) -> None:
        super().__init__()
        self.norm = LayerNorm(dim, eps=DECODER_LAYER_NORM_EPS)
        self.fn = fn

    def forward(self, x: torch.Tensor, *context: torch.Tensor) -> torch.Tensor:
        return self.fn(self.norm(x), *context)


class TransformerCrossAttn(nn.Module):
    """The decoder's layers: [self-attention, cross-attention, feed-forward], each residual."""

    def __init__(self, variant: SmplestVariant) -> None:
        super().__init__()
        dim, heads, head_dim = variant.embed_dim, variant.decoder_heads, variant.decoder_head_dim
        self.layers = nn.ModuleList([
            nn.ModuleList([PreNorm(dim, Attention(dim, heads, head_dim)),
                           PreNorm(dim, CrossAttention(dim, heads, head_dim)),
                           PreNorm(dim, FeedForward(dim, dim))])  # mlp_dim = feat_dim
            for _ in range(variant.decoder_depth)])

    def forward(self, x: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        for self_attention, cross_attention, feed_forward in self.layers:
            x = self_attention(x) + x
            x = cross_attention(x, context) + x
            x = feed_forward(x) + x
        return x


class TransformerDecoder(nn.Module):
    """One learned vector added to every row, then the layers (to_token_embedding unused)."""

    def __init__(self, variant: SmplestVariant) -> None:
        super().__init__()
        dim = variant.embed_dim
        self.to_token_embedding = nn.Linear(TASK_TOKENS, dim)  # in the checkpoint, never applied (see above)
        self.pos_embedding = nn.Parameter(torch.randn(1, 1, dim))  # num_tokens=1: one vector for every row
        self.transformer = TransformerCrossAttn(variant)

    def forward(self, rows: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        return self.transformer(rows + self.pos_embedding, context)


class TransformerDecoderHead(nn.Module):
    """The decoder, token_conv and the linear heads reading fixed token ranges."""

    def __init__(self, variant: SmplestVariant) -> None:
        super().__init__()
        self.transformer = TransformerDecoder(variant)
        self.token_conv = nn.Linear(variant.embed_dim, variant.decoder_out)
        for name, (start, end) in TOKEN_RANGES.items():
            setattr(self, name, nn.Linear((end - start) * variant.decoder_out, HEAD_OUTPUTS[name]))

    def forward(self, tokens: torch.Tensor, feature: torch.Tensor,
                heads: Tuple[str, ...] = tuple(TOKEN_RANGES)) -> Dict[str, torch.Tensor]:
        """Raw head outputs by head name for tokens (B, 80, C) and the feature map (B, C, H, W)."""
        batch = feature.shape[0]
        context = feature.flatten(2).transpose(1, 2)  # b c h w -> b (h w) c
        rows = self.transformer(torch.cat([tokens, context], dim=1), context)
        # token_conv is per row: applying it to the first 80 rows only is the reference's result exactly.
        read = self.token_conv(rows[:, :TASK_TOKENS])
        outputs = {}
        for name in heads:
            start, end = TOKEN_RANGES[name]
            outputs[name] = getattr(self, name)(read[:, start:end].reshape(batch, -1))
        return outputs


# The heads the test-time mesh uses (Model.forward, mode 'test'); the others are training-only.
TEST_HEADS = ("dec_body_root_pose", "dec_body_pose", "dec_body_shape", "dec_body_cam", "dec_hand_pose",
              "dec_face_expression", "dec_face_jaw_pose")


class SMPLestX(nn.Module):
    """SMPLest-X in test mode; input (1, 3, 512, 384) or (1, 3, 256, 192) RGB / 255."""

    family = CHECKPOINT_FAMILY

    def __init__(self, variant: str) -> None:
        super().__init__()
        if variant not in VARIANTS:
            raise ValueError(f"unknown SMPLest-X variant {variant!r}; known: {sorted(VARIANTS)}")
        self.variant = VARIANTS[variant]
        self.encoder = ViTEncoder(self.variant, TASK_TOKENS)
        self.decoder = TransformerDecoderHead(self.variant)

    def forward(self, img: torch.Tensor, hands: bool = True) -> Dict[str, torch.Tensor]:
        """The eight contract outputs (raw 6D rotations, the left hand as it is: not mirrored).

        ``hands=False`` is refused: the hand poses come from the same decoder as the body's, so a
        body-only graph would save nothing (export-hmr --without-hands is for SMPLer-X's hand branch).
        """
        if not hands:
            raise ValueError("SMPLest-X has no separate hand branch: a body-only export saves nothing")
        if img.shape[2:] == INPUT_IMG_SHAPE:
            img = img[:, :, ::2, ::2]  # F.interpolate(nearest) to 256 x 192 takes every other pixel
        feature, tokens = self.encoder(img)
        out = self.decoder(tokens, feature, TEST_HEADS)
        hands_6d = out["dec_hand_pose"]
        half = HAND_ROT_JOINTS * 6
        return {"root_pose": out["dec_body_root_pose"], "body_pose": out["dec_body_pose"],
                "lhand_pose": hands_6d[:, :half], "rhand_pose": hands_6d[:, half:],
                "jaw_pose": out["dec_face_jaw_pose"], "betas": out["dec_body_shape"],
                "expression": out["dec_face_expression"], "cam_param": out["dec_body_cam"]}

