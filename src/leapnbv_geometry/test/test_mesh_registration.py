"""Tests of leapnbv_geometry.mesh_registration on scenes rendered with the rasterizer."""

from __future__ import annotations

import time
from typing import Optional

import numpy as np
import pytest
import trimesh

from leapnbv_geometry.mesh_registration import register_for_frame, register_mesh_to_depth
from leapnbv_geometry.raster import rasterize_mesh
from leapnbv_geometry.target_geometry import compute_target_geometry

WIDTH, HEIGHT = 640, 480
K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])
Z_PERSON = 3.0
PERSON, WALL, OCCLUDER, FLOOR = 0, 1, 2, 3


def box_mesh(centre, extents) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=extents)
    box.apply_translation(centre)
    return box


def person_mesh(x: float = 0.0, z: float = Z_PERSON) -> trimesh.Trimesh:
    """Torso, head, legs, arms: y from -0.73 (head top) to 0.89 (feet), about 0.24 m deep."""
    return trimesh.util.concatenate([
        box_mesh((x, -0.2, z), (0.40, 0.60, 0.24)),
        box_mesh((x, -0.62, z), (0.18, 0.22, 0.18)),
        box_mesh((x - 0.1, 0.5, z), (0.14, 0.78, 0.14)),
        box_mesh((x + 0.1, 0.5, z), (0.14, 0.78, 0.14)),
        box_mesh((x - 0.27, -0.15, z), (0.10, 0.60, 0.10)),
        box_mesh((x + 0.27, -0.15, z), (0.10, 0.60, 0.10)),
    ])


def render(occluder_top: Optional[float] = None):
    """The person at 3 m, a wall 1.5 m behind, a floor 1 m below the camera (and an occluder).

    When ``occluder_top`` is given, a 1.6 m wide panel 1 m in front of the person reaches from
    that height down to the floor.

    Returns:
        (depth, object id image, person mesh)
    """
    person = person_mesh()
    meshes = [person, box_mesh((0.0, 0.0, Z_PERSON + 1.5), (10.0, 4.0, 0.05))]
    if occluder_top is not None:
        meshes.append(box_mesh((0.0, 0.5 * (occluder_top + 1.0), Z_PERSON - 1.0), (1.6, 1.0 - occluder_top, 0.05)))
    else:
        meshes.append(box_mesh((0.0, 0.0, -50.0), (0.1, 0.1, 0.1)))  # behind the camera: not drawn
    floor = trimesh.Trimesh(np.array([[-20, 1.0, 0.2], [20, 1.0, 0.2], [20, 1.0, 30.0], [-20, 1.0, 30.0]]),
                            [[0, 1, 2], [0, 2, 3]], process=False)
    meshes.append(floor)
    ids = np.concatenate([np.full(len(m.faces), i, dtype=np.int32) for i, m in enumerate(meshes)])
    scene = trimesh.util.concatenate(meshes)
    result = rasterize_mesh(scene.vertices, scene.faces, K, WIDTH, HEIGHT, face_object_id=ids)
    return result.depth, result.object_id, person


def silhouette_box(vertices, faces):
    rows, cols = np.nonzero(rasterize_mesh(vertices, faces, K, WIDTH, HEIGHT).silhouette)
    return (float(cols.min()), float(rows.min()), float(cols.max()), float(rows.max()))


@pytest.mark.parametrize("depth_error", [-0.3, -0.2, 0.2, 0.4])
def test_heavy_occlusion_recovers_the_person_depth(depth_error):
    depth, object_id, person = render(occluder_top=-0.2)
    silhouette = rasterize_mesh(person.vertices, person.faces, K, WIDTH, HEIGHT).silhouette
    occluded = np.count_nonzero(silhouette & (object_id == OCCLUDER)) / np.count_nonzero(silhouette)
    assert 0.7 <= occluded <= 0.8  # precondition: the occluder is the majority inside the silhouette
    estimate = person.vertices * (1.0 + depth_error)  # same image, depth off by depth_error
    box = silhouette_box(person.vertices, person.faces)

    result = register_mesh_to_depth(estimate, person.faces, depth, K, box)

    assert result.ok, result.reason
    true_z = person.vertices[:, 2].mean()
    assert abs(result.vertices[:, 2].mean() - true_z) < 0.05
    assert abs(result.scale * (1.0 + depth_error) - 1.0) < 0.05 / Z_PERSON
    assert result.residual < 0.05
    assert 0.15 < result.inlier_share < 0.35  # the visible share, not the occluder's


