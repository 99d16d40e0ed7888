"""The YOLOv8 detector network (inference form) in PyTorch, written here from the architecture's
public description, for building ONNX files of the real architecture without its weights.

What it is for: the CPU benchmarks of the whole frame need the detector's real cost (its layers and
shapes), and the project ships no licensed weights. A network built here with random weights has
the cost of the real one and the same input/output contract (`images` 1x3xSxS RGB/255 ->
`output0` 1x(4+80)xA: box centre x, y, width, height in input pixels, then the 80 class
probabilities; A = (S/8)^2 + (S/16)^2 + (S/32)^2, 8,400 at 640). It detects nothing: a stand-in for
timing, named as such (``random_yolov8``), never a detector. With real ultralytics weights, use
ultralytics' own export.

Architecture (scale s: depth 0.33, width 0.50): Conv = Conv2d (no bias) + BatchNorm (eps 1e-3) +
SiLU; C2f blocks; SPPF; a top-down and bottom-up neck; the decoupled head with a 16-bin
distribution (DFL) per box side, decoded against anchor points at the cell centres of strides 8,
16 and 32. yolov8s has 11,166,560 parameters (the figure the reference prints for it; the test
checks it).
"""

from __future__ import annotations

import math
from typing import Dict, List, Sequence, Tuple

import torch
from torch import nn

REG_MAX = 16
NUM_CLASSES = 80
STRIDES = (8, 16, 32)
# scale: (depth multiple, width multiple, max channels)
SCALES: Dict[str, Tuple[float, float, int]] = {
    "n": (0.33, 0.25, 1024), "s": (0.33, 0.50, 1024), "m": (0.67, 0.75, 768),
    "l": (1.00, 1.00, 512), "x": (1.00, 1.25, 512),
}


class Conv(nn.Module):
    def __init__(self, c1: int, c2: int, k: int = 1, s: int = 1) -> None:
        super().__init__()
        self.conv = nn.Conv2d(c1, c2, k, s, k // 2, bias=False)
        self.bn = nn.BatchNorm2d(c2, eps=1e-3, momentum=0.03)
        self.act = nn.SiLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.bn(self.conv(x)))


class Bottleneck(nn.Module):
    def __init__(self, c1: int, c2: int, shortcut: bool) -> None:
        super().__init__()
        self.cv1 = Conv(c1, c2, 3)
        self.cv2 = Conv(c2, c2, 3)
        self.add = shortcut and c1 == c2

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.cv2(self.cv1(x))
        return x + y if self.add else y


class C2f(nn.Module):
    def __init__(self, c1: int, c2: int, n: int, shortcut: bool) -> None:
        super().__init__()
        self.c = c2 // 2
        self.cv1 = Conv(c1, 2 * self.c, 1)
        self.cv2 = Conv((2 + n) * self.c, c2, 1)
        self.m = nn.ModuleList(Bottleneck(self.c, self.c, shortcut) for _ in range(n))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = list(self.cv1(x).chunk(2, 1))
        for block in self.m:
            y.append(block(y[-1]))
        return self.cv2(torch.cat(y, 1))


