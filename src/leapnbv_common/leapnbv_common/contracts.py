"""Message contracts: the one place that says what a usable input is (ROS-free: numpy and duck typing).

Every node input is checked against these before it is used or cached. A check raises
:class:`ContractError`, whose ``reason`` names the contract; the conversion functions in
:mod:`leapnbv_common.conversions` call the single-message checks, and the nodes call the
cross-message ones (same size, same frame, one content per stamp) through :func:`refused`, which
counts a violation on the node's diagnostics and tells the caller to drop the input.

The contracts:

- numbers are finite (no NaN, no inf) wherever a value is used;
- a quaternion is unit length within :data:`QUATERNION_TOLERANCE` (refused, never normalized);
- a camera pose (the optical frame in a floor-aligned fixed frame, z up, floor z = 0) has a
  finite position above the floor (z > 0) and a unit quaternion;
- a valid ground plane n.x + d = 0 in the optical frame has a unit normal (within
  :data:`NORMAL_TOLERANCE`) pointing up toward the camera: the camera is above the floor (d > 0)
  and n.(-y) > 0 (the optical y axis points down in the image);
- a camera info has a pinhole K (finite, fx, fy > 0) with the principal point inside its
  positive width x height;
- colour and depth of one frame have the same size as each other and as their camera info
  (the depth is aligned to colour); a mesh's image size is the size of the frame's images;
- paired messages (computed from one frame) carry the same frame_id;
- a detection has a finite box with x_max > x_min, y_max > y_min that overlaps the image, whose
  corners lie within :data:`BOX_MARGIN` image sizes beyond the image's edges, and a finite score
  in [0, 1];
- a mesh has at most :data:`MAX_MESH_VERTICES` vertices and :data:`MAX_MESH_FACES` faces
  (``mesh_too_large``);
- a stamp is not later than the receiving node's clock by more than its ``max_stamp_ahead_s``
  (``stamp_in_future``: :func:`check_stamp_not_ahead`);
- one stamp, one content per stream: a second, different message with a stamp already seen is
  refused (an identical repeat is not an error).
"""
from __future__ import annotations

import array
import zlib
from collections import OrderedDict
from typing import Any, Callable, Dict, Optional, Protocol, Sequence, Tuple
from typing import OrderedDict as TypingOrderedDict  # collections.OrderedDict[...] needs Python 3.9

import numpy as np

from leapnbv_common.array_types import Float32Array, FloatArray, FloatingArray

#: | |q| - 1 | of an accepted orientation.
QUATERNION_TOLERANCE = 1e-3
#: | |n| - 1 | of an accepted ground-plane normal.
NORMAL_TOLERANCE = 1e-3
#: Stamps remembered per stream by DuplicateStampGuard (several seconds at 30 FPS).
DUPLICATE_MEMORY = 256
#: Image sizes a box corner may lie beyond the image's edges: a detector's box of a person cut by the edge
#: reaches past it (a head above the frame), by far less than the image itself; a box at +-1e9 px is no
#: person of this image, though it overlaps it.
BOX_MARGIN = 1.0
#: Vertices / faces of an accepted mesh: ~10x SMPL-X (10,475 vertices, 20,908 faces), the largest body
#: model the graph runs; a message contract, the same for every node that takes a mesh (raster, nbv), not
#: a tuning. A 1 M-vertex mesh costs seconds per frame to rasterize and would stall the graph.
MAX_MESH_VERTICES = 100_000
MAX_MESH_FACES = 200_000
#: Reasons of the limits above.
MESH_TOO_LARGE = "mesh_too_large"
STAMP_IN_FUTURE = "stamp_in_future"
#: Fields left out of a message's fingerprint: they differ between two computations of the same output.
FINGERPRINT_SKIPPED_FIELDS = ("compute_time_ms",)


class ContractError(ValueError):
    """An input breaks a message contract.

    Attributes:
        reason: the name the rejection is counted under on /diagnostics, or None to let the caller
            name it (a malformed message of some input: see :func:`refused`).
        detail: what is wrong, with the values.
    """

    def __init__(self, detail: str, reason: Optional[str] = None) -> None:
        super().__init__(detail)
        self.reason = reason
        self.detail = detail


# --------------------------------------------------------------------------- helpers


class RejectionCounter(Protocol):
    """What :func:`refused` counts a refused input with (leapnbv_common.diagnostics.StageDiagnostics)."""

    def reject(self, reason: str, detail: str = "") -> None:
        """Count one refused input under ``reason``; ``detail`` says what was wrong."""


