"""Random scenes: a posed stand-in body on the floor, box occluders hiding part of it, walls, furniture.

:func:`generate_scene` draws everything from the config's seed (the same config gives the same
scene). The start camera sits on the -x side of the person at ``person_distance`` metres and
``camera_height`` metres above the floor, looking along +x at the centre of the body's bounding
box (so its optical axis is pitched down by a few degrees; its x axis stays parallel to the
floor: no roll). Occluders stand between the camera and the person, sized so that the start
view's occluder share hits a drawn target; clutter (furniture, when the config asks for it)
stands around the person off the start view's line of sight. Other people (bystanders,
passers-by) and the target's walk, when the config asks for them, come last, from their own
random streams (:mod:`leapnbv_sim.people`): the rest of the scene is the one-person scene of the seed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional, Sequence, Tuple

import numpy as np

from leapnbv_common.array_types import BoolArray, FloatArray
from leapnbv_geometry.raster import rasterize_mesh
from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_sim.body import PlacedBody, body_model_id, place_body, sample_body_pose
from leapnbv_sim.depth_noise import DepthNoiseConfig
from leapnbv_sim.meshes import box_footprint, box_mesh, convex_hull_2d, convex_polygons_apart, quad_mesh
from leapnbv_sim.people import (
    OTHER_PERSON_COLOURS,
    ROLE_BYSTANDER,
    ROLE_PASSER_BY,
    TARGET_MOTIONS,
    FloorPlan,
    OtherPerson,
    PersonMotion,
    people_rng,
    place_bystander,
    place_passer_by,
    plan_target_motion,
    target_motion_rng,
)
from leapnbv_sim.poses import CameraPose, look_at_pose
from leapnbv_sim.scene import Scene, SceneError, SceneObject, assemble_scene
from leapnbv_sim.visibility import visible_vertex_mask

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
        room_layout: The walls (with ``walls``): "default" (a back wall 2-3 m behind the person, a
            side wall 2.5-3.5 m beside it half of the time), "corridor" (two long walls along the
            camera's line, 1.6-2.4 m apart, the person and camera between them), "corner" (a back
            and a side wall 0.6-1.0 m from the person) or "near_wall" (a back wall 0.4-0.7 m behind
            the person). The layouts other than "default" draw from their own random stream, so the
            rest of the scene is the default layout's.
        bystanders: People standing still near the target (:mod:`leapnbv_sim.people`), 0 = none.
        passers_by: People walking across the start view's line of sight to the target, 0 = none.
        target_motion: "stand" (the target stands still) or "walk" (it walks, or turns in place).
            Other people and the target's motion draw from their own random streams, after everything
            else: a config without them gives exactly the scene it gave before they existed.
        bystander_distance_range: Horizontal distance from the target's pelvis to a bystander's (m), uniform.
        passer_by_speed_range: A passer-by's walking speed (m/s), uniform.
        passer_by_crossing_s_range: When a passer-by crosses the line of sight (s of scene time), uniform.
        target_speed_range: The walking target's speed (m/s), uniform.
        target_walk_length_range: How far the walking target walks (m), uniform.
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
    room_layout: str = "default"
    bystanders: int = 0
    passers_by: int = 0
    target_motion: str = "stand"
    bystander_distance_range: Tuple[float, float] = (0.6, 1.5)
    passer_by_speed_range: Tuple[float, float] = (0.5, 1.0)
    passer_by_crossing_s_range: Tuple[float, float] = (1.0, 3.0)
    target_speed_range: Tuple[float, float] = (0.2, 0.5)
    target_walk_length_range: Tuple[float, float] = (0.8, 2.0)

    @property
    def K(self) -> FloatArray:
        """(3,3) intrinsics."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


