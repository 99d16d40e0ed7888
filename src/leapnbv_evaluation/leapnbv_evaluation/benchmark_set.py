"""The benchmark set of synthetic scenes used by the evaluation: seeds, room config, the scene of a seed.

The set is an endless, fixed sequence of seeds: the committed :data:`BENCHMARK_SEEDS` first (the
tables in the README use their first 50), then every later seed that qualifies
(:func:`select_benchmark_seeds`'s rule), in ascending order. :func:`benchmark_seeds` gives any
slice of it without generating a scene while the slice stays below :data:`VERIFIED_BELOW`
(the seeds there that do not qualify are committed in :data:`UNQUALIFIED_SEEDS`); beyond, it
checks the seeds with the body model.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Dict, FrozenSet, List, Optional

from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_sim.generation import SceneConfig, generate_scene
from leapnbv_sim.scene import Scene, SceneError

#: The scene config of the benchmark (its seed is replaced per scene): the defaults plus 2-4
#: pieces of furniture (shelves, cabinets, standing screens; 0.4-1.2 m wide, 0.8-2.0 m tall) at
#: 0.6-2.0 m around the person, off the start camera's line of sight, as in a furnished room.
#: Without them every viewpoint but the start one sees the person unhindered.
BENCHMARK_CONFIG = SceneConfig(clutter_count_range=(2, 4))

#: Seeds whose scenes (BENCHMARK_CONFIG, stand-in body at "small" resolution) meet the starting
#: occluder share range 0.20-0.60 and show at least MIN_PERSON_PIXELS person pixels in the
#: start view. Produced once by ``select_benchmark_seeds(64, small_model, BENCHMARK_CONFIG)``;
#: do not edit by hand. (The height bisection in generate_scene makes nearly every seed
#: qualify, and the clutter keeps off the start view's line of sight, so this is a contiguous
#: run, the same as without clutter.)
BENCHMARK_SEEDS: List[int] = [
    0,
    1,
    2,
    3,
    4,
    5,
    6,
    7,
    8,
    9,
    10,
    11,
    12,
    13,
    14,
    15,
    16,
    17,
    18,
    19,
    20,
    21,
    22,
    23,
    24,
    25,
    26,
    27,
    28,
    29,
    30,
    31,
    32,
    33,
    34,
    35,
    36,
    37,
    38,
    39,
    40,
    41,
    42,
    43,
    44,
    45,
    46,
    47,
    48,
    49,
    50,
    51,
    52,
    53,
    54,
    55,
    56,
    57,
    58,
    59,
    60,
    61,
    62,
    63,
]

#: A start view must show at least this many person pixels (else the detector has nothing).
MIN_PERSON_PIXELS = 1500

#: Every seed from the last committed one up to here was checked with ``select_benchmark_seeds``
#: (BENCHMARK_CONFIG, small stand-in body) ...
VERIFIED_BELOW = 2104
#: ... and these are the ones that do not qualify (left out of the set).
UNQUALIFIED_SEEDS: FrozenSet[int] = frozenset()

#: Rooms of the benchmark: "furnished" (BENCHMARK_CONFIG) or "open" (no furniture; the seeds
#: qualify under both, the furniture keeps off the start view's line of sight) ...
BASE_ROOMS = ("furnished", "open")

#: ... and the families, each a change of BENCHMARK_CONFIG with its own committed seeds
#: (FAMILY_SEEDS): the room's walls (corner, corridor, near a wall: no furniture, the walls are the
#: obstacles), the starting occlusion, the person's distance, the robot's camera height (the ground
#: node's mounting priors follow it: FAMILY_GRAPH_PARAMETERS), the depth noise, and the people
#: (leapnbv_sim.people; each the furnished room of its seed with the people added): "two_people" (a
#: bystander standing 0.6-1.5 m from the target, in the start view), "three_people" (that bystander and
#: a passer-by walking across the line of sight between the robot and the target at 0.5-1.0 m/s),
#: "walking" (the target walks 0.8-2.0 m at 0.2-0.5 m/s after turning to face its way; one scene in
#: three it only turns in place).
FAMILY_CHANGES: Dict[str, Dict[str, Any]] = {
    "corner": {"room_layout": "corner", "clutter_count_range": (0, 0)},
    "corridor": {"room_layout": "corridor", "clutter_count_range": (0, 0)},
    "near_wall": {"room_layout": "near_wall", "clutter_count_range": (0, 0)},
    "heavy_occlusion": {"occluder_share_range": (0.60, 0.80)},
    "far": {"person_distance_range": (4.0, 6.0)},
    "camera_0.6": {"camera_height_range": (0.6, 0.6)},
    "camera_1.8": {"camera_height_range": (1.8, 1.8)},
    "noise_3x": {"noise": "3x"},
    "two_people": {"bystanders": 1},
    "three_people": {"bystanders": 1, "passers_by": 1},
    "walking": {"target_motion": "walk"},
}
ROOMS = BASE_ROOMS + tuple(FAMILY_CHANGES)

#: Graph parameters a family's robot sets (its camera's mounting height: the ground node's priors).
FAMILY_GRAPH_PARAMETERS: Dict[str, List[str]] = {
    "camera_0.6": ["ground_node.min_camera_height=0.3", "ground_node.max_camera_height=0.9"],
    "camera_1.8": ["ground_node.min_camera_height=1.5", "ground_node.max_camera_height=2.1"],
}

#: The first 40 qualifying seeds of each family (``select_benchmark_seeds(40, small_model,
#: family_config(0, family))``, produced once by ``scripts/experiments/family_seeds.py``; do not edit by hand).
FAMILY_SEEDS: Dict[str, List[int]] = {
    "corner": [
        0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25, 26,
        27, 28, 29, 30, 31, 32, 33, 34, 35, 36, 37, 38, 39
    ],
    "corridor": [
        0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25, 26,
        27, 28, 29, 30, 31, 32, 33, 34, 35, 36, 37, 38, 39
    ],
    "near_wall": [
        0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25, 26,
        27, 28, 29, 30, 31, 32, 33, 34, 35, 36, 37, 38, 39
    ],
    "heavy_occlusion": [
        0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 16, 17, 18, 19, 20, 21, 22, 24, 25, 26, 27, 28,
        29, 30, 31, 32, 33, 34, 35, 36, 37, 38, 39, 40, 41
    ],
    "far": [
        0, 1, 2, 3, 4, 6, 7, 8, 9, 10, 11, 12, 13, 14, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25, 26, 27, 28,
        29, 30, 31, 32, 33, 34, 35, 36, 37, 38, 39, 40, 41
    ],
    "camera_0.6": [
        0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25, 26,
        27, 28, 29, 30, 31, 32, 33, 34, 35, 36, 37, 38, 39
    ],
    "camera_1.8": [
        0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25, 26,
        27, 28, 29, 30, 31, 32, 33, 34, 35, 36, 37, 38, 39
    ],
    "noise_3x": [
        0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25, 26,
        27, 28, 29, 30, 31, 32, 33, 34, 35, 36, 37, 38, 39
    ],
    "two_people": [
        0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25, 26,
        27, 28, 29, 30, 31, 32, 33, 34, 35, 36, 37, 38, 39
    ],
    # A seed whose occluders leave the passer-by no free crossing gives no scene (generate_scene raises).
    "three_people": [
        1, 2, 4, 5, 6, 7, 8, 10, 11, 12, 13, 19, 21, 24, 26, 28, 39, 40, 41, 45, 47, 49, 50, 54, 55, 57, 59,
        62, 63, 68, 70, 74, 75, 76, 78, 84, 87, 88, 90, 91
    ],
    "walking": [
        0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25, 26,
        27, 28, 29, 30, 31, 32, 33, 34, 35, 36, 37, 38, 39
    ],
}


def checked_seed_count() -> int:
    """How many seeds of the sequence are known without generating a scene (those below VERIFIED_BELOW)."""
    later = range(BENCHMARK_SEEDS[-1] + 1, VERIFIED_BELOW)
    return len(BENCHMARK_SEEDS) + sum(1 for seed in later if seed not in UNQUALIFIED_SEEDS)


def benchmark_seeds(count: int, offset: int = 0, body_model: Optional[SMPLXModel] = None) -> List[int]:
    """Seeds ``[offset, offset + count)`` of the benchmark sequence (deterministic for any count).

    Args:
        count: How many seeds, >= 1.
        offset: How many seeds of the sequence to skip first, >= 0.
        body_model: The small stand-in body model; needed only for seeds at or past
            VERIFIED_BELOW (each is generated to check it qualifies).

    Returns:
        The seeds, ascending; the first ``len(BENCHMARK_SEEDS)`` of the sequence are the committed ones.

    Raises:
        ValueError: ``count`` < 1, ``offset`` < 0, or the slice reaches past VERIFIED_BELOW without a body model.
    """
    if count < 1 or offset < 0:
        raise ValueError(f"benchmark seeds need count >= 1 and offset >= 0, got count {count}, offset {offset}")
    wanted = offset + count
    seeds = list(BENCHMARK_SEEDS[:wanted])
    seed = BENCHMARK_SEEDS[-1] + 1
    while len(seeds) < wanted and seed < VERIFIED_BELOW:
        if seed not in UNQUALIFIED_SEEDS:
            seeds.append(seed)
        seed += 1
    if len(seeds) < wanted:
        if body_model is None:
            raise ValueError(f"{wanted} benchmark seeds reach past the checked ones (below {VERIFIED_BELOW}): "
                             "give the body model to check the rest")
        seeds += select_benchmark_seeds(wanted - len(seeds), body_model, first_seed=max(seed, VERIFIED_BELOW),
                                        max_seed=max(seed, VERIFIED_BELOW) + 100 * wanted)
    return seeds[offset:wanted]


def benchmark_config(seed: int, room: str = "furnished") -> SceneConfig:
    """The scene config of one benchmark seed in a room.

    "furnished": BENCHMARK_CONFIG; "open": no furniture; a family of FAMILY_CHANGES:
    BENCHMARK_CONFIG with the family's changes.

    Raises:
        ValueError: An unknown room.
    """
    if room not in ROOMS:
        raise ValueError(f"room must be one of {ROOMS}, got {room!r}")
    if room in BASE_ROOMS:
        clutter = BENCHMARK_CONFIG.clutter_count_range if room == "furnished" else (0, 0)
        return dataclasses.replace(BENCHMARK_CONFIG, seed=int(seed), clutter_count_range=clutter)
    changes = dict(FAMILY_CHANGES[room])
    if changes.get("noise") == "3x":
        noise = BENCHMARK_CONFIG.noise
        changes["noise"] = dataclasses.replace(noise, sigma_quadratic_per_m=3 * noise.sigma_quadratic_per_m,
                                               sigma_constant_m=3 * noise.sigma_constant_m)
    return dataclasses.replace(BENCHMARK_CONFIG, seed=int(seed), **changes)


def room_seeds(room: str, count: int, offset: int = 0, body_model: Optional[SMPLXModel] = None) -> List[int]:
    """Seeds [offset, offset + count) of a room.

    The benchmark sequence for "furnished" / "open", a family's committed FAMILY_SEEDS (then, past
    them, the family's next qualifying seeds, checked with ``body_model``).

    Raises:
        ValueError: an unknown room, a bad count or offset, or seeds past the committed ones without a body model.
    """
    if room in BASE_ROOMS:
        return benchmark_seeds(count, offset, body_model)
    if room not in FAMILY_CHANGES:
        raise ValueError(f"room must be one of {ROOMS}, got {room!r}")
    if count < 1 or offset < 0:
        raise ValueError(f"room seeds need count >= 1 and offset >= 0, got count {count}, offset {offset}")
    seeds = list(FAMILY_SEEDS.get(room, []))
    if len(seeds) < offset + count:
        if body_model is None:
            raise ValueError(f"{offset + count} seeds of {room} reach past the {len(seeds)} committed ones: give "
                             "the body model to find the rest")
        first = seeds[-1] + 1 if seeds else 0
        seeds += select_benchmark_seeds(offset + count - len(seeds), body_model, benchmark_config(0, room),
                                        first_seed=first, max_seed=first + 100 * (offset + count))
    return seeds[offset:offset + count]


def benchmark_scene(seed: int, body_model: SMPLXModel, room: str = "furnished") -> Scene:
    """The scene of one benchmark seed (see :func:`benchmark_config`)."""
    return generate_scene(benchmark_config(seed, room), body_model)


def select_benchmark_seeds(
    n: int,
    body_model: SMPLXModel,
    base_config: Optional[SceneConfig] = None,
    first_seed: int = 0,
    max_seed: int = 100_000,
) -> List[int]:
    """Find the first ``n`` seeds whose generated scene is usable as a benchmark case.

    A seed is kept when :func:`generate_scene` succeeds (its starting occluder share lies in
    the config's range) and the start view shows at least :data:`MIN_PERSON_PIXELS` person
    pixels.

    Args:
        n: How many seeds.
        body_model: The stand-in body model (``SMPLXModel``) the set is made for.
        base_config: Config whose seed is replaced; :data:`BENCHMARK_CONFIG` if None.
        first_seed: First seed tried.
        max_seed: Give up after this seed.

    Returns:
        The seeds, ascending.

    Raises:
        SceneError: Fewer than ``n`` seeds qualify below ``max_seed``.
    """
    config = base_config if base_config is not None else BENCHMARK_CONFIG
    seeds: List[int] = []
    seed = first_seed
    while len(seeds) < n:
        if seed > max_seed:
            raise SceneError(f"only {len(seeds)} of {n} benchmark seeds found up to seed {max_seed}")
        try:
            scene = generate_scene(dataclasses.replace(config, seed=seed), body_model)
        except SceneError:
            seed += 1
            continue
        frame = scene.render()
        if frame.ground_truth.person_pixel_count >= MIN_PERSON_PIXELS:
            seeds.append(seed)
        seed += 1
    return seeds


def load_benchmark_scenes(
    n: int,
    body_model: SMPLXModel,
    base_config: Optional[SceneConfig] = None,
) -> List[Scene]:
    """Generate the first ``n`` scenes of the benchmark set.

    Args:
        n: How many scenes.
        body_model: The stand-in body model (``SMPLXModel``).
        base_config: Config whose seed is replaced; :data:`BENCHMARK_CONFIG` if None (the
            config the seeds were selected under: keep it for comparable numbers).

    Returns:
        The scenes, in seed order.
    """
    config = base_config if base_config is not None else BENCHMARK_CONFIG
    return [generate_scene(dataclasses.replace(config, seed=seed), body_model)
            for seed in benchmark_seeds(n, body_model=body_model)]
