"""Mesh registration to the frame's depth: the depth scale of a metric-placed mesh (docs/ALGORITHMS.md §4b).

An HMR mesh is placed well in the image and poorly in depth. Scaling its vertices about the camera
centre by s keeps every vertex on its viewing ray, so its projection (silhouette) is unchanged and its
rendered depth becomes s * D_mesh at every silhouette pixel. The registration finds the s at which the
measured depth D of the person's pixels agrees with s * D_mesh, robust to occluders in front (D much
nearer) and background behind (D much farther):

1. Render the mesh (silhouette S, depth D_mesh); pixels P = S ∩ dilated box ∩ valid depth.
2. Candidates: peaks of the histogram of r = D / D_mesh over P (bins of the inlier band at the median
   mesh depth); each refined by the median r of its inliers with a shrinking band (3, 2, 1 x band).
   Inliers of s: |D - s D_mesh| <= band.
3. Occluders and background are surfaces that go on past the silhouette; the person's surface ends at
   it. A candidate's spill: of the ring pixels just outside S (inside the dilated box, valid depth) that
   lie next to its inliers, the share whose depth is within half the band of those inliers' depths
   (on a grid of about three samples across the ring). Candidates that spill more than ``max_spill``
   are surfaces (occluder, wall), not the person.
4. The chosen candidate: the one with most inliers among those that do not spill. Refused when none is
   left, or its inlier share of P is under ``min_inlier_share``, or it has fewer than ``MIN_INLIERS``
   pixels, or its residual (RMS of D - s D_mesh over its inliers) is above ``max_residual``.

Limits: only the depth scale is registered, and the spill test assumes the mesh is placed well in the
image: a mesh 10-20 % of the box off the person sees the person go on past its outline, spills like an
occluder and is mostly refused (no plan, never a plan around the wall; docs/ALGORITHMS.md §4b). A person
whose visible part is under ``min_inlier_share`` of the silhouette is refused; an occluder that ends at
the body's outline does not spill and wins if it has more inliers than the visible person.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, List, Optional, Sequence, Tuple

import numpy as np

from leapnbv_common.array_types import BoolArray, FloatArray, FloatingArray, IntArray

from .raster import RasterResult, rasterize_mesh

__all__ = ["MIN_INLIERS", "FrameRegistration", "RegistrationResult", "register_for_frame", "register_mesh_to_depth"]

MIN_INLIERS = 30  # pixels: fewer person pixels than this say nothing about the depth
SCALE_RANGE = (0.25, 4.0)  # depth scales outside this are no HMR depth error but another object
MAX_CANDIDATES = 6
RING_FRACTION = 0.04  # ring width around the silhouette, share of the box's larger side
MIN_RING_PX = 3
SPILL_BAND_SHARE = 0.5  # a surface going on past the silhouette is continuous: half the inlier band


@dataclass
class RegistrationResult:
    """Output of :func:`register_mesh_to_depth`.

    Attributes:
        ok: True when the mesh was registered.
        reason: '' when ok, otherwise why it was refused.
        scale: depth scale s applied about the camera centre (1.0 when refused).
        vertices: (V, 3) float64 registered vertices (s * input; the input when refused).
        residual: RMS of D - s D_mesh over the inliers, metres (0 when there were none).
        inlier_share: inliers / silhouette pixels with valid depth inside the box.
        inlier_count: inlier pixels.
        pixel_count: silhouette pixels with valid depth inside the box.
        spill: the chosen candidate's share of the ring outside the silhouette at its depth.
        depth_shift: metres the vertex mean moved in z ((s - 1) * its z).
        raster: the render of ``vertices`` (the input's, depth scaled by s: the silhouette is the same).
        candidates: (scale, inliers, spill) of every candidate tried, for diagnosis.
    """

    ok: bool
    reason: str
    scale: float
    vertices: FloatArray
    residual: float
    inlier_share: float
    inlier_count: int
    pixel_count: int
    spill: float
    depth_shift: float
    raster: Optional[RasterResult] = None
    candidates: List[Tuple[float, int, float]] = field(default_factory=list)


def _dilate(mask: BoolArray, radius: int) -> BoolArray:
    """Square binary dilation by ``radius`` pixels (separable running max)."""
    out = mask.copy()
    for axis in (0, 1):
        grown = out.copy()
        for step in range(1, radius + 1):
            if axis == 0:
                grown[step:] |= out[:-step]
                grown[:-step] |= out[step:]
            else:
                grown[:, step:] |= out[:, :-step]
                grown[:, :-step] |= out[:, step:]
        out = grown
    return out


def _extreme_filter(values: FloatingArray, radius: int, take_max: bool) -> FloatingArray:
    """Square running max (or min) over a (2 radius + 1) window (separable; edges see fewer pixels)."""
    pick = np.maximum if take_max else np.minimum
    out = values
    for axis in (0, 1):
        grown = out.copy()
        for step in range(1, radius + 1):
            if axis == 0:
                pick(grown[step:], out[:-step], out=grown[step:])
                pick(grown[:-step], out[step:], out=grown[:-step])
            else:
                pick(grown[:, step:], out[:, :-step], out=grown[:, step:])
                pick(grown[:, :-step], out[:, step:], out=grown[:, :-step])
        out = grown
    return out


def _contact_spill(inlier_depth: FloatingArray, ring: BoolArray, measured: FloatingArray, radius: int,
                   band: float) -> float:
    """Share of the ring pixels next to a candidate's inliers that see the same surface go on.

    ``inlier_depth`` is the measured depth at the candidate's inlier pixels and NaN elsewhere. A ring
    pixel touches the candidate when an inlier lies within ``radius``; it continues it when its depth
    is within ``band`` of the depths of the inliers around it.
    """
    highest = _extreme_filter(np.where(np.isnan(inlier_depth), -np.inf, inlier_depth), radius, True)
    lowest = _extreme_filter(np.where(np.isnan(inlier_depth), np.inf, inlier_depth), radius, False)
    touching = ring & np.isfinite(highest)
    if not np.any(touching):
        return 0.0
    depth = measured[touching]
    continued = (depth >= lowest[touching] - band) & (depth <= highest[touching] + band)
    return float(np.mean(continued))


def _box_region(box_xyxy: Sequence[float], dilation: float, width: int, height: int
                ) -> Optional[Tuple[int, int, int, int]]:
    x0, y0, x1, y1 = (float(v) for v in box_xyxy[:4])
    col0 = max(int(np.ceil(min(x0, x1) - dilation)), 0)
    col1 = min(int(np.floor(max(x0, x1) + dilation)) + 1, width)
    row0 = max(int(np.ceil(min(y0, y1) - dilation)), 0)
    row1 = min(int(np.floor(max(y0, y1) + dilation)) + 1, height)
    if col0 >= col1 or row0 >= row1:
        return None
    return row0, row1, col0, col1


def _refine(scale: float, observed: FloatArray, rendered: FloatArray, band: float) -> Tuple[float, BoolArray]:
    """Median ratio of the inliers, with the band shrinking 3, 2, 1 x ``band``."""
    inliers = np.zeros(observed.shape, dtype=bool)
    for factor in (3.0, 2.0, 1.0):
        inliers = np.abs(observed - scale * rendered) <= factor * band
        if not np.any(inliers):
            break
        scale = float(np.median(observed[inliers] / rendered[inliers]))
    inliers = np.abs(observed - scale * rendered) <= band
    return scale, inliers


def _candidates(ratio: FloatArray, bin_width: float, min_count: int) -> List[float]:
    """Ratios at the peaks of the 3-bin smoothed histogram holding at least ``min_count`` values."""
    low, high = SCALE_RANGE
    bins = int(np.ceil((high - low) / bin_width))
    index = np.floor((ratio - low) / bin_width)
    index = index[(index >= 0) & (index < bins)].astype(np.int64)
    counts = np.bincount(index, minlength=bins)
    edges = low + bin_width * np.arange(bins + 1)
    smooth = np.convolve(counts, np.ones(3), mode="same")
    padded = np.concatenate(([-1.0], smooth, [-1.0]))
    peaks = np.nonzero((smooth >= padded[:-2]) & (smooth > padded[2:]) & (smooth >= min_count))[0]
    peaks = peaks[np.argsort(-smooth[peaks])][:MAX_CANDIDATES]
    return [float(0.5 * (edges[i] + edges[i + 1])) for i in peaks]


def register_mesh_to_depth(
    vertices: FloatArray,
    faces: IntArray,
    depth: FloatingArray,
    K: FloatArray,
    box_xyxy: Sequence[float],
    box_dilation_px: float = 10.0,
    inlier_band: float = 0.15,
    min_inlier_share: float = 0.1,
    max_residual: float = 0.1,
    max_spill: float = 0.5,
    min_depth: float = 0.1,
    max_depth: float = 10.0,
) -> RegistrationResult:
    """Register a metric-placed mesh to the measured depth inside its person box (module docstring).

    Args:
        vertices: (V, 3) mesh in the camera optical frame (``target_geometry.place_mesh_metric``).
        faces: (F, 3) int triangles.
        depth: (H, W) float depth in metres (0 / NaN = no return).
        K: (3, 3) camera matrix.
        box_xyxy: person box (x0, y0, x1, y1) in pixels.
        box_dilation_px: growth of the box on every side, pixels.
        inlier_band: metres of |D - s D_mesh| within which a pixel is an inlier.
        min_inlier_share: smallest inlier share of the silhouette's valid pixels.
        max_residual: largest RMS residual of the inliers, metres.
        max_spill: largest share of the ring outside the silhouette at the candidate's depth.
        min_depth: nearest valid depth, metres.
        max_depth: farthest valid depth, metres.

    Returns:
        RegistrationResult (``ok`` False with a reason instead of raising on an unregistrable mesh).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    depth = np.asarray(depth)
    height, width = depth.shape
    tried: List[Tuple[float, int, float]] = []

    def refused(reason: str, residual: float = 0.0, share: float = 0.0, inliers: int = 0, pixels: int = 0,
                spill: float = 0.0) -> RegistrationResult:
        return RegistrationResult(False, reason, 1.0, vertices, residual, share, inliers, pixels, spill, 0.0,
                                  candidates=tried)

    region = _box_region(box_xyxy, float(box_dilation_px), width, height)
    if region is None or vertices.shape[0] == 0:
        return refused("person box outside the image or empty mesh")
    row0, row1, col0, col1 = region
    rendered_full = rasterize_mesh(vertices, faces, K, width, height)
    silhouette = rendered_full.silhouette[row0:row1, col0:col1]
    mesh_depth = rendered_full.depth[row0:row1, col0:col1]
    measured = depth[row0:row1, col0:col1]
    valid = (measured >= min_depth) & (measured <= max_depth)  # NaN fails both
    pixels = silhouette & valid & (mesh_depth > 0.0)
    observed = measured[pixels].astype(np.float64)
    rendered = mesh_depth[pixels].astype(np.float64)
    n_pixels = int(observed.size)
    if n_pixels < MIN_INLIERS:
        return refused(f"{n_pixels} silhouette pixels with valid depth in the box (< {MIN_INLIERS})", pixels=n_pixels)

    ring_px = max(MIN_RING_PX, int(round(RING_FRACTION * max(row1 - row0, col1 - col0))))
    # The spill test runs on a grid of about three samples across the ring: its cost does not grow with the box.
    grid = max(1, ring_px // 3)
    grid_radius = int(np.ceil(ring_px / grid))
    silhouette_grid = silhouette[::grid, ::grid]
    ring_grid = _dilate(silhouette_grid, grid_radius) & ~silhouette_grid & valid[::grid, ::grid]
    measured_grid = measured[::grid, ::grid].astype(np.float32)
    pixel_rows, pixel_cols = np.nonzero(pixels)  # the order of observed / rendered
    on_grid = (pixel_rows % grid == 0) & (pixel_cols % grid == 0)
    grid_index = (pixel_rows[on_grid] // grid, pixel_cols[on_grid] // grid)

    ratio = observed / rendered
    bin_width = inlier_band / float(np.median(rendered))
    min_count = max(MIN_INLIERS, int(np.ceil(0.5 * min_inlier_share * n_pixels)))
    best: Optional[Tuple[int, float, BoolArray, float]] = None
    spilling = 0
    seen: List[float] = []
    for start in _candidates(ratio, bin_width, min_count):
        scale, inliers = _refine(start, observed, rendered, inlier_band)
        if any(abs(scale - other) * float(np.median(rendered)) < inlier_band for other in seen):
            continue  # two peaks of one cluster
        seen.append(scale)
        count = int(np.count_nonzero(inliers))
        if count < MIN_INLIERS:
            continue
        inlier_depth = np.full(ring_grid.shape, np.nan, dtype=np.float32)
        inlier_depth[grid_index] = np.where(inliers[on_grid], observed[on_grid], np.nan)
        spill = _contact_spill(inlier_depth, ring_grid, measured_grid, grid_radius, SPILL_BAND_SHARE * inlier_band)
        tried.append((scale, count, spill))
        if spill > max_spill:
            spilling += 1
            continue
        # A product such as count * (1 - spill) lets a big occluder that spills 0.65 beat a visible person that
        # does not: the spill is a test, not a weight.
        if best is None or count > best[0]:
            best = (count, scale, inliers, spill)
    if best is None:
        detail = f" ({spilling} go on past the silhouette: occluder or background)" if spilling else ""
        return refused(f"no person-shaped depth cluster in the silhouette{detail}", pixels=n_pixels)
    count, scale, inliers, spill = best
    residual = float(np.sqrt(np.mean((observed[inliers] - scale * rendered[inliers]) ** 2)))
    share = count / n_pixels
    if share < min_inlier_share:
        return refused(f"inlier share {share:.3f} < {min_inlier_share}", residual, share, count, n_pixels, spill)
    if residual > max_residual:
        return refused(f"residual {residual:.3f} m > {max_residual} m", residual, share, count, n_pixels, spill)
    registered = vertices * scale
    shift = float((scale - 1.0) * vertices[:, 2].mean())
    scaled = RasterResult(depth=rendered_full.depth * np.float32(scale), face_index=rendered_full.face_index)
    return RegistrationResult(True, "", scale, registered, residual, share, count, n_pixels, spill, shift, scaled,
                              tried)


@dataclass
class FrameRegistration:
    """What raster_node hands to ``compute_target_geometry`` for one frame.

    Attributes:
        vertices: (V, 3) the mesh to make the mask and the target from (registered when it could be).
        depth_offset: 0.0 for a registered mesh (no further offset), None to let the target stage
            estimate it (registration off).
        refused_reason: '' unless the registration refused the mesh.
        depth_shift: metres the registration moved the vertex mean in z.
        summary: 'off', or the scale, residual and inlier share for /diagnostics.
        raster: the registered mesh's render (``compute_target_geometry``'s mesh_raster), or None.
    """

    vertices: FloatArray
    depth_offset: Optional[float]
    refused_reason: str
    depth_shift: float
    summary: str
    raster: Optional[RasterResult] = None


def register_for_frame(vertices: FloatArray, faces: IntArray, depth: FloatingArray, K: FloatArray,
                       box_xyxy: Sequence[float], params: Any) -> FrameRegistration:
    """Run the registration with raster_node's parameters (``leapnbv_geometry.params.RasterParams``).

    Args:
        vertices: (V, 3) metric-placed mesh.
        faces: (F, 3) triangles.
        depth: (H, W) depth in metres.
        K: (3, 3) camera matrix.
        box_xyxy: person box.
        params: RasterParams (``registration_*``, ``box_dilation_px``, ``min_depth``, ``max_depth``).

    Returns:
        FrameRegistration (the input mesh, unchanged, when the registration is off).
    """
    if not params.registration_enabled:
        return FrameRegistration(vertices, None, "", 0.0, "off")
    result = register_mesh_to_depth(
        vertices, faces, depth, K, box_xyxy, box_dilation_px=params.box_dilation_px,
        inlier_band=params.registration_inlier_band, min_inlier_share=params.registration_min_inlier_share,
        max_residual=params.registration_max_residual, max_spill=params.registration_max_spill,
        min_depth=params.min_depth, max_depth=params.max_depth)
    summary = (f"scale={result.scale:.4f} residual_m={result.residual:.4f} inlier_share={result.inlier_share:.3f} "
               f"spill={result.spill:.3f} ok={result.ok}")
    if not result.ok:
        return FrameRegistration(vertices, None, f"mesh not registered: {result.reason}", 0.0, summary)
    return FrameRegistration(result.vertices, 0.0, "", result.depth_shift, summary, result.raster)
