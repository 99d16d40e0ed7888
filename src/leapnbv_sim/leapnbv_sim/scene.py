"""Synthetic RGB-D scenes: a stand-in body, box occluders, floor and walls, rendered with ground truth.

World frame of the simulator: metres, z up, the floor is the plane z = 0, the person stands
at the origin (pelvis above (0, 0)). The start camera sits on the -x side of the person at
``person_distance`` metres and ``camera_height`` metres above the floor, looking along +x at
the centre of the body's bounding box (so its optical axis is pitched down by a few degrees;
its x axis stays parallel to the floor: no roll). Camera poses are ``T_world_camera``: the
rotation's columns are the optical axes (x right, y down, z forward) in world coordinates and
the position is the optical centre in the world.

Object ids in ``RenderedFrame.object_id``: -1 background, 0 floor, 1 person, 2.. occluders,
then walls, then clutter (furniture around the person, when the config asks for it; see
``Scene.object_names``). The static obstacles (occluders, walls, clutter: everything but the
floor and the person) are also available as a voxel map, :meth:`Scene.obstacle_voxel_centres`,
the ground truth of what a robot's mapping stack (e.g. OctoMap's occupied voxel centres) holds.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from leapnbv_geometry.raster import rasterize_mesh
from leapnbv_perception.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from leapnbv_sim.depth_noise import DepthNoiseConfig, apply_depth_noise, depth_m_to_mm
from leapnbv_sim.visibility import visible_vertex_mask

FLOOR_ID = 0
PERSON_ID = 1
FIRST_OCCLUDER_ID = 2

# Base colours (RGB 0..1) per kind of object; the person's is a skin/clothes mid tone that
# stands out from the grey floor and the blue-ish boxes.
_FLOOR_COLOUR = np.array([0.55, 0.55, 0.52])
_WALL_COLOUR = np.array([0.80, 0.78, 0.70])
_OCCLUDER_COLOURS = np.array([[0.25, 0.45, 0.75], [0.70, 0.45, 0.20], [0.35, 0.60, 0.35]])
# Furniture: light wood, white laminate, dark grey metal, grey-green fabric (screens).
_CLUTTER_COLOURS = np.array([[0.62, 0.47, 0.30], [0.86, 0.86, 0.83], [0.30, 0.31, 0.34], [0.45, 0.52, 0.47]])
# Mixed with the seed into the clutter's own random stream.
_CLUTTER_STREAM = 7
_PERSON_COLOUR = np.array([0.85, 0.35, 0.30])
_BACKGROUND_RGB = np.array([40, 40, 48], dtype=np.uint8)
# Light travelling down and slightly sideways (world frame), plus ambient.
_LIGHT_DIRECTION = np.array([0.3, 0.5, -1.0]) / np.linalg.norm([0.3, 0.5, -1.0])
_AMBIENT = 0.35

# SMPL-X joint indices (body_pose holds joints 1..21, three values each).
_LEFT_HIP, _RIGHT_HIP, _SPINE1, _LEFT_KNEE, _RIGHT_KNEE = 1, 2, 3, 4, 5
_SPINE2, _SPINE3, _NECK, _HEAD = 6, 9, 12, 15
_LEFT_SHOULDER, _RIGHT_SHOULDER, _LEFT_ELBOW, _RIGHT_ELBOW = 16, 17, 18, 19


class SceneError(RuntimeError):
    """A scene could not be generated or rendered (names the seed or field at fault)."""


@dataclass
class SceneConfig:
    """Parameters of :func:`generate_scene`; the same config (seed included) gives the same scene.

    Attributes:
        seed: Seed of every random choice of the scene.
        width: Image width in pixels.
        height: Image height in pixels.
        fx: Focal length in x, pixels (RealSense D435 colour at 640x480: ~615).
        fy: Focal length in y, pixels.
        cx: Principal point x, pixels (pixel centres at integer coordinates).
        cy: Principal point y, pixels.
        camera_height_range: Start camera height above the floor (m), uniform.
        person_distance_range: Horizontal camera-to-person distance (m), uniform.
        occluder_count_range: Inclusive range of the number of box occluders.
        occluder_share_range: Accepted share of the body's self-visible vertices that the
            occluders hide in the start view (see ``Scene.start_occluder_share``).
        heading_range_deg: Person heading relative to facing the camera (deg), uniform.
        walls: Add a wall behind the person and, with probability 1/2, one beside.
        body_resolution: Stand-in body resolution the scene is meant for ("small"/"full");
            informative (the body model passed in decides), recorded as ``body_model_id``.
        depth_noise: Corrupt rendered depth with :mod:`leapnbv_sim.depth_noise`.
        noise: Noise parameters.
        max_attempts: Occluder layouts tried before giving up.
        clutter_count_range: Inclusive range of the number of furniture boxes (shelves,
            cabinets, standing screens) around the person; (0, 0) = none, and then the scene is
            exactly the one generated without clutter support (clutter has its own random stream).
        clutter_distance_range: Horizontal distance from the person (pelvis, the world origin) to
            a clutter box's centre (m), uniform.
        clutter_width_range: Clutter box width (m, the side facing the person), uniform.
        clutter_height_range: Clutter box height (m), uniform.
        clutter_depth_range: Clutter box depth (m, along the line to the person), uniform.
        clutter_clearance: Smallest horizontal gap (m) between a clutter box and the start view's
            line of sight to the body (so the box cannot hide the body from the start camera,
            nor touch the body or the camera), the occluders, the walls and the other clutter.
        clutter_max_tries: Placements drawn per clutter box; a box that finds no free spot in as
            many draws is left out (so a scene may hold fewer boxes than drawn).
    """

    seed: int = 0
    width: int = 640
    height: int = 480
    fx: float = 615.0
    fy: float = 615.0
    cx: float = 320.0
    cy: float = 240.0
    camera_height_range: Tuple[float, float] = (1.0, 1.4)
    person_distance_range: Tuple[float, float] = (2.0, 3.5)
    occluder_count_range: Tuple[int, int] = (1, 2)
    occluder_share_range: Tuple[float, float] = (0.20, 0.60)
    heading_range_deg: Tuple[float, float] = (-75.0, 75.0)
    walls: bool = True
    body_resolution: str = "small"
    depth_noise: bool = True
    noise: DepthNoiseConfig = field(default_factory=DepthNoiseConfig)
    max_attempts: int = 40
    clutter_count_range: Tuple[int, int] = (0, 0)
    clutter_distance_range: Tuple[float, float] = (0.6, 2.0)
    clutter_width_range: Tuple[float, float] = (0.4, 1.2)
    clutter_height_range: Tuple[float, float] = (0.8, 2.0)
    clutter_depth_range: Tuple[float, float] = (0.3, 0.6)
    clutter_clearance: float = 0.15
    clutter_max_tries: int = 100

    @property
    def K(self) -> np.ndarray:
        """(3,3) intrinsics."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass
class CameraPose:
    """T_world_camera: rotation (3,3) whose columns are the optical axes in the world, position (3,)."""

    rotation: np.ndarray
    position: np.ndarray

    def as_matrix(self) -> np.ndarray:
        """(4,4) homogeneous T_world_camera."""
        matrix = np.eye(4)
        matrix[:3, :3] = self.rotation
        matrix[:3, 3] = self.position
        return matrix

    @classmethod
    def from_matrix(cls, matrix: np.ndarray) -> CameraPose:
        """Build from a (4,4) homogeneous T_world_camera."""
        matrix = np.asarray(matrix, dtype=np.float64)
        if matrix.shape != (4, 4):
            raise ValueError(f"T_world_camera must be (4,4), got {matrix.shape}")
        return cls(matrix[:3, :3].copy(), matrix[:3, 3].copy())

    def world_to_camera(self, points_world: np.ndarray) -> np.ndarray:
        """(N,3) world points -> (N,3) camera optical frame: R^T (p - position)."""
        return (np.asarray(points_world, dtype=np.float64) - self.position) @ self.rotation


@dataclass
class BodyParams:
    """SMPL-X parameters, axis-angle (radians) per joint; shapes as in SceneGroundTruth.msg."""

    root_pose: np.ndarray  # (3,)
    body_pose: np.ndarray  # (63,)
    left_hand_pose: np.ndarray  # (45,)
    right_hand_pose: np.ndarray  # (45,)
    jaw_pose: np.ndarray  # (3,)
    betas: np.ndarray  # (10,)
    expression: np.ndarray  # (10,)

    def to_smplx_params(self) -> Any:
        """The same parameters as ``leapnbv_perception.smplx_layer.SMPLXParams``."""
        from leapnbv_perception.smplx_layer import SMPLXParams

        return SMPLXParams.from_axis_angle(
            self.root_pose,
            self.body_pose,
            self.left_hand_pose,
            self.right_hand_pose,
            self.jaw_pose,
            self.betas,
            self.expression,
        )

    def with_root(self, root_pose: np.ndarray) -> BodyParams:
        """A copy with another root orientation."""
        return BodyParams(
            np.asarray(root_pose, dtype=np.float64).reshape(3),
            self.body_pose.copy(),
            self.left_hand_pose.copy(),
            self.right_hand_pose.copy(),
            self.jaw_pose.copy(),
            self.betas.copy(),
            self.expression.copy(),
        )


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
        visible_vertices: (V,) bool, the vertices this view sees (see metrics.visible_vertex_mask).
        occlusion_share: Share of body vertices hidden from this view (by occluders, by the
            body itself, or outside the image) = 1 - body coverage.
        occluder_share: Share of the body's self-visible in-image vertices that other objects
            hide (0 without occluders in the line of sight).
        person_pixel_count: Visible person pixels.
    """

    person_box_xyxy: Optional[Tuple[int, int, int, int]]
    body_params_camera: BodyParams
    translation_camera: np.ndarray
    vertices_camera: np.ndarray
    visible_vertices: np.ndarray
    occlusion_share: float
    occluder_share: float
    person_pixel_count: int


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
    """

    rgb: np.ndarray
    depth_mm: np.ndarray
    depth_m: np.ndarray
    depth_clean_m: np.ndarray
    object_id: np.ndarray
    K: np.ndarray
    camera_pose: CameraPose
    ground_truth: FrameGroundTruth


