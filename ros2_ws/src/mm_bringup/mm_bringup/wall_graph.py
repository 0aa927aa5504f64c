"""The Section 2 experiment through the ROS graph: wheeled_sim (lockstep) + sensor_manifold + switching_controller as
separate processes, driven and scored by an evaluation harness node.

The harness is the experimenter, not part of the robot: it resets the simulator to task poses, shows the robot the
goal as a sensor-2 reading (computed from the goal pose with the simulator's sensor model), and scores episodes with
the ground-truth odometry. The learning and control nodes never see any of that (tests check their subscriptions).
Used by `make demo`, the wall_task benchmark and the integration tests.
"""
from __future__ import annotations

import math
import re
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Deque, List, Optional, Sequence

import numpy as np
from mm_common.ros_harness import RosHarness
from mm_msgs.msg import ControllerStatus, ManifoldState, SensorGoal, SensorManifoldModel
from mm_msgs.srv import ResetPose
from nav_msgs.msg import Odometry
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from mm_bringup.process_graph import ProcessGraph

LOOP_QOS = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
DONE = (ControllerStatus.PHASE_GOAL_REACHED, ControllerStatus.PHASE_FAILED)
# mm_planner.wall_agent.WallAgent.blind_report, in the controller's final status detail
BLIND_REPORT = re.compile(r"longest blind stretch (?P<steps>\d+) steps, [\d.]+ x the route's predicted (?P<predicted>\d+)")



class LearningFailed(RuntimeError):
    """The controller ended FAILED before any model was announced ready (it reached its exploration cap)."""

@dataclass
class GraphEpisode:
    poses: List[tuple] = field(default_factory=list)          # ground truth per step (evaluation only)
    blind: List[bool] = field(default_factory=list)           # no sensor group fully in range at that step
    spaces: List[int] = field(default_factory=list)
    coordinates: List[Sequence[float]] = field(default_factory=list)
    sensor1: List[Sequence[float]] = field(default_factory=list)
    sensor2: List[Sequence[float]] = field(default_factory=list)
    phase: int = ControllerStatus.PHASE_IDLE
    detail: str = ''
    wall_seconds: float = 0.0

    @property
    def longest_blind(self) -> tuple:
        """(steps, the route's predicted steps) of the longest blind stretch, as the controller reports it in its
        final status detail ((0, 0) when it did not say)."""
        found = BLIND_REPORT.search(self.detail)
        return (int(found['steps']), int(found['predicted'])) if found else (0, 0)

    @property
    def reached(self) -> bool:
        return self.phase == ControllerStatus.PHASE_GOAL_REACHED

    def add_state(self, msg: ManifoldState) -> None:
        flags = list(msg.in_range)
        self.blind.append(not all(flags[:3]) and not all(flags[3:]))
        self.spaces.append(int(msg.active_space))
        self.coordinates.append(list(msg.coordinates))
        self.sensor1.append(list(msg.sensor1))
        self.sensor2.append(list(msg.sensor2))

    def path_length(self) -> float:
        p = np.array([q[:2] for q in self.poses]) if self.poses else np.zeros((1, 2))
        return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))

    def blind_fraction(self) -> float:
        """Share of the path length travelled while no sensor group saw the wall."""
        if len(self.poses) < 2:
            return 0.0
        n = min(len(self.poses) - 1, len(self.blind))     # odometry and states of the last step may be in flight
        p = np.array([q[:2] for q in self.poses[:n + 1]])
        seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
        total = seg.sum()
        return float(seg[np.array(self.blind[:n], dtype=bool)].sum() / total) if total > 0 else 0.0


def _ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


LOOP_START_TIMEOUT = 30.0    # wall seconds for the first lockstep step after the loop's nodes started
LOOP_START_ATTEMPTS = 2      # starts of the loop's nodes before giving up


