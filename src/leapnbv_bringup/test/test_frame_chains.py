"""The mixed-frame check over recorded `inputs` (leapnbv_bringup.frame_chains): chains the graph records for one
frame pass; an input of another frame anywhere on the chain, a carry too old or from the future, fail; a chain
with an output not received cannot be checked."""

from __future__ import annotations

import pytest

from leapnbv_bringup.frame_chains import (
    CARRIED,
    EXCLUSION_HINT,
    SAME_FRAME,
    STATIC,
    ChainVerdict,
    check_goal_chain,
)

FRAME = 1_700_000_000_500_000_000
BEFORE = FRAME - 100_000_000  # 0.1 s earlier
MAX_CARRY = 500_000_000  # nbv_node's ground_max_age_s, 0.5 s


def graph_records(frame: int = FRAME, plane: int = FRAME, mesh_depth: int = FRAME) -> dict:
    """What the five nodes record for one frame, as tests/test_frame_timing_graph.py sees it."""
    return {
        "view_candidates": {frame: [("target_geometry", frame, SAME_FRAME), ("ground_plane", plane, SAME_FRAME),
                                    ("human_mesh_metric", frame, SAME_FRAME)]},
        "target_geometry": {frame: [("human_mesh", frame, SAME_FRAME), ("depth", mesh_depth, SAME_FRAME),
                                    ("depth/camera_info", frame, SAME_FRAME), ("ground_plane", plane, SAME_FRAME)]},
        "ground_plane": {plane: [("depth", plane, SAME_FRAME), ("depth/camera_info", plane, SAME_FRAME),
                                 ("detections", plane, SAME_FRAME), ("person_mask", BEFORE, EXCLUSION_HINT)]},
        "human_mesh": {frame: [("image", frame, SAME_FRAME), ("detections", frame, SAME_FRAME),
                               ("camera_info", BEFORE, STATIC)]},
    }


def test_one_frames_chain_passes_with_hints_and_static_inputs_of_other_stamps() -> None:
    assert check_goal_chain(graph_records(), FRAME, MAX_CARRY) == ChainVerdict(True, False, "")


def test_another_frames_input_anywhere_on_the_chain_is_found() -> None:
    plane = check_goal_chain(graph_records(plane=BEFORE), FRAME, MAX_CARRY)
    assert plane.verifiable and plane.mixed
    assert plane.detail == f"view_candidates used ground_plane of stamp {BEFORE} (frame {FRAME})"
    # Two levels down: the target geometry's depth frame.
    depth = check_goal_chain(graph_records(mesh_depth=BEFORE), FRAME, MAX_CARRY)
    assert depth == ChainVerdict(True, True, f"target_geometry used depth of stamp {BEFORE} (frame {FRAME})")
    # Three levels down: the mesh's image.
    records = graph_records()
    records["human_mesh"][FRAME][0] = ("image", BEFORE, SAME_FRAME)
    assert check_goal_chain(records, FRAME, MAX_CARRY).detail == \
        f"human_mesh used image of stamp {BEFORE} (frame {FRAME})"


def test_a_carried_plane_passes_within_the_carry_and_fails_beyond_it_or_from_the_future() -> None:
    views = {FRAME: [("target_geometry", FRAME, SAME_FRAME), ("ground_plane", BEFORE, CARRIED),
                     ("camera_pose", BEFORE, CARRIED), ("camera_pose", FRAME, SAME_FRAME)]}
    records = dict(graph_records(), view_candidates=views)
    # The carried plane's own record is of another frame and is not followed.
    del records["ground_plane"]
    records["target_geometry"][FRAME].pop()
    assert check_goal_chain(records, FRAME, MAX_CARRY) == ChainVerdict(True, False, "carried ground_plane,camera_pose")
    assert check_goal_chain(records, FRAME, 50_000_000) == ChainVerdict(
        True, True, f"view_candidates carried ground_plane of stamp {BEFORE} (frame {FRAME})")
    views[FRAME][1] = ("ground_plane", FRAME + 1, CARRIED)
    assert check_goal_chain(records, FRAME, MAX_CARRY).mixed
    views[FRAME][1] = ("ground_plane", FRAME, CARRIED)  # "carried" from its own frame: not a carry
    assert check_goal_chain(records, FRAME, MAX_CARRY).mixed


@pytest.mark.parametrize("missing", ["view_candidates", "target_geometry", "ground_plane", "human_mesh"])
def test_a_chain_with_an_output_not_received_cannot_be_checked(missing: str) -> None:
    records = graph_records()
    del records[missing]
    verdict = check_goal_chain(records, FRAME, MAX_CARRY)
    assert verdict == ChainVerdict(False, False, f"{missing} of stamp {FRAME} not received")


def test_the_relations_are_the_messages() -> None:
    msg = pytest.importorskip("leapnbv_msgs.msg")
    assert (SAME_FRAME, CARRIED, EXCLUSION_HINT, STATIC) == (
        msg.InputStamp.SAME_FRAME, msg.InputStamp.CARRIED, msg.InputStamp.EXCLUSION_HINT, msg.InputStamp.STATIC)