@dataclass
class Scene:
    """A generated scene in the world frame (z up, floor z = 0).

    Attributes:
        config: The config it was generated from.
        vertices_world: (N,3) all scene vertices (floor, person, occluders, walls).
        faces: (M,3) int32 triangles into vertices_world.
        face_object_id: (M,) int32 object id per face.
        face_rgb: (M,3) uint8 flat-shaded colour per face.
        object_names: id -> name ("floor", "person", "occluder_0", "wall_back", ...).
        body_vertex_slice: Where the body's vertices sit in vertices_world.
        body_faces: (F,3) the body model's faces (indices into the body's own vertices).
        body_params_world: Parameters posed in the world: root_pose is the world orientation.
        body_forward_vertices: (V,3) ``model.forward(body_params_world).vertices``.
        body_root_joint: (3,) root joint of that forward pass (fixed under root rotation).
        body_translation_world: (3,) with vertices_world[body] = forward + this.
        start_camera: The robot's start camera pose.
        start_occluder_share: occluder_share of the start view (within the config's range).
        body_model_id: e.g. "stand_in_small".
    """

    config: SceneConfig
    vertices_world: np.ndarray
    faces: np.ndarray
    face_object_id: np.ndarray
    face_rgb: np.ndarray
    object_names: Dict[int, str]
    body_vertex_slice: slice
    body_faces: np.ndarray
    body_params_world: BodyParams
    body_forward_vertices: np.ndarray
    body_root_joint: np.ndarray
    body_translation_world: np.ndarray
    start_camera: CameraPose
    start_occluder_share: float
    body_model_id: str
    # obstacle_voxel_centres per resolution, computed on first use.
    _obstacle_voxels: Dict[float, np.ndarray] = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def K(self) -> np.ndarray:
        """(3,3) intrinsics."""
        return self.config.K

    @property
    def _colour_table(self) -> np.ndarray:
        """(M+1,3) uint8 face colours with the background colour as the last row."""
        table = getattr(self, "_colour_table_cache", None)
        if table is None or len(table) != len(self.face_rgb) + 1:
            table = np.concatenate([self.face_rgb, _BACKGROUND_RGB[None, :]], axis=0)
            self._colour_table_cache = table
        return table

    @property
    def body_vertices_world(self) -> np.ndarray:
        """(V,3) body vertices in the world."""
        return self.vertices_world[self.body_vertex_slice]

    @property
    def body_centre_world(self) -> np.ndarray:
        """(3,) centre of the body's axis-aligned bounding box in the world."""
        body = self.body_vertices_world
        return 0.5 * (body.min(axis=0) + body.max(axis=0))

    def body_params_in_camera(self, camera: CameraPose) -> Tuple[BodyParams, np.ndarray]:
        """Body parameters and translation in a camera's optical frame.

        With R_cw = R^T and J the root joint, the forward pass with root orientation
        R_cw R_root gives R_cw (v_f - J) + J, and the camera-frame vertices are
        R_cw (v_f + t_w - p). Their difference is the translation R_cw (t_w + J - p) - J.

        Args:
            camera: T_world_camera.

        Returns:
            (params, translation (3,)) with forward(params).vertices + translation equal to the
            body vertices in the camera frame.
        """
        R_cw = camera.rotation.T
        R_root_world = axis_angle_to_matrix(self.body_params_world.root_pose)
        root_camera = matrix_to_axis_angle(R_cw @ R_root_world)
        joint = self.body_root_joint
        translation = R_cw @ (self.body_translation_world + joint - camera.position) - joint
        return self.body_params_world.with_root(root_camera), translation

    def render_depth(self, camera: CameraPose, include: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray]:
        """Noise-free depth and object id of the scene (or of a subset of its objects).

        Args:
            camera: T_world_camera.
            include: Object ids to draw; all if None.

        Returns:
            depth (H,W) float32 metres (0 = nothing), object_id (H,W) int32 (-1 = nothing).
        """
        faces = self.faces
        face_ids = self.face_object_id
        if include is not None:
            keep = np.isin(face_ids, include)
            faces = faces[keep]
            face_ids = face_ids[keep]
        result = rasterize_mesh(
            camera.world_to_camera(self.vertices_world),
            faces,
            self.K,
            self.config.width,
            self.config.height,
            face_object_id=face_ids,
        )
        return result.depth, result.object_id

    def occluder_share(
        self, camera: CameraPose, scene_depth_m: Optional[np.ndarray] = None
    ) -> Tuple[float, np.ndarray]:
        """Share of the body's self-visible in-image vertices hidden by other objects.

        Args:
            camera: T_world_camera.
            scene_depth_m: Noise-free depth of the whole scene from this camera, if at hand.

        Returns:
            (share, visible (V,) bool in the full scene).
        """
        vertices_camera = camera.world_to_camera(self.body_vertices_world)
        body_depth, _ = self.render_depth(camera, include=np.array([PERSON_ID]))
        if scene_depth_m is None:
            scene_depth_m, _ = self.render_depth(camera)
        self_visible = visible_vertex_mask(vertices_camera, body_depth, self.K)
        visible = visible_vertex_mask(vertices_camera, scene_depth_m, self.K) & self_visible
        count = int(np.count_nonzero(self_visible))
        share = 1.0 - float(np.count_nonzero(visible)) / count if count else 1.0
        return share, visible

    def render(self, camera: Optional[CameraPose] = None, frame_index: int = 0) -> RenderedFrame:
        """Render RGB, depth and object ids from a camera, with ground truth.

        Args:
            camera: T_world_camera; the start camera if None.
            frame_index: Selects the depth-noise draw (seeded by (config.seed, frame_index)).

        Returns:
            The rendered frame.
        """
        if camera is None:
            camera = self.start_camera
        result = rasterize_mesh(
            camera.world_to_camera(self.vertices_world),
            self.faces,
            self.K,
            self.config.width,
            self.config.height,
            face_object_id=self.face_object_id,
        )
        depth_clean = result.depth
        # One gather: index -1 (no hit) picks the background colour appended as the last row.
        rgb = np.take(self._colour_table, result.face_index, axis=0)
        object_id = result.object_id.astype(np.int16)

        if self.config.depth_noise:
            seed = int(
                np.random.SeedSequence([int(self.config.seed) & 0xFFFFFFFF, int(frame_index)]).generate_state(1)[0]
            )
            depth_noisy = apply_depth_noise(depth_clean, seed, self.config.noise)
        else:
            depth_noisy = depth_clean
        depth_mm = depth_m_to_mm(depth_noisy)
        depth_m = depth_mm.astype(np.float32) / 1000.0

        params, translation = self.body_params_in_camera(camera)
        vertices_camera = camera.world_to_camera(self.body_vertices_world)
        share, visible_occluders = self.occluder_share(camera, depth_clean)
        visible = visible_vertex_mask(vertices_camera, depth_clean, self.K)
        person = object_id == PERSON_ID
        person_pixels = int(np.count_nonzero(person))
        box: Optional[Tuple[int, int, int, int]] = None
        if person_pixels:
            rows = np.nonzero(person.any(axis=1))[0]
            columns = np.nonzero(person.any(axis=0))[0]
            box = (int(columns[0]), int(rows[0]), int(columns[-1]) + 1, int(rows[-1]) + 1)
        truth = FrameGroundTruth(
            person_box_xyxy=box,
            body_params_camera=params,
            translation_camera=translation,
            vertices_camera=vertices_camera,
            visible_vertices=visible,
            occlusion_share=1.0 - float(np.count_nonzero(visible)) / max(1, visible.size),
            occluder_share=share,
            person_pixel_count=person_pixels,
        )
        return RenderedFrame(
            rgb=rgb,
            depth_mm=depth_mm,
            depth_m=depth_m,
            depth_clean_m=depth_clean,
            object_id=object_id,
            K=self.K.copy(),
            camera_pose=camera,
            ground_truth=truth,
        )

    def obstacle_voxel_centres(self, resolution: float = 0.1) -> np.ndarray:
        """World-frame centres of the voxels that the scene's static obstacles occupy.

        The obstacles are every object but the floor and the person: the occluder boxes, the
        walls and the clutter (furniture) boxes. Voxels follow OctoMap's convention: voxel
        (i, j, k) spans [i r, (i+1) r) on each axis (r = ``resolution``) and its centre is
        ((i, j, k) + 0.5) r. A voxel is occupied when an obstacle's solid reaches into it; a
        box that only touches a voxel's face does not occupy it. A wall (a rectangle of zero
        thickness) occupies every voxel it passes through, so it is one voxel thick unless its
        plane lies exactly on a voxel boundary (then both layers). Voxels entirely below the
        floor (k < 0) are left out. Boxes and rectangles are voxelized exactly (separating-axis
        test of each candidate voxel against the oriented box); an obstacle of another shape
        (none is generated today) is voxelized from samples of its triangles at r/4 spacing.

        The result is computed once per resolution and cached.

        Args:
            resolution: Voxel edge length in metres, > 0.

        Returns:
            (N, 3) float64 voxel centres, sorted by (i, j, k); a fresh copy on every call.

        Raises:
            SceneError: ``resolution`` is not a finite number > 0.
        """
        try:
            res = float(resolution)
        except (TypeError, ValueError):
            res = float("nan")
        if not (np.isfinite(res) and res > 0.0):
            raise SceneError(f"obstacle voxel resolution must be a finite number of metres > 0, got {resolution!r}")
        cache = self._obstacle_voxels
        if res not in cache:
            blocks = [np.zeros((0, 3), dtype=np.int64)]
            for object_id in sorted(self.object_names):
                if object_id in (FLOOR_ID, PERSON_ID):
                    continue
                faces = self.faces[self.face_object_id == object_id]
                if len(faces) == 0:
                    continue
                used = np.unique(faces)
                vertices = self.vertices_world[used]
                box = _oriented_box_of(vertices, len(faces))
                if box is not None:
                    blocks.append(_oriented_box_voxels(box[0], box[1], box[2], res))
                else:
                    local_faces = np.searchsorted(used, faces)
                    blocks.append(_triangle_voxels(vertices, local_faces, res))
            indices = np.concatenate(blocks, axis=0)
            indices = indices[indices[:, 2] >= 0]
            indices = np.unique(indices, axis=0) if len(indices) else indices
            cache[res] = (indices.astype(np.float64) + 0.5) * res
        return cache[res].copy()