def generate_scene(config: SceneConfig, body_model: SMPLXModel) -> Scene:
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
    exactly the scene it gave before clutter existed. Then, when the config asks for them, the
    target's motion and the other people (:func:`_place_people`), from their own streams and
    appended after every other object: they keep off the start view's line of sight at time 0, so
    the occluder share holds (measured again), and a config without them gives the scene it gave
    before they existed.

    Args:
        config: Scene parameters and seed.
        body_model: A loaded ``leapnbv_perception.smplx_layer.SMPLXModel``.

    Returns:
        The scene; ``start_occluder_share`` lies in ``config.occluder_share_range``.

    Raises:
        SceneError: No layout met the occlusion range within ``config.max_attempts``, or a person
            found no free place.
    """
    if config.target_motion not in TARGET_MOTIONS:
        raise SceneError(f"target_motion must be one of {TARGET_MOTIONS}, got {config.target_motion!r}")
    if config.bystanders < 0 or config.passers_by < 0:
        raise SceneError(f"bystanders and passers_by must be >= 0, got {config.bystanders}, {config.passers_by}")
    rng = np.random.default_rng(config.seed)
    camera_height = rng.uniform(*config.camera_height_range)
    distance = rng.uniform(*config.person_distance_range)
    heading = np.radians(rng.uniform(*config.heading_range_deg))
    body_pose, betas = sample_body_pose(rng)

    body = place_body(body_model, heading, body_pose, betas)
    body_world = body.vertices_world
    body_faces = body.faces
    body_centre = 0.5 * (body_world.min(axis=0) + body_world.max(axis=0))

    start_camera = look_at_pose(np.array([-distance, 0.0, camera_height]), body_centre)

    objects: List[SceneObject] = []
    floor_half = 30.0
    objects.append(
        (
            "floor",
            *quad_mesh(
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

    walls: List[SceneObject] = []
    # Wall planes (x of the back wall, y of the side wall) that clutter must stay inside.
    wall_back_x: Optional[float] = None
    wall_side_y: Optional[float] = None
    if config.room_layout not in ROOM_LAYOUTS:
        raise SceneError(f"room_layout must be one of {ROOM_LAYOUTS}, got {config.room_layout!r}")
    if config.walls and config.room_layout != "default":
        rng.uniform(2.0, 3.0)  # the default layout's draws, so the rest of the scene does not change
        if rng.random() < 0.5:
            rng.choice([-1.0, 1.0]) * rng.uniform(2.5, 3.5)
        walls, wall_back_x, wall_side_y = _layout_walls(config, distance)
    elif config.walls:
        back = rng.uniform(2.0, 3.0)
        wall_back_x = float(back)
        walls.append(
            (
                "wall_back",
                *quad_mesh(np.array([[back, -8.0, 0.0], [back, 8.0, 0.0], [back, 8.0, 3.0], [back, -8.0, 3.0]])),
                _WALL_COLOUR,
            )
        )
        if rng.random() < 0.5:
            side = rng.choice([-1.0, 1.0]) * rng.uniform(2.5, 3.5)
            wall_side_y = float(side)
            walls.append(
                (
                    "wall_side",
                    *quad_mesh(np.array([[-8.0, side, 0.0], [back, side, 0.0], [back, side, 3.0], [-8.0, side, 3.0]])),
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
        extras: List[Tuple[FloatArray, FloatArray]] = []
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
            vertices, faces = box_mesh(centre, size, box_yaw)
            occluders.append(
                ("occluder_%d" % index, vertices, faces, _OCCLUDER_COLOURS[index % len(_OCCLUDER_COLOURS)])
            )

        def assemble(scene_objects: List[SceneObject], others: Sequence[OtherPerson] = (),
                     target_motion: Optional[PersonMotion] = None) -> Scene:
            assembled = assemble_scene(config, scene_objects, body, start_camera,
                                       body_model_id(body_model, config.body_resolution), others, target_motion)
            assembled.start_occluder_share, _ = assembled.occluder_share(start_camera)
            return assembled

        scene = assemble(objects + occluders + walls)
        if not low <= scene.start_occluder_share <= high:
            continue
        clutter: List[SceneObject] = []
        if config.clutter_count_range[1] > 0:
            # Clutter comes next, from its own random stream, so the draws above (and every scene
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
            if not low <= scene.start_occluder_share <= high:
                continue
        if not (config.bystanders or config.passers_by or config.target_motion != "stand"):
            return scene
        # The people last, from their own streams (the scene so far is the one-person scene).
        others, target_motion = _place_people(config, body_model, body, heading, start_camera, occluders + clutter,
                                              walls)
        scene = assemble(objects + occluders + walls + clutter, others, target_motion)
        if low <= scene.start_occluder_share <= high:
            return scene
        raise SceneError(f"seed {config.seed}: the other people changed the start view's occluder share to "
                         f"{scene.start_occluder_share:.3f}, outside [{low}, {high}]")
    raise SceneError(
        f"seed {config.seed}: no occluder layout reached an occluder share in [{low}, {high}] "
        f"in {config.max_attempts} attempts"
    )


ROOM_LAYOUTS = ("default", "corridor", "corner", "near_wall")
_LAYOUT_STREAM = 11


def _place_people(config: SceneConfig, body_model: SMPLXModel, target: PlacedBody, heading: float,
                  start_camera: CameraPose, obstacles: List[SceneObject],
                  walls: List[SceneObject]) -> Tuple[List[OtherPerson], Optional[PersonMotion]]:
    """The target's motion and the other people (:mod:`leapnbv_sim.people`).

    In this order: the target's motion (its own stream), then the bystanders and the passers-by (the
    people's stream).

    Raises:
        SceneError: A person found no free place.
    """
    plan = FloorPlan.of([vertices for _, vertices, _, _ in obstacles], [vertices for _, vertices, _, _ in walls],
                        target, start_camera)
    motion = None
    if config.target_motion == "walk":
        motion = plan_target_motion(target_motion_rng(config.seed), plan, target, heading, config.target_speed_range,
                                    config.target_walk_length_range)
    rng = people_rng(config.seed)
    others: List[OtherPerson] = []
    for _ in range(config.bystanders):
        placed = place_bystander(rng, body_model, plan, target, start_camera, config.K, config.width,
                                 config.bystander_distance_range)
        if placed is None:
            raise SceneError(f"seed {config.seed}: no free place for bystander {len(others) + 1}")
        colour = OTHER_PERSON_COLOURS[len(others) % len(OTHER_PERSON_COLOURS)]
        others.append(OtherPerson(ROLE_BYSTANDER, placed, colour))
    for index in range(config.passers_by):
        walking = place_passer_by(rng, body_model, plan, target, start_camera, config.passer_by_speed_range,
                                  config.passer_by_crossing_s_range)
        if walking is None:
            raise SceneError(f"seed {config.seed}: no free path for passer-by {index + 1}")
        others.append(OtherPerson(ROLE_PASSER_BY, walking[0],
                                  OTHER_PERSON_COLOURS[len(others) % len(OTHER_PERSON_COLOURS)], walking[1]))
    return others, motion


def _layout_walls(config: SceneConfig, distance: float) -> Tuple[List[SceneObject], Optional[float], Optional[float]]:
    """The walls of a room layout other than "default" (own random stream); (walls, back x, side y)."""
    rng = np.random.default_rng([int(config.seed) & 0xFFFFFFFF, _LAYOUT_STREAM])
    far_x = -distance - 8.0  # behind the start camera

    def wall(name: str, corners: FloatArray, shade: float = 1.0) -> SceneObject:
        return (name, *quad_mesh(corners), _WALL_COLOUR * shade)

    if config.room_layout == "corridor":
        half = 0.5 * rng.uniform(1.6, 2.4)
        offset = rng.uniform(-0.15, 0.15) * half  # the person is not always on the centre line
        left, right = offset - half, offset + half
        end = 8.0
        walls = [wall("wall_side", np.array([[far_x, left, 0.0], [end, left, 0.0], [end, left, 3.0],
                                             [far_x, left, 3.0]]), 0.92),
                 wall("wall_side_2", np.array([[far_x, right, 0.0], [end, right, 0.0], [end, right, 3.0],
                                               [far_x, right, 3.0]]), 0.88)]
        return walls, None, float(left if abs(left) < abs(right) else right)
    if config.room_layout == "corner":
        back = rng.uniform(0.6, 1.0)
        side = rng.choice([-1.0, 1.0]) * rng.uniform(0.6, 1.0)
        back_wall = np.array([[back, -8.0, 0.0], [back, 8.0, 0.0], [back, 8.0, 3.0], [back, -8.0, 3.0]])
        walls = [wall("wall_back", back_wall),
                 wall("wall_side", np.array([[far_x, side, 0.0], [back, side, 0.0], [back, side, 3.0],
                                             [far_x, side, 3.0]]), 0.92)]
        return walls, float(back), float(side)
    back = rng.uniform(0.4, 0.7)  # near_wall
    walls = [wall("wall_back", np.array([[back, -8.0, 0.0], [back, 8.0, 0.0], [back, 8.0, 3.0], [back, -8.0, 3.0]]))]
    return walls, float(back), None


def _clutter_rng(seed: int) -> np.random.Generator:
    """The clutter's random stream: independent of ``default_rng(seed)``, which draws the rest."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, _CLUTTER_STREAM])


