"""The nbv node's parameters: one dataclass, the one source of every default, range and description.

The defaults are the values the robot runs with. The ring and feasibility code
(:mod:`leapnbv_planner.candidates`) takes its values from :class:`CandidateRingParams`, the first
fields of the node's parameters, so there is no second set of defaults.

The weight of each score term is a parameter ``weight_<name>`` (``weight_visibility``, ...) that is
made from the term registry (:mod:`leapnbv_planner.score_terms`): :func:`nbv_params_class` returns
:class:`PlannerParams` extended by one float field per registered term, default = the term's
default weight. A new term module therefore brings its weight parameter with it.

Read-only (set at start-up only): ``use_obstacle_map`` (decides whether the obstacle map is used),
``camera_pose_source`` and ``camera_pose_cache`` (make the camera-pose subscription and its
cache). Every other parameter can be changed at runtime and applies to the next plan.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Dict, List, Tuple, Type

from leapnbv_common.params import ParamsError, StageParams, param
from leapnbv_planner.requirements import REQUIREMENTS
from leapnbv_planner.score_terms import get_term, registered_terms, weight_parameter
from leapnbv_planner.score_terms.visibility import VISIBILITY_POINTS

# The deployed score terms, in summation order: non-occlusion over the whole metric body mesh
# (body_occlusion), which rewards a view of the hidden side; the paper's S_o over the observed points
# ("occlusion") stays registered (docs/ALGORITHMS.md, the family benchmark compares both). travel (weight
# 0.05) breaks near-ties toward the shorter drive: on 50 furnished scenes it cut the mean straight-line
# drive from 3.2 to 2.1 m at the same coverage.
DEFAULT_SCORE_TERMS = ["visibility", "area", "body_occlusion", "travel"]
# S_v stays the paper's (over the observed points) until the closed loop shows the body-mesh count is better:
# the regression goldens and every measured table were made with it (docs/ALGORITHMS.md, S_v).
DEFAULT_VISIBILITY_POINTS = "observed"


@dataclass
class CandidateRingParams:
    """Parameters of the candidate ring and of the feasibility test (the first nbv node parameters)."""

    num_candidates: int = param(16, "viewpoints on the ring (the current view is added as candidate 0)",
                                min=1, max=256)
    # 2.5 m, not the published 1.5 m: at 1.5 m a 42 deg vertical field of view (RealSense colour at
    # 640x480) sees only ~1.2 m of height, so a standing person never fits.
    radius: float = param(2.5, "metres: ring radius around the target, on the ground", min=0.1, max=20.0)
    include_current: bool = param(True, "score the current view as candidate 0, so staying is possible")
    # 6 m, as max_path_length: with 4.5 m the far side of a person in a corridor (about 5-6 m away, and
    # the only view past the occluder) was out of range although a free path reached it.
    max_travel: float = param(6.0, "metres: farthest foot point from the robot's current one (straight line)",
                              min=0.0, max=100.0)
    robot_radius: float = param(0.3, "metres: footprint radius checked for obstacles", min=0.0, max=5.0)
    floor_clearance: float = param(0.05, "metres: background points higher than this above the floor are obstacles",
                                   min=0.0, max=2.0)
    camera_height: float = param(0.0, "metres: the candidates' camera height above the floor (the robot's mounting); "
                                 "0 = the current camera's, from the ground plane (or the camera pose)", min=0.0,
                                 max=10.0)
    camera_tilt: str = param("look_at", "look_at: each candidate camera aims at the target (a pan-tilt head); fixed: "
                             "it turns toward the target and keeps the current camera's pitch", choices=("look_at",
                                                                                                       "fixed"))
    num_rings: int = param(3, "rings of candidates, radii evenly from min_radius to radius (1: radius only)",
                           min=1, max=8)
    min_radius: float = param(1.5, "metres: radius of the innermost ring when num_rings > 1", min=0.1, max=20.0)
    reachability: bool = param(True, "a candidate must be reached by a free path on the floor grid (obstacles "
                               "inflated by robot_radius) of at most max_path_length")
    max_path_length: float = param(6.0, "metres: longest path to a reachable candidate (also the travel term's "
                                   "scale)", min=0.1, max=100.0)
    fit_to_free_space: bool = param(True, "with reachability: a ring candidate in an obstacle or without a path moves "
                                    "to the nearest free, reachable foot point of its patch: radius within its ring's "
                                    "band (down to the next inner ring; the innermost down to min_free_radius), "
                                    "bearing within half the angle between candidates")
    min_free_radius: float = param(1.0, "metres: the nearest to the target a candidate moved by fit_to_free_space "
                                   "may stand", min=0.1, max=20.0)
    grid_resolution: float = param(0.1, "metres: cell edge of the floor grid of the path search", min=0.02,
                                   max=1.0)
    unknown_space: str = param("free", "floor cells outside the current view's field of view: free or occupied "
                               "for the path search", choices=("free", "occupied"))


@dataclass
class CommitmentParams:
    """The goal commitment's parameters (:mod:`leapnbv_planner.commitment`; nbv node parameters, all live)."""

    commit_goals: bool = param(True, "keep the published goal across plans, in the fixed frame of the camera pose,"
                               " re-scored from each view, until another view beats it by commit_margin, it becomes"
                               " infeasible or unreachable, the person moves past commit_person_moved_m or the"
                               " current view is as good; off (or a frame without a camera pose): each plan's"
                               " choice is the goal")
    # 0.02: the two best views of bags/sample_a change places with a score difference that moves by at most
    # 0.0047 from one frame to the next (largest gap 0.0042); 0.02 is four times that, the evaluation's min_gain
    # (the least predicted gain worth a move), and 2.4 % more of the body's facing surface in view (weight 0.83).
    commit_margin: float = param(0.02, "score: how much more than the committed goal (re-scored from the current"
                                 " view) another view must score to replace it; staying is as good when the"
                                 " current view scores within it of the committed goal and of the best view",
                                 min=0.0, max=1.0)
    # 0.05: a plan without an obstacle map (nor the obstacle memory) knows only the furniture its frame shows, and
    # the drive shows more: its scores of the committed goal and the rivals move as the robot goes. In the
    # furnished rooms without the map at 0.02, half of the goal switches came from rivals 0.020-0.035 above the
    # committed goal (seed 31: 11 switches in 30 s, no arrival); 0.05 (6 % more of the facing surface) took
    # success from 87.5 to 95 % there. With the map, 0.05 lost corridor views that were 0.03 better (85 %
    # against 92.5 %), so the map's plans keep commit_margin.
    commit_margin_without_map: float = param(0.05, "score: commit_margin for a plan made without an obstacle map"
                                             " (no map and no obstacle memory in the plan): its scores move as the"
                                             " drive shows furniture the frame did not", min=0.0, max=1.0)
    # 0.5 m: a second at a slow walk; the person's floor position (the ring centre) jitters by 4.5 cm at most
    # over bags/sample_a's frames.
    commit_person_moved_m: float = param(0.5, "metres: how far the person's floor position may move from where it"
                                         " was at the commit before the goal is planned anew", min=0.0, max=10.0)
    # 0.6 s: three frames at the evaluation's 5 Hz. A passage one grid cell wider than the robot (beside a person
    # in a 1.6-2.4 m corridor) closes for one frame in five or so as the grid shifts under the moving robot
    # (corridor seed 10: 18 switches in 15 s without it); a real obstacle costs this long on the old path.
    commit_blocked_s: float = param(0.6, "seconds: a committed goal found infeasible or unreachable is kept on its"
                                    " last path this long before it is replaced (KEPT_BLOCKED); 0: at once",
                                    min=0.0, max=10.0)
    # 5 s and 1 m: in a corridor the way past the occluder closed for seconds as the robot turned toward it (the
    # occluder came into view) and opened as it turned away; the far-side views beat the near goal right back, and
    # the robot went to and fro (corridor seed 16: 28 switches in 30 s). 1 m covers the neighbouring candidates.
    commit_dropped_s: float = param(5.0, "seconds: after a committed goal is dropped as infeasible or unreachable,"
                                    " a view within commit_dropped_radius_m of it does not replace the goal by the"
                                    " margin for this long (0: off)", min=0.0, max=60.0)
    commit_dropped_radius_m: float = param(1.0, "metres: how near a dropped goal a view is refused (commit_dropped_s)",
                                           min=0.0, max=10.0)
    commit_same_goal_m: float = param(0.25, "metres: a view whose foot point is this near the committed goal's is"
                                      " the same goal and never replaces it (0.25: Nav2's default xy goal"
                                      " tolerance)", min=0.0, max=5.0)


