"""The person: PersonDetections, HumanMesh, SceneGroundTruth and ScenePeople (SMPL-X body parameters) <-> arrays."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np
from std_msgs.msg import Header

from leapnbv_common.contracts import ContractError, check_boxes
from leapnbv_common.conversions.base import (
    ConversionError,
    check_finite_fields,
    float32_sequence,
    uint32_sequence,
)
from leapnbv_common.conversions.stamps import input_stamp_msgs
from leapnbv_common.mesh_faces import KnownMeshFaces, faces_id_count
from leapnbv_msgs.msg import HumanMesh, PersonDetection, PersonDetections, SceneGroundTruth, ScenePeople, ScenePerson

if TYPE_CHECKING:
    import numpy.typing as npt


def box_to_detection(box_xyxy_score: npt.ArrayLike) -> PersonDetection:
    """PersonDetection from [x_min, y_min, x_max, y_max, score]."""
    x0, y0, x1, y1, score = (float(v) for v in np.asarray(box_xyxy_score).reshape(5))
    return PersonDetection(x_min=x0, y_min=y0, x_max=x1, y_max=y1, score=score)


def detection_to_box(det: PersonDetection) -> npt.NDArray[np.float32]:
    """(5,) float32 [x_min, y_min, x_max, y_max, score] from a PersonDetection."""
    return np.array([det.x_min, det.y_min, det.x_max, det.y_max, det.score], dtype=np.float32)


def detections_to_boxes(msg: PersonDetections) -> npt.NDArray[np.float32]:
    """(N, 5) float32 [x_min, y_min, x_max, y_max, score] of a PersonDetections, checked.

    Raises:
        ConversionError: an empty image size, or a detection that is not finite, has a score outside
            [0, 1], an empty or inverted box, or a box outside the image (contracts.check_boxes).
    """
    size = (int(msg.image_width), int(msg.image_height))
    if size[0] <= 0 or size[1] <= 0:
        raise ConversionError(f"PersonDetections image size {size[0]}x{size[1]} is empty")
    boxes = np.array([detection_to_box(d) for d in msg.detections], np.float32).reshape(-1, 5)
    try:
        return check_boxes(boxes, size)
    except ContractError as error:
        raise ConversionError(str(error)) from None


# --------------------------------------------------------------------------- HumanMesh


@dataclass
class HumanMeshArrays:
    """The arrays of a HumanMesh message.

    vertices (V, 3) float32 in the virtual crop camera, faces (F, 3) uint32 (from the message, or the
    MeshFaces its faces_id names), virtual intrinsics (fx, fy, cx, cy), the body parameters as
    axis-angle, and the camera translation (float32 when read from a message; any float array when
    written). faces_id: the id the message named its triangles by ("" when it carried them only).
    """

    vertices: npt.NDArray[Any]
    faces: npt.NDArray[Any]
    virtual_intrinsics: Tuple[float, float, float, float]
    image_size: Tuple[int, int]
    detection: npt.NDArray[Any]
    processed_box: npt.NDArray[Any]
    root_pose: npt.NDArray[Any]
    body_pose: npt.NDArray[Any]
    left_hand_pose: npt.NDArray[Any]
    right_hand_pose: npt.NDArray[Any]
    jaw_pose: npt.NDArray[Any]
    betas: npt.NDArray[Any]
    expression: npt.NDArray[Any]
    cam_translation: npt.NDArray[Any]
    model_id: str = ""
    faces_id: str = ""


# SMPL-X body parameters (axis-angle poses, shape, expression) carried by HumanMesh and SceneGroundTruth.
_BODY_PARAM_SIZES: Dict[str, int] = {
    "root_pose": 3,
    "body_pose": 63,
    "left_hand_pose": 45,
    "right_hand_pose": 45,
    "jaw_pose": 3,
    "betas": 10,
    "expression": 10,
}
_MESH_PARAM_SIZES = {"processed_box": 4, **_BODY_PARAM_SIZES, "cam_translation": 3}


def _read_float32_fields(msg: Any, sizes: Mapping[str, int]) -> Dict[str, npt.NDArray[np.float32]]:
    """name -> (size,) float32 array of the fixed-size float fields of a message."""
    return {name: np.asarray(getattr(msg, name), dtype=np.float32).reshape(size) for name, size in sizes.items()}


def _write_float32_fields(msg: Any, values: Any, sizes: Mapping[str, int]) -> None:
    """Set the fixed-size float fields of a message from an object with attributes of the same names."""
    for name, size in sizes.items():
        setattr(msg, name, np.asarray(getattr(values, name), dtype=np.float32).reshape(size))


def human_mesh_to_arrays(msg: HumanMesh, known_faces: Optional[KnownMeshFaces] = None,
                         without_faces: bool = False) -> HumanMeshArrays:
    """Arrays from a HumanMesh, checking that vertices and faces are consistent.

    The triangles are the message's own, or, when it has none, those its faces_id names in
    ``known_faces`` (the MeshFaces received: leapnbv_common.mesh_faces). ``without_faces``: for a reader
    of the vertices only (the detector's box carrying): faces (0, 3), not looked up nor checked.

    Raises:
        ConversionError: vertex or face counts not multiples of 3, a face index out of range,
            non-finite vertices, or non-positive virtual focal lengths.
        ContractError: no triangles in the message and its faces_id not among ``known_faces``
            (``mesh_faces_unknown``), or not an id (``bad_mesh_faces``).
    """
    vertices = np.frombuffer(msg.vertices, dtype=np.float32) if len(msg.vertices) else np.zeros(0, np.float32)
    faces: npt.NDArray[Any]
    if without_faces:
        faces = np.zeros(0, np.uint32)
    elif len(msg.faces):
        faces = np.frombuffer(msg.faces, dtype=np.uint32)
    elif msg.faces_id:
        faces_id_count(msg.faces_id)  # a malformed id is bad_mesh_faces, not unknown
        faces = (known_faces if known_faces is not None else KnownMeshFaces()).get(msg.faces_id).reshape(-1)
    else:
        faces = np.zeros(0, np.uint32)
    if vertices.size == 0 or vertices.size % 3:
        raise ConversionError(f"HumanMesh has {vertices.size} vertex floats (need a non-zero multiple of 3)")
    if (faces.size == 0 and not without_faces) or faces.size % 3:
        raise ConversionError(f"HumanMesh has {faces.size} face indices (need a non-zero multiple of 3)")
    vertices = vertices.reshape(-1, 3)
    faces = faces.reshape(-1, 3)
    if faces.size and int(faces.max()) >= vertices.shape[0]:
        raise ConversionError(
            f"HumanMesh face index {int(faces.max())} out of range for {vertices.shape[0]} vertices"
        )
    if not np.all(np.isfinite(vertices)):
        raise ConversionError("HumanMesh vertices contain NaN or inf")
    if not (msg.fx > 0 and msg.fy > 0):
        raise ConversionError(f"HumanMesh virtual focal lengths must be positive, got {msg.fx}, {msg.fy}")
    if not np.all(np.isfinite([msg.cx, msg.cy])):
        raise ConversionError(f"HumanMesh virtual principal point is not finite: {msg.cx}, {msg.cy}")
    if msg.image_width <= 0 or msg.image_height <= 0:
        raise ConversionError(f"HumanMesh image size {msg.image_width}x{msg.image_height} is empty")
    params = _read_float32_fields(msg, _MESH_PARAM_SIZES)
    check_finite_fields("HumanMesh", params)
    if not np.all(np.isfinite(detection_to_box(msg.detection))):
        raise ConversionError("HumanMesh detection box is not finite")
    return HumanMeshArrays(
        vertices=vertices,
        faces=faces,
        virtual_intrinsics=(float(msg.fx), float(msg.fy), float(msg.cx), float(msg.cy)),
        image_size=(int(msg.image_width), int(msg.image_height)),
        detection=detection_to_box(msg.detection),
        model_id=msg.model_id,
        faces_id=msg.faces_id,
        **params,
    )


def arrays_to_human_mesh(mesh: HumanMeshArrays, header: Optional[Header] = None,
                         compute_time_ms: float = 0.0, inputs: Sequence[Tuple[Any, ...]] = (),
                         inline_faces: bool = True) -> HumanMesh:
    """A HumanMesh message from arrays (the inverse of human_mesh_to_arrays); ``inputs``: see input_stamp_msgs.

    inline_faces: the triangles go into the message; else only ``mesh.faces_id`` names them (the producer
    sends them on mesh_faces), which must then be set.
    """
    msg = HumanMesh(inputs=input_stamp_msgs(inputs))
    if header is not None:
        msg.header = header
    msg.detection = box_to_detection(mesh.detection)
    msg.vertices = float32_sequence(mesh.vertices)
    if not inline_faces and not mesh.faces_id:
        raise ValueError("a HumanMesh without its triangles needs the faces_id that names them")
    msg.faces = uint32_sequence(mesh.faces if inline_faces else np.zeros(0, np.uint32))
    msg.faces_id = mesh.faces_id
    msg.fx, msg.fy, msg.cx, msg.cy = (float(v) for v in mesh.virtual_intrinsics)
    msg.image_width, msg.image_height = (int(v) for v in mesh.image_size)
    _write_float32_fields(msg, mesh, _MESH_PARAM_SIZES)
    msg.model_id = mesh.model_id
    msg.compute_time_ms = float(compute_time_ms)
    return msg


# --------------------------------------------------------------------------- SceneGroundTruth


# The float fields of SceneGroundTruth: the body parameters and the translation in the camera frame.
_GROUND_TRUTH_PARAM_SIZES = {**_BODY_PARAM_SIZES, "translation": 3}
# Those of a ScenePerson (an other person: no hands, jaw nor expression, which are neutral).
_SCENE_PERSON_PARAM_SIZES = {"root_pose": 3, "body_pose": 63, "betas": 10, "translation": 3}
#: The target's object id in a simulated scene (a ScenePerson is never it).
TARGET_OBJECT_ID = 1


@dataclass
class ScenePersonArrays:
    """A person of a simulated scene other than the target (ScenePerson): its object id, its visible box
    (x0, y0, x1, y1, score; all zero when not visible), its body parameters and translation in the camera
    frame (hands, jaw and expression neutral) and its occlusion share."""

    object_id: int
    person_box: npt.NDArray[Any]
    root_pose: npt.NDArray[Any]
    body_pose: npt.NDArray[Any]
    betas: npt.NDArray[Any]
    translation: npt.NDArray[Any]
    occlusion_share: float


@dataclass
class SceneGroundTruthArrays:
    """The simulator's truth for one frame: the target's box (x0, y0, x1, y1, score; all zero when it is
    not visible), its body parameters in the camera frame, its occlusion share (float32 arrays when read
    from a message; any float array when written), and the scene's other people (``others``: from the
    frame's ScenePeople, which travels on its own topic; empty in a one-person scene)."""

    person_box: npt.NDArray[Any]
    root_pose: npt.NDArray[Any]
    body_pose: npt.NDArray[Any]
    left_hand_pose: npt.NDArray[Any]
    right_hand_pose: npt.NDArray[Any]
    jaw_pose: npt.NDArray[Any]
    betas: npt.NDArray[Any]
    expression: npt.NDArray[Any]
    translation: npt.NDArray[Any]
    occlusion_share: float
    body_model_id: str
    others: List[ScenePersonArrays] = field(default_factory=list)


def _check_truth_box(what: str, box: npt.NDArray[Any]) -> None:
    x0, y0, x1, y1, score = (float(v) for v in box)
    if x1 < x0 or y1 < y0 or not 0.0 <= score <= 1.0:
        raise ConversionError(f"{what} [{x0}, {y0}, {x1}, {y1}] with score {score} is inverted "
                              "or its score is outside [0, 1] (an empty box means nobody is visible)")


def _check_share(what: str, share: float) -> None:
    if not 0.0 <= share <= 1.0:
        raise ConversionError(f"{what} occlusion_share {share} is outside [0, 1]")


def _scene_person_to_arrays(msg: ScenePerson, index: int) -> ScenePersonArrays:
    what = f"ScenePeople people[{index}]"
    params = _read_float32_fields(msg, _SCENE_PERSON_PARAM_SIZES)
    person = ScenePersonArrays(object_id=int(msg.object_id), person_box=detection_to_box(msg.person_box),
                               occlusion_share=float(msg.occlusion_share), **params)
    check_finite_fields(what, {"person_box": person.person_box, "occlusion_share": person.occlusion_share, **params})
    if person.object_id < 0 or person.object_id == TARGET_OBJECT_ID:
        raise ConversionError(f"{what} object_id {person.object_id} is negative or the target's "
                              f"({TARGET_OBJECT_ID})")
    _check_share(what, person.occlusion_share)
    _check_truth_box(what + " person_box", person.person_box)
    return person


def scene_people_to_arrays(msg: ScenePeople) -> List[ScenePersonArrays]:
    """The other people of a frame (leapnbv_msgs/ScenePeople), in the message's order.

    Raises:
        ConversionError: a person's value is not finite, its occlusion share is outside [0, 1], its box
            inverted or its score outside [0, 1], its object id negative or the target's (1), or two of
            them have one id.
    """
    people = [_scene_person_to_arrays(person, index) for index, person in enumerate(msg.people)]
    ids = [person.object_id for person in people]
    if len(set(ids)) != len(ids):
        raise ConversionError(f"ScenePeople name an object id twice: {ids}")
    return people


def arrays_to_scene_people(people: Sequence[ScenePersonArrays], header: Optional[Header] = None) -> ScenePeople:
    """leapnbv_msgs/ScenePeople of a frame's other people (empty in a one-person scene)."""
    msg = ScenePeople()
    if header is not None:
        msg.header = header
    for person in people:
        other = ScenePerson(object_id=int(person.object_id), person_box=box_to_detection(person.person_box),
                            occlusion_share=float(person.occlusion_share))
        _write_float32_fields(other, person, _SCENE_PERSON_PARAM_SIZES)
        msg.people.append(other)
    return msg


def scene_ground_truth_to_arrays(msg: SceneGroundTruth,
                                 people: Optional[Sequence[ScenePersonArrays]] = None) -> SceneGroundTruthArrays:
    """The simulator's truth for one frame from its leapnbv_msgs/SceneGroundTruth.

    Args:
        msg: The target's truth.
        people: The frame's other people (:func:`scene_people_to_arrays` of its ScenePeople); None or empty
            in a one-person scene (and from a bag recorded before other people existed).

    Raises:
        ConversionError: a value is not finite, the occlusion share is outside [0, 1], or the person box
            is inverted (x_max < x_min or y_max < y_min; an empty box means nobody is visible) or its
            score is outside [0, 1].
    """
    params = _read_float32_fields(msg, _GROUND_TRUTH_PARAM_SIZES)
    truth = SceneGroundTruthArrays(person_box=detection_to_box(msg.person_box),
                                   occlusion_share=float(msg.occlusion_share), body_model_id=str(msg.body_model_id),
                                   others=list(people or []), **params)
    check_finite_fields("SceneGroundTruth", {"person_box": truth.person_box,
                                              "occlusion_share": truth.occlusion_share, **params})
    _check_share("SceneGroundTruth", truth.occlusion_share)
    _check_truth_box("SceneGroundTruth person_box", truth.person_box)
    return truth


def arrays_to_scene_ground_truth(truth: SceneGroundTruthArrays, header: Optional[Header] = None) -> SceneGroundTruth:
    """A SceneGroundTruth message (the inverse of scene_ground_truth_to_arrays; ``others`` go on ScenePeople)."""
    msg = SceneGroundTruth(person_box=box_to_detection(truth.person_box), body_model_id=str(truth.body_model_id),
                           occlusion_share=float(truth.occlusion_share))
    if header is not None:
        msg.header = header
    _write_float32_fields(msg, truth, _GROUND_TRUTH_PARAM_SIZES)
    return msg
