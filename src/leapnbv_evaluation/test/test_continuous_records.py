"""What a continuous episode records about a wrong-person frame (leapnbv_evaluation.continuous.box_place_people)."""
from __future__ import annotations

import numpy as np
import pytest

from leapnbv_evaluation.benchmark_set import FAMILY_SEEDS, benchmark_scene
from leapnbv_evaluation.continuous import box_place_people, person_ids
from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_stand_ins.stand_in_body_model import build_stand_in_body_model


@pytest.fixture(scope="module")
def body_model() -> SMPLXModel:
    return SMPLXModel(build_stand_in_body_model("small"), source="stand_in_small")


def test_each_persons_box_has_a_place_that_is_their_own_pixels_where_they_stand(body_model: SMPLXModel) -> None:
    scene = benchmark_scene(FAMILY_SEEDS["two_people"][0], body_model, "two_people")
    frame = scene.render()
    ids = np.asarray(frame.object_id)
    boxes, people = [], []
    for person in person_ids(scene):
        rows, cols = np.nonzero(ids == person)
        if rows.size > 2000:  # people well in view: their visible pixels' box, as the ground-truth detector draws it
            boxes.append([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1, 1.0])
            people.append(person)
    assert len(people) == 2
    records = box_place_people(scene, frame, np.array(boxes, dtype=np.float64))
    camera = frame.camera_pose
    for person, record in zip(people, records):
        places, layers = record[:-1], record[-1]["layers"]
        own = [place for place in places if place["person"] == person]
        assert own, (person, record)
        # Where the person's own pixels are, on the floor, in the world (their visible points' median).
        rows, cols = np.nonzero((ids == person) & (frame.depth_m > 0))
        z = frame.depth_m[rows, cols].astype(np.float64)
        k = frame.K
        points = np.column_stack([(cols - k[0, 2]) * z / k[0, 0], (rows - k[1, 2]) * z / k[1, 1], z])
        points = points @ camera.rotation.T + camera.position
        assert np.hypot(*(np.array(own[0]["xy"]) - np.median(points[:, :2], axis=0))) < 0.4
        assert any(layer[4] == person and not layer[3] for layer in layers)  # their layer, not behind a filler