def refused(diagnostics: RejectionCounter, reason: str, check: Callable[..., Any], *args: Any) -> bool:
    """Run ``check(*args)``; when it raises ContractError, count the input as rejected and say so.

    The one-line hook of a node::

        if refused(self.diagnostics, "bad_depth", check_same_frame, "depth", a, "camera_info", b):
            return

    Args:
        diagnostics: anything with ``reject(reason, detail)`` (a StageDiagnostics).
        reason: counted when the error names no reason of its own (a malformed message).
        check: a contract check or a conversion function.
        *args: what ``check`` is called with.

    Returns:
        True when the input was refused (and counted), False when it passed.
    """
    try:
        check(*args)
    except ContractError as error:
        diagnostics.reject(error.reason or reason, error.detail)
        return True
    return False


def check_finite(what: str, values: Any, reason: Optional[str] = None) -> FloatArray:
    """``values`` as a float64 array, or ContractError when any is NaN or inf."""
    array_values = np.asarray(values, dtype=np.float64)
    if not np.all(np.isfinite(array_values)):
        bad = int(np.count_nonzero(~np.isfinite(array_values)))
        raise ContractError(f"{what} has {bad} non-finite value(s) (NaN or inf)", reason)
    return array_values


# --------------------------------------------------------------------------- single-message contracts


def check_unit_quaternion(xyzw: Sequence[float], what: str = "orientation", reason: Optional[str] = None) -> None:
    """A finite quaternion of norm 1 within QUATERNION_TOLERANCE (a NaN one fails too)."""
    norm = float(np.linalg.norm(np.asarray(xyzw, dtype=np.float64)))
    if not abs(norm - 1.0) <= QUATERNION_TOLERANCE:
        raise ContractError(f"{what} is not a unit quaternion (|q| = {norm:.4f}; tolerance {QUATERNION_TOLERANCE})",
                            reason)


def check_camera_pose(xyzw: Sequence[float], position: Sequence[float], reason: Optional[str] = None) -> None:
    """A camera pose in a floor-aligned fixed frame: unit quaternion, finite position, camera above the floor.

    Raises:
        ContractError: naming which of the three fails.
    """
    check_unit_quaternion(xyzw, "camera pose orientation", reason)
    p = np.asarray(position, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(p)):
        raise ContractError(f"camera pose position is not finite: {p.tolist()}", reason)
    if not p[2] > 0.0:
        raise ContractError(f"camera pose is not above the floor: z = {p[2]:.3f} m (the fixed frame's floor is "
                            "z = 0, z up)", reason)


def check_ground_plane(normal: Sequence[float], offset: float, valid: bool, source: int,
                       known_sources: Sequence[int], reason: Optional[str] = None) -> None:
    """A GroundPlane's values: a known source and, when valid, a unit normal pointing up toward the camera.

    ``n.x + d = 0`` in the optical frame (x right, y down, z forward): up toward the camera means the
    camera is on the normal's side, d > 0, and the normal points up in the image, n.(-y) > 0. An
    invalid plane ("no floor in this frame") carries no geometry and is not checked further.
    """
    if int(source) not in known_sources:
        raise ContractError(f"ground plane source {int(source)} is none of {list(known_sources)}", reason)
    if not valid:
        return
    n = np.asarray(normal, dtype=np.float64).reshape(3)
    if not (np.all(np.isfinite(n)) and np.isfinite(offset)):
        raise ContractError(f"ground plane is not finite: normal {n.tolist()}, offset {offset}", reason)
    norm = float(np.linalg.norm(n))
    if not abs(norm - 1.0) <= NORMAL_TOLERANCE:
        raise ContractError(f"ground plane normal is not unit length (|n| = {norm:.4f}; tolerance "
                            f"{NORMAL_TOLERANCE})", reason)
    if not -n[1] > 0.0:
        raise ContractError(f"ground plane normal {np.round(n, 4).tolist()} points down (n.(-y) = {-n[1]:.3f} <= 0 "
                            "in the optical frame): the normal must point up toward the camera", reason)
    if not offset > 0.0:
        raise ContractError(f"ground plane offset d = {offset:.3f} m puts the camera on or below the floor "
                            "(d > 0 needed)", reason)


