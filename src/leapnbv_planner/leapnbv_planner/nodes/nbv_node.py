"""nbv_node: TargetGeometry + the frame's GroundPlane -> ViewCandidates, next-best-view goal, markers.

The computation is :func:`leapnbv_planner.plan.plan_views`; this node unpacks the messages, waits
for the frame's ground plane, calls it, and publishes. Its parameters are the fields of
:func:`leapnbv_planner.params.nbv_params_class` (defaults, ranges, read-only flags there); a runtime
``ros2 param set`` is validated and applies to the next plan.

One frame, one set of inputs: a target is planned with the ground plane of its own frame (same
stamp: ground_node stamps a plane with its frame's, the colour image's, stamp), waited for at most
``ground_wait_s``. When that plane never comes (or is not valid), the newest
valid plane of an older frame (at most ``ground_max_age_s`` older) is carried into the frame by the
camera-pose delta between the two stamps, when the camera pose of both is known; otherwise the
frame is dropped (``rejected.ground_plane_late`` / ``rejected.no_ground_plane``;
:mod:`leapnbv_planner.nodes.nbv_inputs`). ViewCandidates list what they used (``inputs``).

Latest-frame scheduling: the target subscription keeps the newest message only, a target waiting
for its plane is superseded once a newer one is planned, a frame older than one already planned
is dropped, and a frame already older than ``max_goal_age_s`` is dropped before planning; every drop
is counted on /diagnostics (``dropped.<reason>``).

No stale goal: next_best_view / base_goal are published only when the frame is younger than
``max_goal_age_s`` by the node clock at publish time. ``goal_status`` (GoalStatus, latched) says
whether the latched goal may be acted on (CURRENT), and a timer replaces a goal that ages out by
an explicit "no goal" (:mod:`leapnbv_planner.nodes.latched_goal`).

Optional inputs: ``obstacle_map`` (PointCloud2 of occupied voxel centres in a fixed frame, latched,
as a mapping stack publishes it) and the camera pose (from the ``camera_pose_source``, by default
the ``camera_pose`` PoseStamped topic: the camera's optical frame in that fixed frame, stamped with
each camera frame). With both, the map's obstacles join the footprint test and S_o counts only
target points whose line of sight crosses free map space: furniture the current view cannot see
still keeps the robot from choosing a view behind it. A frame waits at most ``camera_pose_wait_s``
for its pose; without one (or without a map) the node plans from the frame alone.
Goal commitment (``commit_*``, :mod:`leapnbv_planner.nodes.goal_commitment`): next_best_view carries the
committed goal, replaced only for a reason goal_status names; ViewCandidates' ``chosen_index`` stays the
plan's own choice (a kept goal is no ring candidate).
The target (:mod:`leapnbv_planner.nodes.target_status`): every goal_status carries hmr_node's newest
TargetTrack; a change of it is said at once, a lost target withdraws the goal (STALE, "target lost"), and a
new target (another track_id) ends the commitment to the goal planned around the previous one.
"""
from __future__ import annotations

import time
from typing import List, Optional, Set

from visualization_msgs.msg import MarkerArray

from leapnbv_common import topics
from leapnbv_common.camera_pose import create_camera_pose_source
from leapnbv_common.conversions import arrays_to_view_candidates, ground_plane_to_arrays, target_geometry_to_arrays
from leapnbv_common.managed_node import ManagedNode, managed_node_main
from leapnbv_common.mesh_faces_topic import MeshFacesInput
from leapnbv_common.pulled_input import PulledInput
from leapnbv_common.qos import stage_input_qos, stage_output_qos
from leapnbv_common.stage import Companion, Frame, KeyInput, Received, Stage
from leapnbv_msgs.msg import GroundPlane, HumanMesh, InputStamp, TargetGeometry, TargetTrack, ViewCandidates
from leapnbv_planner.inputs import PlanInputs
from leapnbv_planner.nodes.goal_commitment import NodeCommitment, decision_path_frames, scores_changed
from leapnbv_planner.nodes.latched_goal import LatchedGoal
from leapnbv_planner.nodes.markers import candidate_markers
from leapnbv_planner.nodes.nbv_inputs import FrameFloor, ObstacleMapInput, ObstacleMemoryInput, body_mesh_arrays
from leapnbv_planner.nodes.target_status import TargetTrackInput
from leapnbv_planner.obstacle_map import warm_up_obstacle_map
from leapnbv_planner.params import PlannerParams, nbv_params_class
from leapnbv_planner.plan import plan_views
from leapnbv_planner.requirements import BODY_MESH, Requirement
from leapnbv_planner.score_terms.base import declared_requirements, get_term, missing_requirement_detail
from leapnbv_planner.scoring import warm_up_scoring

PLANE_CACHE = 30  # ground planes remembered by stamp (to pair, and to carry an older one)
BODY_MESH_CACHE = 30  # body meshes (and frames waiting for theirs) remembered by stamp