class SPPF(nn.Module):
    def __init__(self, c1: int, c2: int, k: int = 5) -> None:
        super().__init__()
        hidden = c1 // 2
        self.cv1 = Conv(c1, hidden, 1)
        self.cv2 = Conv(hidden * 4, c2, 1)
        self.m = nn.MaxPool2d(k, 1, k // 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = [self.cv1(x)]
        for _ in range(3):
            y.append(self.m(y[-1]))
        return self.cv2(torch.cat(y, 1))


class DFL(nn.Module):
    """Expected value of a 16-bin distribution per box side (a fixed 1x1 convolution by 0..15)."""

    def __init__(self) -> None:
        super().__init__()
        self.conv = nn.Conv2d(REG_MAX, 1, 1, bias=False).requires_grad_(False)
        self.conv.weight.data[:] = torch.arange(REG_MAX, dtype=torch.float).view(1, REG_MAX, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        batch, _, anchors = x.shape
        return self.conv(x.view(batch, 4, REG_MAX, anchors).transpose(2, 1).softmax(1)).view(batch, 4, anchors)


class Detect(nn.Module):
    def __init__(self, channels: Sequence[int], num_classes: int = NUM_CLASSES) -> None:
        super().__init__()
        self.nc, self.no = num_classes, num_classes + 4 * REG_MAX
        c2 = max(16, channels[0] // 4, REG_MAX * 4)
        c3 = max(channels[0], min(num_classes, 100))
        self.cv2 = nn.ModuleList(nn.Sequential(Conv(c, c2, 3), Conv(c2, c2, 3), nn.Conv2d(c2, 4 * REG_MAX, 1))
                                 for c in channels)
        self.cv3 = nn.ModuleList(nn.Sequential(Conv(c, c3, 3), Conv(c3, c3, 3), nn.Conv2d(c3, num_classes, 1))
                                 for c in channels)
        self.dfl = DFL()

    def initialise_biases(self, image_size: int = 640) -> None:
        """The reference's prior: box logits 1, class logits log(5 / nc / cells), so that an
        untrained head gives the low class scores of a real frame's background."""
        for box, cls, stride in zip(self.cv2, self.cv3, STRIDES):
            box[-1].bias.data[:] = 1.0
            cls[-1].bias.data[: self.nc] = math.log(5 / self.nc / (image_size / stride) ** 2)

    def forward(self, features: List[torch.Tensor]) -> torch.Tensor:
        batch = features[0].shape[0]
        outputs, anchors, strides = [], [], []
        for level, (x, stride) in enumerate(zip(features, STRIDES)):
            height, width = x.shape[2], x.shape[3]
            outputs.append(torch.cat((self.cv2[level](x), self.cv3[level](x)), 1).view(batch, self.no, -1))
            ys = torch.arange(height, dtype=x.dtype) + 0.5
            xs = torch.arange(width, dtype=x.dtype) + 0.5
            grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
            anchors.append(torch.stack((grid_x, grid_y), -1).view(-1, 2))
            strides.append(torch.full((height * width, 1), float(stride), dtype=x.dtype))
        anchor_points = torch.cat(anchors).transpose(0, 1).unsqueeze(0)  # (1, 2, A)
        stride_tensor = torch.cat(strides).transpose(0, 1)  # (1, A)
        raw = torch.cat(outputs, 2)
        box, cls = raw.split((4 * REG_MAX, self.nc), 1)
        left_top, right_bottom = self.dfl(box).chunk(2, 1)
        x1y1, x2y2 = anchor_points - left_top, anchor_points + right_bottom
        boxes = torch.cat(((x1y1 + x2y2) / 2, x2y2 - x1y1), 1) * stride_tensor
        return torch.cat((boxes, cls.sigmoid()), 1)


class YOLOv8(nn.Module):
    """YOLOv8 (detection) of one scale; forward: (B, 3, S, S) in [0, 1] -> (B, 4 + nc, A)."""

    def __init__(self, scale: str = "s", num_classes: int = NUM_CLASSES) -> None:
        super().__init__()
        depth, width, max_channels = SCALES[scale]

        def ch(c: int) -> int:
            return int(math.ceil(min(c, max_channels) * width / 8) * 8)

        def n(count: int) -> int:
            return max(round(count * depth), 1)

        self.backbone = nn.ModuleList([
            Conv(3, ch(64), 3, 2), Conv(ch(64), ch(128), 3, 2), C2f(ch(128), ch(128), n(3), True),
            Conv(ch(128), ch(256), 3, 2), C2f(ch(256), ch(256), n(6), True),
            Conv(ch(256), ch(512), 3, 2), C2f(ch(512), ch(512), n(6), True),
            Conv(ch(512), ch(1024), 3, 2), C2f(ch(1024), ch(1024), n(3), True), SPPF(ch(1024), ch(1024)),
        ])
        self.up = nn.Upsample(scale_factor=2, mode="nearest")
        self.top_down_p4 = C2f(ch(1024) + ch(512), ch(512), n(3), False)
        self.top_down_p3 = C2f(ch(512) + ch(256), ch(256), n(3), False)
        self.down_p3 = Conv(ch(256), ch(256), 3, 2)
        self.bottom_up_p4 = C2f(ch(256) + ch(512), ch(512), n(3), False)
        self.down_p4 = Conv(ch(512), ch(512), 3, 2)
        self.bottom_up_p5 = C2f(ch(512) + ch(1024), ch(1024), n(3), False)
        self.detect = Detect((ch(256), ch(512), ch(1024)), num_classes)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        taps = []
        for index, layer in enumerate(self.backbone):
            x = layer(x)
            if index in (4, 6):
                taps.append(x)  # P3, P4
        p3, p4, p5 = taps[0], taps[1], x
        t4 = self.top_down_p4(torch.cat((self.up(p5), p4), 1))
        out3 = self.top_down_p3(torch.cat((self.up(t4), p3), 1))
        out4 = self.bottom_up_p4(torch.cat((self.down_p3(out3), t4), 1))
        out5 = self.bottom_up_p5(torch.cat((self.down_p4(out4), p5), 1))
        return self.detect([out3, out4, out5])


def random_yolov8(scale: str = "s", seed: int = 0, image_size: int = 640) -> YOLOv8:
    """A YOLOv8 of the real architecture with random weights (a timing stand-in: it detects nothing)."""
    torch.manual_seed(seed)
    model = YOLOv8(scale)
    model.detect.initialise_biases(image_size)
    return model.eval()


def export_yolov8(model: YOLOv8, path: str, image_size: int = 640, opset: int = 16) -> str:
    """ONNX with the ultralytics export's names: input ``images`` (1, 3, S, S), output ``output0``."""
    example = torch.zeros(1, 3, image_size, image_size)
    with torch.no_grad():
        torch.onnx.export(model, (example,), path, input_names=["images"], output_names=["output0"],
                          opset_version=opset, dynamo=False)
    return path
