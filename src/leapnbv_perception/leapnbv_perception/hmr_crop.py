"""SMPLer-X body crop: box processing (3:4 aspect, 1.25 scale) and the affine crop (docs/ALGORITHMS.md §2)."""

from __future__ import annotations

from typing import Sequence, Tuple, Union

import cv2
import numpy as np

from leapnbv_common.array_types import FloatArray, UInt8Array

CROP_H = 512
CROP_W = 384
BODY_H = 256
BODY_W = 192
DEFAULT_ASPECT = 0.75  # w / h of the crop, 384 / 512
DEFAULT_BOX_SCALE = 1.25


class InvalidBoxError(ValueError):
    """A box is not usable: no area inside the image, or at most one pixel wide or high."""


def xyxy_to_xywh(box_xyxy: Union[Sequence[float], FloatArray]) -> FloatArray:
    """[x_min, y_min, x_max, y_max, ...] -> [x, y, w, h] float64."""
    x_min, y_min, x_max, y_max = (float(v) for v in box_xyxy[:4])
    return np.array([x_min, y_min, x_max - x_min, y_max - y_min], dtype=np.float64)


def sanitize_box(box_xywh: Union[Sequence[float], FloatArray], image_w: int, image_h: int) -> FloatArray:
    """A detection box made to lie on the image's pixel grid, as SMPLer-X's sanitize_bbox does.

    The box [x, y, w, h] starts at (max(0, x), max(0, y)): a box starting outside the image is
    shifted in, keeping its size, not cut. Its far corner is that start plus (w - 1, h - 1) (the
    last pixel it covers, pixel-index convention), clipped at (W - 1, H - 1). The result is
    [x1, y1, x2 - x1, y2 - y1].

    Raises:
        InvalidBoxError: when it is not finite, has w h <= 0, or spans no more than one pixel
            along an axis (x2 <= x1 or y2 <= y1: a box of w <= 1 or h <= 1, or one that starts
            at or past the image's last pixel).
    """
    x, y, w, h = (float(v) for v in box_xywh[:4])
    if not all(np.isfinite([x, y, w, h])):
        raise InvalidBoxError("box %s is not finite" % ([x, y, w, h],))
    x1 = max(0.0, x)
    y1 = max(0.0, y)
    x2 = min(float(image_w) - 1.0, x1 + max(0.0, w - 1.0))
    y2 = min(float(image_h) - 1.0, y1 + max(0.0, h - 1.0))
    if not (w * h > 0.0 and x2 > x1 and y2 > y1):
        raise InvalidBoxError(
            "box [x=%g, y=%g, w=%g, h=%g] has no area inside the %dx%d image (SMPLer-X's sanitize_bbox: "
            "start clamped to 0, end = start + size - 1 clipped at W - 1 / H - 1, more than one pixel each way)"
            % (x, y, w, h, image_w, image_h)
        )
    return np.array([x1, y1, x2 - x1, y2 - y1], dtype=np.float64)


def process_box(
    box_xywh: Union[Sequence[float], FloatArray],
    image_w: int,
    image_h: int,
    aspect: float = DEFAULT_ASPECT,
    scale: float = DEFAULT_BOX_SCALE,
) -> FloatArray:
    """Turn a detection box into the crop box SMPLer-X expects (its process_bbox).

    Steps: `sanitize_box` (SMPLer-X's pixel convention: w - 1 / h - 1, clip at W - 1 / H - 1,
    shift a box that starts outside, reject boxes of at most one pixel); grow the short side
    about the centre until w / h = aspect; scale w and h by `scale` about the centre. The result
    may extend beyond the image (the crop pads with black there).

    Args:
        box_xywh: [x, y, w, h] in source pixels.
        image_w: image width.
        image_h: image height.
        aspect: target w / h (0.75 = 384 / 512).
        scale: enlargement about the centre (SMPLer-X 1.25, SMPLest-X 1.2).

    Returns:
        (4,) float64 [x, y, w, h] with w / h == aspect.

    Raises:
        InvalidBoxError: see `sanitize_box`.
    """
    x_min, y_min, width, height = sanitize_box(box_xywh, image_w, image_h)
    center_x = x_min + 0.5 * width
    center_y = y_min + 0.5 * height
    if width > aspect * height:
        height = width / aspect
    elif width < aspect * height:
        width = height * aspect
    width *= scale
    height *= scale
    return np.array([center_x - 0.5 * width, center_y - 0.5 * height, width, height], dtype=np.float64)


