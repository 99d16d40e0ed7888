"""A time-indexed tree of coordinate frames, ROS-free: what tf2's buffer does, for machines without tf2.

A robot publishes its frames as transforms ``parent -> child`` (``map -> odom -> base_link -> camera_link ->
camera_color_optical_frame``): each says where the child's frame is in its parent's, at a stamp (a dynamic
link, ``/tf``) or for all time (a static link, ``/tf_static``). :class:`TransformBuffer` keeps each child's
link (its parent and, for a dynamic one, the samples of the last ``cache_time_ns``, 10 s like tf2's
cache) and answers :meth:`TransformBuffer.lookup`: the transform ``T_target_source`` at a stamp, composed
along the tree through the frames' common ancestor, each dynamic link interpolated between the two
samples around the stamp (the translation on a straight line, the rotation slerped).

The semantics follow tf2's ``BufferCore``, so that the robot (tf2_ros) and this machine agree:

* a stamp of 0 means "the latest": the newest stamp that every dynamic link of the chain covers;
* a dynamic link with a sample at exactly the stamp answers with it; between two samples it is
  interpolated; before its oldest or after its newest sample the lookup fails with an
  :class:`ExtrapolationError` that says by how much (tf2 never extrapolates);
* a frame nobody published, or two frames in different trees, is a :class:`MissingTransformError`;
* a child gets a new parent (the robot re-parented it, or two publishers disagree): the newest
  message wins, and the child's older samples (of the old parent) are forgotten;
* a sample older than the link's newest by more than the cache time is ignored (tf2's
  ``TF_OLD_DATA``), and samples beyond the cache time are pruned as new ones come.

A transform is ``(rotation, translation)``: a unit quaternion (x, y, z, w) and a vector, with
``p_parent = R(q) p_child + t``.
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from leapnbv_common.array_types import FloatArray
from leapnbv_common.rotations import quaternion_to_rotation, rotations_to_quaternions

__all__ = ["DEFAULT_CACHE_TIME_NS", "TransformError", "MissingTransformError", "ExtrapolationError", "Transform",
           "StampedTransform", "TransformBuffer", "slerp", "interpolate"]

#: How long a dynamic link's samples are kept (tf2's default cache time).
DEFAULT_CACHE_TIME_NS = 10_000_000_000
#: Longest chain walked up from a frame: a longer one is a loop (tf2 stops at the same depth).
MAX_TREE_DEPTH = 1000
#: |q| may differ from 1 by this much in a published transform (the contract of camera poses).
QUATERNION_TOLERANCE = 1e-3


class TransformError(Exception):
    """A lookup that cannot be answered; the message names the frames and says why."""


class MissingTransformError(TransformError):
    """A frame nobody published, or two frames that no chain of links connects (tf2's Lookup /
    ConnectivityException)."""


class ExtrapolationError(TransformError):
    """The stamp is outside the buffered time of a dynamic link of the chain (tf2's ExtrapolationException).

    Attributes:
        parent, child: The link ('' when the error comes from tf2, whose message names it).
        stamp_ns: The stamp asked for.
        by_ns: How far outside: > 0 into the future (after the link's newest sample), < 0 into the past
            (before its oldest); 0 when unknown (tf2's message says it).
    """

    def __init__(self, message: str, parent: str = "", child: str = "", stamp_ns: int = 0, by_ns: int = 0) -> None:
        super().__init__(message)
        self.parent, self.child, self.stamp_ns, self.by_ns = parent, child, int(stamp_ns), int(by_ns)

    @classmethod
    def outside(cls, parent: str, child: str, stamp_ns: int, earliest_ns: int, latest_ns: int) -> ExtrapolationError:
        """The error of a stamp outside a link's buffered time [earliest_ns, latest_ns]."""
        stamp_ns = int(stamp_ns)
        by_ns = stamp_ns - int(latest_ns) if stamp_ns > latest_ns else stamp_ns - int(earliest_ns)
        direction, side = ("future", "after") if by_ns > 0 else ("past", "before")
        return cls(f"extrapolation into the {direction}: {parent!r} -> {child!r} at {stamp_ns} ns is "
                   f"{abs(by_ns) * 1e-9:.3f} s {side} its buffered time [{int(earliest_ns)}, {int(latest_ns)}] ns",
                   parent, child, stamp_ns, by_ns)


def _normalized(quaternion: Union[Sequence[float], FloatArray]) -> FloatArray:
    q: FloatArray = np.asarray(quaternion, dtype=np.float64).reshape(4)
    norm = float(np.sqrt(q @ q))
    if not (np.all(np.isfinite(q)) and abs(norm - 1.0) <= QUATERNION_TOLERANCE):
        raise ValueError(f"not a unit quaternion (|q| = {norm:.4f}; tolerance {QUATERNION_TOLERANCE})")
    unit: FloatArray = q / norm
    return unit


def _multiply(a: FloatArray, b: FloatArray) -> FloatArray:
    """Hamilton product a b of (x, y, z, w) quaternions: the rotation b, then a."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz])


def _rotate(q: FloatArray, v: FloatArray) -> FloatArray:
    """R(q) v for a unit (x, y, z, w) quaternion: v + 2 w (u x v) + 2 u x (u x v), u = (x, y, z)."""
    u, w = q[:3], q[3]
    uv = np.cross(u, v)
    rotated: FloatArray = v + 2.0 * w * uv + 2.0 * np.cross(u, uv)
    return rotated


def slerp(q0: FloatArray, q1: FloatArray, fraction: float) -> FloatArray:
    """The rotation ``fraction`` of the way from q0 to q1 on the shorter arc (unit (x, y, z, w) quaternions).

    q(f) = sin((1 - f) theta) / sin(theta) q0 + sin(f theta) / sin(theta) q1, cos(theta) = |q0 . q1|,
    with q1 negated first when q0 . q1 < 0 (q and -q are the same rotation); a straight line, normalized,
    when the two are nearly equal (sin(theta) ~ 0).
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    dot = float(q0 @ q1)
    if dot < 0.0:
        q1, dot = -q1, -dot
    q: FloatArray
    if dot > 0.9995:
        q = q0 + fraction * (q1 - q0)
        q = q / np.sqrt(q @ q)
        return q
    theta = np.arccos(min(1.0, dot))
    q = (np.sin((1.0 - fraction) * theta) * q0 + np.sin(fraction * theta) * q1) / np.sin(theta)
    return q


@dataclass(frozen=True)
class Transform:
    """A rigid transform T_parent_child: p_parent = R(rotation) p_child + translation.

    Attributes:
        rotation: (4,) unit quaternion (x, y, z, w).
        translation: (3,) metres.
    """

    rotation: FloatArray
    translation: FloatArray

    @classmethod
    def identity(cls) -> Transform:
        return cls(np.array([0.0, 0.0, 0.0, 1.0]), np.zeros(3))

    @classmethod
    def checked(cls, rotation: Union[Sequence[float], FloatArray],
                translation: Union[Sequence[float], FloatArray]) -> Transform:
        """A transform from published values: a unit quaternion (normalized), a finite translation.

        Raises:
            ValueError: a quaternion that is not unit length (or NaN), or a non-finite translation.
        """
        t = np.asarray(translation, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(t)):
            raise ValueError(f"translation is not finite: {t.tolist()}")
        return cls(_normalized(rotation), t)

    def __matmul__(self, other: Transform) -> Transform:
        """T_a_b @ T_b_c = T_a_c."""
        return Transform(_multiply(self.rotation, other.rotation),
                         _rotate(self.rotation, other.translation) + self.translation)

    def inverse(self) -> Transform:
        """T_b_a of T_a_b."""
        conjugate = self.rotation * np.array([-1.0, -1.0, -1.0, 1.0])
        return Transform(conjugate, -_rotate(conjugate, self.translation))

    @classmethod
    def from_matrix(cls, rotation: FloatArray, translation: Union[Sequence[float], FloatArray]) -> Transform:
        """The transform of a (3, 3) rotation matrix (columns: the child's axes in the parent) and a translation."""
        return cls(rotations_to_quaternions(np.asarray(rotation, dtype=np.float64).reshape(1, 3, 3))[0],
                   np.asarray(translation, dtype=np.float64).reshape(3).copy())

    def rotation_matrix(self) -> FloatArray:
        """(3, 3) R(q): its columns are the child's axes in the parent's frame."""
        return quaternion_to_rotation(self.rotation)


def interpolate(a: Transform, b: Transform, fraction: float) -> Transform:
    """The transform ``fraction`` of the way from a to b: translation lerped, rotation slerped."""
    return Transform(slerp(a.rotation, b.rotation, fraction),
                     a.translation + fraction * (b.translation - a.translation))


@dataclass(frozen=True)
class StampedTransform:
    """One published link: where ``child`` is in ``parent`` at ``stamp_ns`` (any stamp for a static link)."""

    parent: str
    child: str
    stamp_ns: int
    transform: Transform


@dataclass
class _Link:
    """A child's link to its parent: static (one transform) or dynamic (samples sorted by stamp)."""

    parent: str
    static: bool
    stamps: List[int] = field(default_factory=list)
    transforms: List[Transform] = field(default_factory=list)

    def at(self, child: str, stamp_ns: int) -> Transform:
        if self.static:
            return self.transforms[0]
        stamps = self.stamps
        if stamp_ns == 0:
            return self.transforms[-1]
        i = bisect.bisect_left(stamps, stamp_ns)
        if i < len(stamps) and stamps[i] == stamp_ns:
            return self.transforms[i]
        if i == 0 or i == len(stamps):
            raise ExtrapolationError.outside(self.parent, child, stamp_ns, stamps[0], stamps[-1])
        t0, t1 = stamps[i - 1], stamps[i]
        return interpolate(self.transforms[i - 1], self.transforms[i], (stamp_ns - t0) / (t1 - t0))


class TransformBuffer:
    """The frames published so far, each child's link kept for ``cache_time_ns`` (see the module docstring).

    Args:
        cache_time_ns: How long a dynamic link's samples are kept behind its newest.

    Attributes:
        parent_changes: How many times a child got a new parent (the newest won).
        old_samples_ignored: Samples older than their link's newest by more than the cache time.
    """

    def __init__(self, cache_time_ns: int = DEFAULT_CACHE_TIME_NS) -> None:
        if cache_time_ns <= 0:
            raise ValueError(f"cache time must be > 0 ns, got {cache_time_ns}")
        self.cache_time_ns = int(cache_time_ns)
        self._links: Dict[str, _Link] = {}
        self.parent_changes = 0
        self.old_samples_ignored = 0

    # ------------------------------------------------------------------ filling

    def set_transform(self, link: StampedTransform, static: bool = False) -> None:
        """Add a published link (from /tf, or /tf_static with ``static``).

        Raises:
            ValueError: a link of a frame to itself, or an empty frame name.
        """
        parent, child = link.parent.lstrip("/"), link.child.lstrip("/")  # tf2 ignores a leading slash
        if not parent or not child:
            raise ValueError(f"a transform needs both frames, got parent {parent!r}, child {child!r}")
        if parent == child:
            raise ValueError(f"a transform from frame {child!r} to itself")
        current = self._links.get(child)
        if current is not None and (current.parent != parent or current.static != static):
            if current.parent != parent:
                self.parent_changes += 1
            current = None  # the newest wins: the old parent's samples (or the other kind) go
        if current is None:
            current = self._links[child] = _Link(parent, static)
        if static:
            current.stamps, current.transforms = [int(link.stamp_ns)], [link.transform]
            return
        stamp = int(link.stamp_ns)
        stamps = current.stamps
        if stamps and stamp < stamps[-1] - self.cache_time_ns:
            self.old_samples_ignored += 1
            return
        i = bisect.bisect_left(stamps, stamp)
        if i < len(stamps) and stamps[i] == stamp:
            current.transforms[i] = link.transform  # a repeated stamp: the newest message wins
        else:
            stamps.insert(i, stamp)
            current.transforms.insert(i, link.transform)
        cut = bisect.bisect_left(stamps, stamps[-1] - self.cache_time_ns)
        if cut:
            del stamps[:cut]
            del current.transforms[:cut]

    def clear(self) -> None:
        """Forget every link (the clock jumped back, a new session)."""
        self._links.clear()

    # ------------------------------------------------------------------ asking

    def frames(self) -> List[str]:
        """Every frame known (as a child or a parent), sorted."""
        return sorted(set(self._links) | {link.parent for link in self._links.values()})

    def parent_of(self, frame: str) -> Optional[str]:
        link = self._links.get(frame.lstrip("/"))
        return link.parent if link is not None else None

    def _chain(self, frame: str) -> List[str]:
        """The frame and its ancestors up to its tree's root, nearest first."""
        chain = [frame]
        while chain[-1] in self._links:
            chain.append(self._links[chain[-1]].parent)
            if len(chain) > MAX_TREE_DEPTH:
                raise MissingTransformError(f"the tree above {frame!r} is a loop or deeper than {MAX_TREE_DEPTH}")
        return chain

    def _path(self, target: str, source: str) -> Tuple[List[str], List[str]]:
        """(source up to the common ancestor, target up to it): the children whose links the lookup uses.

        Raises:
            MissingTransformError: an unknown frame, or no common ancestor.
        """
        known = set(self._links) | {link.parent for link in self._links.values()}
        for frame, role in ((target, "target"), (source, "source")):
            if frame not in known:
                raise MissingTransformError(f"{role} frame {frame!r} does not exist (known frames: "
                                            f"{', '.join(sorted(known)) or 'none'})")
        up_source, up_target = self._chain(source), self._chain(target)
        common = next((frame for frame in up_source if frame in set(up_target)), None)
        if common is None:
            raise MissingTransformError(
                f"frames {target!r} and {source!r} are not connected: {target!r} is in the tree of "
                f"{up_target[-1]!r}, {source!r} in the tree of {up_source[-1]!r}")
        return up_source[:up_source.index(common)], up_target[:up_target.index(common)]

    def latest_common_stamp(self, target: str, source: str) -> int:
        """The newest stamp every dynamic link between the two frames covers (0 when all are static).

        Raises:
            MissingTransformError: the frames are not connected.
        """
        from_source, from_target = self._path(target.lstrip("/"), source.lstrip("/"))
        dynamic = [self._links[child] for child in from_source + from_target if not self._links[child].static]
        return min(link.stamps[-1] for link in dynamic) if dynamic else 0

    def lookup(self, target: str, source: str, stamp_ns: int) -> Transform:
        """T_target_source at a stamp: p_target = R p_source + t (0: the latest common stamp).

        Raises:
            MissingTransformError: an unknown frame, or frames that are not connected.
            ExtrapolationError: the stamp is outside a dynamic link's buffered time (the message
                names the link and by how much).
        """
        target, source = target.lstrip("/"), source.lstrip("/")
        from_source, from_target = self._path(target, source)
        stamp = int(stamp_ns)
        if stamp == 0:
            stamp = self.latest_common_stamp(target, source)
        # T_common_source = T_common_a ... T_b_source: compose from the ancestor down.
        common_source = Transform.identity()
        for child in from_source:
            common_source = self._links[child].at(child, stamp) @ common_source
        common_target = Transform.identity()
        for child in from_target:
            common_target = self._links[child].at(child, stamp) @ common_target
        return common_target.inverse() @ common_source

    def can_transform(self, target: str, source: str, stamp_ns: int) -> bool:
        """Whether :meth:`lookup` would answer."""
        try:
            self.lookup(target, source, stamp_ns)
        except TransformError:
            return False
        return True
