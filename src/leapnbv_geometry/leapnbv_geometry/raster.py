"""Z-buffer rasterization of a triangle mesh in the camera optical frame (numba kernel)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Optional, Tuple, TypeVar

import numpy as np

from leapnbv_common.array_types import BoolArray, Float32Array, FloatArray, Int32Array, Int64Array, IntArray

if TYPE_CHECKING:
    _Kernel = TypeVar("_Kernel", bound=Callable[..., Any])

    def njit(*args: Any, **kwargs: Any) -> Callable[[_Kernel], _Kernel]:
        """The njit decorator of numba as the type checker sees it: the compiled kernel keeps its signature."""
else:
    from numba import njit

# Conventions (shared with ``target_geometry.backproject``):
#
# * Vertices are in the camera optical frame (x right, y down, z forward), metres.
# * A point (x, y, z) projects to continuous image coordinates
#       u = (fx x + s y) / z + cx,    v = fy y / z + cy
#   with K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]] (s, the skew, is normally 0).
# * Pixel (row i, column j) samples the ray through (u, v) = (j, i): integer coordinates are
#   pixel centres. This is the OpenCV / ROS CameraInfo convention, in which an ideal camera of
#   width W has cx = (W - 1) / 2. Back-projection inverts exactly this mapping.
# * Coverage uses the top-left fill rule: a pixel centre exactly on an edge shared by two
#   triangles belongs to exactly one of them (no holes, no double draws). Edge functions are
#   evaluated from canonically ordered end points so that the two triangles sharing an edge
#   compute bit-identical values of opposite sign.
# * Depth is perspective-correct: 1/z is interpolated linearly in screen space.

__all__ = [
    "RasterError",
    "RasterResult",
    "rasterize_mesh",
    "warm_up",
]


class RasterError(ValueError):
    """Invalid input to the rasterizer (names the argument and shape at fault)."""


@dataclass
class RasterResult:
    """Output of :func:`rasterize_mesh`.

    Attributes:
        depth: (H, W) float32 camera-frame z of the nearest surface in metres; 0.0 where no
            triangle covers the pixel centre.
        face_index: (H, W) int32 index into ``faces`` of the nearest triangle; -1 where none.
        object_id: (H, W) int32 ``face_object_id[face_index]``, -1 where nothing was hit;
            ``None`` unless ``face_object_id`` was given.
    """

    depth: Float32Array
    face_index: Int32Array
    object_id: Optional[Int32Array] = None

    @property
    def silhouette(self) -> BoolArray:
        """(H, W) bool: True where a triangle was hit."""
        return self.face_index >= 0


@njit(cache=True, nogil=True)
def _edge_coefficients(pu: float, pv: float, qu: float, qv: float, orientation: float) -> Tuple[float, float, float]:
    """Coefficients (A, B, C) of the edge function of edge p->q, pointing into the triangle.

    E(x, y) = A x + B y + C = cross(q - p, (x, y) - p) * orientation. The end points are first
    put in a canonical (lexicographic) order so that the neighbour triangle sharing this edge
    gets exactly the negated coefficients, whatever its vertex order.
    """
    sign = orientation
    if pu > qu or (pu == qu and pv > qv):
        pu, qu = qu, pu
        pv, qv = qv, pv
        sign = -sign
    a = (pv - qv) * sign
    b = (qu - pu) * sign
    c = (pu * qv - pv * qu) * sign
    return a, b, c


@njit(cache=True, nogil=True)
def _raster_triangle(
    u0: float, v0: float, w0: float,
    u1: float, v1: float, w1: float,
    u2: float, v2: float, w2: float,
    face: int,
    inv_depth: Float32Array,
    face_index: Int32Array,
) -> None:
    """Draw one screen-space triangle (u, v, w = 1/z per vertex) into the z-buffer."""
    height = inv_depth.shape[0]
    width = inv_depth.shape[1]
    area = (u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0)
    if not (area > 0.0 or area < 0.0):  # zero area or NaN: degenerate, skip
        return
    orientation = 1.0 if area > 0.0 else -1.0  # both sides are drawn
    inv_area = 1.0 / abs(area)

    # Bounding box of pixel centres, clamped to the image (in float first: clipped vertices can
    # project very far outside the image).
    umin = min(u0, min(u1, u2))
    umax = max(u0, max(u1, u2))
    vmin = min(v0, min(v1, v2))
    vmax = max(v0, max(v1, v2))
    if umax < 0.0 or vmax < 0.0 or umin > width - 1.0 or vmin > height - 1.0:
        return
    col0 = int(np.ceil(max(umin, 0.0)))
    col1 = int(np.floor(min(umax, width - 1.0)))
    row0 = int(np.ceil(max(vmin, 0.0)))
    row1 = int(np.floor(min(vmax, height - 1.0)))
    if col0 > col1 or row0 > row1:
        return

    # Edge i is opposite vertex i, so E_i / |area| is the barycentric weight of vertex i.
    a0, b0, c0 = _edge_coefficients(u1, v1, u2, v2, orientation)
    a1, b1, c1 = _edge_coefficients(u2, v2, u0, v0, orientation)
    a2, b2, c2 = _edge_coefficients(u0, v0, u1, v1, orientation)
    # Top-left rule: an edge owns the pixel centres lying exactly on it when its inward normal
    # points right (a left edge) or straight down (a top edge, image rows grow downward).
    own0 = a0 > 0.0 or (a0 == 0.0 and b0 > 0.0)
    own1 = a1 > 0.0 or (a1 == 0.0 and b1 > 0.0)
    own2 = a2 > 0.0 or (a2 == 0.0 and b2 > 0.0)

    for row in range(row0, row1 + 1):
        y = float(row)
        r0 = b0 * y + c0
        r1 = b1 * y + c1
        r2 = b2 * y + c2
        start = col0
        stop = col1
        if col1 - col0 > 16:
            # Wide triangles (floor and wall quads): narrow the column range analytically,
            # with a one-pixel margin (the exact test below decides), instead of scanning the
            # whole bounding box.
            lo = float(col0)
            hi = float(col1)
            if a0 > 0.0:
                lo = max(lo, -r0 / a0 - 1.0)
            elif a0 < 0.0:
                hi = min(hi, -r0 / a0 + 1.0)
            if a1 > 0.0:
                lo = max(lo, -r1 / a1 - 1.0)
            elif a1 < 0.0:
                hi = min(hi, -r1 / a1 + 1.0)
            if a2 > 0.0:
                lo = max(lo, -r2 / a2 - 1.0)
            elif a2 < 0.0:
                hi = min(hi, -r2 / a2 + 1.0)
            if not (lo <= hi):
                continue
            start = int(np.ceil(lo))
            stop = int(np.floor(hi))
        for col in range(start, stop + 1):
            x = float(col)
            e0 = a0 * x + r0
            e1 = a1 * x + r1
            e2 = a2 * x + r2
            if e0 < 0.0 or e1 < 0.0 or e2 < 0.0:
                continue
            if (e0 == 0.0 and not own0) or (e1 == 0.0 and not own1) or (e2 == 0.0 and not own2):
                continue
            # 1/z is affine in screen space: perspective-correct depth.
            inv_z = (e0 * w0 + e1 * w1 + e2 * w2) * inv_area
            if inv_z > inv_depth[row, col]:
                inv_depth[row, col] = inv_z
                face_index[row, col] = face


@njit(cache=True, nogil=True)
def _rasterize_kernel(
    vertices: FloatArray,
    faces: Int64Array,
    fx: float, skew: float, cx: float, fy: float, cy: float,
    near: float,
    inv_depth: Float32Array,
    face_index: Int32Array,
) -> None:
    """Rasterize every face into ``inv_depth`` (1/z, 0 = empty) and ``face_index``."""
    n_vertices = vertices.shape[0]
    proj_u = np.empty(n_vertices)
    proj_v = np.empty(n_vertices)
    proj_w = np.empty(n_vertices)
    in_front = np.zeros(n_vertices, dtype=np.bool_)
    finite = np.zeros(n_vertices, dtype=np.bool_)
    for k in range(n_vertices):
        x = vertices[k, 0]
        y = vertices[k, 1]
        z = vertices[k, 2]
        finite[k] = np.isfinite(x) and np.isfinite(y) and np.isfinite(z)
        if finite[k] and z >= near:
            w = 1.0 / z
            proj_u[k] = (fx * x + skew * y) * w + cx
            proj_v[k] = fy * y * w + cy
            proj_w[k] = w
            in_front[k] = True

    # Scratch polygon for near-plane clipping: a triangle clipped by one plane has <= 4 corners.
    poly_u = np.empty(4)
    poly_v = np.empty(4)
    poly_w = np.empty(4)
    inv_near = 1.0 / near
    for f in range(faces.shape[0]):
        ia = faces[f, 0]
        ib = faces[f, 1]
        ic = faces[f, 2]
        if in_front[ia] and in_front[ib] and in_front[ic]:
            _raster_triangle(
                proj_u[ia], proj_v[ia], proj_w[ia],
                proj_u[ib], proj_v[ib], proj_w[ib],
                proj_u[ic], proj_v[ic], proj_w[ic],
                f, inv_depth, face_index,
            )
            continue
        if not (finite[ia] and finite[ib] and finite[ic]):
            continue
        if not (in_front[ia] or in_front[ib] or in_front[ic]):
            continue
        # Sutherland-Hodgman against the plane z = near, in camera space.
        n_poly = 0
        for e in range(3):
            if e == 0:
                p, q = ia, ib
            elif e == 1:
                p, q = ib, ic
            else:
                p, q = ic, ia
            if in_front[p]:
                poly_u[n_poly] = proj_u[p]
                poly_v[n_poly] = proj_v[p]
                poly_w[n_poly] = proj_w[p]
                n_poly += 1
            if in_front[p] != in_front[q]:
                # Intersect with the end points in index order, so the neighbour face that
                # shares this edge computes the bit-identical point.
                lo_i = min(p, q)
                hi_i = max(p, q)
                za = vertices[lo_i, 2]
                t = (near - za) / (vertices[hi_i, 2] - za)
                xi = vertices[lo_i, 0] + t * (vertices[hi_i, 0] - vertices[lo_i, 0])
                yi = vertices[lo_i, 1] + t * (vertices[hi_i, 1] - vertices[lo_i, 1])
                poly_u[n_poly] = (fx * xi + skew * yi) * inv_near + cx
                poly_v[n_poly] = fy * yi * inv_near + cy
                poly_w[n_poly] = inv_near
                n_poly += 1
        for k in range(1, n_poly - 1):
            _raster_triangle(
                poly_u[0], poly_v[0], poly_w[0],
                poly_u[k], poly_v[k], poly_w[k],
                poly_u[k + 1], poly_v[k + 1], poly_w[k + 1],
                f, inv_depth, face_index,
            )


@njit(cache=True, nogil=True)
def _inverse_depth_to_depth(inv_depth: Float32Array) -> None:
    """In place: 1/z -> z where hit, 0 stays 0."""
    for i in range(inv_depth.shape[0]):
        for j in range(inv_depth.shape[1]):
            w = inv_depth[i, j]
            if w > 0.0:
                inv_depth[i, j] = 1.0 / w


@njit(cache=True, nogil=True)
def _lookup_object_id(face_index: Int32Array, face_object_id: Int32Array) -> Int32Array:
    """(H, W) object id of the face hit in each pixel, -1 where none."""
    out = np.empty(face_index.shape, dtype=np.int32)
    for i in range(face_index.shape[0]):
        for j in range(face_index.shape[1]):
            f = face_index[i, j]
            out[i, j] = face_object_id[f] if f >= 0 else -1
    return out


def rasterize_mesh(
    vertices: FloatArray,
    faces: IntArray,
    K: FloatArray,
    width: int,
    height: int,
    near: float = 0.01,
    face_object_id: Optional[IntArray] = None,
) -> RasterResult:
    """Render the depth and face-index images of a mesh with a z-buffer.

    Pixel (i, j) samples the ray through image point (u, v) = (j, i) (integer coordinates are
    pixel centres, as in OpenCV / ROS CameraInfo). Triangles are drawn from both sides;
    triangles crossing the plane z = ``near`` are clipped against it in camera space (floor
    and wall quads that extend behind the camera render correctly); triangles with zero
    screen area, or using a non-finite vertex, are skipped. Shared edges follow the top-left
    fill rule, so a closed mesh renders without holes or double-drawn pixels.

    The kernel is compiled by numba on the first call in a process: about 1.5 s on one
    desktop x86 core with an empty cache (expect several times that on a Jetson), about 0.1 s
    when loaded from numba's on-disk cache (``__pycache__`` next to this module, or
    NUMBA_CACHE_DIR). Call :func:`warm_up` at start-up to pay that cost before the first
    frame. The kernel releases the GIL, so a node may run it in a worker thread.

    Args:
        vertices: (N, 3) float vertex positions in the camera optical frame, metres.
        faces: (M, 3) int vertex indices per triangle.
        K: (3, 3) camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]].
        width: image width W in pixels.
        height: image height H in pixels.
        near: near clipping plane z (metres), > 0.
        face_object_id: optional (M,) int per-face object id; when given the result carries
            an ``object_id`` image. (Equivalently callers may map ``face_index`` themselves.)

    Returns:
        RasterResult with ``depth`` (H, W) float32 (0 = no hit), ``face_index`` (H, W)
        int32 (-1 = no hit) and optionally ``object_id`` (H, W) int32.

    Raises:
        RasterError: on wrong shapes, out-of-range face indices, non-positive image size or
            near plane, or a non-finite / singular K.
    """
    vertices = np.asarray(vertices)
    faces = np.asarray(faces)
    K = np.asarray(K, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise RasterError(f"rasterize_mesh: vertices must be (N, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise RasterError(f"rasterize_mesh: faces must be (M, 3), got {faces.shape}")
    if faces.size and not np.issubdtype(faces.dtype, np.integer):
        raise RasterError(f"rasterize_mesh: faces must be integers, got dtype {faces.dtype}")
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] == 0.0 or K[1, 1] == 0.0:
        raise RasterError(f"rasterize_mesh: K must be a finite (3, 3) camera matrix, got {K!r}")
    width = int(width)
    height = int(height)
    if width <= 0 or height <= 0:
        raise RasterError(f"rasterize_mesh: image size must be positive, got {width}x{height}")
    if not near > 0.0:
        raise RasterError(f"rasterize_mesh: near must be > 0, got {near}")
    if faces.size and (faces.min() < 0 or faces.max() >= vertices.shape[0]):
        raise RasterError(
            f"rasterize_mesh: face indices must lie in [0, {vertices.shape[0]}), "
            f"got [{faces.min()}, {faces.max()}]"
        )
    object_ids32 = None
    if face_object_id is not None:
        object_ids32 = np.ascontiguousarray(face_object_id, dtype=np.int32)
        if object_ids32.shape != (faces.shape[0],):
            raise RasterError(
                f"rasterize_mesh: face_object_id must be ({faces.shape[0]},), "
                f"got {object_ids32.shape}"
            )

    # One dtype per argument keeps numba to a single compiled signature.
    vertices64 = np.ascontiguousarray(vertices, dtype=np.float64)
    faces64 = np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3)
    inv_depth = np.zeros((height, width), dtype=np.float32)
    face_index = np.full((height, width), -1, dtype=np.int32)
    _rasterize_kernel(
        vertices64, faces64,
        float(K[0, 0]), float(K[0, 1]), float(K[0, 2]), float(K[1, 1]), float(K[1, 2]),
        float(near), inv_depth, face_index,
    )
    _inverse_depth_to_depth(inv_depth)
    object_id = None
    if object_ids32 is not None:
        object_id = _lookup_object_id(face_index, object_ids32)
    return RasterResult(depth=inv_depth, face_index=face_index, object_id=object_id)


def warm_up() -> float:
    """Compile (or load from the numba cache) every kernel of this module.

    Returns:
        Seconds spent, i.e. the first-call JIT cost in this process.
    """
    start = time.perf_counter()
    vertices = np.array([[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [0.0, 1.0, -1.0]])
    faces = np.array([[0, 1, 2]])
    K = np.array([[4.0, 0.0, 3.5], [0.0, 4.0, 3.5], [0.0, 0.0, 1.0]])
    rasterize_mesh(vertices, faces, K, 8, 8, face_object_id=np.zeros(1, dtype=np.int32))
    return time.perf_counter() - start