# ----------------------------------------------------------------------------- camera poses


def look_at_pose(
    position: np.ndarray, target: np.ndarray, up: Tuple[float, float, float] = (0.0, 0.0, 1.0)
) -> CameraPose:
    """Camera at ``position`` with its optical z toward ``target`` and x parallel to the floor.

    z = normalize(target - position), x = normalize(z x up) (right), y = z x x (down).

    Args:
        position: (3,) camera centre in the world.
        target: (3,) point to look at.
        up: World up direction.

    Returns:
        T_world_camera.

    Raises:
        ValueError: target coincides with position or lies straight above/below it.
    """
    position = np.asarray(position, dtype=np.float64).reshape(3)
    forward = np.asarray(target, dtype=np.float64).reshape(3) - position
    norm = np.linalg.norm(forward)
    if norm < 1e-9:
        raise ValueError("look_at_pose: target coincides with position")
    z_axis = forward / norm
    x_axis = np.cross(z_axis, np.asarray(up, dtype=np.float64))
    x_norm = np.linalg.norm(x_axis)
    if x_norm < 1e-9:
        raise ValueError("look_at_pose: viewing direction is parallel to up")
    x_axis /= x_norm
    y_axis = np.cross(z_axis, x_axis)
    return CameraPose(np.stack([x_axis, y_axis, z_axis], axis=1), position)


def pose_in_world(T_world_obscam: CameraPose, R_obs_new: np.ndarray, p_obs_new: np.ndarray) -> CameraPose:
    """Move the camera to a pose given in an observation's optical frame.

    T_world_new = T_world_obs T_obs_new: R = R_wo R_on, p = R_wo p_on + p_wo.

    Args:
        T_world_obscam: Pose of the camera that made the observation.
        R_obs_new: (3,3) new camera axes in the observation's optical frame.
        p_obs_new: (3,) new camera centre in the observation's optical frame.

    Returns:
        T_world_newcam.
    """
    R_on = np.asarray(R_obs_new, dtype=np.float64).reshape(3, 3)
    p_on = np.asarray(p_obs_new, dtype=np.float64).reshape(3)
    return CameraPose(
        T_world_obscam.rotation @ R_on,
        T_world_obscam.rotation @ p_on + T_world_obscam.position,
    )


def camera_pose_from_base_goal(
    base_xy: np.ndarray,
    heading_rad: float,
    camera_height: float,
    pitch_rad: float = 0.0,
) -> CameraPose:
    """Camera pose of a robot whose base stands at ``base_xy`` (floor z = 0) facing ``heading_rad``.

    The camera sits straight above the base point at ``camera_height``; its optical axis points
    along the heading (angle from world +x about +z), pitched down by ``pitch_rad``.

    Args:
        base_xy: (2,) base position on the floor, world metres.
        heading_rad: Heading about world z.
        camera_height: Optical centre height above the floor (m).
        pitch_rad: Downward pitch of the optical axis (rad).

    Returns:
        T_world_camera.
    """
    base = np.asarray(base_xy, dtype=np.float64).reshape(2)
    direction = np.array(
        [np.cos(heading_rad) * np.cos(pitch_rad), np.sin(heading_rad) * np.cos(pitch_rad), -np.sin(pitch_rad)]
    )
    position = np.array([base[0], base[1], float(camera_height)])
    return look_at_pose(position, position + direction)


# ----------------------------------------------------------------------------- geometry


def _box_mesh(centre: np.ndarray, size: np.ndarray, yaw: float) -> Tuple[np.ndarray, np.ndarray]:
    """Axis-aligned-in-yaw box: 8 vertices, 12 triangles (world frame)."""
    half = 0.5 * np.asarray(size, dtype=np.float64)
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64) * half
    c, s = np.cos(yaw), np.sin(yaw)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    vertices = corners @ rotation.T + centre
    # Corner index = 4*ix + 2*iy + iz.
    faces = np.array(
        [
            [0, 1, 3],
            [0, 3, 2],  # x-
            [4, 6, 7],
            [4, 7, 5],  # x+
            [0, 4, 5],
            [0, 5, 1],  # y-
            [2, 3, 7],
            [2, 7, 6],  # y+
            [0, 2, 6],
            [0, 6, 4],  # z-
            [1, 5, 7],
            [1, 7, 3],  # z+
        ],
        dtype=np.int32,
    )
    return vertices, faces


