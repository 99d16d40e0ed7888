"""A body mesh's triangles sent once per model: ids, the readers' store, and meshes that name them."""
import hashlib

import numpy as np
import pytest

from leapnbv_common import conversions as cv
from leapnbv_common.contracts import ContractError
from leapnbv_common.mesh_faces import (
    BAD_MESH_FACES,
    MESH_FACES_UNKNOWN,
    FacesIdMemo,
    KnownMeshFaces,
    faces_id_count,
    mesh_faces_id,
)
from leapnbv_common.stage_inputs import checked_human_mesh, human_mesh_face_count

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


def test_id_is_the_count_and_the_sha1_of_the_little_endian_triangles():
    digest = hashlib.sha1(FACES.astype("<u4").tobytes()).hexdigest()[:16]
    assert mesh_faces_id(FACES) == f"3:{digest}"
    assert mesh_faces_id(FACES.astype(np.int64)) == mesh_faces_id(FACES)  # the values, not the dtype
    assert mesh_faces_id(FACES[:, ::-1]) != mesh_faces_id(FACES)  # winding is part of the triangles
    assert faces_id_count(mesh_faces_id(FACES)) == 3


@pytest.mark.parametrize("bad", ["", "3", "x:0123456789abcdef", "3:0123"])
def test_a_malformed_id_is_bad_mesh_faces(bad):
    with pytest.raises(ContractError) as error:
        faces_id_count(bad)
    assert error.value.reason == BAD_MESH_FACES


def test_memo_hashes_again_only_for_other_triangles():
    memo = FacesIdMemo()
    faces = FACES.copy()
    first = memo.id_of(faces)
    assert memo.id_of(faces) == first == mesh_faces_id(FACES)
    faces[0, 0] = 3  # changed in place: the same object, other triangles
    assert memo.id_of(faces) == mesh_faces_id(faces) != first


def test_known_faces_checks_the_id_and_keeps_the_newest():
    known = KnownMeshFaces(capacity=2)
    ids = []
    for shift in range(3):
        faces = FACES + shift
        ids.append(mesh_faces_id(faces))
        np.testing.assert_array_equal(known.add(ids[-1], faces.ravel()), faces)
    assert ids[0] not in known and ids[1] in known and ids[2] in known and len(known) == 2
    with pytest.raises(ContractError) as error:
        known.get(ids[0])
    assert error.value.reason == MESH_FACES_UNKNOWN
    with pytest.raises(ContractError, match="are not those their id") as error:
        known.add(ids[1], (FACES + 7).ravel())  # triangles that are not what the id names
    assert error.value.reason == BAD_MESH_FACES
    np.testing.assert_array_equal(known.get(ids[1]), FACES + 1)  # the good set stays
    with pytest.raises(ContractError, match="non-zero multiple of 3"):
        known.add(mesh_faces_id(FACES), FACES.ravel()[:4])


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