class WallGraph:
    """Start the graph (optionally with a recorder already running elsewhere) and run reaching episodes."""

    loop_start_attempts = LOOP_START_ATTEMPTS

    def __init__(self, work_dir: Path, exploration_steps: int = 10000, noise_range_fraction: float = 0.0,
                 dropout: float = 0.0, model_path=None, seed: int = 0,
                 graph: Optional[ProcessGraph] = None, dt: float = 0.05, recorder: Optional[str] = None,
                 recorded_topics: Sequence[str] = (), sim_params_files: Sequence[Path] = (), composed: bool = False,
                 rehearsals: Optional[int] = None):
        """`recorder`: name of a recorder node already running in `graph`, and `recorded_topics` the topics it must
        have subscribed to before the loop may start. The simulator starts first (it re-publishes its first step until
        a command arrives), then the controller (it only answers states), and the manifold node last, which closes
        the loop; each waits until the recorder subscribes to the topics of the nodes before it, so the bag holds the
        loop from its first step. `model_path`: where the learner keeps its model (default <work_dir>/wall_model.npz;
        '' = not persisted, as in the shipped sensor_manifold.yaml: the controller gets the model as a message
        either way, kept here as `model_msg`) and, next to it (.samples.csv), its samples. `sim_params_files`: parameter files for wheeled_sim (e.g. wheeled_sim.yaml
        and a sensor layout of mm_sim/layouts), loaded in order before the parameters set here. `composed`: the
        three nodes in one process (mm_bringup wheeled_container; it waits for the recorder in the same way), else
        one process each. `rehearsals`: switching_controller's (None: its default)."""
        self.work_dir = Path(work_dir)
        self.work_dir.mkdir(parents=True, exist_ok=True)
        self.dt = dt
        self.graph = graph or ProcessGraph(log_dir=self.work_dir / 'logs')
        learner_path = '' if model_path == '' else str(Path(model_path) if model_path else
                                                        self.work_dir / 'wall_model.npz')
        # the samples are kept next to a kept model (a restarted learner resumes with all it explored)
        samples_path = '' if learner_path == '' else str(Path(learner_path).with_suffix('.samples.csv'))
        self.ros = RosHarness()
        node = self.node = self.ros.node('wall_experimenter')
        self.status: Optional[ControllerStatus] = None
        self.episode: Optional[GraphEpisode] = None
        self.last_pose: Optional[tuple] = None
        self.samples = 0
        self.state_stamp: Optional[int] = None
        self.episode_from = 0
        self.recent_odom: Deque[tuple] = deque(maxlen=100)
        self.recent_states: Deque[ManifoldState] = deque(maxlen=100)
        self.sensor1_samples: List[tuple] = []       # every in-range sensor-1 reading seen (for Fig. 7)
        node.create_subscription(ControllerStatus, 'wheeled/controller/status', self._on_status, LOOP_QOS)
        node.create_subscription(ManifoldState, 'wheeled/manifold/state', self._on_state, LOOP_QOS)
        # Ground truth scores episodes only: taken from the first episode on (watch_ground_truth), so that during
        # exploration this process, one of four on the loop's CPUs, does not take an odometry message every step.
        self.odom_sub = None
        self.model_msg: Optional[SensorManifoldModel] = None
        node.create_subscription(SensorManifoldModel, 'wheeled/manifold/model',
                                 lambda msg: setattr(self, 'model_msg', msg), LATCHED_QOS)
        self.goal_pub = node.create_publisher(SensorGoal, 'wheeled/goal', LATCHED_QOS)
        self.reset_client = node.create_client(ResetPose, 'wheeled/reset')
        self.nodes = []
        sim_time = {'use_sim_time': True}
        sim_topics = ['/clock', '/wheeled/bumper', '/wheeled/ground_truth/odom'] + [
            f'/wheeled/range/{n}' for n in ('front_left', 'front_center', 'front_right', 'side_front', 'side_rear')]
        steps = [
            ('mm_sim', 'wheeled_sim', {'dt': dt, 'noise_range_fraction': noise_range_fraction, 'dropout': dropout,
                                       'random_seed': seed, 'republish_period': 0.5}, sim_topics),
            ('mm_planner', 'switching_controller', {**sim_time, 'dt': dt, 'random_seed': seed,
                                                    'exploration_steps': exploration_steps,
                                                    **({} if rehearsals is None else {'rehearsals': rehearsals})},
             ['/wheeled/wheel_velocity_controller/commands', '/wheeled/controller/status']),
            ('mm_manifold', 'sensor_manifold', {**sim_time, 'dt': dt, 'learn_after': exploration_steps,
                                                'model_path': learner_path, 'samples_path': samples_path,
                                                'range_input': 'grouped'}, []),
        ]
        sim_files = [a for f in sim_params_files for a in ('--params-file', str(f))]
        extra_args = {'wheeled_sim': ['--ros-args', *sim_files] if sim_files else []}
        if composed:
            # One process; its first node (the simulator) shows it started, and it waits for the recorder itself.
            container = {f'{executable}:{name}': value for _, executable, parameters, _ in steps
                         for name, value in parameters.items() if name != 'use_sim_time'}
            wait = ['--wait-for-subscriber', recorder, '--wait-topics', *recorded_topics] if recorder and \
                recorded_topics else []
            extra_args['wheeled_container'] = wait + extra_args['wheeled_sim']
            steps = [('mm_bringup', 'wheeled_container', container, [])]
        try:
            self._start_loop(steps, extra_args, 'wheeled_sim' if composed else None, recorder, recorded_topics)
        except BaseException:
            self.close()            # no node or DDS participant outlives a harness that failed to start
            raise

    def _start_loop(self, steps, extra_args, shown_name, recorder, recorded_topics) -> None:
        """Start the loop's nodes one by one and wait for its first steps; start them again when it never starts."""
        node = self.node
        for attempt in range(self.loop_start_attempts):
            for package, executable, parameters, published in steps:
                self.nodes.append(self.graph.start(package, executable, parameters,
                                                   extra_args=extra_args.get(executable, [])))
                # One node at a time, each seen on the graph before the next starts (simultaneous starts
                # occasionally left two participants without matching endpoints, and the loop never started).
                name = shown_name or executable
                self.spin_until(lambda: name in node.get_node_names(), 60.0, f'{name} to appear')
                wait = [t for t in published if t in recorded_topics]
                if recorder and wait:
                    self.spin_until(lambda: all(any(i.node_name == recorder
                                                    for i in node.get_subscriptions_info_by_topic(t))
                                                for t in wait), 60.0, f'{recorder} to subscribe to {wait}')
            # A loop that never starts (endpoints that never matched) is detected here within LOOP_START_TIMEOUT
            # and the loop's nodes are started again, instead of an experiment waiting for learning for good.
            try:
                self.spin_until(lambda: len({_ns(m.header.stamp) for m in self.recent_states}) >= 2,
                                LOOP_START_TIMEOUT, 'the lockstep loop to start')
                break
            except TimeoutError as stall:
                logs = self.log_tails()
                if attempt + 1 == self.loop_start_attempts:
                    raise TimeoutError(f'{stall}, after {self.loop_start_attempts} start(s) of the loop\'s nodes\n'
                                       f'{logs}') from stall
                print(f'[wall_graph] the lockstep loop did not start within {LOOP_START_TIMEOUT:.0f} s: '
                      f'restarting {[n.label for n in self.nodes]}\n{logs}', flush=True)
                for n in reversed(self.nodes):
                    self.graph.stop(n)
                self.nodes.clear()
                self.recent_states.clear()

    # --- callbacks (evaluation side) --------------------------------------------------------------------------------
    def _on_status(self, msg: ControllerStatus) -> None:
        self.status = msg

    def _on_odom(self, msg: Odometry) -> None:
        q = msg.pose.pose.orientation
        self.last_pose = (msg.pose.pose.position.x, msg.pose.pose.position.y, 2 * math.atan2(q.z, q.w))
        self.recent_odom.append((_ns(msg.header.stamp), self.last_pose))
        if self.episode is not None and _ns(msg.header.stamp) >= self.episode_from:
            self.episode.poses.append(self.last_pose)

    def _on_state(self, msg: ManifoldState) -> None:
        self.samples = msg.samples
        self.state_stamp = _ns(msg.header.stamp)
        self.recent_states.append(msg)
        if all(msg.in_range[:3]):
            self.sensor1_samples.append(tuple(msg.sensor1))
        if self.episode is not None and self.state_stamp >= self.episode_from:
            self.episode.add_state(msg)

    # --- experiment steps -------------------------------------------------------------------------------------------
    def _check_alive(self) -> None:
        for n in self.nodes:
            if n.process.poll() is not None:
                raise RuntimeError(f'{n.label} exited with {n.process.returncode}:\n{self.graph.log_tail(n)}')

    def log_tails(self, lines: int = 15) -> str:
        """The last lines of every loop node's log: the nodes' own words on a stall (unmatched peers, a state waiting
        for its command), for the error where the run is watched, since the log files may be gone with the work
        directory (a CI run's tmp)."""
        return '\n'.join(f'--- {n.label} (last lines) ---\n{self.graph.log_tail(n, lines)}' for n in self.nodes)

    def spin_until(self, predicate, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return
            self.ros.executor.spin_once(timeout_sec=0.05)
            self._check_alive()
        raise TimeoutError(f'timed out after {timeout:.0f} s waiting for {what}')

    def wait_learned(self, timeout: float = 600.0, on_status=None) -> None:
        """Exploration and learning happen on their own; wait until the controller waits for a goal. Raises
        LearningFailed as soon as the controller gives up (its exploration cap), with its reason, instead of waiting
        out `timeout`. `on_status(status)` sees the status (possibly None) at every poll, e.g. for progress lines."""
        def learned() -> bool:
            if on_status is not None:
                on_status(self.status)
            if self.status is not None and self.status.phase == ControllerStatus.PHASE_FAILED:
                raise LearningFailed(f'the controller gave up learning after {self.samples} samples: '
                                     f'{self.status.detail}')
            return self.status is not None and self.status.phase == ControllerStatus.PHASE_WAITING_FOR_GOAL

        self.spin_until(learned, timeout, 'exploration and learning')

    def watch_ground_truth(self) -> None:
        """Subscribe to the ground-truth odometry (once) and wait until the simulator's publisher is matched, so the
        next step's pose is not missed."""
        if self.odom_sub is None:
            self.odom_sub = self.node.create_subscription(Odometry, 'wheeled/ground_truth/odom', self._on_odom,
                                                          LOOP_QOS)
        self.spin_until(lambda: self.odom_sub.get_publisher_count() > 0, 30.0, 'the ground-truth odometry')

    def reset(self, pose: Sequence[float]) -> int:
        """Teleport the robot; returns the stamp [ns] of the step the reset produced."""
        self.watch_ground_truth()
        self.spin_until(lambda: self.reset_client.service_is_ready(), 30.0, 'the reset service')
        future = self.reset_client.call_async(ResetPose.Request(x=float(pose[0]), y=float(pose[1]),
                                                                theta=float(pose[2])))
        self.spin_until(future.done, 30.0, 'the reset')
        if not future.result().success:
            raise RuntimeError(future.result().message)
        return _ns(future.result().stamp)

    def run_episode(self, start: Sequence[float], goal_reading: Sequence[float], tolerance: float,
                    timeout: float = 300.0) -> GraphEpisode:
        """Show the goal, put the robot at the start, and record until the controller reports the outcome."""
        goal = SensorGoal(sensor_group=SensorGoal.SENSOR2, reading=[float(v) for v in goal_reading],
                          tolerance=float(tolerance))
        began = time.monotonic()
        # Reset first: the loop is paused (the controller answers no state between tasks), the reset produces the
        # episode's first readings, and once the controller has seen them the goal makes it answer exactly that
        # state - one command in flight, as lockstep requires.
        self.episode = None
        first = self.reset(start)
        # Record from the reset's own step on (its messages may have arrived before the service response).
        self.episode_from = first
        self.episode = GraphEpisode(poses=[p for stamp, p in self.recent_odom if stamp >= first])
        for msg in self.recent_states:
            if _ns(msg.header.stamp) >= first:
                self.episode.add_state(msg)
        self.spin_until(lambda: self.state_stamp is not None and self.state_stamp >= first, 30.0, 'the first state')
        self.spin_until(lambda: self.status is not None and _ns(self.status.header.stamp) >= first, 30.0,
                        'the controller to see the first state')
        goal.header.stamp = self.node.get_clock().now().to_msg()
        self.goal_pub.publish(goal)
        goal_ns = _ns(goal.header.stamp)
        self.spin_until(lambda: self.status is not None and _ns(self.status.goal_stamp) == goal_ns
                        and self.status.phase in DONE, timeout, 'the episode')
        episode, self.episode = self.episode, None
        episode.phase, episode.detail = self.status.phase, self.status.detail
        episode.wall_seconds = time.monotonic() - began
        return episode

    def close(self) -> None:
        self.ros.close()
        for n in reversed(self.nodes):
            self.graph.stop(n)

    def __enter__(self) -> 'WallGraph':
        return self

    def __exit__(self, *exc) -> None:
        self.close()