def _quad_mesh(corners: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Planar quad from 4 corners in order: 4 vertices, 2 triangles."""
    return np.asarray(corners, dtype=np.float64), np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)


# Half thickness (m) given to a flat obstacle (a wall quad) so that it occupies the voxels its
# plane passes through, and the slack of the separating-axis test against round-off.
_FLAT_HALF_THICKNESS = 1e-6
_SEPARATION_SLACK = 1e-9


def _oriented_box_of(vertices: np.ndarray, face_count: int) -> Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(centre (3,), axes (3,3) unit rows, half extents (3,)) of a :func:`_box_mesh` or :func:`_quad_mesh` object.

    A box has 8 vertices (corner index 4 ix + 2 iy + iz) and 12 faces; a quad has 4 corners in
    order and 2 faces (a flat box: half extent 0 along its normal). Returns None when the
    vertices do not form a rectangular box or rectangle in that order.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    if len(vertices) == 8 and face_count == 12:
        origin = vertices[0]
        edges = np.stack([vertices[4] - origin, vertices[2] - origin, vertices[1] - origin])
        signs = np.array([[sx, sy, sz] for sx in (0, 1) for sy in (0, 1) for sz in (0, 1)], dtype=np.float64)
        rebuilt = origin + signs @ edges
    elif len(vertices) == 4 and face_count == 2:
        origin = vertices[0]
        u, v = vertices[1] - origin, vertices[3] - origin
        edges = np.stack([u, v, np.cross(u, v)])
        rebuilt = np.stack([origin, origin + u, origin + u + v, origin + v])
    else:
        return None
    lengths = np.linalg.norm(edges, axis=1)
    if np.any(lengths < 1e-12):
        return None
    axes = edges / lengths[:, None]
    scale = max(1.0, float(np.abs(vertices).max()))
    if np.abs(axes @ axes.T - np.eye(3)).max() > 1e-6 or np.abs(rebuilt - vertices).max() > 1e-9 * scale:
        return None
    half = 0.5 * lengths
    if len(vertices) == 4:
        half[2] = 0.0
    return vertices.mean(axis=0), axes, half


def _oriented_box_voxels(centre: np.ndarray, axes: np.ndarray, half: np.ndarray, res: float) -> np.ndarray:
    """(N,3) int64 indices of the voxels (edge ``res``, OctoMap convention) an oriented box reaches into.

    Separating-axis test of every voxel of the box's bounding range: the 3 world axes, the 3
    box axes and their 9 cross products; a voxel is kept when no axis separates it from the
    box (touching counts as separated). Flat boxes get ``_FLAT_HALF_THICKNESS``.
    """
    half = np.maximum(np.asarray(half, dtype=np.float64), _FLAT_HALF_THICKNESS)
    extent = np.abs(axes).T @ half  # world-axis half extents of the box
    low = np.floor((centre - extent) / res).astype(np.int64)
    high = np.floor((centre + extent) / res).astype(np.int64)
    low[2] = max(low[2], 0)  # nothing entirely below the floor
    if np.any(high < low):
        return np.zeros((0, 3), dtype=np.int64)
    grids = np.meshgrid(*[np.arange(low[i], high[i] + 1) for i in range(3)], indexing="ij")
    indices = np.stack([grid.reshape(-1) for grid in grids], axis=1)
    offsets = (indices + 0.5) * res - centre
    test_axes = [np.eye(3)[i] for i in range(3)] + [axes[j] for j in range(3)]
    test_axes += [np.cross(np.eye(3)[i], axes[j]) for i in range(3) for j in range(3)]
    keep = np.ones(len(indices), dtype=bool)
    for axis in test_axes:
        norm = np.linalg.norm(axis)
        if norm < 1e-9:  # parallel edges: no axis
            continue
        axis = axis / norm
        reach = 0.5 * res * np.abs(axis).sum() + np.abs(axes @ axis) @ half
        keep &= np.abs(offsets @ axis) < reach - _SEPARATION_SLACK
    return indices[keep]


def _triangle_voxels(vertices: np.ndarray, faces: np.ndarray, res: float) -> np.ndarray:
    """(N,3) int64 indices of the voxels (edge ``res``) holding samples of triangles at <= res/4 spacing."""
    blocks = [np.zeros((0, 3), dtype=np.int64)]
    for a, b, c in np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]:
        longest = max(np.linalg.norm(b - a), np.linalg.norm(c - b), np.linalg.norm(a - c))
        steps = max(1, int(np.ceil(longest / (0.25 * res))))
        i, j = np.meshgrid(np.arange(steps + 1), np.arange(steps + 1), indexing="ij")
        inside = i + j <= steps
        u, v = i[inside] / steps, j[inside] / steps
        points = a + u[:, None] * (b - a) + v[:, None] * (c - a)
        blocks.append(np.floor(points / res).astype(np.int64))
    return np.concatenate(blocks, axis=0)


def _face_colours(vertices: np.ndarray, faces: np.ndarray, base_rgb: np.ndarray) -> np.ndarray:
    """Lambert flat shading per face (both sides lit: |n . l|), (M,3) uint8."""
    a = vertices[faces[:, 0]]
    normals = np.cross(vertices[faces[:, 1]] - a, vertices[faces[:, 2]] - a)
    lengths = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = normals / np.maximum(lengths, 1e-12)
    lambert = np.abs(normals @ _LIGHT_DIRECTION)
    shade = _AMBIENT + (1.0 - _AMBIENT) * lambert
    colour = base_rgb[None, :] * shade[:, None] if base_rgb.ndim == 1 else base_rgb * shade[:, None]
    return np.clip(np.rint(colour * 255.0), 0, 255).astype(np.uint8)


def _yaw_matrix(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# Body rest frame (y up, facing +z) -> world (z up) facing -x (toward a camera on the -x side):
# columns are the images of the body's x, y, z axes.
_BODY_TO_WORLD_FACING_MINUS_X = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def sample_body_pose(rng: np.random.Generator) -> Tuple[np.ndarray, np.ndarray]:
    """A mild standing pose and shape.

    Arms lowered from the T-pose by 55-80 degrees at the shoulders, elbows bent 0-40 degrees,
    small random bends (sigma 0.06 rad, clipped to 0.15) at every body joint, a slight knee
    flex, the head turned a little. Betas ~ N(0, 0.5) clipped to +-1.2.

    Args:
        rng: Random generator.

    Returns:
        (body_pose (63,), betas (10,)).
    """
    pose = np.clip(rng.normal(0.0, 0.06, size=(21, 3)), -0.15, 0.15)

    def add(joint: int, axis_angle: Tuple[float, float, float]) -> None:
        pose[joint - 1] += np.asarray(axis_angle)

    left_lower = rng.uniform(np.radians(55), np.radians(80))
    right_lower = rng.uniform(np.radians(55), np.radians(80))
    # The left arm points along +x in the rest frame; a negative turn about z lowers it.
    add(_LEFT_SHOULDER, (0.0, 0.0, -left_lower))
    add(_RIGHT_SHOULDER, (0.0, 0.0, right_lower))
    add(_LEFT_ELBOW, (0.0, -rng.uniform(0.0, np.radians(40)), 0.0))
    add(_RIGHT_ELBOW, (0.0, rng.uniform(0.0, np.radians(40)), 0.0))
    knee = rng.uniform(0.0, np.radians(15))
    add(_LEFT_KNEE, (knee, 0.0, 0.0))
    add(_RIGHT_KNEE, (knee, 0.0, 0.0))
    add(_HEAD, (0.0, rng.uniform(-0.3, 0.3), 0.0))
    betas = np.clip(rng.normal(0.0, 0.5, size=10), -1.2, 1.2)
    return pose.reshape(63), betas


def _body_model_id(body_model: Any, config: SceneConfig) -> str:
    model_id = getattr(body_model, "model_id", None)
    return str(model_id) if model_id else "stand_in_" + config.body_resolution


def generate_scene(config: SceneConfig, body_model: Any) -> Scene:
    """Generate a scene: posed body on the floor, occluders hiding part of it, floor, walls.

    Random choices, all from ``np.random.default_rng(config.seed)``: camera height and
    distance, person heading, pose and shape; walls; then occluder layouts. Each layout draws
    1-2 boxes; the first ("the occluder") stands on the floor between the camera and the person
    (30-60 % of the way from the person, lateral offset up to 0.5 m, 0.3-1.1 m wide); its
    height is found by bisection so that the start view's occluder share hits a target drawn
    uniformly from the config's range; a second box, when drawn, stands to one side. A layout
    whose share cannot reach the range is discarded and another drawn. Last, when
    ``config.clutter_count_range`` allows any, furniture boxes are placed around the person
    from a separate stream, ``np.random.default_rng([seed, 7])`` (see :func:`_place_clutter`):
    they keep clear of the start view's line of sight to the body, so the occluder share found
    above holds (it is measured again on the full scene), and a config without clutter gives
    exactly the scene it gave before clutter existed.

    Args:
        config: Scene parameters and seed.
        body_model: A loaded ``leapnbv_perception.smplx_layer.SMPLXModel``.

    Returns:
        The scene; ``start_occluder_share`` lies in ``config.occluder_share_range``.

    Raises:
        SceneError: No layout met the occlusion range within ``config.max_attempts``.
    """
    rng = np.random.default_rng(config.seed)
    camera_height = rng.uniform(*config.camera_height_range)
    distance = rng.uniform(*config.person_distance_range)
    heading = np.radians(rng.uniform(*config.heading_range_deg))
    body_pose, betas = sample_body_pose(rng)

    R_root_world = _yaw_matrix(heading) @ _BODY_TO_WORLD_FACING_MINUS_X
    params_world = BodyParams(
        root_pose=matrix_to_axis_angle(R_root_world),
        body_pose=body_pose,
        left_hand_pose=np.zeros(45),
        right_hand_pose=np.zeros(45),
        jaw_pose=np.zeros(3),
        betas=betas,
        expression=np.zeros(10),
    )
    output = body_model.forward(params_world.to_smplx_params())
    forward_vertices = np.asarray(output.vertices, dtype=np.float64)
    root_joint = np.asarray(output.joints, dtype=np.float64)[0]
    # Pelvis above the world origin, lowest vertex on the floor.
    translation_world = np.array([-root_joint[0], -root_joint[1], -forward_vertices[:, 2].min()])
    body_world = forward_vertices + translation_world
    body_faces = np.asarray(body_model.faces, dtype=np.int32)
    body_centre = 0.5 * (body_world.min(axis=0) + body_world.max(axis=0))

    start_camera = look_at_pose(np.array([-distance, 0.0, camera_height]), body_centre)

    objects: List[Tuple[str, np.ndarray, np.ndarray, np.ndarray]] = []
    floor_half = 30.0
    objects.append(
        (
            "floor",
            *_quad_mesh(
                np.array(
                    [
                        [-floor_half, -floor_half, 0.0],
                        [floor_half, -floor_half, 0.0],
                        [floor_half, floor_half, 0.0],
                        [-floor_half, floor_half, 0.0],
                    ]
                )
            ),
            _FLOOR_COLOUR,
        )
    )
    objects.append(("person", body_world, body_faces, _PERSON_COLOUR))

    walls: List[Tuple[str, np.ndarray, np.ndarray, np.ndarray]] = []
    # Wall planes (x of the back wall, y of the side wall) that clutter must stay inside.
    wall_back_x: Optional[float] = None
    wall_side_y: Optional[float] = None
    if config.walls:
        back = rng.uniform(2.0, 3.0)
        wall_back_x = float(back)
        walls.append(
            (
                "wall_back",
                *_quad_mesh(np.array([[back, -8.0, 0.0], [back, 8.0, 0.0], [back, 8.0, 3.0], [back, -8.0, 3.0]])),
                _WALL_COLOUR,
            )
        )
        if rng.random() < 0.5:
            side = rng.choice([-1.0, 1.0]) * rng.uniform(2.5, 3.5)
            wall_side_y = float(side)
            walls.append(
                (
                    "wall_side",
                    *_quad_mesh(np.array([[-8.0, side, 0.0], [back, side, 0.0], [back, side, 3.0], [-8.0, side, 3.0]])),
                    _WALL_COLOUR * 0.92,
                )
            )

    # The body's self-visible vertices in the start view, computed once; each occluder layout
    # then only needs a render of its boxes (a vertex is hidden when a box is nearer).
    body_camera = start_camera.world_to_camera(body_world)
    body_depth = rasterize_mesh(body_camera, body_faces, config.K, config.width, config.height).depth
    self_visible = visible_vertex_mask(body_camera, body_depth, config.K)
    if not np.any(self_visible):
        raise SceneError(f"seed {config.seed}: the body is not visible from the start camera")

    low, high = config.occluder_share_range
    n_min, n_max = config.occluder_count_range
    for _attempt in range(config.max_attempts):
        count = int(rng.integers(n_min, n_max + 1))
        target_share = rng.uniform(low + 0.1 * (high - low), high - 0.1 * (high - low))
        along = rng.uniform(0.3, 0.6) * distance
        lateral = rng.uniform(-0.5, 0.5)
        width = rng.uniform(0.3, 1.1)
        thickness = rng.uniform(0.2, 0.5)
        yaw = rng.uniform(-0.4, 0.4)
        extras: List[Tuple[np.ndarray, np.ndarray]] = []
        for _ in range(count - 1):
            side_lateral = rng.choice([-1.0, 1.0]) * rng.uniform(0.4, 0.9)
            size = np.array([rng.uniform(0.2, 0.5), rng.uniform(0.2, 0.5), rng.uniform(0.4, 1.6)])
            centre = np.array([-rng.uniform(0.3, 0.6) * distance, side_lateral, 0.5 * size[2]])
            extras.append((centre, size))

        layout = _OccluderLayout(along, lateral, width, thickness, yaw, extras)

        def share_for(main_height: float, layout: _OccluderLayout = layout) -> float:
            boxes = layout.boxes(main_height)
            return _occluder_share_of_boxes(boxes, start_camera, body_camera, self_visible, config)

        # Bisection on the main box's height: a taller box hides a superset of pixels.
        lower_height, upper_height = 0.1, 2.2
        if share_for(upper_height) < low or share_for(lower_height) > high:
            continue
        best_height: Optional[float] = None
        best_share = 0.0
        for _ in range(14):
            middle = 0.5 * (lower_height + upper_height)
            share = share_for(middle)
            if low <= share <= high and (
                best_height is None or abs(share - target_share) < abs(best_share - target_share)
            ):
                best_height, best_share = middle, share
            if abs(share - target_share) < 0.02:
                break
            if share < target_share:
                lower_height = middle
            else:
                upper_height = middle
        if best_height is None:
            continue
        occluders = []
        for index, (centre, size, box_yaw) in enumerate(layout.boxes(best_height)):
            vertices, faces = _box_mesh(centre, size, box_yaw)
            occluders.append(
                ("occluder_%d" % index, vertices, faces, _OCCLUDER_COLOURS[index % len(_OCCLUDER_COLOURS)])
            )
        def assemble(scene_objects: List) -> Scene:
            assembled = _assemble(config, scene_objects, params_world, forward_vertices, root_joint,
                                  translation_world, body_faces, start_camera, _body_model_id(body_model, config))
            assembled.start_occluder_share, _ = assembled.occluder_share(start_camera)
            return assembled

        scene = assemble(objects + occluders + walls)
        if not low <= scene.start_occluder_share <= high:
            continue
        if config.clutter_count_range[1] <= 0:
            return scene
        # Clutter comes last, from its own random stream, so the draws above (and every scene
        # without clutter) stay as they were. It stays clear of the start view's line of sight
        # to the body, so it cannot change the start view's occluder share; the share is
        # measured again on the full scene all the same.
        clutter = _place_clutter(
            config,
            body_world,
            start_camera,
            layout.boxes(best_height),
            wall_back_x,
            wall_side_y,
        )
        scene = assemble(objects + occluders + walls + clutter)
        if low <= scene.start_occluder_share <= high:
            return scene
    raise SceneError(
        f"seed {config.seed}: no occluder layout reached an occluder share in [{low}, {high}] "
        f"in {config.max_attempts} attempts"
    )


def _clutter_rng(seed: int) -> np.random.Generator:
    """The clutter's random stream: independent of ``default_rng(seed)``, which draws the rest."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, _CLUTTER_STREAM])


def _place_clutter(
    config: SceneConfig,
    body_world: np.ndarray,
    start_camera: CameraPose,
    occluder_boxes: List[Tuple[np.ndarray, np.ndarray, float]],
    wall_back_x: Optional[float],
    wall_side_y: Optional[float],
) -> List[Tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """Furniture-like boxes standing around the person, off the start view's line of sight.

    Per box (count uniform in ``config.clutter_count_range``): a direction uniform around the
    person, a centre distance, width, depth and height uniform in the config's ranges, the broad
    side turned toward the person (yaw jitter +-0.3 rad), a colour from the furniture palette.
    A draw is kept when its footprint keeps ``config.clutter_clearance`` from: the convex hull of
    the start camera (a disc of the robot's 0.3 m radius) and the body's footprint, which holds
    every ray from the camera to the body (so the box hides nothing of the body in the start view
    and touches neither the body nor the camera); the occluders; the earlier clutter; and the
    inside of the walls. Up to ``config.clutter_max_tries`` draws per box; then the box is left out.

    Args:
        config: Scene parameters (clutter ranges; the seed selects the clutter stream).
        body_world: (V,3) body vertices in the world.
        start_camera: The start camera (T_world_camera).
        occluder_boxes: (centre (3,), size (3,), yaw) of each occluder box.
        wall_back_x: x of the back wall plane behind the person, None without one.
        wall_side_y: y of the side wall plane, None without one.

    Returns:
        ("clutter_<i>", vertices (8,3), faces (12,3), base colour (3,)) per placed box.
    """
    rng = _clutter_rng(config.seed)
    clearance = float(config.clutter_clearance)
    body_min = body_world[:, :2].min(axis=0)
    body_max = body_world[:, :2].max(axis=0)
    body_corners = np.array(
        [[body_min[0], body_min[1]], [body_max[0], body_min[1]], [body_max[0], body_max[1]], [body_min[0], body_max[1]]]
    )
    # The camera as a 16-gon around its foot point, scaled so the polygon contains the disc.
    robot_radius = 0.3
    angles = np.linspace(0.0, 2.0 * np.pi, 16, endpoint=False)
    camera_disc = start_camera.position[:2] + (robot_radius / np.cos(np.pi / 16)) * np.stack(
        [np.cos(angles), np.sin(angles)], axis=1
    )
    keep_out = [_convex_hull_2d(np.concatenate([body_corners, camera_disc]))]
    keep_out += [_box_footprint(centre, size, yaw) for centre, size, yaw in occluder_boxes]

    count = int(rng.integers(config.clutter_count_range[0], config.clutter_count_range[1] + 1))
    placed: List[Tuple[str, np.ndarray, np.ndarray, np.ndarray]] = []
    for _ in range(count):
        for _try in range(config.clutter_max_tries):
            azimuth = rng.uniform(-np.pi, np.pi)
            distance = rng.uniform(*config.clutter_distance_range)
            size = np.array(
                [
                    rng.uniform(*config.clutter_depth_range),
                    rng.uniform(*config.clutter_width_range),
                    rng.uniform(*config.clutter_height_range),
                ]
            )
            yaw = azimuth + rng.uniform(-0.3, 0.3)
            colour = _CLUTTER_COLOURS[int(rng.integers(len(_CLUTTER_COLOURS)))]
            centre = np.array([distance * np.cos(azimuth), distance * np.sin(azimuth), 0.5 * size[2]])
            footprint = _box_footprint(centre, size, yaw)
            if wall_back_x is not None and footprint[:, 0].max() > wall_back_x - clearance:
                continue
            if wall_side_y is not None and (
                footprint[:, 1].max() > wall_side_y - clearance
                if wall_side_y > 0
                else footprint[:, 1].min() < wall_side_y + clearance
            ):
                continue
            if not all(_convex_polygons_apart(footprint, other, clearance) for other in keep_out):
                continue
            keep_out.append(footprint)
            vertices, faces = _box_mesh(centre, size, yaw)
            placed.append(("clutter_%d" % len(placed), vertices, faces, colour))
            break
    return placed


def _box_footprint(centre: np.ndarray, size: np.ndarray, yaw: float) -> np.ndarray:
    """(4,2) floor footprint of a box of :func:`_box_mesh`, counter-clockwise."""
    half = 0.5 * np.asarray(size, dtype=np.float64)[:2]
    corners = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]) * half
    c, s = np.cos(yaw), np.sin(yaw)
    return corners @ np.array([[c, s], [-s, c]]) + np.asarray(centre, dtype=np.float64)[:2]


