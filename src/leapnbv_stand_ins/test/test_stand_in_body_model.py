"""Tests for the stand-in body model: SMPL-X layout, closed surfaces, sensible skinning."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from leapnbv_stand_ins.stand_in_body_model import (
    FULL_NUM_FACES,
    FULL_NUM_VERTICES,
    SMPLX_PARENTS,
    build_stand_in_body_model,
    write_stand_in_body_model,
)


@pytest.fixture(scope="module", params=["small", "full"])
def arrays(request: pytest.FixtureRequest) -> dict:
    return dict(build_stand_in_body_model(request.param), resolution=request.param)


def test_counts(arrays: dict) -> None:
    vertices, faces = arrays["v_template"], arrays["f"]
    if arrays["resolution"] == "full":
        assert vertices.shape == (FULL_NUM_VERTICES, 3) and faces.shape == (FULL_NUM_FACES, 3)
    else:
        assert 1000 <= len(vertices) <= 3000
    num_vertices = len(vertices)
    assert arrays["shapedirs"].shape == (num_vertices, 3, 20)
    assert arrays["posedirs"].shape == (num_vertices, 3, 486)
    assert arrays["J_regressor"].shape == (55, num_vertices)
    assert arrays["weights"].shape == (num_vertices, 55)
    assert arrays["hands_componentsl"].shape == (45, 45)


def test_closed_consistently_oriented_outward(arrays: dict) -> None:
    vertices, faces = arrays["v_template"], arrays["f"].astype(np.int64)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    keys = edges[:, 0] * len(vertices) + edges[:, 1]
    reverse = edges[:, 1] * len(vertices) + edges[:, 0]
    assert len(np.unique(keys)) == len(keys)  # no directed edge twice: consistent winding
    assert np.all(np.isin(reverse, keys))  # every edge has its twin: closed
    corners = vertices[faces]
    volume = np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum() / 6.0
    assert 0.05 < volume < 0.12  # m^3, outward normals (a person is ~0.07 m^3)
    assert len(np.unique(faces)) == len(vertices) - 1  # exactly one interior vertex


def test_proportions(arrays: dict) -> None:
    vertices = arrays["v_template"]
    height = vertices[:, 1].max() - vertices[:, 1].min()
    assert 1.6 < height < 1.85
    assert abs(vertices[:, 0].max() + vertices[:, 0].min()) < 1e-9  # left/right symmetric
    joints = arrays["J_regressor"] @ vertices
    assert np.linalg.norm(joints[0]) < 0.05  # pelvis near the origin
    assert joints[15, 1] > joints[12, 1] > joints[9, 1] > 0.0 > joints[4, 1] > joints[7, 1]  # y up
    assert joints[16, 0] > 0.0 > joints[17, 0]  # left is +x
    assert joints[23, 2] > joints[15, 2]  # eyes in front: facing +z


def test_skinning_and_regressor_rows(arrays: dict) -> None:
    np.testing.assert_allclose(arrays["weights"].sum(axis=1), 1.0, atol=1e-9)
    assert arrays["weights"].min() >= 0.0
    np.testing.assert_allclose(arrays["J_regressor"].sum(axis=1), 1.0, atol=1e-9)
    parents = arrays["kintree_table"][0].astype(np.int64)
    assert parents[0] == 4294967295 and list(parents[1:]) == list(SMPLX_PARENTS[1:])
    # Joints follow the body shape (height direction moves the head joint up).
    shaped = arrays["v_template"] + arrays["shapedirs"][:, :, 0]
    assert (arrays["J_regressor"] @ shaped)[15, 1] > (arrays["J_regressor"] @ arrays["v_template"])[15, 1] + 0.01


def test_expression_moves_only_the_face(arrays: dict) -> None:
    moved = np.linalg.norm(arrays["shapedirs"][:, :, 10:], axis=(1, 2)) > 0
    assert np.count_nonzero(moved) > 10
    assert np.all(arrays["v_template"][moved, 1] > 0.55)


def test_write_is_loadable_without_pickle(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "stand_in.npz"
    write_stand_in_body_model(str(path), "small")
    with np.load(path, allow_pickle=False) as archive:
        assert archive["v_template"].shape[1] == 3
        assert "not SMPL-X" in str(archive["stand_in"])
    assert [p.name for p in path.parent.iterdir()] == ["stand_in.npz"]  # no temporary left
