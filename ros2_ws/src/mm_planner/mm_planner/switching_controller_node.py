"""Switching-controller node: the ROS driver of mm_planner.wall_agent.WallAgent (the wheeled robot's behaviour in the
wall task; the offline runner mm_bringup.wall_experiment drives the same class).

One wheel command per `wheeled/manifold/state` (the lockstep loop: simulator -> manifold -> controller -> simulator);
phases (EXPLORING -> LEARNING -> REHEARSING -> WAITING_FOR_GOAL -> REACHING_* -> GOAL_REACHED / FAILED, see
wall_agent) are published on `wheeled/controller/status`. The verdict of the rehearsals on a model the learner found
ready goes out on the latched `wheeled/controller/model_verdict` (a rejected model makes the learner refit). Goals
come as mm_msgs/SensorGoal on `wheeled/goal` (latched) or through the `wheeled/set_goal` service. The learned model
arrives as an mm_msgs/SensorManifoldModel message on the latched `wheeled/manifold/model` topic: no file, so learner
and controller may run on different hosts. Every input is checked first; a bad one is dropped with a throttled log
line saying why, and the node keeps running. Nothing here sees world coordinates.
"""
from __future__ import annotations

import inspect
import math
import time
from typing import Optional

import numpy as np
from builtin_interfaces.msg import Time
from mm_common.node_utils import clock_went_back, declare, reject_non_finite, run_node
from mm_common.qos import LOOP_QOS  # RELIABLE, deep history: see mm_common/qos.py
from mm_msgs.msg import ControllerStatus, ManifoldState, ModelVerdict, SensorGoal
from mm_msgs.msg import SensorManifoldModel as ModelMsg
from mm_msgs.srv import SetSensorGoal
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Bool, Float64MultiArray

from mm_planner.exploration import RandomExplorer
from mm_planner.switching_controller import SwitchingController
from mm_planner.wall_agent import Decision, FitFailure, Goal, Observation, WallAgent
from mm_planner.wall_model import WallModel

# Goals, the model and the verdict on it are latched state (TRANSIENT_LOCAL, depth 1): a node started or restarted
# after they were published still gets the newest; RELIABLE because a lost model would leave the controller unable to
# control (and a lost rejection the learner waiting with a model the controller will not use).
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
SPACES = (ManifoldState.SPACE_NONE, ManifoldState.SPACE_SENSOR1, ManifoldState.SPACE_VIRTUAL_SENSOR1,
          ManifoldState.SPACE_SENSOR2)
MAX_STAMP_AHEAD = 60.0       # [s] a state stamped further ahead of this node's clock is refused (a forged stamp)
# [wall s] an answered step that comes again later than this lost its command (the simulator re-sends a step only after
# its republish period without one, e.g. when it restarted): the command is sent again. Sooner, the re-sent step only
# crossed the command on its way and is dropped (a second command would advance the simulator one step too far).
RESEND_AFTER = 0.25


def _ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def _readings_problem(name: str, values, length: int) -> Optional[str]:
    """REP 117 readings: a distance >= 0, +-inf out of range, NaN lost. (Plain Python: it runs every step, and numpy's
    per-call overhead on a few values costs the lockstep loop more than the check itself.)"""
    if len(values) != length:
        return f'{name} has {len(values)} values, expected {length}'
    if any(v < 0 and math.isfinite(v) for v in values):
        return f'{name} {list(values)} has a negative distance'
    return None


def _finite(values) -> bool:
    return all(math.isfinite(v) for v in values)