def _convex_hull_2d(points: np.ndarray) -> np.ndarray:
    """(K,2) convex hull, counter-clockwise (Andrew's monotone chain) of (N,2) points."""
    unique = sorted(set(map(tuple, np.asarray(points, dtype=np.float64).tolist())))
    if len(unique) < 3:
        return np.asarray(unique, dtype=np.float64)

    def cross(o: Tuple[float, float], a: Tuple[float, float], b: Tuple[float, float]) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: List[Tuple[float, float]] = []
    for point in unique:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], point) <= 0:
            lower.pop()
        lower.append(point)
    upper: List[Tuple[float, float]] = []
    for point in reversed(unique):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], point) <= 0:
            upper.pop()
        upper.append(point)
    return np.asarray(lower[:-1] + upper[:-1], dtype=np.float64)


def _convex_polygons_apart(a: np.ndarray, b: np.ndarray, gap: float) -> bool:
    """Whether two convex polygons (K,2) are at least ``gap`` apart along one of their edge normals.

    A separating axis with a gap of ``gap`` proves a distance of at least ``gap`` (conservative:
    polygons whose closest points are vertex to vertex may be refused a little early).
    """
    for polygon in (a, b):
        edges = np.roll(polygon, -1, axis=0) - polygon
        normals = np.stack([edges[:, 1], -edges[:, 0]], axis=1)
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        project_a = a @ normals.T
        project_b = b @ normals.T
        apart = (project_a.min(axis=0) - project_b.max(axis=0) >= gap) | (
            project_b.min(axis=0) - project_a.max(axis=0) >= gap
        )
        if np.any(apart):
            return True
    return False