def test_clean_view_registers_the_whole_silhouette():
    depth, _, person = render()
    box = silhouette_box(person.vertices, person.faces)
    result = register_mesh_to_depth(person.vertices * 0.75, person.faces, depth, K, box)
    assert result.ok, result.reason
    assert abs(result.vertices[:, 2].mean() - person.vertices[:, 2].mean()) < 0.02
    assert result.inlier_share > 0.9
    assert result.residual < 0.02
    assert result.depth_shift == pytest.approx((result.scale - 1.0) * 0.75 * person.vertices[:, 2].mean())


def test_background_only_is_refused():
    depth, _, _ = render()
    nobody = person_mesh(x=1.6)  # where only the wall and the floor are
    box = silhouette_box(nobody.vertices, nobody.faces)
    result = register_mesh_to_depth(nobody.vertices, nobody.faces, depth, K, box)
    assert not result.ok  # the wall spills past the silhouette; a floor patch has too small a share
    np.testing.assert_array_equal(result.vertices, nobody.vertices)


def test_too_few_pixels_and_box_outside_are_refused():
    depth, _, person = render()
    box = silhouette_box(person.vertices, person.faces)
    no_depth = np.zeros_like(depth)
    assert "silhouette pixels" in register_mesh_to_depth(person.vertices, person.faces, no_depth, K, box).reason
    outside = register_mesh_to_depth(person.vertices, person.faces, depth, K, (900, 900, 950, 950))
    assert not outside.ok and "outside" in outside.reason


def test_registration_timing():
    depth, _, person = render(occluder_top=-0.2)
    box = silhouette_box(person.vertices, person.faces)
    register_mesh_to_depth(person.vertices * 1.3, person.faces, depth, K, box)
    times = []
    for _ in range(20):
        start = time.perf_counter()
        register_mesh_to_depth(person.vertices * 1.3, person.faces, depth, K, box)
        times.append((time.perf_counter() - start) * 1e3)
    print(f"register_mesh_to_depth: median {np.median(times):.2f} ms, max {max(times):.2f} ms (small mesh)")


class _Params:
    registration_enabled = True
    box_dilation_px = 10.0
    registration_inlier_band = 0.15
    registration_min_inlier_share = 0.1
    registration_max_residual = 0.1
    registration_max_spill = 0.5
    min_depth = 0.1
    max_depth = 10.0


def test_registered_mesh_makes_the_target_and_a_refused_one_none():
    depth, object_id, person = render(occluder_top=-0.2)
    box = silhouette_box(person.vertices, person.faces)
    estimate = person.vertices * 1.4
    frame = register_for_frame(estimate, person.faces, depth, K, box, _Params())
    assert frame.refused_reason == "" and frame.depth_offset == 0.0
    target = compute_target_geometry(frame.vertices, person.faces, depth, K, box, depth_offset=frame.depth_offset,
                                     mesh_raster=frame.raster)
    assert target.valid and target.depth_offset == 0.0
    # The mask is the person's visible pixels: none of the occluder's, nor the wall's.
    assert np.all(object_id[target.mask] == PERSON)
    assert abs(target.centroid[2] - Z_PERSON) < 0.15
    assert abs(frame.depth_shift - (Z_PERSON - estimate[:, 2].mean())) < 0.05
    # The scaled render is the render of the registered mesh.
    fresh = rasterize_mesh(frame.vertices, person.faces, K, WIDTH, HEIGHT)
    np.testing.assert_array_equal(fresh.silhouette, frame.raster.silhouette)
    np.testing.assert_allclose(fresh.depth, frame.raster.depth, atol=1e-4)

    nobody = person_mesh(x=1.6)
    refused = register_for_frame(nobody.vertices, nobody.faces, depth, K, silhouette_box(nobody.vertices, nobody.faces),
                                 _Params())
    assert refused.refused_reason.startswith("mesh not registered")
    empty = compute_target_geometry(refused.vertices, nobody.faces, depth, K, box,
                                    refused_reason=refused.refused_reason)
    assert not empty.valid and empty.invalid_reason == refused.refused_reason
    assert empty.target_points.shape == (0, 3) and empty.background_points.shape[0] > 0

    off = _Params()
    off.registration_enabled = False
    unchanged = register_for_frame(estimate, person.faces, depth, K, box, off)
    assert unchanged.vertices is estimate and unchanged.depth_offset is None and unchanged.summary == "off"