class NbvNode(ManagedNode):
    def __init__(self) -> None:
        super().__init__("nbv_node", nbv_params_class())

    def configure_stage(self) -> None:
        p = self.params.value
        self.candidates_pub = self.create_lifecycle_publisher(ViewCandidates, topics.VIEW_CANDIDATES,
                                                              stage_output_qos())
        self.goal = LatchedGoal(self)
        self.markers_pub = self.create_lifecycle_publisher(MarkerArray, topics.MARKERS, stage_output_qos())
        warm_up_scoring()  # compile the kernels before subscribing: the graph is ready only after it
        warm_up_obstacle_map()
        # Optional: the robot's map of static obstacles and the camera's pose in that map per frame. Without
        # them the planner sees only what the frame shows.
        self.obstacle_map = ObstacleMapInput(self)
        self.obstacle_memory = ObstacleMemoryInput(self)  # without a map: the one the frames build on the way
        self.mesh_faces = MeshFacesInput(self)  # the triangles the metric meshes name by id
        self.commitment = NodeCommitment(self)
        self.target = TargetTrackInput(self, self.target_changed)
        self.goal.target = self.target.current  # every goal_status carries the newest TargetTrack
        # The target starts the work (the newest only); it takes the plane of its own frame (waited for),
        # its camera pose while a map or the commitment is in use (DDS does not order topics: waited for briefly)
        # and its metric body mesh while a chosen term reads it (BODY_MESH) and some node publishes them.
        self.stage = Stage(self, KeyInput("target_geometry", TargetGeometry, topics.TARGET_GEOMETRY,
                                          target_geometry_to_arrays, stage_input_qos(1), bad_reason="bad_target",
                                          frame_name="target", accept=self.accept_target), [
            Companion("ground_plane", GroundPlane, topics.GROUND_PLANE, ground_plane_to_arrays,
                      stage_input_qos(PLANE_CACHE), wait_s=lambda f: self.params.value.ground_wait_s,
                      capacity=PLANE_CACHE),
            Companion("camera_pose", lookup=self.frame_camera_pose,
                      needed=lambda f: self.commitment.needs_pose(self.map_in_use()),
                      wait_s=lambda f: self.commitment.pose_wait_s(self.map_in_use()),
                      expect=lambda f: self.camera_poses.expect(f.stamp_ns, f.header.frame_id)),
            Companion(topics.HUMAN_MESH_METRIC, HumanMesh, topics.HUMAN_MESH_METRIC,
                      lambda msg: body_mesh_arrays(msg, self.mesh_faces.known),
                      stage_input_qos(5), needed=lambda f: self.terms_need(BODY_MESH),
                      wait_s=self.body_mesh_wait_s, missing_reason="no_body_mesh",
                      missing_detail=lambda f: "no metric body mesh of this frame: body_occlusion scored the observed"
                      " points", capacity=BODY_MESH_CACHE, bad_reason="bad_body_mesh"),
        ], self.plan, capacity=PLANE_CACHE)
        # The camera poses also carry an older ground plane into a frame whose own plane never came. They
        # come at camera rate and are pulled when a frame needs one (leapnbv_common.pulled_input); the source is
        # released on cleanup.
        self.camera_poses = self.owned(create_camera_pose_source(
            p.camera_pose_source, self, p.camera_pose_cache, lambda pose: self.stage.companion_arrived("camera_pose")))
        self.stage.add_pulled(PulledInput.adopt(self, self.camera_poses))  # None for a source without one
        self.frame_floor = FrameFloor(self, self.camera_poses)

    def activate_stage(self) -> None:
        if self.params.value.use_obstacle_map:
            self.obstacle_map.subscribe()
        self.mesh_faces.subscribe()
        self.target.subscribe()
        self.stage.start()
        self.diagnostics.await_publishers(topics.TARGET_GEOMETRY, topics.GROUND_PLANE)
        self.goal.start()

    def deactivate_stage(self) -> None:
        self.stage.stop()
        self.goal.stop()
        self.commitment.clear()  # a goal committed before is no goal of the next activation
        self.obstacle_memory.forget()

    def on_params_change(self, new: PlannerParams, changed: Set[str]) -> None:
        """Rebuild what depends on changed parameters (everything else is read at each plan)."""
        self.obstacle_memory.params_changed(changed)
        if "obstacle_map_resolution" in changed:
            self.obstacle_map.rebuild(new.obstacle_map_resolution)  # a grid too large: the change is refused
        if changed & {"max_goal_age_s", "hidden_target_goal_hold_s"}:
            self.goal.limit_changed(new.max_goal_age_s)
        if scores_changed(changed):
            self.commitment.clear()  # the committed goal's score is no longer comparable with the new ones

    def target_changed(self, track: TargetTrack, previous: Optional[TargetTrack]) -> None:
        """Say the target's change on goal_status now; a lost target withdraws the goal, another person ends the
        commitment (the goal was planned around the previous one)."""
        if previous is not None and track.track_id != previous.track_id:
            self.commitment.clear()
        self.goal.target_changed(lost=track.reason if track.state == TargetTrack.STATE_LOST else "")

    def terms_need(self, requirement: Requirement) -> bool:
        """Whether a chosen score term reads this requirement with the current parameters (the node waits only for
        inputs a term reads)."""
        terms = [get_term(name) for name in self.params.value.score_terms]
        return requirement.name in declared_requirements(terms, self.params.value)

    def body_mesh_wait_s(self, frame: Frame) -> float:
        """Wait for a body mesh only while some node publishes them (the graph's raster_node): else none comes."""
        if self.count_publishers(topics.HUMAN_MESH_METRIC) == 0:
            return 0.0
        return float(self.params.value.body_mesh_wait_s)

    def map_in_use(self) -> bool:
        """Whether frames are planned with a map: the robot's, or the obstacle memory."""
        return self.obstacle_map.in_use() or self.obstacle_memory.in_use()

    def frame_camera_pose(self, frame: Frame) -> Optional[Received]:
        pose = self.camera_poses.pose_at(frame.stamp_ns, frame.header.frame_id)
        return None if pose is None else self.commitment.seen(Received(pose.stamp_ns, frame.header, pose))

    def accept_target(self, target: Received) -> Optional[str]:
        """Drop a frame that is already too old for a goal before any work (a drop reason, or None)."""
        return "too_old_to_plan" if self.goal.too_old(target.stamp_ns) else None

    def plan(self, frame: Frame) -> None:
        started = time.perf_counter()
        target: TargetGeometry = frame.key.message
        stamp = frame.stamp_ns
        if self.goal.too_old(stamp):
            self.diagnostics.drop("too_old_to_plan")
            return
        if not target.valid:
            self.diagnostics.reject("empty_target", "no person points in this frame: no goal")
            return
        floor = self.frame_floor(frame)
        if floor is None:
            return
        inputs: List[tuple] = [("target_geometry", stamp), *floor[1]]
        body_mesh = frame[topics.HUMAN_MESH_METRIC]
        planned_without = {}  # optional inputs in use that this frame lacks (goal_status says so)
        if body_mesh is not None:
            inputs.append((topics.HUMAN_MESH_METRIC, stamp))
        elif self.terms_need(BODY_MESH) and self.count_publishers(topics.HUMAN_MESH_METRIC) > 0:
            planned_without[topics.HUMAN_MESH_METRIC] = "no metric body mesh of this frame: " + \
                missing_requirement_detail(BODY_MESH, self.params.value)
        camera_pose, without_map = self.obstacle_map.camera_pose_for(frame, self.camera_poses)
        obstacle_map = self.obstacle_map.map if camera_pose is not None else None
        if without_map:
            planned_without["obstacle_map"] = without_map
        elif self.obstacle_memory.in_use():
            camera_pose, obstacle_map, without_memory = self.obstacle_memory.take(frame, frame["target_geometry"])
            if without_memory:
                planned_without["obstacle_memory"] = without_memory
        fixed_pose = self.commitment.camera_pose(frame)  # the committed goal's fixed frame
        if (camera_pose is not None or fixed_pose is not None) \
                and ("camera_pose", stamp, InputStamp.SAME_FRAME) not in inputs:
            inputs.append(("camera_pose", stamp))
        if camera_pose is not None and obstacle_map is self.obstacle_map.map:
            inputs.append(("obstacle_map", self.obstacle_map.stamp_ns, InputStamp.STATIC))
        elif obstacle_map is not None:
            inputs.append(("obstacle_memory", stamp))  # built up to and with this frame
        plan = plan_views(PlanInputs(frame["target_geometry"], floor[0], self.params.value, obstacle_map, camera_pose,
                                     body_mesh, extra_foot_points=self.commitment.extra_foot_points(fixed_pose)))
        decision = self.commitment.update(plan, fixed_pose, stamp)
        compute_time_ms = (time.perf_counter() - started) * 1e3
        # The goal first (what the motion stack waits for), then the candidates, the path and the markers.
        goal_published = self.goal.publish_decision(target.header, stamp, decision, planned_without)
        out = arrays_to_view_candidates(plan.to_arrays(), target.header, compute_time_ms, inputs=inputs)
        self.candidates_pub.publish(out)
        if goal_published:
            self.goal.publish_path(decision_path_frames(plan, decision), target.header)
        if self.markers_pub.get_subscription_count() > 0:  # built and sent only while RViz / Foxglove listens
            self.markers_pub.publish(candidate_markers(target.header, out, plan))
        self.diagnostics.frame_out(target.header.stamp, out.compute_time_ms)


main = managed_node_main(NbvNode)  # the console script (leapnbv_common.managed_node: the process tuned, then run)


if __name__ == "__main__":
    main()
