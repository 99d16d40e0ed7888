"""A body mesh's triangles, sent once per model: their id, and the triangles a reader knows.

A body model's triangles are the same in every frame (SMPL-X: 20,908 of them, 251 KB of its 377 KB
HumanMesh), so hmr_node publishes them once per model on the latched topic ``mesh_faces``
(leapnbv_msgs/MeshFaces) and each HumanMesh names them by ``faces_id`` instead of carrying them
(docs/TWO_HOSTS.md: what crosses a Wi-Fi link per frame). The id is the triangle count and a digest
of the triangles' bytes: the same triangles have the same id whoever sends them, and a reader checks
that the triangles it received are the ones their id names.
"""
from __future__ import annotations

import hashlib
import typing
from collections import OrderedDict
from typing import Optional

import numpy as np
import numpy.typing as npt

from leapnbv_common.array_types import IntArray
from leapnbv_common.contracts import MAX_MESH_FACES, ContractError

#: Hex digits of the SHA-1 kept in an id (64 bits: no two body models collide by chance).
FACES_ID_DIGEST_CHARS = 16
#: Triangle sets a reader keeps (and the latched topic's depth): more than one model at a time, e.g. while a
#: model is swapped, or a ground-truth and an engine producer on one graph.
KNOWN_FACES_CAPACITY = 4
#: Why a mesh or a MeshFaces message was refused (counted on /diagnostics).
MESH_FACES_UNKNOWN = "mesh_faces_unknown"
BAD_MESH_FACES = "bad_mesh_faces"


def mesh_faces_id(faces: npt.ArrayLike) -> str:
    """The id of a triangle set: ``"<triangle count>:<first 16 hex digits of the SHA-1 of its uint32 bytes>"``."""
    triangles = np.ascontiguousarray(faces, dtype="<u4").reshape(-1, 3)
    return f"{len(triangles)}:{hashlib.sha1(triangles.tobytes()).hexdigest()[:FACES_ID_DIGEST_CHARS]}"


def faces_id_count(faces_id: str) -> int:
    """The triangle count an id states (read before the triangles, to refuse a mesh too large early).

    Raises:
        ContractError: not an id of mesh_faces_id's form (``bad_mesh_faces``).
    """
    count, _, digest = faces_id.partition(":")
    if not count.isdigit() or len(digest) != FACES_ID_DIGEST_CHARS:
        raise ContractError(f"faces_id {faces_id!r} is not '<triangle count>:<{FACES_ID_DIGEST_CHARS} hex digits>'",
                            BAD_MESH_FACES)
    return int(count)


class FacesIdMemo:
    """mesh_faces_id of the last triangle array seen, computed again only for another array.

    A producer hands the same model's array every frame: hashing 251 KB a frame would cost ~0.3 ms for nothing.
    """

    def __init__(self) -> None:
        self._faces: Optional[npt.NDArray[np.uint32]] = None
        self._copy: Optional[npt.NDArray[np.uint32]] = None
        self._id = ""

    def id_of(self, faces: npt.NDArray[np.uint32]) -> str:
        # The same object with the same contents: an array changed in place gets a new id.
        if faces is not self._faces or self._copy is None or not np.array_equal(faces, self._copy):
            self._faces, self._copy, self._id = faces, np.array(faces, copy=True), mesh_faces_id(faces)
        return self._id


class KnownMeshFaces:
    """The triangle sets a reader received, by id, the newest ``capacity`` kept.

    Args:
        capacity: How many triangle sets to keep (the oldest received goes first).
    """

    def __init__(self, capacity: int = KNOWN_FACES_CAPACITY) -> None:
        self.capacity = capacity
        self._faces: typing.OrderedDict[str, IntArray] = OrderedDict()

    def add(self, faces_id: str, faces: npt.ArrayLike) -> IntArray:
        """Keep the triangles of one MeshFaces message; returns them as (F, 3) uint32.

        Raises:
            ContractError: an empty or ragged triangle list, more than MAX_MESH_FACES triangles, or
                triangles that are not what their id names (``bad_mesh_faces``).
        """
        count = faces_id_count(faces_id)
        flat = np.asarray(faces, dtype=np.uint32).reshape(-1)
        if flat.size == 0 or flat.size % 3:
            raise ContractError(f"MeshFaces {faces_id!r} has {flat.size} indices (need a non-zero multiple of 3)",
                                BAD_MESH_FACES)
        if count > MAX_MESH_FACES:
            raise ContractError(f"MeshFaces {faces_id!r} has {count} triangles (limit {MAX_MESH_FACES})",
                                BAD_MESH_FACES)
        triangles = flat.reshape(-1, 3)
        if mesh_faces_id(triangles) != faces_id:
            raise ContractError(f"MeshFaces triangles ({len(triangles)}, id {mesh_faces_id(triangles)!r}) are not "
                                f"those their id {faces_id!r} names", BAD_MESH_FACES)
        triangles.setflags(write=False)  # shared by every mesh that names them
        self._faces[faces_id] = triangles
        self._faces.move_to_end(faces_id)
        while len(self._faces) > self.capacity:
            self._faces.popitem(last=False)
        return triangles

    def get(self, faces_id: str) -> IntArray:
        """The triangles of an id.

        Raises:
            ContractError: no MeshFaces of this id received (``mesh_faces_unknown``).
        """
        try:
            return self._faces[faces_id]
        except KeyError:
            known = ", ".join(self._faces) or "none"
            raise ContractError(f"HumanMesh names triangles {faces_id!r} that no MeshFaces message on mesh_faces "
                                f"gave (known: {known})", MESH_FACES_UNKNOWN) from None

    def __contains__(self, faces_id: object) -> bool:
        return faces_id in self._faces

    def __len__(self) -> int:
        return len(self._faces)
