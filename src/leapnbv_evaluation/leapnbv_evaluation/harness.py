"""The evaluation's ROS session: the node graph (started once), an in-process simulator node, output collection.

The five-node graph runs as separate processes (``leapnbv_bringup.graph_runner``; ground-truth
perception with the small stand-in body by default). A
:class:`~leapnbv_sim.nodes.simulator_node.SimulatorNode` runs in this process with rate 0 and
publishes frames only when asked; a collector node files the graph's outputs under the frame of
their stamp (:class:`~leapnbv_evaluation.frame_outputs.FrameOutputs`). The session publishes a frame
and waits for the graph's answer (or for a certain failure), waits for goals and moves the robot;
what an episode does with that (the frames of a scene, the methods, the moves and when to stop) is
:mod:`leapnbv_evaluation.closed_loop`. With ``options.continuous`` the simulator runs its motion stack and
owns sim time (``/clock``; every graph node runs with ``use_sim_time`` and the deployed goal age limit) and
the episodes are :mod:`leapnbv_evaluation.continuous`'s (:meth:`ClosedLoopEvaluator.evaluate_continuous`).
"""
from __future__ import annotations

import time
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image

from leapnbv_bringup.graph import node_names
from leapnbv_bringup.graph_runner import (
    GraphError,
    GraphRunner,
    merge_overrides,
    parse_set_arguments,
    perception_overrides,
)
from leapnbv_bringup.runner_cli import sim_time_overrides
from leapnbv_common.conversions import stamp_to_ns
from leapnbv_common.power_monitor import PowerMonitor, start_power_monitor
from leapnbv_common.stage import WAIT_CHECK_PERIOD_S
from leapnbv_common.topics import (
    COLOR_INFO_TOPIC,
    DETECTIONS,
    GROUND_PLANE,
    GROUND_TRUTH_TOPIC,
    HUMAN_MESH,
    HUMAN_MESH_METRIC,
    NAMESPACE,
    NEXT_BEST_VIEW_TOPIC,
    PERSON_MASK,
    SCENE_PEOPLE_TOPIC,
    TARGET_GEOMETRY,
    TARGET_TRACK,
    VIEW_CANDIDATES,
    output_topic,
)
from leapnbv_evaluation.benchmark_set import FAMILY_GRAPH_PARAMETERS, benchmark_scene, room_seeds
from leapnbv_evaluation.closed_loop import ClosedLoopEpisodes, stay_where_the_graph_failed
from leapnbv_evaluation.continuous import ContinuousEpisodes, StatusRecord
from leapnbv_evaluation.continuous_results import ContinuousEpisode, ContinuousRun
from leapnbv_evaluation.episode import DEFAULT_METHOD, SCENE_STAMP_SPACING_NS, EvaluationError
from leapnbv_evaluation.frame_outputs import END_TO_END, STAGE_TOPICS, STAGES, FrameOutputs
from leapnbv_evaluation.options import EvaluationOptions
from leapnbv_evaluation.results import EvaluationRun, SceneResult
from leapnbv_msgs.msg import (
    GoalStatus,
    GroundPlane,
    HumanMesh,
    PersonDetections,
    TargetGeometry,
    TargetTrack,
    ViewCandidates,
)
from leapnbv_perception.smplx_layer import SMPLXModel
from leapnbv_sim.nodes.simulator_node import SimulatorNode, clock_publisher
from leapnbv_sim.poses import CameraPose, RobotModel
from leapnbv_sim.render import RenderedFrame
from leapnbv_sim.scene import Scene
from leapnbv_sim.simulator import DrivenRobot
from leapnbv_stand_ins.files import ensure_stand_in_body_model

#: Continuous lockstep: while a frame is in flight, sim time moves on by the stages' wait-check period (their timers
#: run on sim time: a companion that came after its frame is found only when one fires) every this many wall
#: seconds, but never to the next frame's stamp.
CLOCK_TICK_WALL_S = 0.05
#: A frame that ends early (no person, no target) waits at most this long, in wall seconds, for its target track.
FAILURE_RECORD_WAIT_S = 3.0

# The names callers import from here (the frame record and the options have their own modules).
__all__ = [
    "END_TO_END",
    "STAGES",
    "STAGE_TOPICS",
    "ClosedLoopEvaluator",
    "EvaluationOptions",
    "FrameOutputs",
    "simulator_parameters",
]


