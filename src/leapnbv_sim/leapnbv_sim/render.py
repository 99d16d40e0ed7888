"""Rendering a scene: flat-shaded RGB, depth (noisy like the sensor, and noise-free), object ids, ground truth.

The mesh is rasterized by :func:`leapnbv_geometry.raster.rasterize_mesh` (z-buffer, pixel centres
at integer coordinates). Faces are flat shaded once, when the scene is assembled
(:func:`shade_faces`: Lambert with both sides lit, plus ambient).

Object ids, in a scene's faces and in ``RenderedFrame.object_id``: -1 background (frames only),
:data:`FLOOR_ID` 0, :data:`PERSON_ID` 1 (the target), occluders from :data:`FIRST_OCCLUDER_ID` 2 on,
then walls, then clutter, then the other people (see ``Scene.object_names``). The ground truth
describes the target and, in ``FrameGroundTruth.others``, every other person of the scene.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, List, Optional, Tuple

import numpy as np

from leapnbv_common.array_types import (
    BoolArray,
    Float32Array,
    FloatArray,
    FloatingArray,
    Int16Array,
    Int32Array,
    IntArray,
    UInt8Array,
    UInt16Array,
)
from leapnbv_geometry.raster import rasterize_mesh
from leapnbv_sim.body import BodyParams, body_params_in_camera
from leapnbv_sim.depth_noise import apply_depth_noise, depth_m_to_mm
from leapnbv_sim.poses import CameraPose
from leapnbv_sim.visibility import visible_vertex_mask

if TYPE_CHECKING:  # annotations only: the Scene's methods render through this module
    from leapnbv_sim.scene import Scene

FLOOR_ID = 0
PERSON_ID = 1
FIRST_OCCLUDER_ID = 2
BACKGROUND_RGB = np.array([40, 40, 48], dtype=np.uint8)
# Light travelling down and slightly sideways (world frame), plus ambient.
_LIGHT_DIRECTION = np.array([0.3, 0.5, -1.0]) / np.linalg.norm([0.3, 0.5, -1.0])
_AMBIENT = 0.35


@dataclass
class PersonGroundTruth:
    """What the simulator knows about a person other than the target in one view (camera optical frame).

    Attributes:
        object_id: The person's object id (``Scene.object_names``).
        role: "bystander" or "passer_by" (:mod:`leapnbv_sim.people`).
        box_xyxy: (x_min, y_min, x_max, y_max) of its visible pixels, max edges exclusive; None when
            none is visible.
        body_params_camera: Its body parameters; root_pose is the orientation in the camera frame
            (hands, jaw and expression neutral).
        translation_camera: (3,) added to ``model.forward(params).vertices`` to place them in the camera frame.
        occlusion_share: Share of its body vertices hidden from this view (by anything, itself included,
            or outside the image).
        pixel_count: Its visible pixels.
    """

    object_id: int
    role: str
    box_xyxy: Optional[Tuple[int, int, int, int]]
    body_params_camera: BodyParams
    translation_camera: FloatArray
    occlusion_share: float
    pixel_count: int


@dataclass
class FrameGroundTruth:
    """What the simulator knows about one rendered view (camera optical frame, metres).

    Attributes:
        person_box_xyxy: (x_min, y_min, x_max, y_max) of the visible person pixels, max edges
            exclusive; None when no person pixel is visible.
        body_params_camera: Body parameters; root_pose is the orientation in the camera frame.
        translation_camera: (3,) added to ``model.forward(params).vertices`` to get
            ``vertices_camera``.
        vertices_camera: (V,3) body vertices in the camera frame.
        visible_vertices: (V,) bool, the vertices this view sees (see visibility.visible_vertex_mask).
        occlusion_share: Share of body vertices hidden from this view (by occluders, by the
            body itself, or outside the image) = 1 - body coverage.
        occluder_share: Share of the body's self-visible in-image vertices that other objects
            hide (0 without occluders in the line of sight).
        person_pixel_count: Visible person pixels.
        others: The other people of the scene, in id order (empty in a one-person scene).
    """

    person_box_xyxy: Optional[Tuple[int, int, int, int]]
    body_params_camera: BodyParams
    translation_camera: FloatArray
    vertices_camera: FloatArray
    visible_vertices: BoolArray
    occlusion_share: float
    occluder_share: float
    person_pixel_count: int
    others: List[PersonGroundTruth] = field(default_factory=list)


@dataclass
class RenderedFrame:
    """One rendered RGB-D view with its ground truth.

    Attributes:
        rgb: (H,W,3) uint8.
        depth_mm: (H,W) uint16 millimetres, 0 = no return (noisy when the scene's noise is on).
        depth_m: (H,W) float32 metres, the same data as depth_mm (noisy when noise is on).
        depth_clean_m: (H,W) float32 metres, noise-free render (for metrics).
        object_id: (H,W) int16, -1 background (ids: see Scene.object_names).
        K: (3,3) intrinsics.
        camera_pose: The T_world_camera it was rendered from.
        ground_truth: FrameGroundTruth.
        scene_time_s: The scene time it shows (``Scene.elapsed_s``: where its moving people were).
    """

    rgb: UInt8Array
    depth_mm: UInt16Array
    depth_m: Float32Array
    depth_clean_m: Float32Array
    object_id: Int16Array
    K: FloatArray
    camera_pose: CameraPose
    ground_truth: FrameGroundTruth
    scene_time_s: float = 0.0


def shade_faces(vertices: FloatArray, faces: IntArray, base_rgb: FloatArray) -> UInt8Array:
    """Lambert flat shading per face (both sides lit: |n . l|), (M,3) uint8."""
    a = vertices[faces[:, 0]]
    normals = np.cross(vertices[faces[:, 1]] - a, vertices[faces[:, 2]] - a)
    lengths = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = normals / np.maximum(lengths, 1e-12)
    lambert = np.abs(normals @ _LIGHT_DIRECTION)
    shade = _AMBIENT + (1.0 - _AMBIENT) * lambert
    colour = base_rgb[None, :] * shade[:, None] if base_rgb.ndim == 1 else base_rgb * shade[:, None]
    rgb: UInt8Array = np.clip(np.rint(colour * 255.0), 0, 255).astype(np.uint8)
    return rgb


def render_depth(
    scene: Scene, camera: CameraPose, include: Optional[IntArray] = None
) -> Tuple[Float32Array, Int32Array]:
    """Noise-free depth and object id of the scene (or of a subset of its objects).

    Args:
        scene: The scene.
        camera: T_world_camera.
        include: Object ids to draw; all if None.

    Returns:
        depth (H,W) float32 metres (0 = nothing), object_id (H,W) int32 (-1 = nothing).
    """
    faces = scene.faces
    face_ids = scene.face_object_id
    if include is not None:
        keep = np.isin(face_ids, include)
        faces = faces[keep]
        face_ids = face_ids[keep]
    result = rasterize_mesh(
        camera.world_to_camera(scene.vertices_world),
        faces,
        scene.K,
        scene.config.width,
        scene.config.height,
        face_object_id=face_ids,
    )
    assert result.object_id is not None  # face_object_id was given
    return result.depth, result.object_id


def occluder_share(
    scene: Scene, camera: CameraPose, scene_depth_m: Optional[FloatingArray] = None
) -> Tuple[float, BoolArray]:
    """Share of the body's self-visible in-image vertices hidden by other objects.

    Args:
        scene: The scene.
        camera: T_world_camera.
        scene_depth_m: Noise-free depth of the whole scene from this camera, if at hand.

    Returns:
        (share, visible (V,) bool in the full scene).
    """
    vertices_camera = camera.world_to_camera(scene.body_vertices_world)
    body_depth, _ = render_depth(scene, camera, include=np.array([PERSON_ID]))
    if scene_depth_m is None:
        scene_depth_m, _ = render_depth(scene, camera)
    self_visible = visible_vertex_mask(vertices_camera, body_depth, scene.K)
    visible = visible_vertex_mask(vertices_camera, scene_depth_m, scene.K) & self_visible
    count = int(np.count_nonzero(self_visible))
    share = 1.0 - float(np.count_nonzero(visible)) / count if count else 1.0
    return share, visible


def render_frame(scene: Scene, camera: CameraPose, frame_index: int = 0) -> RenderedFrame:
    """Render RGB, depth and object ids from a camera, with ground truth.

    Args:
        scene: The scene.
        camera: T_world_camera.
        frame_index: Selects the depth-noise draw (seeded by (config.seed, frame_index)).

    Returns:
        The rendered frame.
    """
    result = rasterize_mesh(
        camera.world_to_camera(scene.vertices_world),
        scene.faces,
        scene.K,
        scene.config.width,
        scene.config.height,
        face_object_id=scene.face_object_id,
    )
    depth_clean = result.depth
    # One gather: index -1 (no hit) picks the background colour appended as the last row.
    rgb = np.take(scene.colour_table, result.face_index, axis=0)
    assert result.object_id is not None  # face_object_id was given
    object_id = result.object_id.astype(np.int16)

    if scene.config.depth_noise:
        seed = int(np.random.SeedSequence([int(scene.config.seed) & 0xFFFFFFFF, int(frame_index)]).generate_state(1)[0])
        depth_noisy = apply_depth_noise(depth_clean, seed, scene.config.noise)
    else:
        depth_noisy = depth_clean
    depth_mm = depth_m_to_mm(depth_noisy)
    depth_m = depth_mm.astype(np.float32) / 1000.0

    params, translation = scene.body_params_in_camera(camera)
    vertices_camera = camera.world_to_camera(scene.body_vertices_world)
    share, _ = occluder_share(scene, camera, depth_clean)
    visible = visible_vertex_mask(vertices_camera, depth_clean, scene.K)
    box, person_pixels = _pixel_box(object_id == PERSON_ID)
    others = []
    for other in scene.others:
        other_box, other_pixels = _pixel_box(object_id == other.object_id)
        other_params, other_translation = body_params_in_camera(
            other.body.params_world, other.body.root_joint, other.body.translation_world, camera)
        other_visible = visible_vertex_mask(camera.world_to_camera(other.body.vertices_world), depth_clean, scene.K)
        others.append(PersonGroundTruth(
            object_id=other.object_id, role=other.role, box_xyxy=other_box, body_params_camera=other_params,
            translation_camera=other_translation,
            occlusion_share=1.0 - float(np.count_nonzero(other_visible)) / max(1, other_visible.size),
            pixel_count=other_pixels))
    truth = FrameGroundTruth(
        person_box_xyxy=box,
        body_params_camera=params,
        translation_camera=translation,
        vertices_camera=vertices_camera,
        visible_vertices=visible,
        occlusion_share=1.0 - float(np.count_nonzero(visible)) / max(1, visible.size),
        occluder_share=share,
        person_pixel_count=person_pixels,
        others=others,
    )
    return RenderedFrame(
        rgb=rgb,
        depth_mm=depth_mm,
        depth_m=depth_m,
        depth_clean_m=depth_clean,
        object_id=object_id,
        K=scene.K.copy(),
        camera_pose=camera,
        ground_truth=truth,
        scene_time_s=float(scene.elapsed_s),
    )


def _pixel_box(pixels: BoolArray) -> Tuple[Optional[Tuple[int, int, int, int]], int]:
    """(x_min, y_min, x_max, y_max) of the set pixels, max edges exclusive (None: none), and their count."""
    count = int(np.count_nonzero(pixels))
    if not count:
        return None, 0
    rows = np.nonzero(pixels.any(axis=1))[0]
    columns = np.nonzero(pixels.any(axis=0))[0]
    return (int(columns[0]), int(rows[0]), int(columns[-1]) + 1, int(rows[-1]) + 1), count
