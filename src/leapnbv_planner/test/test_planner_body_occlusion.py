"""Tests of the body_occlusion term: S_o over the whole body mesh rewards the view that reveals the hidden part."""
from __future__ import annotations

import numpy as np
import pytest

from leapnbv_planner.candidates import camera_look_at
from leapnbv_planner.plan import mesh_vertex_normals
from leapnbv_planner.requirements import SurfacePoints
from leapnbv_planner.scoring import score_candidates

K = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])
UP = np.array([0.0, -1.0, 0.0])
CENTRE = np.array([0.0, 0.3, 3.0])


def sphere(radius=0.3, rings=24, segments=48):
    """A closed UV sphere about CENTRE (vertices, faces)."""
    theta = np.linspace(0.0, np.pi, rings + 1)[1:-1]
    phi = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    body = np.column_stack([np.sin(t).ravel() * np.cos(p).ravel(), np.cos(t).ravel(),
                            np.sin(t).ravel() * np.sin(p).ravel()])
    vertices = np.vstack([[0.0, 1.0, 0.0], body, [0.0, -1.0, 0.0]]) * radius + CENTRE
    faces = []
    top, bottom = 0, len(vertices) - 1
    index = lambda r, s: 1 + r * segments + s % segments  # noqa: E731
    for s in range(segments):
        faces.append([top, index(0, s + 1), index(0, s)])
        faces.append([bottom, index(rings - 2, s), index(rings - 2, s + 1)])
        for r in range(rings - 2):
            faces.append([index(r, s), index(r, s + 1), index(r + 1, s)])
            faces.append([index(r, s + 1), index(r + 1, s + 1), index(r + 1, s)])
    return vertices, np.array(faces)


def test_vertex_normals_point_outward():
    vertices, faces = sphere()
    normals = mesh_vertex_normals(vertices, faces)
    radial = (vertices - CENTRE) / np.linalg.norm(vertices - CENTRE, axis=1, keepdims=True)
    assert np.min(np.sum(normals * radial, axis=1)) > 0.95
    flipped = mesh_vertex_normals(vertices, faces[:, ::-1])  # the other winding: still outward
    np.testing.assert_allclose(flipped, normals, atol=1e-12)
    with pytest.raises(ValueError, match="face indices"):
        mesh_vertex_normals(vertices, faces + len(vertices))


def test_the_whole_body_score_prefers_the_view_that_reveals_the_hidden_half():
    vertices, faces = sphere()
    normals = mesh_vertex_normals(vertices, faces)
    # A screen at 2 m hides the lower half (image down = +y) from the current camera.
    xs, ys = np.meshgrid(np.linspace(-0.6, 0.6, 121), np.linspace(0.3, 1.2, 91))
    screen = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, 2.0)])
    # The current view's target points: only the upper half is observed (what the depth camera shows).
    toward = np.sum(normals * (-vertices), axis=1) > 0
    observed = vertices[toward & (vertices[:, 1] < 0.3)]
    side_position = np.array([2.5, 0.0, 3.0])
    rotations = np.stack([np.eye(3), camera_look_at(side_position, CENTRE, UP)])
    positions = np.stack([np.zeros(3), side_position])
    terms = [("occlusion", 1.0), ("body_occlusion", 1.0)]
    scores = score_candidates(observed, screen, rotations, positions, K, 640, 480, terms,
                              given={"body_mesh": SurfacePoints(vertices, normals)})
    paper, body = scores.term("occlusion"), scores.term("body_occlusion")
    assert paper[0] > 0.95  # the paper's S_o: what is observed is unhidden, staying looks perfect
    assert body[0] < 0.75  # the lower part of the near side is behind the screen
    assert body[1] > 0.95 and body[1] > body[0] + 0.3  # the side view sees the whole near side
    # Without a mesh the term is the paper's S_o.
    plain = score_candidates(observed, screen, rotations, positions, K, 640, 480, terms)
    np.testing.assert_array_equal(plain.term("body_occlusion"), plain.term("occlusion"))