@dataclass
class _OccluderLayout:
    """One draw of occluder boxes; the main box's height is left free for the bisection."""

    along: float
    lateral: float
    width: float
    thickness: float
    yaw: float
    extras: List[Tuple[np.ndarray, np.ndarray]]

    def boxes(self, main_height: float) -> List[Tuple[np.ndarray, np.ndarray, float]]:
        """(centre, size, yaw) per box, the main box first, standing on the floor."""
        main = (
            np.array([-self.along, self.lateral, 0.5 * main_height]),
            np.array([self.thickness, self.width, main_height]),
            self.yaw,
        )
        return [main] + [(centre, size, 0.0) for centre, size in self.extras]


def _occluder_share_of_boxes(
    boxes: List[Tuple[np.ndarray, np.ndarray, float]],
    camera: CameraPose,
    body_camera: np.ndarray,
    self_visible: np.ndarray,
    config: SceneConfig,
) -> float:
    """Share of the self-visible body vertices that the boxes hide (boxes-only render)."""
    vertex_blocks = []
    face_blocks = []
    for index, (centre, size, yaw) in enumerate(boxes):
        vertices, faces = _box_mesh(centre, size, yaw)
        vertex_blocks.append(vertices)
        face_blocks.append(faces + 8 * index)
    box_depth = rasterize_mesh(
        camera.world_to_camera(np.concatenate(vertex_blocks)),
        np.concatenate(face_blocks),
        config.K,
        config.width,
        config.height,
    ).depth
    still_visible = visible_vertex_mask(body_camera[self_visible], box_depth, config.K)
    return 1.0 - float(np.count_nonzero(still_visible)) / float(still_visible.size)


