"""Was a goal computed from one camera frame? The check over the `inputs` the graph's outputs record.

Every HumanMesh, TargetGeometry, GroundPlane and ViewCandidates lists the stamps of what it used
(`leapnbv_msgs/InputStamp`: name, stamp, relation). A goal's chain starts at the ViewCandidates of
its stamp and follows each SAME_FRAME input that is itself a stage output of the graph
(target_geometry, ground_plane, human_mesh) to that output's own record. The goal is from mixed
frames when, anywhere on the chain, a SAME_FRAME input carries another stamp than the goal's, or a
CARRIED input is not older than the goal by at most the allowed carry (nbv_node's
`ground_max_age_s`). EXCLUSION_HINT and STATIC inputs are allowed to be of other stamps.

ROS-free: the records are plain `(name, stamp_ns, relation)` tuples, as
`leapnbv_common.conversions.input_stamps` returns them, kept per output name and stamp by whoever
listened to the graph (the load benchmark, the frame-timing tests).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Mapping, Sequence, Set, Tuple

# InputStamp relations by value (leapnbv_msgs/InputStamp.msg; test_frame_chains.py checks them against
# the message), so this module needs no message package.
SAME_FRAME = 0
CARRIED = 1
EXCLUSION_HINT = 2
STATIC = 3

#: The output a goal's chain starts at: nbv_node's ViewCandidates of the goal's stamp.
CHAIN_START = "view_candidates"
#: Stage outputs whose own record the chain follows when an output lists them as a SAME_FRAME input.
FOLLOWED_OUTPUTS = ("target_geometry", "ground_plane", "human_mesh")
#: Outputs whose record must have been received for a goal to be checked at all.
REQUIRED_OUTPUTS = (CHAIN_START,) + FOLLOWED_OUTPUTS

InputRecord = Tuple[str, int, int]  # (input name, input stamp ns, relation)
#: output name -> stamp ns -> that output's recorded inputs.
OutputRecords = Mapping[str, Mapping[int, Sequence[InputRecord]]]


@dataclass(frozen=True)
class ChainVerdict:
    """What the recorded inputs say about one goal.

    Attributes:
        verifiable: False when an output on the chain was not received (nothing can be said).
        mixed: True when the chain used an input of another frame (see the module docstring).
        detail: for a mixed goal, which output used what; else the CARRIED inputs ("carried a,b")
            or "".
    """

    verifiable: bool
    mixed: bool
    detail: str = ""


def check_goal_chain(records: OutputRecords, stamp_ns: int, max_carry_ns: int) -> ChainVerdict:
    """Check that the goal of frame `stamp_ns` was computed from that frame's inputs only.

    Args:
        records: output name -> stamp -> recorded inputs (`(name, stamp_ns, relation)` tuples).
        stamp_ns: the goal's (its ViewCandidates') stamp.
        max_carry_ns: the largest age a CARRIED input may have (nbv_node's ground_max_age_s).

    Returns:
        ChainVerdict: unverifiable when an output on the chain is missing from `records`; mixed with
        the first offending input named; else clean, naming the CARRIED inputs used.
    """
    chain: List[Tuple[str, int]] = [(CHAIN_START, stamp_ns)]
    seen: Set[Tuple[str, int]] = set()
    carried: List[str] = []
    while chain:
        name, stamp = chain.pop()
        if (name, stamp) in seen:
            continue
        seen.add((name, stamp))
        inputs = records.get(name, {}).get(stamp)
        if inputs is None:
            if name in REQUIRED_OUTPUTS:
                return ChainVerdict(False, False, f"{name} of stamp {stamp} not received")
            continue
        for input_name, input_stamp, relation in inputs:
            if relation == SAME_FRAME and input_stamp != stamp_ns:
                return ChainVerdict(True, True, f"{name} used {input_name} of stamp {input_stamp} (frame {stamp_ns})")
            if relation == CARRIED:
                if not 0 < stamp_ns - input_stamp <= max_carry_ns:
                    return ChainVerdict(True, True,
                                        f"{name} carried {input_name} of stamp {input_stamp} (frame {stamp_ns})")
                carried.append(input_name)
                continue
            if relation == SAME_FRAME and input_name in FOLLOWED_OUTPUTS:
                chain.append((input_name, input_stamp))
    return ChainVerdict(True, False, "carried " + ",".join(carried) if carried else "")