class SwitchingControllerNode(Node):
    def __init__(self, **node_kwargs):
        super().__init__('switching_controller', **node_kwargs)
        self.dt = declare(self, 'dt', 0.05, 'Control step = simulator step [s]; fixed at start-up',
                          min_value=1e-4, max_value=1.0, read_only=True)
        exploration_steps = declare(self, 'exploration_steps', 10000, 'Random exploration commands before waiting '
                                    'for the model; fixed at start-up', min_value=0, max_value=10_000_000,
                                    read_only=True)
        max_wheel_speed = declare(self, 'max_wheel_speed', 6.0, 'Largest wheel command while reaching [rad/s] '
                                  '(a change applies from the next goal)', min_value=0.1, max_value=30.0)
        tolerance = declare(self, 'tolerance', 0.01, 'Goal tolerance per sensor-2 reading [m] when the goal gives '
                            'none (a change applies from the next goal)', min_value=1e-4, max_value=0.2)
        max_reach_steps = declare(self, 'max_reach_steps', 1500, 'Steps before a reach counts as failed',
                                  min_value=1, max_value=1_000_000)
        # Reporting only: what the explorer does never depends on how long a message took (determinism under load).
        self.stall_warning = declare(self, 'stall_warning', 2.0, 'Wall seconds a state may wait for its bumper '
                                     'reading before a (throttled) warning says so; the wait goes on',
                                     min_value=0.1, max_value=3600.0)
        seed = declare(self, 'random_seed', 0, 'Seed of the exploration; fixed at start-up', min_value=0,
                       max_value=2**31 - 1, read_only=True)
        max_exploration = declare(self, 'max_exploration_steps', 0, 'Exploration steps, extra exploration included, '
                                  'after which a model that is still not ready ends FAILED with the reason (0: 4 x '
                                  'exploration_steps); fixed at start-up', min_value=0, max_value=40_000_000,
                                  read_only=True)
        explorer_defaults = inspect.signature(RandomExplorer).parameters
        approach = declare(self, 'exploration_approach_probability', explorer_defaults['approach_probability'].default,
                           'Share of new excursions that first drive toward the wall (0 with exploration_excursion_'
                           'share 0 and exploration_repeat_probability 0: the paper\'s undirected exploration); fixed '
                           'at start-up', min_value=0.0, max_value=1.0, read_only=True)
        share = declare(self, 'exploration_excursion_share', explorer_defaults['excursion_share'].default,
                        'Excursions start whenever they have had less than this share of the exploration steps; '
                        'fixed at start-up', min_value=0.0, max_value=1.0, read_only=True)
        repeat = declare(self, 'exploration_repeat_probability', explorer_defaults['repeat_probability'].default,
                         'Share of new excursions that repeat, jittered, one that brought sensor 2 into range (0: '
                         'always a new random one, as in the paper); fixed at start-up', min_value=0.0, max_value=1.0,
                         read_only=True)
        rehearsals = declare(self, 'rehearsals', inspect.signature(WallAgent).parameters['rehearsals'].default,
                             'Practice reaches to practised sensor-2 readings a model the learner found ready must '
                             'pass before it is announced (0: the learner\'s held-out check decides alone); fixed at '
                             'start-up', min_value=0, max_value=100, read_only=True)
        replay = declare(self, 'replay_practised_routes',
                         inspect.signature(SwitchingController).parameters['replay_routes'].default,
                         'Cross the blind stretch by replaying the chosen practised excursion\'s commands from its '
                         'exit (false: the paper\'s virtual-space plan alone); fixed at start-up', read_only=True)
        blind_budget = declare(self, 'blind_budget',
                               float(inspect.signature(SwitchingController).parameters['blind_budget'].default),
                               'Turn back from a blind crossing (sensor 1 last in sight) once the way out and back '
                               'would exceed this many times its predicted length (past a replay the route\'s '
                               'practised blind length) (0: off, only the watchdog\'s limit; else >= 1; README '
                               'issue 11); fixed at start-up',
                               min_value=0.0, max_value=100.0, read_only=True)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.agent = WallAgent(self.dt, exploration_steps, max_wheel_speed, tolerance, max_reach_steps,
                               random_state=seed, max_exploration_steps=max_exploration or None,
                               explorer_params={'approach_probability': approach, 'excursion_share': share,
                                                'repeat_probability': repeat},
                               rehearsals=rehearsals,
                               controller_params={'replay_routes': replay, 'blind_budget': blind_budget})

        self.bumped = False
        # The bumper reading of a step travels on its own topic and may arrive after the state: in lockstep the
        # first bumper message after a command belongs to the step that command produced, so while exploring (the
        # explorer's reflex reads it) a state is answered once it came, however long that takes: the simulator
        # re-sends a step (bumper included) when no command came, so a lost bumper message is sent again.
        self.bumper_since_command = False
        self.waiting: Optional[Observation] = None
        self.state_wall = 0.0
        self.state_stamp: Optional[Time] = None
        self.newest_ns = -1          # newest state accepted
        self.last_answered = -1      # newest state answered with a command
        self.last_command: Optional[Float64MultiArray] = None
        self.answered_wall = 0.0     # monotonic time the last command was sent
        self.rejected = 0

        self.command_pub = self.create_publisher(Float64MultiArray, 'wheeled/wheel_velocity_controller/commands',
                                                 LOOP_QOS)
        self.status_pub = self.create_publisher(ControllerStatus, 'wheeled/controller/status', LOOP_QOS)
        self.status_msg = ControllerStatus()
        self.verdict_pub = self.create_publisher(ModelVerdict, 'wheeled/controller/model_verdict', LATCHED_QOS)
        self.create_subscription(ManifoldState, 'wheeled/manifold/state', self._on_state, LOOP_QOS)
        self.create_subscription(Bool, 'wheeled/bumper', self._on_bumper, LOOP_QOS)
        self.create_timer(0.5, self._on_wall_timer, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.create_subscription(ModelMsg, 'wheeled/manifold/model', self._on_model, LATCHED_QOS)
        self.create_subscription(SensorGoal, 'wheeled/goal', self._on_goal_topic, LATCHED_QOS)
        self.create_service(SetSensorGoal, 'wheeled/set_goal', self._on_set_goal)

    @property
    def explored(self) -> int:
        return self.agent.explored

    @property
    def phase(self) -> int:
        return self.agent.phase

    def _on_set_parameters(self, params) -> SetParametersResult:
        result = reject_non_finite(params)
        if result.successful:
            for p in params:
                if p.name in ('tolerance', 'max_reach_steps', 'max_wheel_speed'):
                    setattr(self.agent, p.name, p.value)
                elif p.name == 'stall_warning':
                    self.stall_warning = p.value
        return result

    def _reject(self, what: str, reason: str) -> None:
        self.rejected += 1
        self.get_logger().warn(f'{what} rejected ({self.rejected} inputs so far): {reason}',
                               throttle_duration_sec=1.0)

    # --- inputs ---------------------------------------------------------------------------------------------------
    def _on_model(self, msg: ModelMsg) -> None:
        no_model = msg.grid_rows == 0 and msg.grid_cols == 0 and not msg.ready
        if no_model and msg.format_version == ModelMsg.FORMAT_VERSION:
            # the learner could not fit what was explored (SensorManifoldModel.msg)
            reason = msg.readiness[:300] or 'the learner could not fit a model (no reason given)'
            self.get_logger().warn(f'no model from {msg.samples} samples: {reason}', throttle_duration_sec=1.0)
            self._publish(self.agent.step(Observation(fit_failure=FitFailure(reason, int(msg.samples)))))
            return
        try:
            model = WallModel.from_msg(msg)
            if not math.isclose(model.dt, self.dt):
                raise ValueError(f'model dt {model.dt} s != control step {self.dt} s')
        except ValueError as exc:
            self._reject('model', str(exc))
            return
        self.get_logger().info(f'model received: {model.samples} samples, '
                               f'{"ready" if model.ready else "cannot map sensor-2 goals yet"}')
        self._publish(self.agent.step(Observation(model=model)))

    def _on_goal_topic(self, msg: SensorGoal) -> None:
        accepted, reason = self._take_goal(msg)
        if not accepted:
            self._reject('goal', reason)

    def _on_set_goal(self, request: SetSensorGoal.Request, response: SetSensorGoal.Response):
        response.accepted, response.message = self._take_goal(request.goal)
        return response

    def _take_goal(self, goal: SensorGoal):
        if goal.sensor_group != SensorGoal.SENSOR2:
            return False, f'the goal must be a sensor-2 reading (sensor_group={SensorGoal.SENSOR2})'
        decision = self.agent.step(Observation(goal=Goal(np.asarray(goal.reading, dtype=float),
                                                         float(goal.tolerance), goal.header.stamp)))
        self._publish(decision)
        return decision.goal_accepted, decision.goal_reason

    def _on_bumper(self, msg: Bool) -> None:
        self.bumped = bool(msg.data)
        self.bumper_since_command = True
        if self.waiting is not None:
            self._step_waiting()

    def _on_wall_timer(self) -> None:
        """A state waiting long for its bumper reading is reported; the wait goes on (no timeout decides)."""
        waited = time.monotonic() - self.state_wall
        if self.waiting is not None and waited > self.stall_warning:
            stamp = self.waiting.stamp
            self.get_logger().warn(f'state {stamp.sec + stamp.nanosec * 1e-9:.3f} s has waited {waited:.1f} s for its '
                                   'wheeled/bumper reading (none since the last command); answered once it comes',
                                   throttle_duration_sec=5.0)

    def _state_problem(self, msg: ManifoldState) -> Optional[str]:
        for name, length in (('sensor1', 3), ('sensor2', 2)):
            problem = _readings_problem(name, getattr(msg, name), length)
            if problem:
                return problem
        limits = msg.sensor1_range
        if len(limits) != 2 or not (_finite(limits) and 0.0 <= limits[0] < limits[1]):
            return f'sensor1_range {list(limits)} is not [min, max] with 0 <= min < max (the front sensors\' range)'
        if len(msg.in_range) not in (0, 5):
            return f'in_range has {len(msg.in_range)} flags, expected 5'
        if msg.active_space not in SPACES:
            return f'unknown active_space {msg.active_space}'
        for name in ('coordinates', 'sensor2_estimate'):
            values = getattr(msg, name)
            if len(values) not in (0, 2):
                return f'{name} has {len(values)} values, expected 0 or 2'
            if not _finite(values):
                return f'{name} {list(values)} is not finite'
        model = self.agent.model
        if model is not None and len(msg.coordinates):
            low, high = model.virtual_bounds
            span = high - low
            if np.any(np.asarray(msg.coordinates) < low - span) or np.any(np.asarray(msg.coordinates) > high + span):
                return f'coordinates {list(msg.coordinates)} far outside the learned space {low}..{high}'
        if model is not None and len(msg.sensor2_estimate):
            low, high = model.sensor2_range
            span = high - low
            if np.any(np.abs(np.asarray(msg.sensor2_estimate) - (low + high) / 2) > 1.5 * span):
                return f'sensor2_estimate {list(msg.sensor2_estimate)} far outside what sensor 2 reads'
        needs = {ManifoldState.SPACE_SENSOR1: 'coordinates', ManifoldState.SPACE_VIRTUAL_SENSOR1: 'coordinates',
                 ManifoldState.SPACE_SENSOR2: 'sensor2_estimate'}.get(msg.active_space)
        if needs and not len(getattr(msg, needs)):
            return f'active_space {msg.active_space} without {needs}'
        now = self.get_clock().now().nanoseconds
        stamp = _ns(msg.header.stamp)
        if clock_went_back(now, self.newest_ns if self.newest_ns >= 0 else None, stamp):
            self.get_logger().warn(f'the clock went back to {now * 1e-9:.3f} s, before the newest state '
                                   f'{self.newest_ns * 1e-9:.3f} s: following the new time')
            self.newest_ns = self.last_answered = -1
        if now > 0 and stamp > now + MAX_STAMP_AHEAD * 1e9:
            return f'stamp {stamp * 1e-9:.3f} s is more than {MAX_STAMP_AHEAD} s ahead of the clock ({now * 1e-9:.3f} s)'
        if stamp < self.newest_ns:
            return f'stamp {stamp * 1e-9:.3f} s goes backwards (newest {self.newest_ns * 1e-9:.3f} s)'
        return None

    def _on_state(self, msg: ManifoldState) -> None:
        stamp = _ns(msg.header.stamp)
        if stamp == self.last_answered:          # a step that was already answered, sent again
            if self.last_command is not None and time.monotonic() - self.answered_wall > RESEND_AFTER:
                self.get_logger().info(f'step {stamp * 1e-9:.3f} s came again: its command was lost, sending it '
                                       'again', throttle_duration_sec=1.0)
                self.answered_wall = time.monotonic()
                self.command_pub.publish(self.last_command)
            return
        problem = self._state_problem(msg)
        if problem:
            self._reject('manifold state', problem)
            return
        self.newest_ns = stamp
        self.state_stamp = msg.header.stamp
        self.waiting = Observation(
            state=True, stamp=msg.header.stamp, space=int(msg.active_space),
            coordinates=np.asarray(msg.coordinates, dtype=float) if len(msg.coordinates) else None,
            sensor2_estimate=np.asarray(msg.sensor2_estimate, dtype=float) if len(msg.sensor2_estimate) else None,
            readings=np.array(list(msg.sensor1) + list(msg.sensor2), dtype=float),
            sensor1_range=np.asarray(msg.sensor1_range, dtype=float),
            learner_samples=int(msg.samples) or None)     # a learner's state counts its own sample: 0 = not given
        self.state_wall = time.monotonic()
        if not (self.agent.needs_bumper and not self.bumper_since_command):
            self._step_waiting()

    # --- output ---------------------------------------------------------------------------------------------------
    def _step_waiting(self) -> None:
        observation, self.waiting = self.waiting, None
        observation.bumped = self.bumped
        self._publish(self.agent.step(observation))

    def _publish(self, decision: Decision) -> None:
        for line in decision.log:
            self.get_logger().info(line)
        if decision.command is not None:
            self.last_answered = _ns(decision.stamp)
            self.bumper_since_command = False
            if self.last_command is None:
                self.last_command = Float64MultiArray()
            # written in place (a new message each step cost the lockstep loop microseconds): the latest command,
            # which is what a lost one is re-sent as
            self.last_command.data = np.asarray(decision.command, dtype=float).tolist()
            self.answered_wall = time.monotonic()
            self.command_pub.publish(self.last_command)
        # Stamped with the state it answers (the sim clock on /clock may lag behind the state that just arrived).
        stamp = decision.stamp if decision.stamp is not None else self.state_stamp
        if stamp is None:
            stamp = self.get_clock().now().to_msg()
        # Written only for a subscriber: unread, the status would cost the lockstep loop its serialisation every step.
        if self.status_pub.get_subscription_count():
            msg = self.status_msg                   # every field written each time
            msg.header.stamp = stamp
            msg.phase, msg.phase_name, msg.detail = decision.phase, decision.phase_name, decision.detail
            msg.error, msg.target, msg.step = float(decision.error), list(decision.target), decision.step
            msg.goal_stamp = decision.goal_stamp if decision.goal_stamp is not None else Time()
            self.status_pub.publish(msg)
        if decision.verdict is not None:
            v = decision.verdict
            verdict = ModelVerdict(model_samples=v.model_samples, accepted=v.accepted, reason=v.reason,
                                   learner_samples=v.learner_samples)
            verdict.header.stamp = stamp
            self.verdict_pub.publish(verdict)


def main(args=None):
    run_node(SwitchingControllerNode, args)


if __name__ == '__main__':
    main()