def _assemble(
    config: SceneConfig,
    objects: List[Tuple[str, np.ndarray, np.ndarray, np.ndarray]],
    params_world: BodyParams,
    forward_vertices: np.ndarray,
    root_joint: np.ndarray,
    translation_world: np.ndarray,
    body_faces: np.ndarray,
    start_camera: CameraPose,
    body_model_id: str,
) -> Scene:
    """Concatenate named objects into one mesh with per-face ids and colours."""
    vertex_blocks: List[np.ndarray] = []
    face_blocks: List[np.ndarray] = []
    id_blocks: List[np.ndarray] = []
    colour_blocks: List[np.ndarray] = []
    names: Dict[int, str] = {}
    offset = 0
    body_slice = slice(0, 0)
    next_occluder = FIRST_OCCLUDER_ID
    occluder_names = [name for name, _, _, _ in objects if name.startswith("occluder")]
    next_wall = FIRST_OCCLUDER_ID + len(occluder_names)
    for name, vertices, faces, base_rgb in objects:
        if name == "floor":
            object_id = FLOOR_ID
        elif name == "person":
            object_id = PERSON_ID
            body_slice = slice(offset, offset + len(vertices))
        elif name.startswith("occluder"):
            object_id = next_occluder
            next_occluder += 1
        else:
            object_id = next_wall
            next_wall += 1
        names[object_id] = name
        vertex_blocks.append(vertices)
        face_blocks.append(faces.astype(np.int32) + offset)
        id_blocks.append(np.full(len(faces), object_id, dtype=np.int32))
        colour_blocks.append(_face_colours(vertices, faces, np.asarray(base_rgb)))
        offset += len(vertices)
    return Scene(
        config=config,
        vertices_world=np.concatenate(vertex_blocks, axis=0),
        faces=np.concatenate(face_blocks, axis=0),
        face_object_id=np.concatenate(id_blocks),
        face_rgb=np.concatenate(colour_blocks, axis=0),
        object_names=names,
        body_vertex_slice=body_slice,
        body_faces=body_faces,
        body_params_world=params_world,
        body_forward_vertices=forward_vertices,
        body_root_joint=root_joint,
        body_translation_world=translation_world,
        start_camera=start_camera,
        start_occluder_share=0.0,
        body_model_id=body_model_id,
    )