def check_intrinsics(k: FloatArray, width: int, height: int, what: str = "camera_info",
                     reason: Optional[str] = None) -> None:
    """A pinhole K (finite, fx, fy > 0) whose principal point lies inside a positive width x height."""
    k = np.asarray(k, dtype=np.float64).reshape(3, 3)
    if not (np.all(np.isfinite(k)) and k[0, 0] > 0 and k[1, 1] > 0):
        raise ContractError(f"{what} K is not a valid pinhole matrix: {k.ravel().tolist()}", reason)
    if int(width) <= 0 or int(height) <= 0:
        raise ContractError(f"{what} size {int(width)}x{int(height)} is empty", reason)
    if not (0.0 <= k[0, 2] <= width and 0.0 <= k[1, 2] <= height):
        raise ContractError(f"{what} principal point ({k[0, 2]:.1f}, {k[1, 2]:.1f}) lies outside its "
                            f"{int(width)}x{int(height)} image", reason)


def check_boxes(boxes: FloatingArray, image_size: Tuple[int, int], what: str = "detection",
                reason: Optional[str] = None) -> Float32Array:
    """(N, 5) [x0, y0, x1, y1, score] rows: finite, x1 > x0, y1 > y0, score in [0, 1], overlapping the image.

    Every corner lies within BOX_MARGIN image sizes beyond the image's edges (a box of +-1e9 px overlaps the
    image, but is no detection of it): refused like a box outside the image, under the caller's reason.

    Args:
        boxes: the rows (N may be 0).
        image_size: (width, height) of the image the boxes are in; (0, 0) skips the overlap test.
        what: how the error text names a box ("detection 2 ...").
        reason: the rejection reason the error carries (None: the caller's).

    Returns:
        The boxes as an (N, 5) float32 array.
    """
    rows: Float32Array = np.asarray(boxes, dtype=np.float32).reshape(-1, 5)
    for i, (x0, y0, x1, y1, score) in enumerate(rows.astype(np.float64)):
        if not np.all(np.isfinite([x0, y0, x1, y1, score])):
            raise ContractError(f"{what} {i} is not finite: {[x0, y0, x1, y1, score]}", reason)
        if not 0.0 <= score <= 1.0:
            raise ContractError(f"{what} {i} score {score} is outside [0, 1]", reason)
        if not (x1 > x0 and y1 > y0):
            raise ContractError(f"{what} {i} box [{x0:.1f}, {y0:.1f}, {x1:.1f}, {y1:.1f}] is empty or inverted",
                                reason)
        width, height = (int(v) for v in image_size)
        if width > 0 and height > 0 and (x1 <= 0 or y1 <= 0 or x0 >= width or y0 >= height):
            raise ContractError(f"{what} {i} box [{x0:.1f}, {y0:.1f}, {x1:.1f}, {y1:.1f}] lies outside the "
                                f"{width}x{height} image", reason)
        if width > 0 and height > 0 and (min(x0, x1) < -BOX_MARGIN * width or max(x0, x1) > (1 + BOX_MARGIN) * width
                                         or min(y0, y1) < -BOX_MARGIN * height
                                         or max(y0, y1) > (1 + BOX_MARGIN) * height):
            raise ContractError(f"{what} {i} box [{x0:.4g}, {y0:.4g}, {x1:.4g}, {y1:.4g}] reaches more than "
                                f"{BOX_MARGIN:g} image size beyond the {width}x{height} image", reason)
    return rows


def check_mesh_size(what: str, vertex_count: int, face_count: int) -> None:
    """A mesh of at most MAX_MESH_VERTICES vertices and MAX_MESH_FACES faces (``mesh_too_large``).

    Checked on the message's counts, before its arrays are read.
    """
    if vertex_count > MAX_MESH_VERTICES or face_count > MAX_MESH_FACES:
        raise ContractError(f"{what} has {vertex_count} vertices and {face_count} faces (limit {MAX_MESH_VERTICES}"
                            f" vertices, {MAX_MESH_FACES} faces: a body mesh, SMPL-X has 10,475 and 20,908)",
                            MESH_TOO_LARGE)


