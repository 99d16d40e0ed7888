"""The scene model: one triangle mesh of named objects (floor, person, occluders, walls, clutter) and the start camera.

World frame of the simulator: metres, z up, the floor is the plane z = 0, the person stands
at the origin (pelvis above (0, 0)). Scenes are made by :func:`leapnbv_sim.generation.generate_scene`
from named objects (:func:`assemble_scene`); :meth:`Scene.render` renders one
(:mod:`leapnbv_sim.render`). Object ids (``Scene.object_names``): 0 floor, 1 the target person,
2.. occluders, then walls, then clutter, then the other people (bystanders, then passers-by:
:mod:`leapnbv_sim.people`), so the ids of a one-person scene are those it always had. The static
obstacles (occluders, walls, clutter and the people who stand still other than the target) are also
available as a voxel map, :meth:`Scene.obstacle_voxel_centres` (:mod:`leapnbv_sim.voxels`), the ground
truth of what a robot's mapping stack (e.g. OctoMap's occupied voxel centres) holds. People who move
(the walking target, passers-by) are where they are at a time: :meth:`Scene.at_time`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Dict, List, Optional, Sequence, Tuple

import numpy as np

from leapnbv_common.array_types import BoolArray, Float32Array, FloatArray, Int32Array, IntArray, UInt8Array
from leapnbv_sim.body import BodyParams, PlacedBody, body_params_in_camera
from leapnbv_sim.people import ROLE_TARGET, OtherPerson, Person, PersonMotion
from leapnbv_sim.poses import CameraPose
from leapnbv_sim.render import (
    BACKGROUND_RGB,
    FIRST_OCCLUDER_ID,
    FLOOR_ID,
    PERSON_ID,
    RenderedFrame,
    occluder_share,
    render_depth,
    render_frame,
    shade_faces,
)
from leapnbv_sim.voxels import occupied_voxel_centres

if TYPE_CHECKING:  # annotation only: generation.py builds scenes, so it imports this module
    from leapnbv_sim.generation import SceneConfig

#: One named object of a scene: (name, vertices (N,3), faces (M,3), base colour RGB 0..1 (3,)).
SceneObject = Tuple[str, FloatArray, IntArray, FloatArray]


class SceneError(RuntimeError):
    """A scene could not be generated or rendered (names the seed or field at fault)."""


@dataclass
class Scene:
    """A generated scene in the world frame (z up, floor z = 0).

    Attributes:
        config: The SceneConfig it was generated from.
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
        people: Every person, the target first (:class:`leapnbv_sim.people.Person`: id, role, body now
            and at time 0, motion); the target's ``body_*`` fields above are its body now.
        elapsed_s: The sim time the scene shows (:meth:`at_time`; 0 for a scene as generated).
    """

    config: SceneConfig
    vertices_world: FloatArray
    faces: IntArray
    face_object_id: IntArray
    face_rgb: UInt8Array
    object_names: Dict[int, str]
    body_vertex_slice: slice
    body_faces: IntArray
    body_params_world: BodyParams
    body_forward_vertices: FloatArray
    body_root_joint: FloatArray
    body_translation_world: FloatArray
    start_camera: CameraPose
    start_occluder_share: float
    body_model_id: str
    people: List[Person] = field(default_factory=list)
    elapsed_s: float = 0.0
    # obstacle_voxel_centres per resolution, computed on first use.
    _obstacle_voxels: Dict[float, FloatArray] = field(default_factory=dict, init=False, repr=False, compare=False)
    # face_rgb with the background colour as the last row, made on first use.
    _colour_table: Optional[UInt8Array] = field(default=None, init=False, repr=False, compare=False)

    @property
    def K(self) -> FloatArray:
        """(3,3) intrinsics."""
        return self.config.K

    @property
    def colour_table(self) -> UInt8Array:
        """(M+1,3) uint8 face colours with the background colour as the last row (face index -1)."""
        if self._colour_table is None or len(self._colour_table) != len(self.face_rgb) + 1:
            self._colour_table = np.concatenate([self.face_rgb, BACKGROUND_RGB[None, :]], axis=0)
        return self._colour_table

    @property
    def body_vertices_world(self) -> FloatArray:
        """(V,3) body vertices in the world."""
        return self.vertices_world[self.body_vertex_slice]

    @property
    def body_centre_world(self) -> FloatArray:
        """(3,) centre of the body's axis-aligned bounding box in the world."""
        body = self.body_vertices_world
        centre: FloatArray = 0.5 * (body.min(axis=0) + body.max(axis=0))
        return centre

    def body_params_in_camera(self, camera: CameraPose) -> Tuple[BodyParams, FloatArray]:
        """Body parameters and translation in a camera's frame (:func:`leapnbv_sim.body.body_params_in_camera`)."""
        return body_params_in_camera(self.body_params_world, self.body_root_joint, self.body_translation_world, camera)

    def render_depth(
        self, camera: CameraPose, include: Optional[IntArray] = None
    ) -> Tuple[Float32Array, Int32Array]:
        """Noise-free depth and object id of the scene or of some objects (:func:`leapnbv_sim.render.render_depth`)."""
        return render_depth(self, camera, include)

    def occluder_share(
        self, camera: CameraPose, scene_depth_m: Optional[FloatArray] = None
    ) -> Tuple[float, BoolArray]:
        """Share of the self-visible body hidden by other objects (:func:`leapnbv_sim.render.occluder_share`)."""
        return occluder_share(self, camera, scene_depth_m)

    def render(self, camera: Optional[CameraPose] = None, frame_index: int = 0) -> RenderedFrame:
        """Render RGB, depth and object ids with ground truth (:func:`leapnbv_sim.render.render_frame`).

        Args:
            camera: T_world_camera; the start camera if None.
            frame_index: Selects the depth-noise draw (seeded by (config.seed, frame_index)).
        """
        return render_frame(self, self.start_camera if camera is None else camera, frame_index)

    @property
    def others(self) -> List[Person]:
        """The people other than the target (bystanders, passers-by), in id order."""
        return [person for person in self.people if person.role != ROLE_TARGET]

    @property
    def moving_person_ids(self) -> List[int]:
        """Object ids of the people who move (the walking target, passers-by)."""
        return [person.object_id for person in self.people if person.moves]

    @property
    def target_motion(self) -> Optional[PersonMotion]:
        """How the target moves (None: it stands)."""
        return self.people[0].motion if self.people else None

    def at_time(self, elapsed_s: float) -> Scene:
        """The scene as it is ``elapsed_s`` seconds of sim time after it was set (its people moved).

        The one place where a scene's moving people are placed at a time; the simulator renders every
        frame from the scene at its stamp. A scene whose people all stand is the same at every time
        (``self``). Otherwise a new scene whose moving people's vertices are their bodies at that time
        (a rigid motion of each body's posed vertices: :func:`leapnbv_sim.people.move_body`), their
        faces re-shaded when turned, the target's ``body_*`` fields its body then; everything else is
        shared with this scene (the static obstacles' voxel map too). Always measured from the scene's
        time 0, whichever scene of it is asked: ``scene.at_time(2).at_time(1)`` is ``scene.at_time(1)``.

        Raises:
            SceneError: ``elapsed_s`` is not a finite number.
        """
        if not any(person.moves for person in self.people):
            return self
        t = float(elapsed_s)
        if not math.isfinite(t):
            raise SceneError(f"a scene's time must be a finite number of seconds, got {elapsed_s!r}")
        vertices = self.vertices_world.copy()
        face_rgb = self.face_rgb
        people = list(self.people)
        for index, person in enumerate(self.people):
            if not person.moves:
                continue
            body, turned = person.body_at(t)
            vertices[person.vertex_slice] = body.vertices_world
            if turned:
                if face_rgb is self.face_rgb:
                    face_rgb = face_rgb.copy()
                face_rgb[person.face_slice] = shade_faces(body.vertices_world, body.faces, person.base_rgb)
            people[index] = dataclasses.replace(person, body=body)
        target = people[0].body
        scene = dataclasses.replace(self, vertices_world=vertices, face_rgb=face_rgb, people=people, elapsed_s=t,
                                    body_params_world=target.params_world,
                                    body_forward_vertices=target.forward_vertices,
                                    body_translation_world=target.translation_world)
        scene._obstacle_voxels = self._obstacle_voxels  # the static obstacles do not move
        if face_rgb is self.face_rgb:
            scene._colour_table = self._colour_table
        return scene

    def obstacle_voxel_centres(self, resolution: float = 0.1) -> FloatArray:
        """World-frame centres of the voxels that the scene's static obstacles occupy.

        The obstacles are every object but the floor, the target and the people who move: the occluder
        boxes, the walls, the clutter (furniture) boxes and the bystanders (people who stand still are
        what a mapping stack integrates; a passer-by is not where the map would put it by the time the
        robot gets there, and a mapping stack clears what moves); the voxel convention is that of
        :mod:`leapnbv_sim.voxels` (OctoMap's). The result is computed once per resolution and cached.

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
        if res not in self._obstacle_voxels:
            moving = set(self.moving_person_ids)
            obstacles = [i for i in sorted(self.object_names) if i not in (FLOOR_ID, PERSON_ID) and i not in moving]
            self._obstacle_voxels[res] = occupied_voxel_centres(
                self.vertices_world, self.faces, self.face_object_id, obstacles, res)
        return self._obstacle_voxels[res].copy()


def assemble_scene(
    config: SceneConfig,
    objects: Sequence[SceneObject],
    body: PlacedBody,
    start_camera: CameraPose,
    body_model_id: str,
    others: Sequence[OtherPerson] = (),
    target_motion: Optional[PersonMotion] = None,
) -> Scene:
    """Concatenate named objects into one mesh with per-face ids and flat-shaded colours.

    Ids: "floor" 0, "person" 1 (its vertices are the body's), "occluder*" from 2 on in order,
    every other object (walls, clutter) after the occluders in order, then ``others`` in order,
    named "person_<role>" (with "_<k>" from the second of a role on): appended last, so a scene
    without them has the ids, vertices and faces it has with them up to there.
    ``start_occluder_share`` is left 0 for the caller to measure.
    """
    vertex_blocks: List[FloatArray] = []
    face_blocks: List[IntArray] = []
    id_blocks: List[Int32Array] = []
    colour_blocks: List[UInt8Array] = []
    names: Dict[int, str] = {}
    offset = 0
    face_offset = 0
    body_slice = slice(0, 0)
    target_faces = slice(0, 0)
    next_occluder = FIRST_OCCLUDER_ID
    occluder_names = [name for name, _, _, _ in objects if name.startswith("occluder")]
    next_wall = FIRST_OCCLUDER_ID + len(occluder_names)
    for name, vertices, faces, base_rgb in objects:
        if name == "floor":
            object_id = FLOOR_ID
        elif name == "person":
            object_id = PERSON_ID
            body_slice = slice(offset, offset + len(vertices))
            target_faces = slice(face_offset, face_offset + len(faces))
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
        colour_blocks.append(shade_faces(vertices, faces, np.asarray(base_rgb)))
        offset += len(vertices)
        face_offset += len(faces)
    target_rgb = next((np.asarray(rgb) for name, _, _, rgb in objects if name == "person"), np.zeros(3))
    people = [Person("person", PERSON_ID, ROLE_TARGET, body, body, target_rgb, target_motion, body_slice,
                     target_faces)]
    next_person = max(names) + 1
    roles: Dict[str, int] = {}
    for other in others:
        count = roles[other.role] = roles.get(other.role, 0) + 1
        name = "person_" + other.role + ("" if count == 1 else "_%d" % count)
        vertices = other.body.vertices_world
        faces = np.asarray(other.body.faces)
        names[next_person] = name
        people.append(Person(name, next_person, other.role, other.body, other.body, np.asarray(other.base_rgb),
                             other.motion, slice(offset, offset + len(vertices)),
                             slice(face_offset, face_offset + len(faces))))
        vertex_blocks.append(vertices)
        face_blocks.append(faces.astype(np.int32) + offset)
        id_blocks.append(np.full(len(faces), next_person, dtype=np.int32))
        colour_blocks.append(shade_faces(vertices, faces, np.asarray(other.base_rgb)))
        offset += len(vertices)
        face_offset += len(faces)
        next_person += 1
    return Scene(
        config=config,
        vertices_world=np.concatenate(vertex_blocks, axis=0),
        faces=np.concatenate(face_blocks, axis=0),
        face_object_id=np.concatenate(id_blocks),
        face_rgb=np.concatenate(colour_blocks, axis=0),
        object_names=names,
        body_vertex_slice=body_slice,
        body_faces=body.faces,
        body_params_world=body.params_world,
        body_forward_vertices=body.forward_vertices,
        body_root_joint=body.root_joint,
        body_translation_world=body.translation_world,
        start_camera=start_camera,
        start_occluder_share=0.0,
        body_model_id=body_model_id,
        people=people,
    )