def simulator_parameters(publish_obstacle_map: bool = True, robot: Optional[RobotModel] = None,
                         continuous: bool = False) -> List[Parameter]:
    """The in-process simulator's parameters: frames only when asked, goals reached at once, the robot's motion.

    ``continuous``: the motion stack drives the robot instead, and the simulator publishes /clock.
    """
    robot = robot or RobotModel()
    return [Parameter("rate_hz", value=0.0), Parameter("move_speed_m_s", value=0.0),
            Parameter("publish_obstacle_map", value=bool(publish_obstacle_map)),
            Parameter("robot_motion", value=robot.motion), Parameter("robot_head", value=robot.head),
            Parameter("robot_camera_height", value=float(robot.camera_height)),
            Parameter("motion_stack", value=bool(continuous)), Parameter("publish_clock", value=bool(continuous))]


class ClosedLoopEvaluator:
    """The graph (started once), the in-process simulator node and an output collector.

    Use as a context manager; :meth:`evaluate` may be called several times (each call's stamps
    continue after the previous call's, so no node ever sees a stamp twice). It is the
    :class:`~leapnbv_evaluation.closed_loop.GraphSession` its episodes run through.

    Args:
        options: Perception, models, timeouts, the episode's rules.
    """

    def __init__(self, options: Optional[EvaluationOptions] = None) -> None:
        self.episodes = ClosedLoopEpisodes(self, options or EvaluationOptions())
        self.continuous_episodes = ContinuousEpisodes(self, self.episodes.options)
        self._next_stamp_ns = int(self.options.stamp_base_ns)
        self._started = False
        self._owns_rclpy = False
        self.runner: Optional[GraphRunner] = None
        self.sim: Optional[SimulatorNode] = None
        self.collector: Optional[Node] = None
        self.executor: Optional[SingleThreadedExecutor] = None
        self.frames: Dict[int, FrameOutputs] = {}
        #: Continuous lockstep: how far sim time ticked on (ns past the stamp) while each frame was in flight.
        self.clock_ticked_ns: Dict[int, int] = {}
        self._scene_body_model: Optional[SMPLXModel] = None
        self._subscriptions: Dict[str, Any] = {}
        self.ready_s: Optional[float] = None
        #: The board's power rails, sampled while the graph runs (None without rails: no J/frame then).
        self.power: Optional[PowerMonitor] = None

    @property
    def options(self) -> EvaluationOptions:
        """The run's options (the episodes read the same object)."""
        return self.episodes.options

    @options.setter
    def options(self, options: EvaluationOptions) -> None:
        self.episodes.options = options
        self.continuous_episodes.options = options

    @property
    def term_names(self) -> Optional[List[str]]:
        """The planner's score terms, from the first view candidates seen (the methods follow them)."""
        return self.episodes.term_names

    @property
    def methods(self) -> List[str]:
        """The methods of this run (the "<term>_only" baselines once the planner's terms are known)."""
        return self.episodes.methods

    # ------------------------------------------------------------------ lifecycle

    def __enter__(self) -> ClosedLoopEvaluator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def scene_body_model(self) -> SMPLXModel:
        """The body model scenes are generated with (loaded once)."""
        if self._scene_body_model is None:
            path = self.options.scene_body_model or ensure_stand_in_body_model("small")
            self._scene_body_model = SMPLXModel.load(path)
        return self._scene_body_model

    def _graph_overrides(self) -> Dict[str, Dict[str, str]]:
        o = self.options
        body = o.body_model or (ensure_stand_in_body_model("small") if not o.real_models else None)
        if o.detector_backend not in (None, o.perception, "ground_truth"):
            raise EvaluationError(f"--detector-backend {o.detector_backend!r}: the perception's "
                                  f"({o.perception!r}) or ground_truth")
        needs_detector = o.real_models and not o.detector_truth
        if o.real_models and not ((o.detector_model or not needs_detector) and o.hmr_model and o.body_model):
            raise EvaluationError("real perception needs --detector-model (unless --detector-backend ground_truth), "
                                  "--hmr-model and --body-model")
        # The map in use: the room's (the simulator publishes it), nbv_node's obstacle memory, or none.
        map_switch = [] if o.obstacle_map else ["nbv_node.use_obstacle_map=false"]
        if o.obstacle_memory:
            map_switch.append("nbv_node.obstacle_memory=true")
        if not o.continuous:  # simulated stamps, not the clock's: no goal age limit
            map_switch.append("nbv_node.max_goal_age_s=0.0")
        # Continuous: the graph runs on the simulator's clock, with the deployed staleness rules.
        sim_time = sim_time_overrides(node_names()) if o.continuous else {}
        robot = FAMILY_GRAPH_PARAMETERS.get(o.room, [])  # the family's robot (camera mounting), before --set
        detector = {"detector_node": {"backend": o.detector_backend}} if o.detector_backend else {}
        return merge_overrides(sim_time, perception_overrides(o.perception, o.detector_model, o.hmr_model, body),
                               detector, parse_set_arguments(map_switch + robot + list(o.set_parameters)))

    def start(self) -> None:
        """Start the graph's processes and the in-process nodes; wait until all are connected.

        Raises:
            EvaluationError: A node died or did not appear, or the topics did not connect.
        """
        overrides = self._graph_overrides()
        if not rclpy.ok():
            rclpy.init()
            self._owns_rclpy = True
        # The room's first committed seed (seed 0 of some families gives no scene: three_people).
        first_scene = self._load_scene(room_seeds(self.options.room, 1)[0])
        collector = self.collector = Node("leapnbv_evaluation")
        runner = self.runner = GraphRunner(self.options.params_file, overrides, log_dir=self.options.log_dir)
        self._started = True
        try:
            runner.start()
            self.ready_s = runner.wait_ready(collector, timeout_s=self.options.ready_timeout_s,
                                             spin=self._start_up_spin(collector))
        except GraphError as exc:
            raise EvaluationError(f"the graph did not start: {exc}") from exc
        sim = self.sim = SimulatorNode(scene=first_scene, parameter_overrides=simulator_parameters(
            self.options.obstacle_map, self.options.robot, self.options.continuous))
        self._subscribe_outputs(collector)
        executor = self.executor = SingleThreadedExecutor()
        executor.add_node(sim)
        executor.add_node(collector)
        self._wait_connected(sim)
        self.power, _ = start_power_monitor(clock=time.monotonic)
        # One throw-away frame: the first frame through fresh processes pays for imports and
        # caches; it must not count in the latency tables. Its candidates name the planner's terms.
        stamp = self._take_stamps(1)
        self.set_scene(first_scene)
        _, warm_up = self.run_frame(stamp)
        self.episodes.learn_terms(warm_up.candidates())
        if warm_up.view_candidates is not None and warm_up.view_candidates.chosen_index >= 0:
            self.wait_goal(stamp)  # consumed here, not rejected as stale by the first scene

    def _start_up_spin(self, collector: Node) -> Optional[Callable[[float], None]]:
        """Continuous: the collector's spin while the graph starts, with sim time running on /clock meanwhile.

        Every node's timers run on sim time; before the simulator's first frame no /clock would come, and a
        node's /diagnostics (a timer: what the readiness check reads, e.g. which inputs still lack a publisher)
        would stay at its first report. The clock runs with the wall clock, ending a second before the first
        frame's stamp. None: not continuous (rclpy's default spin).
        """
        if not self.options.continuous:
            return None
        publish = clock_publisher(collector)
        end_ns = int(self.options.stamp_base_ns) - 1_000_000_000
        start_ns, started = end_ns - 600_000_000_000, time.monotonic()

        def spin(timeout: float) -> None:
            rclpy.spin_once(collector, timeout_sec=timeout)
            publish(min(end_ns, start_ns + int((time.monotonic() - started) * 1e9)))

        return spin

    def stop(self) -> None:
        """Stop the graph's processes and the in-process nodes (safe to call twice)."""
        if self.power is not None:
            self.power.stop()
            self.power = None
        if self.runner is not None and self._started:
            self.runner.stop()
        self._started = False
        if self.executor is not None:
            self.executor.shutdown()
            self.executor = None
        for node in (self.sim, self.collector):
            if node is not None:
                node.destroy_node()
        self.sim = None
        self.collector = None
        if self._owns_rclpy:
            rclpy.try_shutdown()
            self._owns_rclpy = False

    def _load_scene(self, seed: int) -> Scene:
        return benchmark_scene(seed, self.scene_body_model(), self.options.room)

    def _simulator(self) -> SimulatorNode:
        if self.sim is None:
            raise EvaluationError("the evaluation is not started")
        return self.sim

    def _subscribe_outputs(self, collector: Node) -> None:
        topics = {DETECTIONS: PersonDetections, HUMAN_MESH: HumanMesh, TARGET_GEOMETRY: TargetGeometry,
                  GROUND_PLANE: GroundPlane, VIEW_CANDIDATES: ViewCandidates, PERSON_MASK: Image,
                  TARGET_TRACK: TargetTrack}  # the target track: a frame without the target's mesh ends early
        if self.options.real_models:
            topics[HUMAN_MESH_METRIC] = HumanMesh
        qos = QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE)
        for name, msg_type in topics.items():
            self._subscriptions[name] = collector.create_subscription(
                msg_type, output_topic(name), self._output_callback(name), qos)

    def _output_callback(self, name: str) -> Callable[[Any], None]:
        def on_output(msg: Any) -> None:
            self._on_output(name, msg)

        return on_output

    def _on_output(self, name: str, msg: Any) -> None:
        frame = self.frames.get(stamp_to_ns(msg.header.stamp))
        if frame is None or name in frame.messages:
            return  # a stamp this evaluator did not publish, or a duplicate
        frame.messages[name] = msg
        frame.received_ns[name] = time.monotonic_ns()

    def _spin_until(self, done: Callable[[], bool], timeout_s: float) -> bool:
        if self.executor is None:
            raise EvaluationError("the evaluation is not started")
        deadline = time.monotonic() + timeout_s
        while not done():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            self.executor.spin_once(timeout_sec=min(0.01, remaining))
        return True

    def _wait_connected(self, sim: SimulatorNode, timeout_s: float = 20.0) -> None:
        """Every camera topic has the graph's subscribers and every output its publisher."""
        # The colour camera_info, the ground truth and the other people have readers only with ground-truth
        # perception.
        unread = (COLOR_INFO_TOPIC, GROUND_TRUTH_TOPIC, SCENE_PEOPLE_TOPIC) if self.options.real_models else ()
        publishers = [pub for topic, pub in sim.frame_pubs.items() if topic not in unread]

        def connected() -> bool:
            outputs = all(sub.get_publisher_count() > 0 for sub in self._subscriptions.values())
            goal = sim.count_publishers(NEXT_BEST_VIEW_TOPIC) > 0
            return all(pub.get_subscription_count() > 0 for pub in publishers) and outputs and goal

        if not self._spin_until(connected, timeout_s):
            raise EvaluationError(f"the simulator and the graph did not connect within {timeout_s:.0f} s")
        self._spin_until(lambda: False, 0.5)  # let the matching settle on both sides

    def _take_stamps(self, scene_slots: int) -> int:
        first = self._next_stamp_ns
        self._next_stamp_ns += int(scene_slots) * SCENE_STAMP_SPACING_NS
        return first

    # ------------------------------------------------------------------ the session (closed_loop.GraphSession)

    def set_scene(self, scene: Scene) -> None:
        """Put the simulator in a scene, its camera at the scene's start view."""
        self._simulator().set_scene(scene)

    def run_frame(self, stamp_ns: int) -> Tuple[RenderedFrame, FrameOutputs]:
        """Publish the simulator's current view at ``stamp_ns`` and collect the graph's outputs.

        Waits for the view candidates (``frame_timeout_s``), or half a second past the output that
        makes it certain none come (:meth:`FrameOutputs.early_failure`); the frame's ``failure``
        says which, if any.

        Raises:
            EvaluationError: A graph process died (from the runner's check).
        """
        if self.runner is None:
            raise EvaluationError("the evaluation is not started")
        frame = FrameOutputs(stamp_ns=stamp_ns, published_ns=0)
        self.frames[stamp_ns] = frame
        frame.published_ns = time.monotonic_ns()
        _, rendered = self._simulator().publish_frame(stamp_ns)
        timeout = self.options.frame_timeout_s
        failure_seen_at: List[float] = []
        ticks = self._clock_ticks(stamp_ns)

        def answered() -> bool:
            if frame.view_candidates is not None:
                return True
            ticks()
            if frame.early_failure() is not None:
                if not failure_seen_at:
                    failure_seen_at.append(time.monotonic())
                # nbv_node publishes nothing for such a frame; wait a moment for certainty, and for the frame's
                # target track (a slow run's may come later; FAILURE_RECORD_WAIT_S bounds a frame hmr_node dropped).
                waited = time.monotonic() - failure_seen_at[0]
                return waited > 0.5 and (frame.failure_recorded() or waited > FAILURE_RECORD_WAIT_S)
            return False

        if not self._spin_until(answered, timeout) and frame.early_failure() is None:
            frame.failure = f"no view_candidates within {timeout:.0f} s (got {sorted(frame.messages)})"
        elif frame.view_candidates is None:
            frame.failure = frame.early_failure()
        else:
            # The remaining outputs of this stamp (person mask, metric mesh) are on their way.
            real_models = self.options.real_models
            self._spin_until(lambda: frame.complete(real_models), 1.0)
        self.runner.check_alive()
        return rendered, frame

    def _clock_ticks(self, stamp_ns: int) -> Callable[[], None]:
        """Continuous lockstep: a callable that ticks sim time on while the frame of ``stamp_ns`` is in flight.

        The graph's stages look for a companion that came after its frame (a pulled depth image) on a wait-check
        timer, and their timers run on sim time: with the clock held at the frame's stamp that frame would wait
        for ever. So every CLOCK_TICK_WALL_S of wall time the clock moves on by one wait-check period, up to one
        tick before the next frame's stamp. Decisions do not depend on how far it got: every wait limit of the
        graph is at least a camera period (a frame's stage waits are 0.2 s and more), so none runs out within the
        frame's period; only the re-checks fire. The goal age (1 s) can run out within one, and the planner's
        withdrawal then comes only if the clock ticked: the simulated motion stack brakes at the goal's
        ``valid_until`` on its own clock instead, whenever the withdrawal comes.
        """
        o, sim = self.options, self._simulator()
        if not (o.continuous and o.clock == "lockstep" and sim.clock_pub is not None):
            return lambda: None
        tick_ns = int(round(WAIT_CHECK_PERIOD_S * 1e9))
        last_ns = stamp_ns + int(round(1e9 / o.camera_rate_hz)) - tick_ns
        next_wall = [time.monotonic() + CLOCK_TICK_WALL_S]

        def tick() -> None:
            now_ns = sim.clock_ns if sim.clock_ns is not None else stamp_ns
            if time.monotonic() < next_wall[0] or now_ns + tick_ns > last_ns:
                return
            sim.publish_clock(now_ns + tick_ns)
            self.clock_ticked_ns[stamp_ns] = now_ns + tick_ns - stamp_ns
            next_wall[0] = time.monotonic() + CLOCK_TICK_WALL_S

        return tick

    def run_frame_real_time(self, stamp_ns: int, until_wall_s: float) -> Tuple[RenderedFrame, FrameOutputs]:
        """Continuous real time: publish the view at ``stamp_ns`` and let the graph work until ``until_wall_s``.

        Sim time follows the wall clock from the frame on (``/clock`` every CLOCK_TICK_WALL_S); what the graph
        answers after the deadline still lands in the returned record (its callbacks fill it later).
        """
        if self.runner is None:
            raise EvaluationError("the evaluation is not started")
        sim = self._simulator()
        frame = FrameOutputs(stamp_ns=stamp_ns, published_ns=time.monotonic_ns())
        self.frames[stamp_ns] = frame
        published = time.monotonic()
        _, rendered = sim.publish_frame(stamp_ns)
        while time.monotonic() < until_wall_s:
            if self.executor is None:
                raise EvaluationError("the evaluation is not started")
            self.executor.spin_once(timeout_sec=min(CLOCK_TICK_WALL_S, max(0.0, until_wall_s - time.monotonic())))
            sim.publish_clock(stamp_ns + int((time.monotonic() - published) * 1e9))
        self.runner.check_alive()
        return rendered, frame

    def wait_goal(self, stamp_ns: int, timeout_s: float = 5.0) -> bool:
        """Wait until the simulator has the graph's goal planned on the frame of ``stamp_ns``; whether it came."""
        sim = self._simulator()
        return self._spin_until(lambda: sim.last_goal_stamp_ns == stamp_ns, timeout_s)

    def move_to(self, pose: CameraPose) -> None:
        """Move the simulator's camera to ``pose``."""
        self._simulator().move_to(pose)

    def camera_pose(self) -> CameraPose:
        """The simulator's camera now."""
        camera = self._simulator().camera
        if camera is None:
            raise EvaluationError("the simulator has no scene")
        return camera

    def camera_pose_at(self, stamp_ns: int) -> Optional[CameraPose]:
        """Where the simulator's camera was when it rendered the frame of ``stamp_ns`` (None: unknown)."""
        return self._simulator().camera_pose_at(stamp_ns)

    # ------------------------------------------------------------------ continuous.ContinuousSession

    def forget_last_scene(self, timeout_s: float = 5.0) -> None:
        """Make the graph forget the last scene: nbv_node its committed goal (and its obstacle memory), hmr_node
        its target and the people it followed.

        A new scene is another room with the person at the same fixed-frame place: a goal committed in the
        last one must not be re-scored and kept in it, and neither the last target's place (its
        re-acquisition window) nor the last bystanders' may decide who the new target is. A change of a
        score weight, undone at once, ends the commitment; obstacle_memory off and on forgets the memory;
        hmr_node's track_previous_target off and on forgets the tracks.

        Raises:
            EvaluationError: a node's parameter service did not answer.
        """
        from rclpy.parameter import parameter_value_to_python
        from rclpy.parameter_client import AsyncParameterClient

        if self.collector is None or not self.term_names:
            return
        client = AsyncParameterClient(self.collector, NAMESPACE + "/nbv_node")
        name = "weight_" + self.term_names[0]
        got = client.get_parameters([name])
        if not self._spin_until(got.done, timeout_s) or got.result() is None:
            raise EvaluationError("nbv_node's parameters did not answer")
        value = parameter_value_to_python(got.result().values[0])
        if not isinstance(value, float):
            raise EvaluationError(f"nbv_node's {name} is not a number: {value!r}")
        weight = value
        nbv = ("nbv_node", client)
        steps = [(nbv, name, weight + 0.5 if weight <= 0.5 else weight - 0.5), (nbv, name, weight)]
        if self.options.obstacle_memory:  # the last room's obstacles are no obstacles of this one
            steps += [(nbv, "obstacle_memory", False), (nbv, "obstacle_memory", True)]
        hmr = ("hmr_node", AsyncParameterClient(self.collector, NAMESPACE + "/hmr_node"))
        steps += [(hmr, "track_previous_target", False), (hmr, "track_previous_target", True)]
        for (node_name, node_client), key, step in steps:
            done = node_client.set_parameters([Parameter(key, value=step)])
            if not self._spin_until(done.done, timeout_s):
                raise EvaluationError(f"{node_name} did not take {key}={step}")

    def settle_goal(self, stamp_ns: int, outputs: FrameOutputs, timeout_s: float = 2.0) -> None:
        """Wait until the goal topics of the frame of ``stamp_ns`` have reached the simulator's motion stack.

        nbv_node publishes the goal, its status, the view candidates and then the path, on separate topics: the
        robot drives on only once it has every one of them that the frame gives (its view candidates; while the
        goal is CURRENT its goal, status and path), in whatever order they came, so that each run drives the same.
        A frame whose plan chose nothing gets at most a withdrawal, awaited briefly.
        """
        sim = self._simulator()
        candidates = outputs.view_candidates
        if outputs.failure is not None or candidates is None or candidates.chosen_index < 0:
            self._spin_until(lambda: candidates is None or sim.last_view_candidates_stamp_ns == stamp_ns, timeout_s)
            self._spin_until(lambda: False, 0.05)
            return

        def arrived() -> bool:
            status = sim.goal_status
            if sim.last_view_candidates_stamp_ns != stamp_ns or status is None or \
                    stamp_to_ns(status.goal_stamp) != stamp_ns:
                return False
            return status.state != GoalStatus.STATE_CURRENT or (sim.last_path_msg_stamp_ns == stamp_ns
                                                                 and sim.last_goal_stamp_ns == stamp_ns)

        self._spin_until(arrived, timeout_s)

    def ticked_between(self, first_ns: int, last_ns: int) -> int:
        """How many frames stamped in [first_ns, last_ns] needed sim time to tick on before the graph answered."""
        return sum(1 for stamp, ticked in self.clock_ticked_ns.items() if first_ns <= stamp <= last_ns and ticked)

    def driven_robot(self) -> DrivenRobot:
        """The simulator's robot (continuous mode)."""
        robot = self._simulator().robot
        if robot is None:
            raise EvaluationError("the simulator runs no motion stack (continuous mode is off)")
        return robot

    def goal_statuses(self) -> List[StatusRecord]:
        """Every goal status the simulator received in this scene, in order."""
        return [StatusRecord(state=int(s.state), goal_stamp_ns=stamp_to_ns(s.goal_stamp),
                             goal_changed=bool(s.goal_changed), commitment=str(s.commitment),
                             committed_since_ns=stamp_to_ns(s.committed_since), reason=str(s.reason))
                for s in self._simulator().goal_statuses]

    def last_path(self) -> Optional[Tuple[int, Any]]:
        """(stamp, (P, 3) world points) of the latest base path the robot took in this scene."""
        sim = self._simulator()
        if sim.last_path_stamp_ns is None or sim.last_path_world is None:
            return None
        return sim.last_path_stamp_ns, sim.last_path_world

    # ------------------------------------------------------------------ evaluation

    def evaluate_continuous(self, seeds: Sequence[int], first_index: int = 0,
                            on_episode: Optional[Callable[[ContinuousEpisode], None]] = None) -> ContinuousRun:
        """Run one continuous episode per scene (options.continuous must have been set when the graph started).

        Args:
            seeds: Scene seeds.
            first_index: Scene index of the first seed (its stamps).
            on_episode: Called with each episode as it is done (progress).

        Returns:
            The run.

        Raises:
            EvaluationError: Not started in continuous mode.
        """
        o = self.options
        if not o.continuous or self.sim is None or self.sim.robot is None:
            raise EvaluationError("continuous episodes need the evaluator started with options.continuous")
        started = time.monotonic()
        spacing = self.continuous_episodes.spacing_ns()
        self._next_stamp_ns = max(self._next_stamp_ns, int(o.stamp_base_ns) + SCENE_STAMP_SPACING_NS)
        base = self._next_stamp_ns
        self._next_stamp_ns += (int(first_index) + len(seeds)) * spacing
        episodes = []
        for offset, seed in enumerate(seeds):
            index = int(first_index) + offset
            episodes.append(self.continuous_episodes.run(self._load_scene(seed), int(seed), index,
                                                         base + index * spacing))
            if on_episode is not None:
                on_episode(episodes[-1])
        return ContinuousRun(room=o.room, obstacle_map=o.obstacle_map, obstacle_memory=o.obstacle_memory, clock=o.clock,
                             camera_rate_hz=float(o.camera_rate_hz), time_limit_s=float(o.time_limit_s),
                             commit_hold_s=float(o.commit_hold_s), episodes=episodes,
                             total_wall_s=round(time.monotonic() - started, 3))

    def evaluate(self, seeds: Sequence[int], first_index: int = 0,
                 on_scene: Optional[Callable[[SceneResult], None]] = None) -> EvaluationRun:
        """Run every scene once through the graph and score every method.

        Args:
            seeds: Scene seeds (benchmark seeds for comparable numbers).
            first_index: Scene index of the first seed: the scenes get the stamps they would get
                at these places of a longer run (a worker of a parallel run gives its share's
                place, so its stamps are those of a one-process run).
            on_scene: Called with each scene's result as it is done (progress).

        Returns:
            The run (methods, one result per scene in seed order, wall time of the scenes).
        """
        started = time.monotonic()
        stamp_base = self._take_stamps(int(first_index) + len(seeds))
        scenes = []
        for offset, seed in enumerate(seeds):
            scenes.append(self.episodes.run(self._load_scene(seed), int(seed), int(first_index) + offset, stamp_base))
            if on_scene is not None:
                on_scene(scenes[-1])
        methods = self.methods
        stay_where_the_graph_failed(scenes, methods)
        o = self.options
        return EvaluationRun(methods=methods, default_method=DEFAULT_METHOD, stages=list(STAGES), scenes=scenes,
                             perception=o.perception_label, room=o.room, obstacle_map=o.obstacle_map, workers=1,
                             ready_s=self.ready_s, scenes_wall_s=time.monotonic() - started)