def check_stamp_not_ahead(what: str, stamp_ns: int, now_ns: int, max_ahead_s: float) -> None:
    """A stamp not later than the node clock's ``now_ns`` by more than ``max_ahead_s`` (``stamp_in_future``).

    No limit when ``max_ahead_s`` is 0 or the clock reads 0 (a sim-time node before its first /clock).
    A camera frame from the future would never age out of the no-stale-goal rules (its age is negative).
    """
    if max_ahead_s > 0 and now_ns > 0 and stamp_ns - now_ns > max_ahead_s * 1e9:
        raise ContractError(f"{what} stamped {(stamp_ns - now_ns) * 1e-9:.3f} s ahead of the node clock (limit"
                            f" {max_ahead_s:g} s, max_stamp_ahead_s): are the clocks synchronised?", STAMP_IN_FUTURE)


# --------------------------------------------------------------------------- cross-message contracts

IMAGE_SIZE_MISMATCH = "image_size_mismatch"
FRAME_ID_MISMATCH = "frame_id_mismatch"
DUPLICATE_STAMP = "duplicate_stamp"


def check_same_size(what_a: str, size_a: Tuple[int, int], what_b: str, size_b: Tuple[int, int]) -> None:
    """Two (width, height) sizes of one frame agree (colour, depth, camera infos, a mesh's image size)."""
    a = tuple(int(v) for v in size_a)
    b = tuple(int(v) for v in size_b)
    if a != b:
        raise ContractError(f"{what_a} is {a[0]}x{a[1]} but {what_b} is {b[0]}x{b[1]}", IMAGE_SIZE_MISMATCH)


def check_same_frame(what_a: str, frame_a: str, what_b: str, frame_b: str) -> None:
    """Two messages paired as one camera frame name the same frame_id."""
    if str(frame_a) != str(frame_b):
        raise ContractError(f"{what_a} is in frame {str(frame_a)!r} but {what_b} in {str(frame_b)!r}",
                            FRAME_ID_MISMATCH)


def fingerprint(message: Any, skip: Sequence[str] = FINGERPRINT_SKIPPED_FIELDS) -> int:
    """A CRC-32 of a ROS message's content (every field, nested ones too, but not ``skip``).

    Works on any object with ``get_fields_and_field_types`` (rclpy messages): byte and typed-array
    fields go through zlib.crc32 as they are (about 0.3 ms for a 640x480 RGB image), scalars
    through their repr.
    """
    crc = 0
    stack = [message]
    while stack:
        value = stack.pop()
        fields = getattr(value, "get_fields_and_field_types", None)
        if fields is not None:
            for name in reversed(list(fields())):
                if name not in skip:
                    stack.append(getattr(value, name))
        elif isinstance(value, (bytes, bytearray, memoryview, array.array)):
            crc = zlib.crc32(value, crc)
            crc = zlib.crc32(b"|%d" % len(value), crc)
        elif isinstance(value, np.ndarray):
            crc = zlib.crc32(np.ascontiguousarray(value).tobytes(), crc)
        elif isinstance(value, (list, tuple)):
            stack.extend(reversed(value))
            crc = zlib.crc32(b"[%d" % len(value), crc)
        else:
            crc = zlib.crc32(repr(value).encode(), crc)
    return crc


def header_stamp_ns(message: Any) -> int:
    """Nanoseconds of ``message.header.stamp`` (duck-typed: sec and nanosec)."""
    stamp = message.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


class DuplicateStampGuard:
    """One stamp, one content, per input stream of a node.

    ``check(stream, message)`` remembers a fingerprint of each message by stream and stamp (the
    newest ``capacity`` stamps per stream); a later message of a remembered stamp with another
    content raises ContractError(``duplicate_stamp``), so it never overwrites what the node has
    cached or computed for that frame. An identical repeat (a resend) passes.
    """

    def __init__(self, capacity: int = DUPLICATE_MEMORY) -> None:
        self.capacity = max(1, int(capacity))
        self._seen: Dict[str, TypingOrderedDict[int, int]] = {}  # per stream: oldest stamp first
        self.repeats = 0  # identical repeats let through

    def check(self, stream: str, message: Any) -> None:
        """Raises ContractError(duplicate_stamp) for a different message with an already-seen stamp."""
        stamp = header_stamp_ns(message)
        digest = fingerprint(message)
        seen = self._seen.setdefault(stream, OrderedDict())
        previous = seen.get(stamp)
        if previous is None:
            seen[stamp] = digest
            while len(seen) > self.capacity:
                seen.popitem(last=False)
            return
        if previous == digest:
            self.repeats += 1
            return
        raise ContractError(f"a second, different {stream} message with stamp {stamp} ns (the first is kept)",
                            DUPLICATE_STAMP)