def crop_affine(
    processed_box: Union[Sequence[float], FloatArray], out_h: int = CROP_H, out_w: int = CROP_W
) -> FloatArray:
    """Affine (2, 3) mapping source pixels to crop pixels for a processed box.

    The box centre goes to (out_w / 2, out_h / 2) with the uniform scale s = out_w / box_w,
    so the box corners land on the crop corners.

    Args:
        processed_box: [x, y, w, h] from `process_box` (w / h = out_w / out_h).
        out_h: crop height.
        out_w: crop width.

    Returns:
        (2, 3) float64 [[s, 0, tx], [0, s, ty]].
    """
    x, y, w, h = (float(v) for v in processed_box[:4])
    s = out_w / w
    center_x = x + 0.5 * w
    center_y = y + 0.5 * h
    return np.array(
        [[s, 0.0, 0.5 * out_w - s * center_x], [0.0, s, 0.5 * out_h - s * center_y]], dtype=np.float64
    )


def invert_affine(affine: FloatArray) -> FloatArray:
    """Inverse of a (2, 3) affine, as (2, 3)."""
    return cv2.invertAffineTransform(np.asarray(affine, dtype=np.float64))


def crop_for_hmr(
    rgb: UInt8Array, processed_box: Union[Sequence[float], FloatArray], out_h: int = CROP_H, out_w: int = CROP_W
) -> Tuple[FloatArray, FloatArray, FloatArray]:
    """Crop the processed box into the HMR input tensor.

    Args:
        rgb: (H, W, 3) uint8 RGB image.
        processed_box: [x, y, w, h] from `process_box`.
        out_h: crop height (512).
        out_w: crop width (384).

    Returns:
        (tensor (1, 3, out_h, out_w) float32 RGB / 255 NCHW (no mean/std normalization),
         affine (2, 3) source -> crop, inverse affine (2, 3) crop -> source).

    Raises:
        ValueError: for an image that is not (H, W, 3) uint8.
    """
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError("crop_for_hmr expects an (H, W, 3) uint8 image, got %s %s" % (rgb.shape, rgb.dtype))
    affine = crop_affine(processed_box, out_h, out_w)
    patch = cv2.warpAffine(
        rgb,
        affine,
        (out_w, out_h),
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=(0, 0, 0),
    )
    tensor = patch.transpose(2, 0, 1)[None].astype(np.float32) * np.float32(1.0 / 255.0)
    return np.ascontiguousarray(tensor), affine, invert_affine(affine)


def fit_to_engine_input(tensor: FloatArray, input_hw: Tuple[int, int]) -> FloatArray:
    """Give the engine the crop at the size it declares.

    SMPLer-X downsamples the 512x384 crop to 256x192 with nearest interpolation, which
    takes exactly every other pixel; an engine exported after that step gets the same.

    Args:
        tensor: (1, 3, 512, 384) crop.
        input_hw: (H, W) the engine declares: (512, 384) or (256, 192).

    Returns:
        (1, 3, H, W) float32 contiguous.

    Raises:
        ValueError: for any other input size.
    """
    height, width = int(input_hw[0]), int(input_hw[1])
    if (height, width) == tensor.shape[2:]:
        return tensor
    if tensor.shape[2] == 2 * height and tensor.shape[3] == 2 * width:
        return np.ascontiguousarray(tensor[:, :, ::2, ::2])
    raise ValueError(
        "the HMR engine input is %dx%d; supported: %dx%d or %dx%d"
        % (height, width, tensor.shape[2], tensor.shape[3], tensor.shape[2] // 2, tensor.shape[3] // 2)
    )


def engine_input_for_box(rgb: UInt8Array, box_xyxy: Union[Sequence[float], FloatArray], input_hw: Tuple[int, int],
                         box_scale: float = DEFAULT_BOX_SCALE) -> Tuple[FloatArray, FloatArray, FloatArray]:
    """The HMR engine's input for one person box, as inference makes it.

    The node, the INT8 calibration and the distillation data all use this: SMPLer-X's box
    processing (process_box), the 512x384 affine crop, then the engine's input size
    (fit_to_engine_input).

    Args:
        rgb: (H, W, 3) uint8 RGB image.
        box_xyxy: [x_min, y_min, x_max, y_max, ...] in source pixels.
        input_hw: (H, W) the engine declares.
        box_scale: enlargement about the box centre (SMPLer-X: 1.25).

    Returns:
        (engine input (1, 3, H, W) float32, processed box (4,) xywh, affine (2, 3) source -> crop).

    Raises:
        InvalidBoxError: when the box has no area inside the image.
    """
    image_h, image_w = rgb.shape[:2]
    processed = process_box(xyxy_to_xywh(box_xyxy), image_w, image_h, DEFAULT_ASPECT, box_scale)
    crop, affine, _ = crop_for_hmr(rgb, processed, CROP_H, CROP_W)
    return fit_to_engine_input(crop, input_hw), processed, affine
