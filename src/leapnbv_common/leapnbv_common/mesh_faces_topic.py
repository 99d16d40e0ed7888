"""The mesh_faces topic: a body model's triangles published once (producer) and kept by id (readers).

hmr_node names each mesh's triangles by id and publishes them once per model
(:class:`MeshFacesPublisher`); raster_node and nbv_node keep what arrives (:class:`MeshFacesInput`)
and look a mesh's triangles up by its faces_id (leapnbv_common.mesh_faces, the ROS-free part).
"""
from __future__ import annotations

import typing
from collections import OrderedDict
from typing import Any

import numpy as np

from leapnbv_common.conversions import HumanMeshArrays, uint32_sequence
from leapnbv_common.diagnostics import rejects_bad_input
from leapnbv_common.mesh_faces import BAD_MESH_FACES, KNOWN_FACES_CAPACITY, FacesIdMemo, KnownMeshFaces
from leapnbv_common.qos import latched_mesh_faces_qos
from leapnbv_common.topics import MESH_FACES
from leapnbv_msgs.msg import MeshFaces

__all__ = ["MeshFacesPublisher", "MeshFacesInput"]


class MeshFacesPublisher:
    """Names a mesh's triangles by id and publishes each triangle set once on mesh_faces (latched).

    Made in the producer's configure (a lifecycle publisher: published while active). A triangle set is
    published again only if it fell out of the topic's history (more than KNOWN_FACES_CAPACITY models since).

    Args:
        node: The producing ManagedNode.
    """

    def __init__(self, node: Any) -> None:
        self.node = node
        self.publisher = node.create_lifecycle_publisher(MeshFaces, MESH_FACES, latched_mesh_faces_qos())
        self.memo = FacesIdMemo()
        self.sent: typing.OrderedDict[str, None] = OrderedDict()

    def name(self, mesh: HumanMeshArrays) -> None:
        """Set ``mesh.faces_id``, publishing its triangles first if this publisher has not yet."""
        faces = np.ascontiguousarray(mesh.faces, dtype=np.uint32)
        mesh.faces_id = self.memo.id_of(faces)
        if mesh.faces_id in self.sent:
            self.sent.move_to_end(mesh.faces_id)
            return
        msg = MeshFaces(faces_id=mesh.faces_id, faces=uint32_sequence(faces), model_id=mesh.model_id)
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self.publisher.publish(msg)
        self.sent[mesh.faces_id] = None
        while len(self.sent) > KNOWN_FACES_CAPACITY:
            self.sent.popitem(last=False)


class MeshFacesInput:
    """The triangle sets received on mesh_faces (``known``), for the meshes that name theirs by id.

    A MeshFaces message whose triangles are not what its id names is refused (``rejected.bad_mesh_faces``)
    and the sets already known stay. What is known outlives a deactivate (the triangles of an id never change).

    Args:
        node: The reading ManagedNode (its ``diagnostics``, logger).
    """

    def __init__(self, node: Any) -> None:
        self.node = node
        self.diagnostics = node.diagnostics
        self.get_logger = node.get_logger  # rejects_bad_input logs through it
        self.known = KnownMeshFaces()

    def subscribe(self) -> None:
        """Subscribe (activate; the base class destroys the subscription on deactivate)."""
        self.node.create_subscription(MeshFaces, MESH_FACES, self.on_message, latched_mesh_faces_qos())

    @rejects_bad_input(BAD_MESH_FACES)
    def on_message(self, msg: MeshFaces) -> None:
        if msg.faces_id in self.known:
            return
        faces = self.known.add(msg.faces_id, np.frombuffer(msg.faces, dtype=np.uint32) if len(msg.faces) else ())
        self.node.get_logger().info(f"mesh faces {msg.faces_id!r} of model {msg.model_id!r}: {len(faces)} triangles")