@dataclass
class PlannerParams(CandidateRingParams, CommitmentParams, StageParams):
    """Every nbv node parameter but the term weights (see nbv_params_class for the full class).

    The goal commitment's (``commit_*``, :class:`CommitmentParams`) are among them.
    """

    score_terms: List[str] = param(DEFAULT_SCORE_TERMS, "score terms summed into the score, in this order"
                                   " (registered in leapnbv_planner.score_terms; weight of each: weight_<name>)")
    score_infeasible: bool = param(False, "score every candidate, also those the robot cannot take (to look at their"
                                   " terms); off: infeasible candidates are not scored and carry score 0")
    delta_px: float = param(4.0, "pixels: neighbourhood of the background depth test in S_o", min=0.0, max=100.0)
    # DEFAULT_VISIBILITY_POINTS below says why.
    visibility_points: str = param(DEFAULT_VISIBILITY_POINTS, "what S_v counts: body_mesh: the share of the "
                                   "metric body mesh's vertices (the whole predicted body) in the candidate's image"
                                   " and depth range, the observed points when the frame has no mesh; observed: the"
                                   " share of the target points the current view saw (the paper's S_v)",
                                   choices=VISIBILITY_POINTS)
    # 0.1 and 10 m: raster_node's min_depth / max_depth, the depths the graph takes person points from.
    visibility_min_depth: float = param(0.1, "metres: S_v over the body mesh counts a vertex only at this camera"
                                        " depth (z) or farther", min=0.0, max=100.0)
    visibility_max_depth: float = param(10.0, "metres: S_v over the body mesh counts a vertex only at this camera"
                                        " depth (z) or nearer", min=0.01, max=100.0)
    ground_wait_s: float = param(0.5, "s: how long a frame waits for the ground plane of its depth frame; then an"
                                 " older frame's plane carried by the camera-pose delta, or the frame is dropped"
                                 " (never planned with another frame's plane as it is)", min=0.0, max=10.0)
    ground_max_age_s: float = param(0.5, "s: the oldest plane (stamp difference) that may be carried into a frame"
                                    " by the camera-pose delta when the frame's own plane did not come; 0 = never"
                                    " carry", min=0.0, max=60.0)
    max_goal_age_s: float = param(1.0, "s: next_best_view / base_goal are published only for a frame younger than"
                                  " this (node clock at publish time), and a published goal that grows older is"
                                  " replaced by 'no goal' (goal_status STALE); 0 = no limit (only for offline"
                                  " runs whose stamps are not the clock's: regression, evaluation)",
                                  min=0.0, max=60.0)
    hidden_target_goal_hold_s: float = param(3.0, "s: while hmr_node reports the target NOT_SEEN (out of view, not "
                                             "yet lost), a CURRENT goal may be this much older than max_goal_age_s "
                                             "before it is withdrawn (valid_until says so): the drive to it passes "
                                             "behind furniture that hides the person, and no frame can be planned "
                                             "until they are seen again; a LOST target withdraws it at once; 0 = "
                                             "the plain age limit", min=0.0, max=60.0)
    use_obstacle_map: bool = param(True, "use the robot's obstacle map (obstacle_map + camera_pose topics) when"
                                   " they arrive", read_only=True)
    obstacle_map_resolution: float = param(0.1, "metres: voxel edge of the obstacle map (its points are voxel"
                                           " centres)", min=0.01, max=2.0)
    max_obstacle_voxels: int = param(200_000, "occupied voxels an obstacle map may have; a larger one is refused"
                                     " (rejected.obstacle_map_too_large) and the previous map kept (200,000: a"
                                     " 40 x 40 m floor's walls and furniture at 0.1 m; a map of millions is a"
                                     " mapping fault, and each costs memory and time per plan)",
                                     min=1, max=100_000_000)
    obstacle_memory: bool = param(False, "while no obstacle map is in use: plan with a map built from the frames' "
                                  "background points and camera poses (leapnbv_planner.obstacle_memory; obstacles "
                                  "seen on the way enter the plan); false forgets it")
    obstacle_memory_half_life_s: float = param(20.0, "s: the obstacle memory's evidence halves in this much of the "
                                               "frames' time (what is not seen again fades)", min=0.1, max=3600.0)
    obstacle_memory_max_voxels: int = param(50_000, "voxels the obstacle memory keeps at most (the weakest go first)",
                                            min=1, max=10_000_000)
    map_max_target_points: int = param(1500, "target points whose line of sight is walked through the map, per"
                                       " candidate", min=1, max=1_000_000)
    map_target_margin: float = param(0.1, "metres: the end of each line of sight, at the target, not checked in"
                                     " the map", min=0.0, max=2.0)
    camera_pose_wait_s: float = param(0.1, "s: a frame planned with the obstacle map waits this long for its camera"
                                      " pose (DDS does not order topics); then it is planned without the map",
                                      min=0.0, max=10.0)
    body_mesh_wait_s: float = param(0.2, "s: with body_occlusion scored and a human_mesh_metric publisher, a frame "
                                    "waits this long for its metric body mesh (raster_node publishes it with the "
                                    "target), then is scored on the observed points", min=0.0, max=10.0)
    camera_pose_source: str = param("topic", "where the camera pose of each frame comes from (a key of"
                                    " leapnbv_common.camera_pose.CAMERA_POSE_SOURCES)", read_only=True)
    camera_pose_cache: int = param(150, "camera poses remembered by stamp, to find the pose of each planned frame"
                                   " (150: 5 s at 30 Hz, longer than any frame's way through the graph)",
                                   min=1, max=10_000, read_only=True)

    def check(self) -> None:
        """Rules between fields: the score terms are registered, distinct, each has its weight and its requirements are
        registered; the rings; S_v's depth range."""
        if not self.visibility_min_depth < self.visibility_max_depth:
            raise ParamsError(f"visibility_min_depth ({self.visibility_min_depth}) must be below visibility_max_depth"
                              f" ({self.visibility_max_depth})")
        if self.num_rings > 1 and not self.min_radius < self.radius:
            raise ParamsError(f"min_radius ({self.min_radius}) must be below radius ({self.radius}) with "
                              f"num_rings = {self.num_rings}")
        if not self.score_terms:
            raise ParamsError("score_terms must name at least one score term")
        known = {term.name for term in registered_terms()}
        for name in self.score_terms:
            if name not in known:
                raise ParamsError(f"score_terms: unknown score term {name!r}; registered: {sorted(known)}")
            if not hasattr(self, weight_parameter(name)):
                raise ParamsError(f"score_terms: {name!r} has no {weight_parameter(name)} parameter in"
                                  f" {type(self).__name__} (registered after the class was made)")
            missing = sorted(need for need in get_term(name).requires if need not in REQUIREMENTS)
            if missing:
                raise ParamsError(f"score_terms: {name!r} needs the requirements {missing}, which are not registered;"
                                  f" registered: {REQUIREMENTS.names()}")
        duplicates = sorted({name for name in self.score_terms if self.score_terms.count(name) > 1})
        if duplicates:
            raise ParamsError(f"score_terms: {duplicates} listed more than once")

    def term_weights(self) -> List[Tuple[str, float]]:
        """(name, weight) of each term in score_terms, in order."""
        return [(name, float(getattr(self, weight_parameter(name)))) for name in self.score_terms]


_CLASSES: Dict[Tuple[Tuple[str, float, str], ...], Type[PlannerParams]] = {}


def nbv_params_class() -> Type[PlannerParams]:
    """The nbv node's params dataclass: PlannerParams plus ``weight_<name>`` for each registered term.

    Made once per set of registered terms (so repeated calls give the same class); a term
    registered later gets its field in the class made after it.
    """
    key = tuple((term.name, term.default_weight, term.description) for term in registered_terms())
    if key not in _CLASSES:
        weights = [(weight_parameter(name), float,
                    param(float(default), f"weight of {description}", min=0.0))
                   for name, default, description in key]
        _CLASSES[key] = dataclasses.make_dataclass(
            "NbvParams", weights, bases=(PlannerParams,),
            namespace={"__module__": __name__, "__doc__": "Every nbv node parameter (see nbv_params_class)."})
    return _CLASSES[key]


def default_nbv_params() -> PlannerParams:
    """The robot's values: an instance of nbv_params_class() with every default."""
    return nbv_params_class()()
