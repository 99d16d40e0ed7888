"""HumanMesh messages that name their triangles by id (leapnbv_common.mesh_faces) instead of carrying them."""
import numpy as np
import pytest

pytest.importorskip("leapnbv_msgs.msg")

from leapnbv_common import conversions as cv  # noqa: E402
from leapnbv_common.contracts import ContractError  # noqa: E402
from leapnbv_common.mesh_faces import MESH_FACES_UNKNOWN, KnownMeshFaces, mesh_faces_id  # noqa: E402
from leapnbv_common.stage_inputs import checked_human_mesh, human_mesh_face_count  # noqa: E402

pytestmark = pytest.mark.ros
FACES = np.array([[0, 1, 2], [2, 3, 4], [4, 0, 1]], np.uint32)


def _mesh(faces_id=""):
    rng = np.random.default_rng(3)
    return cv.HumanMeshArrays(
        vertices=rng.normal(size=(5, 3)).astype(np.float32), faces=FACES,
        virtual_intrinsics=(500.0, 510.0, 300.0, 200.0), image_size=(640, 480),
        detection=np.array([1, 2, 30, 40, 0.9], np.float32), processed_box=np.array([0, 1, 2, 3]),
        root_pose=np.ones(3), body_pose=np.zeros(63), left_hand_pose=np.zeros(45), right_hand_pose=np.zeros(45),
        jaw_pose=np.zeros(3), betas=np.zeros(10), expression=np.zeros(10), cam_translation=np.array([0, 0, 5.0]),
        model_id="m", faces_id=faces_id)


def test_a_mesh_that_names_its_triangles_reads_them_from_the_known_ones():
    mesh = _mesh(faces_id=mesh_faces_id(FACES))
    msg = cv.arrays_to_human_mesh(mesh, inline_faces=False)
    assert len(msg.faces) == 0 and msg.faces_id == mesh_faces_id(FACES)
    assert human_mesh_face_count(msg) == 3  # stated by the id, before any lookup
    with pytest.raises(ContractError) as error:
        checked_human_mesh(msg)
    assert error.value.reason == MESH_FACES_UNKNOWN
    known = KnownMeshFaces()
    known.add(msg.faces_id, FACES)
    back = checked_human_mesh(msg, known)
    np.testing.assert_array_equal(back.faces, FACES)
    np.testing.assert_array_equal(back.vertices, mesh.vertices)
    assert back.faces_id == msg.faces_id
    # Triangles of another model's vertex count are refused as any out-of-range face.
    known.add(mesh_faces_id(FACES + 5), FACES + 5)
    msg.faces_id = mesh_faces_id(FACES + 5)
    with pytest.raises(cv.ConversionError, match="out of range for 5 vertices"):
        checked_human_mesh(msg, known)


def test_vertices_only_reader_needs_no_triangles():
    msg = cv.arrays_to_human_mesh(_mesh(faces_id=mesh_faces_id(FACES)), inline_faces=False)
    arrays = cv.human_mesh_to_arrays(msg, without_faces=True)
    assert arrays.faces.shape == (0, 3) and arrays.vertices.shape == (5, 3)


def test_inline_triangles_still_read_without_any_known_faces():
    msg = cv.arrays_to_human_mesh(_mesh())
    assert msg.faces_id == "" and human_mesh_face_count(msg) == 3
    np.testing.assert_array_equal(checked_human_mesh(msg).faces, FACES)
    with pytest.raises(ValueError, match="needs the faces_id"):
        cv.arrays_to_human_mesh(_mesh(), inline_faces=False)
