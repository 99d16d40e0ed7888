"""A body mesh's triangles sent once per model: their ids and the readers' store (ROS-free)."""
import hashlib

import numpy as np
import pytest

from leapnbv_common.contracts import ContractError
from leapnbv_common.mesh_faces import (
    BAD_MESH_FACES,
    MESH_FACES_UNKNOWN,
    FacesIdMemo,
    KnownMeshFaces,
    faces_id_count,
    mesh_faces_id,
)

FACES = np.array([[0, 1, 2], [2, 3, 4], [4, 0, 1]], np.uint32)


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