def _place_clutter(
    config: SceneConfig,
    body_world: FloatArray,
    start_camera: CameraPose,
    occluder_boxes: List[Tuple[FloatArray, FloatArray, float]],
    wall_back_x: Optional[float],
    wall_side_y: Optional[float],
) -> List[SceneObject]:
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
    keep_out = [convex_hull_2d(np.concatenate([body_corners, camera_disc]))]
    keep_out += [box_footprint(centre, size, yaw) for centre, size, yaw in occluder_boxes]

    count = int(rng.integers(config.clutter_count_range[0], config.clutter_count_range[1] + 1))
    placed: List[SceneObject] = []
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
            footprint = box_footprint(centre, size, yaw)
            if wall_back_x is not None and footprint[:, 0].max() > wall_back_x - clearance:
                continue
            if wall_side_y is not None and (
                footprint[:, 1].max() > wall_side_y - clearance
                if wall_side_y > 0
                else footprint[:, 1].min() < wall_side_y + clearance
            ):
                continue
            if not all(convex_polygons_apart(footprint, other, clearance) for other in keep_out):
                continue
            keep_out.append(footprint)
            vertices, faces = box_mesh(centre, size, yaw)
            placed.append(("clutter_%d" % len(placed), vertices, faces, colour))
            break
    return placed


@dataclass
class _OccluderLayout:
    """One draw of occluder boxes; the main box's height is left free for the bisection."""

    along: float
    lateral: float
    width: float
    thickness: float
    yaw: float
    extras: List[Tuple[FloatArray, FloatArray]]

    def boxes(self, main_height: float) -> List[Tuple[FloatArray, FloatArray, float]]:
        """(centre, size, yaw) per box, the main box first, standing on the floor."""
        main = (
            np.array([-self.along, self.lateral, 0.5 * main_height]),
            np.array([self.thickness, self.width, main_height]),
            self.yaw,
        )
        return [main] + [(centre, size, 0.0) for centre, size in self.extras]


def _occluder_share_of_boxes(
    boxes: List[Tuple[FloatArray, FloatArray, float]],
    camera: CameraPose,
    body_camera: FloatArray,
    self_visible: BoolArray,
    config: SceneConfig,
) -> float:
    """Share of the self-visible body vertices that the boxes hide (boxes-only render)."""
    vertex_blocks = []
    face_blocks = []
    for index, (centre, size, yaw) in enumerate(boxes):
        vertices, faces = box_mesh(centre, size, yaw)
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
