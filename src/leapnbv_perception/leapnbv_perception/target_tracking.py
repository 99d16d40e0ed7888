"""Keeping the same person across frames and robot moves: the target's track in the fixed frame (ROS-free).

Each detections frame, :meth:`TargetTracker.update` decides which detection is the target
(docs/ALGORITHMS.md, "Keeping the same person"):

1. **Where each detection is.** The median of the valid depth readings in the central part of its box
   (``central_share`` of its width and height about its centre: background at the box's edges and an
   occluder over less than half of the central part do not move the median), back-projected through the
   box centre with the depth camera's intrinsics, then taken to the fixed frame with the frame's camera pose
   (p_fixed = R p_camera + t). A box with fewer than ``min_depth_pixels`` valid readings has no position.
   Besides that place, a box has the places of its depth layers (:func:`depth_layers`: the readings of the
   whole box fall into layers, an occluder's, the person's, the background's): a track measures a box at the candidate
   nearest its prediction, so an occluder over most of the target's central box does not move the target to
   the occluder (nor start a track there that later claims the target's box). A place at which the box
   would be larger than ``max_person_extent_m`` (height or width) is no person's, and neither is a layer behind
   one that fills the box (:func:`box_depth_layers`; the box's central median neither): a near person's box that
   shows a hidden target behind them is not measured at the target's depth.
2. **Where the target should be.** A constant-velocity Kalman filter of the target's horizontal position
   (x, y of the fixed frame, whose z is up) and velocity, predicted to the frame's stamp.
3. **Which detection it is.** The gate: a detection is the target only within ``gate_m + gate_growth_m_s *
   (time since the target's last measured position)`` of the predicted place (horizontal distance), at most
   ``reacquire_radius_m`` (or ``gate_m`` when larger). The other people in view are tracked too (same filter
   and gate, not published); detections are given to tracks nearest first (distances within
   :data:`DISTANCE_TIE_M` tie: the target first, then the lowest detection index), so a bystander standing
   next to a hidden target keeps its own track and is never taken for it. Boxes measured within
   ``ambiguity_m`` of one place in the gate (a box mostly covered by another person's has only that person's
   depth) are told apart in the image: the one overlapping the target's expected box most is the target (its
   last box as a rectangle at its depth, moved to the predicted place and seen from this frame's camera: the
   robot may have moved or turned since), and the place, which is neither person's for certain, moves no track
   (the prediction stands). When none of them overlaps that box by ``min_track_iou``, none is the target.
4. **States.** TRACKED (a detection is the target), NOT_SEEN (none is: the target is kept at its
   predicted place and only a detection inside the gate can be it again), LOST (not seen for longer than
   ``lost_after_s``: dropped), NONE (no target yet). A frame that finds the target lost takes a new one
   at once if it has a candidate, else says LOST (every frame until one has).
5. **Acquisition** (the first target, and after LOST), the only way another person becomes the target:
   :func:`leapnbv_perception.target_selection.acquisition_index` over the frame's candidates (the highest
   score, ties within 1e-3 to the box nearest the image centre, then the lowest index); each acquisition
   has a new ``track_id``. For ``reacquire_window_s`` after a target with a fixed-frame place was lost, the
   candidates are only the detections within ``reacquire_radius_m`` of that place (the lost person found
   again), and not a detection of another person followed in a frame that also had the lost target (seen
   side by side, they are someone else); after it, anyone in view.

Without a camera pose, a depth frame or any box with depth (or with ``fixed_frame`` off) the frame is
decided in the image only, by today's overlap rule (:func:`~leapnbv_perception.target_selection.select_target`):
the box overlapping the last target box by ``min_track_iou``. For a target that has a fixed-frame track, a
frame without an overlapping box is NOT_SEEN (an image-only frame never takes another person); for a track
that never had a position (a graph without poses or depth), no overlap is an acquisition, as the image-only
rule always did. The decision says which way it was made (``mode``, ``reason``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import AbstractSet, Any, Dict, List, Optional, Protocol, Set, Tuple

import numpy as np

from leapnbv_common.array_types import BoolArray, FloatArray, FloatingArray
from leapnbv_perception.target_selection import acquisition_index, box_iou, overlapping_index, usable_boxes

__all__ = ["STATE_NONE", "STATE_TRACKED", "STATE_NOT_SEEN", "STATE_LOST", "STATE_NAMES", "MODE_FIXED_FRAME",
           "MODE_IMAGE", "DISTANCE_TIE_M", "TrackerConfig", "CameraPoseLike", "TargetDecision", "TargetTracker",
           "box_positions_camera", "box_places_camera", "box_depth_layers", "DepthLayer", "depth_layers",
           "depth_layer_ranges", "layer_column_share", "layer_extent_share", "LAYER_MIN_COLUMNS",
           "LAYER_FILLS_EXTENT", "LAYER_IN_ANOTHER_BOX", "SMALLER_BOX_SHARE", "person_fit_depth"]

# leapnbv_msgs/TargetTrack's states, by value (this core imports no message package).
STATE_NONE = 0
STATE_TRACKED = 1
STATE_NOT_SEEN = 2
STATE_LOST = 3
STATE_NAMES = {STATE_NONE: "NONE", STATE_TRACKED: "TRACKED", STATE_NOT_SEEN: "NOT_SEEN", STATE_LOST: "LOST"}

MODE_FIXED_FRAME = "fixed_frame"
MODE_IMAGE = "image"

#: Distances (m) between a track's prediction and detections closer than this tie: the assignment then goes
#: by track (the target first) and detection index, never by the last bit of a depth median or a pose.
DISTANCE_TIE_M = 1e-3
#: Depth layers of a box (:func:`depth_layers`): histogram bin (m), the share of readings a bin needs to join a
#: layer, and the share a layer needs to be a candidate place.
LAYER_BIN_M = 0.1
LAYER_GAP_SHARE = 0.005
MIN_LAYER_SHARE = 0.15
# A depth layer found in at least LAYER_MIN_COLUMNS of its box's columns whose readings span at least
# LAYER_FILLS_EXTENT of the box's area fills the box: it is the box's person (a detector draws the box around
# them), and what lies behind it (a hidden person seen in its gaps, the background) is no place of the box.
LAYER_MIN_COLUMNS = 0.7
LAYER_FILLS_EXTENT = 0.8
# A layer of a box that does not fill it, at the depth of a layer that fills another box and inside that box (this
# share of its readings' rectangle), is that other box's person seen in this box: no place of this box.
LAYER_IN_ANOTHER_BOX = 0.8
# A box below this share of another's area, inside it and filled by that box's person, shows nobody of its own.
SMALLER_BOX_SHARE = 0.8
#: Initial standard deviation (m/s) of a new track's velocity (people walk at up to about 1.5 m/s).
INITIAL_SPEED_SIGMA_M_S = 0.5


@dataclass(frozen=True)
class TrackerConfig:
    """How the tracker decides (hmr_node's parameters; docs/ALGORITHMS.md, "Keeping the same person").

    Attributes:
        fixed_frame: Track in the camera pose's fixed frame (False: every frame in the image only).
        follow: Follow the target at all (False: every frame takes the acquisition rule's box).
        gate_m: m, the gate's radius around the predicted place for a target seen in the last frame.
        gate_growth_m_s: m/s, how fast the gate grows with the time since the last measured position.
        lost_after_s: s, a target not seen for longer than this is lost.
        min_track_iou: The overlap with the last target box that continues an image-only track.
        central_share: Share of the box's width and height, about its centre, whose depth is the position.
        min_depth_m: m, depth readings nearer than this are invalid.
        max_depth_m: m, depth readings farther than this are invalid.
        min_depth_pixels: Valid readings a box needs for a position.
        measurement_sigma_m: m, standard deviation of a measured position (depth noise, the body turning).
        acceleration_sigma_m_s2: m/s^2, the filter's white-noise acceleration (people start, stop, turn).
        ambiguity_m: m, boxes measured this near one another in the gate are one place, not two people:
            told apart by their overlap with the target's last box.
        reacquire_window_s: s after a target with a fixed-frame place is lost during which only a detection
            near that place may become the target (0: anyone at once).
        reacquire_radius_m: m, how near the lost target's place a detection must be in that window.
        max_person_extent_m: m, the largest height or width a person's box can have at its place: a depth at
            which the box would be larger is not where the box's person stands.
        coast_s: s a track's velocity carries its prediction without a measurement; after that the prediction
            stands where it got to and its velocity is unknown again (0 +- INITIAL_SPEED_SIGMA_M_S). A person
            hidden behind furniture mostly stops there; carried on at the last speed the place drifts ~2 m in
            3 s and the gate misses them when they reappear.
    """

    fixed_frame: bool = True
    follow: bool = True
    gate_m: float = 0.6
    gate_growth_m_s: float = 0.5
    lost_after_s: float = 3.0
    min_track_iou: float = 0.3
    central_share: float = 0.5
    min_depth_m: float = 0.2
    max_depth_m: float = 12.0
    min_depth_pixels: int = 20
    measurement_sigma_m: float = 0.1
    acceleration_sigma_m_s2: float = 0.5
    ambiguity_m: float = 0.3
    reacquire_window_s: float = 10.0
    reacquire_radius_m: float = 1.5
    max_person_extent_m: float = 2.4
    coast_s: float = 1.5


class CameraPoseLike(Protocol):
    """The camera's optical frame in a floor-aligned fixed frame (z up): p_fixed = rotation @ p + position.

    leapnbv_common.camera_pose.StampedCameraPose is one.
    """

    @property
    def frame_id(self) -> str: ...

    @property
    def rotation(self) -> np.ndarray[Any, Any]: ...

    @property
    def position(self) -> np.ndarray[Any, Any]: ...


@dataclass(frozen=True)
class TargetDecision:
    """One frame's decision (the fields of leapnbv_msgs/TargetTrack, plus how it was made).

    Attributes:
        state: STATE_NONE, STATE_TRACKED, STATE_NOT_SEEN or STATE_LOST.
        detection_index: The target's row in the frame's boxes, -1 when it is not among them.
        track_id: The target's id (0: no target yet); a new one on every acquisition.
        fixed_frame: Frame of position and velocity; "" when the track has no fixed-frame position.
        position: (3,) the target's place in fixed_frame (filtered x, y; the last measured z); zeros without one.
        velocity: (3,) filtered horizontal velocity, m/s (z = 0).
        position_sigma_m: Standard deviation of each horizontal coordinate (grows while not seen); 0 without one.
        last_seen_ns: Stamp of the last frame in which the target was among the detections (0: never).
        reason: How the decision was made, in words.
        mode: MODE_FIXED_FRAME or MODE_IMAGE (decided in the image only; ``reason`` says why).
        acquired: This frame took a new target (by the acquisition rule).
        gate_m: The gate in force for this frame (0 in the image only).
    """

    state: int
    detection_index: int
    track_id: int
    fixed_frame: str
    position: FloatArray
    velocity: FloatArray
    position_sigma_m: float
    last_seen_ns: int
    reason: str
    mode: str
    acquired: bool = False
    gate_m: float = 0.0

    @property
    def state_name(self) -> str:
        return STATE_NAMES[self.state]


def depth_layer_ranges(values: FloatArray) -> List[Tuple[float, float, float]]:
    """The layers in a box's valid readings as (median, nearest, farthest) depths (m), the most populated first.

    A layer is a run of :data:`LAYER_BIN_M` histogram bins each holding at least :data:`LAYER_GAP_SHARE` of
    the readings (a few stray readings between an occluder and a person do not join them); layers with
    less than :data:`MIN_LAYER_SHARE` of the readings are left out. Ties in population go to the nearer layer.
    """
    values = np.sort(np.asarray(values, dtype=np.float64).ravel())
    if values.size == 0:
        return []
    bins = np.floor((values - values[0]) / LAYER_BIN_M).astype(np.int64)
    counts = np.bincount(bins)
    dense = counts >= max(1.0, LAYER_GAP_SHARE * values.size)
    layers: List[Tuple[int, float, float, float]] = []
    start = None
    for b in range(len(counts) + 1):
        if b < len(counts) and dense[b]:
            start = b if start is None else start
            continue
        if start is not None:
            members = values[(bins >= start) & (bins < b)]
            if members.size >= MIN_LAYER_SHARE * values.size:
                layers.append((int(members.size), float(np.median(members)), float(members[0]), float(members[-1])))
            start = None
    layers.sort(key=lambda layer: (-layer[0], layer[1]))
    return [(median, near, far) for _, median, near, far in layers]


def depth_layers(values: FloatArray) -> List[float]:
    """Depths (m) of the layers in a box's valid readings (:func:`depth_layer_ranges`), most populated first."""
    return [median for median, _, _ in depth_layer_ranges(values)]


def layer_column_share(grid: FloatArray, near: float, far: float) -> float:
    """Share of the columns with a valid reading in a box's depth ``grid`` that have one in [near, far] (m).

    ``grid`` is rows x columns of the box's depth, NaN where a reading is not valid. A person fills their box
    from side to side at their depth (a box is drawn around them); a person hidden behind a nearer one shows
    only in the gaps beside the nearer one, in some of the nearer box's columns.
    """
    valid = int(np.count_nonzero(np.isfinite(grid).any(axis=0))) if grid.size else 0
    if valid == 0:
        return 0.0
    with np.errstate(invalid="ignore"):
        inside = (grid >= near) & (grid <= far)
    return float(np.count_nonzero(inside.any(axis=0))) / float(valid)


def layer_extent_share(grid: FloatArray, near: float, far: float) -> float:
    """Share of a box's ``grid`` that the readings in [near, far] (m) span: their bounding rectangle's area.

    A detector draws a box around its person's visible pixels, so their layer spans the box (1.0 for a tight
    box, occluded parts included in the span); a person farther behind, seen through a near person's box,
    spans only the part of it where their own, smaller box lies.
    """
    if grid.size == 0:
        return 0.0
    with np.errstate(invalid="ignore"):
        inside = (grid >= near) & (grid <= far)
    rows, columns = np.flatnonzero(inside.any(axis=1)), np.flatnonzero(inside.any(axis=0))
    if rows.size == 0:
        return 0.0
    return float((rows[-1] - rows[0] + 1) * (columns[-1] - columns[0] + 1)) / float(grid.shape[0] * grid.shape[1])


@dataclass(frozen=True)
class DepthLayer:
    """One depth layer of a box (:func:`box_depth_layers`).

    Attributes:
        z: m, its median depth.
        near: m, its nearest reading.
        far: m, its farthest reading.
        columns: share of the box's columns with a reading in it (:func:`layer_column_share`).
        extent: share of the box its readings span (:func:`layer_extent_share`).
        fills: it is in LAYER_MIN_COLUMNS of the columns, spans LAYER_FILLS_EXTENT of the box, the box fits a
            person at its depth, and it is not the farthest of several layers (the background).
        behind_a_filler: behind the box's person (the layer that fills the box and spans most of it): someone or
            something seen through their gaps.
        rect: (u0, v0, u1, v1) image pixels: the rectangle its readings span.
    """

    z: float
    near: float
    far: float
    columns: float
    extent: float
    fills: bool
    behind_a_filler: bool
    rect: Tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)

    def overlaps_depth(self, other: DepthLayer) -> bool:
        """Whether the two layers' depth ranges overlap."""
        return self.near <= other.far and other.near <= self.far


def person_fit_depth(box: FloatArray, scale: Tuple[float, float], k: FloatArray, config: TrackerConfig) -> float:
    """The largest depth (m) at which ``box`` still fits a person (``config.max_person_extent_m`` high and wide).

    Size = pixels x depth / focal length; a box cut by the image border gives a lower bound of the size.
    """
    return float(config.max_person_extent_m / max((box[2] - box[0]) * scale[0] / k[0, 0],
                                                  (box[3] - box[1]) * scale[1] / k[1, 1], 1e-9))


def box_depth_layers(box: FloatArray, scale: Tuple[float, float], depth: FloatingArray,
                     config: TrackerConfig, fits_m: float = np.inf) -> Tuple[Optional[float], List[DepthLayer]]:
    """(the median of the box's central part or None without enough readings, the layers of the whole box).

    ``scale``: (depth width / image width, depth height / image height). A layer ``fills`` the box when it is
    in :data:`LAYER_MIN_COLUMNS` of its columns, its readings span :data:`LAYER_FILLS_EXTENT` of its area, it is
    no farther than ``fits_m`` (where the box still fits a person) and it is not the farthest of the box's layers
    (the background: the wall around a person, cut by an occluder and the image border, can fill the box while
    the person does not; furnished seed 22). A person's box is drawn around them, so the nearest layer that fills
    it is the box's person, and a layer behind them is ``behind_a_filler``: a hidden person seen in their gaps, or
    the background. An occluder in
    front of a person's lower body (full width, part of the height), a narrow pole down the middle or an occluder
    over the centre fills no box: the person behind stays a place. One over 80 % of the person's box does, and
    takes the person's place away (not seen, never someone else).
    """
    height, width = depth.shape[:2]
    sx, sy = scale
    if not np.all(np.isfinite(box[:4])):
        return None, []
    half = 0.5 * float(config.central_share)
    u, v = 0.5 * (box[0] + box[2]) * sx, 0.5 * (box[1] + box[3]) * sy
    hw, hh = half * (box[2] - box[0]) * sx, half * (box[3] - box[1]) * sy
    u0, u1 = int(np.clip(np.floor(u - hw), 0, width)), int(np.clip(np.ceil(u + hw), 0, width))
    v0, v1 = int(np.clip(np.floor(v - hh), 0, height)), int(np.clip(np.ceil(v + hh), 0, height))
    values = np.asarray(depth[v0:v1, u0:u1], dtype=np.float64).ravel()
    with np.errstate(invalid="ignore"):
        values = values[np.isfinite(values) & (values >= config.min_depth_m) & (values <= config.max_depth_m)]
    if values.size < max(1, int(config.min_depth_pixels)):
        return None, []
    # The layers come from the whole box (every other pixel): an occluder may cover all of its central part.
    b0, b1 = int(np.clip(np.floor(box[1] * sy), 0, height)), int(np.clip(np.ceil(box[3] * sy), 0, height))
    a0, a1 = int(np.clip(np.floor(box[0] * sx), 0, width)), int(np.clip(np.ceil(box[2] * sx), 0, width))
    grid = np.asarray(depth[b0:b1:2, a0:a1:2], dtype=np.float64)
    with np.errstate(invalid="ignore"):
        grid = np.where(np.isfinite(grid) & (grid >= config.min_depth_m) & (grid <= config.max_depth_m), grid, np.nan)
    ranges = depth_layer_ranges(grid[np.isfinite(grid)])
    stats = [(z, near, far, layer_column_share(grid, near, far), layer_extent_share(grid, near, far))
             for z, near, far in ranges]
    # The box's person: the nearest layer that fills it. The wall seen around a person can fill the box too: the
    # farthest of several layers is the background, never the person (and at its depth a tall box fits no person).
    farthest = max(z for z, _, _, _, _ in stats) if len(stats) > 1 else np.inf

    def fills(z: float, columns: float, extent: float) -> bool:
        return columns >= LAYER_MIN_COLUMNS and extent >= LAYER_FILLS_EXTENT and z <= fits_m and z < farthest

    person_far = min((far for z, near, far, columns, extent in stats if fills(z, columns, extent)), default=np.inf)
    layers = []
    for z, near, far, columns, extent in stats:
        with np.errstate(invalid="ignore"):
            inside = (grid >= near) & (grid <= far)
        rows, cols = np.flatnonzero(inside.any(axis=1)), np.flatnonzero(inside.any(axis=0))
        rect = ((a0 + 2 * cols[0]) / sx, (b0 + 2 * rows[0]) / sy, (a0 + 2 * cols[-1] + 2) / sx,
                (b0 + 2 * rows[-1] + 2) / sy)
        layers.append(DepthLayer(z, near, far, columns, extent, fills(z, columns, extent),
                                 near > person_far, (float(rect[0]), float(rect[1]), float(rect[2]),
                                                                  float(rect[3]))))
    return float(np.median(values)), layers


def _inside_share(rect: Tuple[float, float, float, float], box: FloatArray) -> float:
    """Share of ``rect``'s area inside ``box`` (both [x0, y0, x1, y1])."""
    width = max(0.0, min(rect[2], box[2]) - max(rect[0], box[0]))
    height = max(0.0, min(rect[3], box[3]) - max(rect[1], box[1]))
    area = max(rect[2] - rect[0], 1e-9) * max(rect[3] - rect[1], 1e-9)
    return float(width * height / area)


def _another_persons(layer: DepthLayer, j: int, boxes: FloatArray,
                     box_layers: List[Tuple[Optional[float], List[DepthLayer]]]) -> bool:
    """Whether box j's ``layer`` is another box's person.

    It is at the depth of a layer that fills another box, and its readings' rectangle lies inside that box (at
    least :data:`LAYER_IN_ANOTHER_BOX` of it). A layer that fills box j itself is another's only when box j is
    clearly the smaller box (:data:`SMALLER_BOX_SHARE` of the other's area: a hidden person's box inside the
    target's, which the target fills); of two boxes about as large, each keeps its person.
    """
    def area(box: FloatArray) -> float:
        return float(max(box[2] - box[0], 0.0) * max(box[3] - box[1], 0.0))

    return any(i != j and other.fills and other.overlaps_depth(layer)
               and _inside_share(layer.rect, boxes[i]) >= LAYER_IN_ANOTHER_BOX
               and (not layer.fills or area(boxes[j]) < SMALLER_BOX_SHARE * area(boxes[i]))
               for i, (_, others) in enumerate(box_layers) for other in others)


def box_places_camera(boxes: FloatArray, image_size: Tuple[int, int], depth: FloatingArray, k: FloatArray,
                      config: TrackerConfig) -> List[FloatArray]:
    """Each box's candidate places in the depth camera's optical frame (m): a (M, 3) array per box.

    Row 0 is the box's place (:func:`box_positions_camera`); the rest are the depth layers (:func:`depth_layers`)
    of the whole box (every other pixel) that differ from it by more than half a bin, back-projected through
    the box centre the same way: where an occluder covers the central part of a person's box, the person is
    one of the layers (the parts of them around the occluder), and so is the background. Two checks keep a
    hidden person's depth, seen through a nearer person's box, from being a place of that box (or its row 0):
    places at which the box would measure more than ``config.max_person_extent_m`` high or wide (size =
    pixels * depth / focal length) are left out, and so is every layer :func:`box_depth_layers` finds behind a
    nearer layer that fills the box (a narrow occluder in front of a person, or one over their lower body, fills
    no box and leaves the person's layer a place). Nor is a layer that does not fill the box but lies at the
    depth of a layer that fills another box, inside that box (:data:`LAYER_IN_ANOTHER_BOX`): a near person
    over most of the target's box, whose own box holds that part (three-people seed 74 measured the target's
    box at the passer-by over it and followed the passer-by). Row 0 is the nearest layer that fills the box when
    there is one (the box's person), the central median otherwise (the most populated place left when the
    median is in another box's person). (0, 3) for a box without enough valid readings, or none that fits.
    """
    boxes = np.asarray(boxes, dtype=np.float64)
    boxes = boxes.reshape(len(boxes), -1) if len(boxes) else np.zeros((0, 4))
    height, width = depth.shape[:2]
    sx, sy = width / float(image_size[0]), height / float(image_size[1])
    fits = [person_fit_depth(box, (sx, sy), k, config) if np.all(np.isfinite(box[:4])) else 0.0 for box in boxes]
    box_layers = [box_depth_layers(box, (sx, sy), depth, config, fit) for box, fit in zip(boxes, fits)]
    out: List[FloatArray] = []
    for j, (box, (median, layers)) in enumerate(zip(boxes, box_layers)):
        if median is None:
            out.append(np.zeros((0, 3)))
            continue
        others = [layer for layer in layers if _another_persons(layer, j, boxes, box_layers)]
        kept = [layer for layer in layers if not layer.behind_a_filler and layer not in others]
        front = min((layer for layer in layers if layer.fills), key=lambda layer: layer.z, default=None)
        if front is not None and front in others:  # the box's person is a larger box's: it shows nobody of its own
            out.append(np.zeros((0, 3)))
            continue
        # The layer that fills the box is its person: their place first, not the central median, which may be an
        # occluder over the person's middle or, behind them, a hidden person seen through a gap in their middle
        # (too small to be a layer of the whole box). Without one, a median in another box's person is no place.
        if front is not None:
            zs = [front.z]
        elif any(layer.near <= median <= layer.far for layer in others):
            zs = [layer.z for layer in kept[:1]]
        else:
            zs = [median]
        zs += [layer.z for layer in kept if all(abs(layer.z - z) > 0.5 * LAYER_BIN_M for z in zs)]
        u, v = 0.5 * (box[0] + box[2]) * sx, 0.5 * (box[1] + box[3]) * sy
        places = [((u - k[0, 2]) * z / k[0, 0], (v - k[1, 2]) * z / k[1, 1], z) for z in zs if z <= fits[j]]
        out.append(np.array(places, dtype=np.float64).reshape(-1, 3))
    return out


def box_positions_camera(boxes: FloatArray, image_size: Tuple[int, int], depth: FloatingArray, k: FloatArray,
                         config: TrackerConfig) -> FloatArray:
    """(N, 3) each box's position in the depth camera's optical frame (m); NaN rows for boxes without one.

    The median of the valid readings (finite, within [min_depth_m, max_depth_m]) in the central part of the
    box, back-projected through the box centre: X = (u - cx) z / fx, Y = (v - cy) z / fy. Boxes are in the
    pixels of an image of ``image_size``; the depth frame (aligned to it) may have another size: boxes are
    scaled to it.

    Args:
        boxes: (N, >=4) [x_min, y_min, x_max, y_max, ...].
        image_size: (width, height) of the image the boxes are in.
        depth: (H, W) metres, 0 for no reading.
        k: (3, 3) the depth camera's intrinsics.
        config: central_share, the valid depth range, min_depth_pixels.
    """
    places = box_places_camera(boxes, image_size, depth, k, config)
    out = np.full((len(places), 3), np.nan)
    for i, candidates in enumerate(places):
        if len(candidates):
            out[i] = candidates[0]
    return out


class _Filter:
    """A constant-velocity Kalman filter of a horizontal position: state [[x, y], [vx, vy]].

    One 2x2 covariance is shared by both axes (the same model and noise on each).
    """

    def __init__(self, stamp_ns: int, xy: FloatArray, z: float, config: TrackerConfig) -> None:
        self.stamp_ns = int(stamp_ns)  # of the last measurement (the state is the posterior there)
        self.state = np.array([[xy[0], xy[1]], [0.0, 0.0]])
        r = config.measurement_sigma_m ** 2
        self.covariance = np.diag([r, INITIAL_SPEED_SIGMA_M_S ** 2])
        self.z = float(z)

    def predicted(self, stamp_ns: int, config: TrackerConfig) -> Tuple[FloatArray, FloatArray]:
        """(state, covariance) predicted to stamp_ns (never back in time); the velocity carries for coast_s only."""
        dt = max(0.0, (int(stamp_ns) - self.stamp_ns) * 1e-9)
        coast = max(0.0, config.coast_s)
        if dt <= coast:
            return _constant_velocity(self.state, self.covariance, dt, config)
        state, covariance = _constant_velocity(self.state, self.covariance, coast, config)
        state = np.array([state[0], [0.0, 0.0]])
        covariance = np.diag([covariance[0, 0], INITIAL_SPEED_SIGMA_M_S ** 2])
        return _constant_velocity(state, covariance, dt - coast, config)

    def update(self, stamp_ns: int, xy: FloatArray, z: float, config: TrackerConfig) -> None:
        state, covariance = self.predicted(stamp_ns, config)
        innovation = np.asarray(xy, dtype=np.float64)[:2] - state[0]
        gain = covariance[:, 0] / (covariance[0, 0] + config.measurement_sigma_m ** 2)  # H = [1, 0]
        self.state = state + np.outer(gain, innovation)
        self.covariance = covariance - np.outer(gain, covariance[0, :])
        self.covariance = 0.5 * (self.covariance + self.covariance.T)
        self.stamp_ns = int(stamp_ns)
        self.z = float(z)

    def gate_m(self, stamp_ns: int, config: TrackerConfig) -> float:
        grown = config.gate_m + config.gate_growth_m_s * max(0.0, (int(stamp_ns) - self.stamp_ns) * 1e-9)
        # A person unseen for long is no looser than a lost one (the re-acquisition radius): a bystander who comes
        # into view 1.9 m from a target hidden for 2.6 s was taken for it (two-people seed 26).
        return float(min(grown, max(config.gate_m, config.reacquire_radius_m)))


def _constant_velocity(state: FloatArray, covariance: FloatArray, dt: float,
                       config: TrackerConfig) -> Tuple[FloatArray, FloatArray]:
    """The constant-velocity model's (state, covariance) dt seconds on (white-noise acceleration)."""
    f = np.array([[1.0, dt], [0.0, 1.0]])
    q = config.acceleration_sigma_m_s2 ** 2 * np.array([[dt ** 3 / 3.0, dt ** 2 / 2.0], [dt ** 2 / 2.0, dt]])
    return f @ state, f @ covariance @ f.T + q


@dataclass
class _Track:
    track_id: int
    last_seen_ns: int
    fixed_frame: str = ""
    filter: Optional[_Filter] = None
    last_box: Optional[FloatArray] = None
    # The last box as a rectangle in the fixed frame (4 corners at its place's depth) and that place's x, y: the
    # box expected in a later frame from another camera pose (:meth:`TargetTracker._expected_box`).
    box_corners: Optional[FloatArray] = None
    box_xy: Optional[FloatArray] = None
    seen_with_target: int = 0  # another person's: the track_id of the target last seen in the same frame


class TargetTracker:
    """The target's track across frames (see the module docstring). One per node; not thread-safe.

    Args:
        config: How it decides; ``config`` may be replaced between frames (live parameters).
    """

    def __init__(self, config: Optional[TrackerConfig] = None) -> None:
        self.config = config or TrackerConfig()
        self.next_id = 1  # track ids keep increasing across resets: an id names one person for a node's life
        self.reset()

    def reset(self) -> None:
        """Forget the target and the others (the stamps started over: a replay, a simulator reset)."""
        self.target: Optional[_Track] = None
        self.lost: Optional[TargetDecision] = None  # the decision that found the target lost, repeated until one
        self.others: List[_Track] = []
        self.last_stamp_ns: Optional[int] = None
        self._places: List[FloatArray] = []  # this frame's candidate places of each box, in the fixed frame
        # This frame's camera (rotation, position, intrinsics, depth px per image px) when it has positions.
        self._view: Optional[Tuple[FloatArray, FloatArray, FloatArray, float, float]] = None

    # ------------------------------------------------------------------ the frame

    def update(self, stamp_ns: int, boxes: FloatArray, image_size: Optional[Tuple[int, int]] = None,
               depth: Optional[FloatingArray] = None, k: Optional[FloatArray] = None,
               pose: Optional[CameraPoseLike] = None) -> TargetDecision:
        """Decide which of this frame's boxes is the target.

        Args:
            stamp_ns: The frame's stamp (a stamp before the last one decided resets the tracker).
            boxes: (N, 5) [x_min, y_min, x_max, y_max, score] in the image's pixels.
            image_size: (width, height) of that image (the acquisition rule's centre; the boxes' scale in depth).
            depth: (H, W) metres of the frame's depth (aligned to the image), 0 = no reading; None: none.
            k: (3, 3) the depth camera's intrinsics; None: none.
            pose: The frame's camera pose in the fixed frame; None: none.
        """
        stamp_ns = int(stamp_ns)
        if self.last_stamp_ns is not None and stamp_ns < self.last_stamp_ns:
            self.reset()
        self.last_stamp_ns = stamp_ns
        cfg = self.config
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 5)
        usable = usable_boxes(boxes)
        if not cfg.follow:
            self.target, self.others, self.lost = None, [], None
            return self._acquire(stamp_ns, boxes, usable, image_size, None, None, "track_previous_target is off")
        self._view = None
        why_image, positions = self._positions(boxes, usable, image_size, depth, k, pose)
        frame = "" if positions is None or pose is None else str(pose.frame_id)
        if positions is not None and self.others and self.others[0].fixed_frame != frame:
            self.others = []  # another fixed frame: their places mean nothing in it
        # People not seen for lost_after_s are forgotten before they can claim a detection (their gates have grown).
        self.others = [o for o in self.others if (stamp_ns - o.last_seen_ns) * 1e-9 <= cfg.lost_after_s]
        with_position = usable if positions is None else usable & np.all(np.isfinite(positions), axis=1)
        target = self.target
        if target is not None and (stamp_ns - target.last_seen_ns) * 1e-9 > cfg.lost_after_s:
            self._lose(stamp_ns, target)
            target = None
        if target is None:
            return self._acquire(stamp_ns, boxes, with_position, image_size, positions, frame or None, why_image)
        if positions is None:
            return self._image_frame(stamp_ns, boxes, usable, image_size, target, why_image)
        if target.filter is None or target.fixed_frame != frame:
            return self._start_filter(stamp_ns, boxes, with_position, image_size, positions, frame, target)
        return self._fixed_frame(stamp_ns, boxes, with_position, positions, frame, target)

    def _positions(self, boxes: FloatArray, usable: BoolArray, image_size: Optional[Tuple[int, int]],
                   depth: Optional[FloatingArray], k: Optional[FloatArray],
                   pose: Optional[CameraPoseLike]) -> Tuple[str, Optional[FloatArray]]:
        """(why the frame is decided in the image only, or ""; (N, 3) fixed-frame positions, NaN rows, or None)."""
        if not self.config.fixed_frame:
            return "track_in_fixed_frame is off", None
        if pose is None:
            return "no camera pose of this frame", None
        if depth is None or k is None or image_size is None:
            return "no depth frame of this frame", None
        places = [candidates if ok else np.zeros((0, 3)) for candidates, ok in
                  zip(box_places_camera(boxes, image_size, depth, k, self.config), usable)]
        if np.any(usable) and not any(len(candidates) for candidates in places):
            return "no valid depth in any box", None
        rotation = np.asarray(pose.rotation, dtype=np.float64).reshape(3, 3)
        position = np.asarray(pose.position, dtype=np.float64).reshape(3)
        self._places = [candidates @ rotation.T + position for candidates in places]
        self._view = (rotation, position, np.asarray(k, dtype=np.float64).reshape(3, 3),
                      depth.shape[1] / float(image_size[0]), depth.shape[0] / float(image_size[1]))
        primary = np.full((len(places), 3), np.nan)
        for i, candidates in enumerate(self._places):
            if len(candidates):
                primary[i] = candidates[0]
        return "", primary

    def _measured(self, j: int, xy: FloatArray) -> Tuple[float, FloatArray]:
        """(horizontal distance, point): the candidate place of box j nearest ``xy``.

        Distances within DISTANCE_TIE_M tie: the box's place first, then its most populated layer.
        """
        candidates = self._places[j]
        distances = np.hypot(candidates[:, 0] - xy[0], candidates[:, 1] - xy[1])
        best = int(np.flatnonzero(distances <= distances.min() + DISTANCE_TIE_M)[0])
        return float(distances[best]), candidates[best]

    def _remember_box(self, track: _Track, box: FloatArray, point: FloatArray) -> None:
        """The track's last box, and that box as a rectangle in the fixed frame at ``point``'s depth."""
        track.last_box = np.asarray(box[:4], dtype=np.float64).copy()
        track.box_corners, track.box_xy = None, None
        if self._view is None or not np.all(np.isfinite(point)):
            return
        rotation, position, k, sx, sy = self._view
        z = float((rotation.T @ (np.asarray(point, dtype=np.float64) - position))[2])
        if z <= 0.0:
            return
        corners = np.array([[u * sx, v * sy] for u in (box[0], box[2]) for v in (box[1], box[3])])
        camera = np.column_stack([(corners[:, 0] - k[0, 2]) * z / k[0, 0], (corners[:, 1] - k[1, 2]) * z / k[1, 1],
                                  np.full(4, z)])
        track.box_corners, track.box_xy = camera @ rotation.T + position, np.asarray(point[:2], dtype=np.float64)

    def _expected_box(self, track: _Track, stamp_ns: int) -> Optional[FloatArray]:
        """The track's last box as this frame's camera sees it at the predicted place (None: cannot say).

        The rectangle of :meth:`_remember_box`, moved by the prediction's displacement since, projected with this
        frame's pose and intrinsics: after the robot moved or turned, the image box the target should have.
        """
        if self._view is None or track.box_corners is None or track.box_xy is None or track.filter is None:
            return None
        rotation, position, k, sx, sy = self._view
        shift = np.append(track.filter.predicted(stamp_ns, self.config)[0][0] - track.box_xy, 0.0)
        camera = (track.box_corners + shift - position) @ rotation
        if np.any(camera[:, 2] <= 0.1):
            return None
        u = (k[0, 0] * camera[:, 0] / camera[:, 2] + k[0, 2]) / sx
        v = (k[1, 1] * camera[:, 1] / camera[:, 2] + k[1, 2]) / sy
        return np.array([u.min(), v.min(), u.max(), v.max()])

    # ------------------------------------------------------------------ outcomes

    def _lose(self, stamp_ns: int, target: _Track) -> None:
        unseen_s = (stamp_ns - target.last_seen_ns) * 1e-9
        position, velocity, sigma = self._estimate(target, stamp_ns)
        self.lost = TargetDecision(STATE_LOST, -1, target.track_id, target.fixed_frame if target.filter else "",
                                   position, velocity, sigma, target.last_seen_ns,
                                   f"lost: track {target.track_id} not seen for {unseen_s:.2f} s (limit "
                                   f"{self.config.lost_after_s:g} s)",
                                   MODE_FIXED_FRAME if target.filter is not None else MODE_IMAGE)
        self.target = None

    def _acquire(self, stamp_ns: int, boxes: FloatArray, candidates: BoolArray,
                 image_size: Optional[Tuple[int, int]], positions: Optional[FloatArray], frame: Optional[str],
                 why_image: str) -> TargetDecision:
        """A new target by the acquisition rule among the candidates; NONE (or LOST, repeated) without one.

        Within the re-acquisition window of a target lost with a fixed-frame place, only candidates measured
        within reacquire_radius_m of that place may be taken (:meth:`_near_lost_place`).
        """
        fixed = positions is not None and frame is not None
        assignment = self._assign(stamp_ns, positions, candidates, with_target=False) if fixed else {}
        candidates, window = self._near_lost_place(stamp_ns, candidates, positions, frame, assignment)
        index = acquisition_index(boxes, candidates, image_size)
        if index < 0:
            if fixed:
                self._apply_others(stamp_ns, positions, str(frame), assignment, set(), with_target=0)
            what = "no detections" if len(boxes) == 0 else ("no usable detection" if not np.any(
                usable_boxes(boxes)) else "no detection with depth")
            if window:
                what = window
            if self.lost is not None:
                return dataclasses.replace(self.lost, reason=f"{self.lost.reason}; {what}")
            zero = np.zeros(3)
            return TargetDecision(STATE_NONE, -1, 0, "", zero, zero.copy(), 0.0, 0, f"no target yet: {what}",
                                  MODE_FIXED_FRAME if fixed else MODE_IMAGE)
        previous = self.lost
        track = _Track(self.next_id, stamp_ns)
        self._remember_box(track, boxes[index], positions[index] if positions is not None else np.full(3, np.nan))
        self.next_id += 1
        if fixed:
            assert positions is not None and frame is not None
            claimed = next((key for key, j in assignment.items() if j == index), None)
            track.fixed_frame = str(frame)
            if claimed is None:
                track.filter = _Filter(stamp_ns, positions[index], positions[index, 2], self.config)
            else:  # a person already followed as another: their filter (their velocity) comes with them
                track.filter = self.others[claimed].filter
                assert track.filter is not None
                point = self._measured(index, track.filter.predicted(stamp_ns, self.config)[0][0])[1]
                track.filter.update(stamp_ns, point, point[2], self.config)
                del assignment[claimed]
                self._apply_others(stamp_ns, positions, str(frame), assignment, {index}, drop=claimed,
                                   with_target=track.track_id)
            if claimed is None:
                self._apply_others(stamp_ns, positions, str(frame), assignment, {index}, with_target=track.track_id)
        self.target, self.lost = track, None
        count = int(np.count_nonzero(candidates))
        reason = f"acquired track {track.track_id}: detection {index}, the highest score ({boxes[index, 4]:.3f})"
        if window:
            reason += f" of those {window}"
        if count > 1:
            reason += f" of {count} candidates (ties: nearest the image centre)"
        if previous is not None:
            reason += f"; {previous.reason}"
        if why_image:
            reason += f"; image only: {why_image}"
        return self._decision(track, stamp_ns, STATE_TRACKED, index, reason,
                              MODE_FIXED_FRAME if fixed else MODE_IMAGE, acquired=True)

    def _near_lost_place(self, stamp_ns: int, candidates: BoolArray, positions: Optional[FloatArray],
                         frame: Optional[str], assignment: Dict[int, int]) -> Tuple[BoolArray, str]:
        """(the candidates the acquisition may take, what limited them or ""): the re-acquisition window.

        For ``reacquire_window_s`` after the target was lost with a place in a fixed frame, a new target must
        stand within ``reacquire_radius_m`` of that place (horizontally, at the box's candidate place nearest
        it): the lost person coming back, not a bystander who happens to be in view. Nor may it be a detection
        that ``assignment`` gives to another person followed in a frame that also had the lost target: they
        were seen side by side, so that person is not the lost one. Frames without positions in that fixed
        frame take nobody in the window.
        """
        cfg, lost = self.config, self.lost
        if lost is None or not lost.fixed_frame or cfg.reacquire_window_s <= 0.0:
            return candidates, ""
        since_s = (stamp_ns - lost.last_seen_ns) * 1e-9 - cfg.lost_after_s  # time since it was found lost
        if since_s > cfg.reacquire_window_s:
            return candidates, ""
        left = f"{cfg.reacquire_window_s - since_s:.1f} s of the re-acquisition window left"
        if positions is None or frame != lost.fixed_frame:
            return np.zeros_like(candidates), f"no detection placed in {lost.fixed_frame!r} ({left})"
        near = np.zeros_like(candidates)
        for j in np.flatnonzero(candidates & np.all(np.isfinite(positions), axis=1)):
            near[j] = self._measured(int(j), lost.position[:2])[0] <= cfg.reacquire_radius_m
        beside = [j for key, j in assignment.items() if key >= 0 and near[j]
                  and self.others[key].seen_with_target == lost.track_id]
        near[beside] = False
        what = f", {len(beside)} of them seen beside it" if beside else ""
        return near, (f"within {cfg.reacquire_radius_m:g} m of where track {lost.track_id} was lost{what} "
                      f"({int(np.count_nonzero(near))} of {int(np.count_nonzero(candidates))} detections; {left})")

    def _image_frame(self, stamp_ns: int, boxes: FloatArray, usable: BoolArray,
                     image_size: Optional[Tuple[int, int]], target: _Track, why_image: str) -> TargetDecision:
        """An image-only frame of a live target: the box overlapping its last box."""
        index, iou = overlapping_index(boxes, target.last_box, self.config.min_track_iou, usable)
        if index >= 0:
            target.last_seen_ns = stamp_ns
            self._remember_box(target, boxes[index], np.full(3, np.nan))
            return self._decision(target, stamp_ns, STATE_TRACKED, index, f"image only ({why_image}): overlaps the"
                                  f" last target box, IoU {iou:.2f}", MODE_IMAGE)
        if target.filter is None and np.any(usable):  # a track that never had a position: the image-only rule
            self.target = None
            return self._acquire(stamp_ns, boxes, usable, image_size, None, None,
                                 f"{why_image}; no box overlaps the last target box (best IoU {iou:.2f})")
        what = "no detections" if len(boxes) == 0 else f"no box overlaps the last target box (best IoU {iou:.2f})"
        return self._decision(target, stamp_ns, STATE_NOT_SEEN, -1, f"not seen, image only ({why_image}): {what}",
                              MODE_IMAGE)

    def _start_filter(self, stamp_ns: int, boxes: FloatArray, with_position: BoolArray,
                      image_size: Optional[Tuple[int, int]], positions: FloatArray, frame: str,
                      target: _Track) -> TargetDecision:
        """A live target without a place in this fixed frame: continued by box overlap, which starts its filter."""
        index, iou = overlapping_index(boxes, target.last_box, self.config.min_track_iou, with_position)
        if index < 0 and target.filter is None:  # an image-only track: the image-only rule takes the best box
            self.target = None
            return self._acquire(stamp_ns, boxes, with_position, image_size, positions, frame, "")
        candidates = with_position.copy()
        if index >= 0:
            candidates[index] = False
        assignment = self._assign(stamp_ns, positions, candidates, with_target=False)
        self._apply_others(stamp_ns, positions, frame, assignment, set() if index < 0 else {index},
                           with_target=0 if index < 0 else target.track_id)
        if index < 0:  # the fixed frame changed: the old place means nothing in the new one
            target.filter = None
            return self._decision(target, stamp_ns, STATE_NOT_SEEN, -1, f"not seen: the fixed frame changed to "
                                  f"{frame!r} and no box overlaps the last target box", MODE_FIXED_FRAME)
        target.filter = _Filter(stamp_ns, positions[index], positions[index, 2], self.config)
        target.fixed_frame = frame
        target.last_seen_ns = stamp_ns
        self._remember_box(target, boxes[index], positions[index])
        return self._decision(target, stamp_ns, STATE_TRACKED, index, f"overlaps the last target box (IoU "
                              f"{iou:.2f}): its place in {frame!r} starts the track", MODE_FIXED_FRAME)

    def _fixed_frame(self, stamp_ns: int, boxes: FloatArray, with_position: BoolArray, positions: FloatArray,
                     frame: str, target: _Track) -> TargetDecision:
        """A frame with positions, of a target with a filter in this fixed frame: the gate decides."""
        cfg = self.config
        assert target.filter is not None
        predicted, _ = target.filter.predicted(stamp_ns, cfg)
        gate = target.filter.gate_m(stamp_ns, cfg)
        points = np.full_like(positions, np.nan)  # each box's candidate place nearest the prediction
        distances = np.full(len(positions), np.nan)
        for j in np.flatnonzero(with_position):
            distances[j], points[j] = self._measured(int(j), predicted[0])
        chosen, iou, group = self._disambiguated(stamp_ns, boxes, points, with_position, distances, gate, target)
        refused: AbstractSet[int] = frozenset()
        if chosen >= 0 and iou < cfg.min_track_iou:  # no box of the group is where the target's last box was
            chosen, refused = -1, group
        assignment = self._assign(stamp_ns, positions, with_position, with_target=True, target_detection=chosen,
                                  not_target=refused)
        index = assignment.pop(-1, -1)
        self._apply_others(stamp_ns, positions, frame, assignment, set() if index < 0 else {index}, unmeasured=group,
                           with_target=0 if index < 0 else target.track_id)
        if index >= 0:
            if chosen < 0:  # boxes measured at one place say where neither person is: the prediction stands
                target.filter.update(stamp_ns, points[index], points[index, 2], cfg)
            target.last_seen_ns = stamp_ns
            self._remember_box(target, boxes[index], points[index])
            how = (f"nearest detection to the predicted place, {distances[index]:.2f} m (gate {gate:.2f} m)"
                   if chosen < 0 else f"{len(group)} detections measured within {cfg.ambiguity_m:g} m of one place "
                   f"{distances[index]:.2f} m from the predicted one (gate {gate:.2f} m): the one overlapping the "
                   f"target's expected box most, IoU {iou:.2f} (the place is not a measurement: the prediction kept)")
            return self._decision(target, stamp_ns, STATE_TRACKED, index, how, MODE_FIXED_FRAME, gate_m=gate)
        if not np.any(with_position):
            what = "no detections" if len(boxes) == 0 else "no detection with depth"
        else:
            nearest = float(np.min(distances[with_position]))
            what = f"no detection within the gate {gate:.2f} m of the predicted place (nearest {nearest:.2f} m)"
            if nearest <= gate:
                what = f"the detections within the gate {gate:.2f} m are nearer other people followed"
            if refused:
                what = (f"{len(refused)} detections measured within {cfg.ambiguity_m:g} m of one place in the gate "
                        f"{gate:.2f} m, none overlapping the target's expected box by {cfg.min_track_iou:g} (best "
                        f"IoU {iou:.2f}): none of them is taken for the target")
        return self._decision(target, stamp_ns, STATE_NOT_SEEN, -1, f"not seen: {what}", MODE_FIXED_FRAME,
                              gate_m=gate)

    # ------------------------------------------------------------------ the assignment and the other people

    def _disambiguated(self, stamp_ns: int, boxes: FloatArray, points: FloatArray, with_position: BoolArray,
                       distances: FloatArray, gate: float, target: _Track) -> Tuple[int, float, Set[int]]:
        """(the target's detection among boxes measured at one place, its IoU with the expected box, them).

        The place is the nearest detection's in the gate; the boxes measured within ambiguity_m of it
        (horizontally) are the group, and the one overlapping the target's expected box most is the target
        (IoUs within 1e-6 tie: the nearest to the prediction, then the lowest index). The expected box is the
        last target box as this frame's camera sees it at the predicted place (:meth:`_expected_box`), the last
        box itself when that cannot be said. (-1, 0, {}) when the group has one box, or the target has no box.
        """
        inside = np.flatnonzero(with_position & (distances <= gate))
        if inside.size < 2 or target.last_box is None:
            return -1, 0.0, set()
        nearest = int(inside[np.argmin(distances[inside])])
        apart = np.hypot(points[inside, 0] - points[nearest, 0], points[inside, 1] - points[nearest, 1])
        group = inside[apart <= self.config.ambiguity_m]
        if group.size < 2:
            return -1, 0.0, set()
        expected = self._expected_box(target, stamp_ns)
        reference = target.last_box if expected is None else expected
        overlaps = box_iou(np.asarray(reference, dtype=np.float64), boxes[group])
        best = float(overlaps.max())
        tied = group[overlaps >= best - 1e-6]
        lowest = float(np.min(distances[tied]))
        chosen = int(min(j for j in tied if distances[j] <= lowest + DISTANCE_TIE_M))
        return chosen, best, {int(j) for j in group}

    def _assign(self, stamp_ns: int, positions: Optional[FloatArray], candidates: BoolArray,
                with_target: bool, target_detection: int = -1,
                not_target: AbstractSet[int] = frozenset()) -> Dict[int, int]:
        """Detections given to tracks nearest first, within each track's gate: {track key: detection index}.

        The target's key is -1, another person's its index in ``self.others``. Distances within DISTANCE_TIE_M
        of the nearest pair left tie: then the target first, then the others in the order they were first
        seen, then the lowest detection index. ``target_detection`` >= 0: the target's detection, decided
        before (:meth:`_disambiguated`); the others share the rest. ``not_target``: detections the target may
        not have (a group measured at one place, none of it overlapping the target's last box).
        """
        if positions is None:
            return {}
        cfg = self.config
        tracks: List[Tuple[int, _Filter]] = []
        if with_target and self.target is not None and self.target.filter is not None:
            tracks.append((-1, self.target.filter))
        tracks.extend((n, other.filter) for n, other in enumerate(self.others) if other.filter is not None)
        rows = np.flatnonzero(np.asarray(candidates, dtype=bool) & np.all(np.isfinite(positions), axis=1))
        pairs: List[Tuple[float, int, int, int]] = []
        for rank, (key, filt) in enumerate(tracks):
            predicted, _ = filt.predicted(stamp_ns, cfg)
            gate = filt.gate_m(stamp_ns, cfg)
            distances = [self._measured(int(j), predicted[0])[0] for j in rows]
            pairs.extend((float(d), rank, int(j), key) for d, j in zip(distances, rows) if d <= gate)
        assignment: Dict[int, int] = {}
        if target_detection >= 0 and with_target:
            assignment[-1] = int(target_detection)
            pairs = [p for p in pairs if p[3] != -1 and p[2] != target_detection]
        pairs = [p for p in pairs if not (p[3] == -1 and p[2] in not_target)]
        while pairs:
            nearest = min(p[0] for p in pairs)
            _, _, j, key = min((p for p in pairs if p[0] <= nearest + DISTANCE_TIE_M), key=lambda p: (p[1], p[2]))
            assignment[key] = j
            pairs = [p for p in pairs if p[3] != key and p[2] != j]
        return assignment

    def _apply_others(self, stamp_ns: int, positions: Optional[FloatArray], frame: str, assignment: Dict[int, int],
                      taken: Set[int], drop: Optional[int] = None, unmeasured: AbstractSet[int] = frozenset(),
                      with_target: int = 0) -> None:
        """The other people: update those given a detection, follow each detection nobody has as a new one.

        A detection in ``unmeasured`` (measured at another box's place) marks its track seen without moving
        it, and starts no new one. Forget those not seen for lost_after_s (and ``drop``, who became the target).
        ``with_target``: the track_id of the target seen in this frame (0: none), which every person seen in it
        was seen beside.
        """
        if positions is None:
            return
        cfg = self.config
        for key, j in assignment.items():
            if key >= 0:
                other = self.others[key]
                assert other.filter is not None
                if j not in unmeasured:
                    point = self._measured(j, other.filter.predicted(stamp_ns, cfg)[0][0])[1]
                    other.filter.update(stamp_ns, point, point[2], cfg)
                other.last_seen_ns = stamp_ns
                other.seen_with_target = with_target or other.seen_with_target
        used = set(taken) | set(assignment.values()) | set(unmeasured)
        self.others = [o for n, o in enumerate(self.others)
                       if n != drop and (stamp_ns - o.last_seen_ns) * 1e-9 <= cfg.lost_after_s]
        for j in np.flatnonzero(np.all(np.isfinite(positions), axis=1)):
            if int(j) not in used:
                self.others.append(_Track(0, stamp_ns, frame, _Filter(stamp_ns, positions[j], positions[j, 2], cfg),
                                          seen_with_target=with_target))

    # ------------------------------------------------------------------ the decision

    def _estimate(self, track: _Track, stamp_ns: int) -> Tuple[FloatArray, FloatArray, float]:
        if track.filter is None:
            return np.zeros(3), np.zeros(3), 0.0
        state, covariance = track.filter.predicted(stamp_ns, self.config)
        return (np.array([state[0, 0], state[0, 1], track.filter.z]), np.array([state[1, 0], state[1, 1], 0.0]),
                float(np.sqrt(max(covariance[0, 0], 0.0))))

    def _decision(self, track: _Track, stamp_ns: int, state: int, index: int, reason: str, mode: str,
                  acquired: bool = False, gate_m: float = 0.0) -> TargetDecision:
        position, velocity, sigma = self._estimate(track, stamp_ns)
        return TargetDecision(state, int(index), track.track_id, track.fixed_frame if track.filter else "",
                              position, velocity, sigma, track.last_seen_ns, reason, mode, acquired, gate_m)
