"""Switching controller node: explores, waits for the learned model, then reaches goals given as sensor-2 readings.

    ./mm run mm_planner switching_controller --ros-args -p use_sim_time:=true -p exploration_steps:=10000

One wheel command per `wheeled/manifold/state` (the lockstep loop: simulator -> manifold -> controller ->
simulator). Phases, published on `wheeled/controller/status`: EXPLORING (RandomExplorer: random motion with a
reflex on the readings and the bumper) -> LEARNING (no commands: the loop pauses while the manifold node fits;
a model that has not seen sensor 2 during its excursions cannot map any goal, so `exploration_steps // 4` more
exploration steps follow, until the manifold node's refit has) -> WAITING_FOR_GOAL -> REACHING_SENSOR1 /
REACHING_VIRTUAL_SENSOR1 / REACHING_SENSOR2 (SwitchingController) -> GOAL_REACHED or FAILED (then waiting again).
Goals come as mm_msgs/SensorGoal on `wheeled/goal` (latched) or through the `wheeled/set_goal` service. The learned
model is read from the file the manifold node announces on `wheeled/manifold/model`. Nothing here sees world
coordinates.
"""
from __future__ import annotations

import math
import time
from typing import Optional

import numpy as np
from mm_common.node_utils import declare, reject_non_finite, run_node
from mm_manifold.sensor_manifold import SensorManifoldModel
from mm_msgs.msg import ControllerStatus, ManifoldState, SensorGoal
from mm_msgs.srv import SetSensorGoal
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from builtin_interfaces.msg import Time
from std_msgs.msg import Bool, Float64MultiArray, String

from mm_planner.exploration import RandomExplorer
from mm_planner.switching_controller import SPACE_SENSOR1, SPACE_SENSOR2, SPACE_VIRTUAL, SwitchingController

# The lockstep loop is RELIABLE end to end: a lost state or command would stall the loop.
LOOP_QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
# Goals and the model announcement are latched state.
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
PHASE_NAMES = {getattr(ControllerStatus, n): n[len('PHASE_'):] for n in dir(ControllerStatus) if n.startswith('PHASE_')}
REACHING = {SPACE_SENSOR1: ControllerStatus.PHASE_REACHING_SENSOR1,
            SPACE_VIRTUAL: ControllerStatus.PHASE_REACHING_VIRTUAL_SENSOR1,
            SPACE_SENSOR2: ControllerStatus.PHASE_REACHING_SENSOR2}


class SwitchingControllerNode(Node):
    def __init__(self, **node_kwargs):
        super().__init__('switching_controller', **node_kwargs)
        self.dt = declare(self, 'dt', 0.05, 'Control step = simulator step [s]', min_value=1e-4, max_value=1.0)
        self.exploration_steps = declare(self, 'exploration_steps', 10000,
                                         'Random exploration commands before waiting for the model',
                                         min_value=0, max_value=10_000_000)
        self.max_wheel_speed = declare(self, 'max_wheel_speed', 6.0, 'Largest wheel command while reaching [rad/s]',
                                       min_value=0.1, max_value=30.0)
        self.tolerance = declare(self, 'tolerance', 0.01, 'Goal tolerance per sensor-2 reading [m] when the goal '
                                 'gives none', min_value=1e-4, max_value=0.2)
        self.max_reach_steps = declare(self, 'max_reach_steps', 1500, 'Steps before a reach counts as failed',
                                       min_value=1, max_value=1_000_000)
        self.bumper_wait = declare(self, 'bumper_wait', 0.2, 'Wall seconds a state waits for its bumper reading '
                                   'while exploring', min_value=0.0, max_value=5.0)
        seed = declare(self, 'random_seed', 0, 'Seed of the exploration', min_value=0, max_value=2**31 - 1)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.explorer = RandomExplorer(random_state=seed)
        self.controller: Optional[SwitchingController] = None
        self.model: Optional[SensorManifoldModel] = None
        self.goal: Optional[SensorGoal] = None
        self.goal_stamp = Time()
        self.phase = ControllerStatus.PHASE_EXPLORING if self.exploration_steps else ControllerStatus.PHASE_LEARNING
        self.phase_step = 0
        self.explored = 0
        self.exploration_budget = self.exploration_steps    # grows when the learned model is not ready
        self.bumped = False
        # The bumper reading of a step travels on its own topic and may arrive after the state: in lockstep the
        # first bumper message after a command belongs to the step that command produced, so the explorer (whose
        # reflex reads it) answers a state only once it came, or after `bumper_wait` wall seconds.
        self.bumper_since_command = False
        self.state_wall = 0.0
        self.pending: Optional[ManifoldState] = None
        self.state_stamp = None
        self.last_answered = -1
        self.reach_steps = 0
        self.detail = 'started'

        self.command_pub = self.create_publisher(Float64MultiArray, 'wheeled/wheel_velocity_controller/commands',
                                                 LOOP_QOS)
        self.status_pub = self.create_publisher(ControllerStatus, 'wheeled/controller/status', LOOP_QOS)
        self.create_subscription(ManifoldState, 'wheeled/manifold/state', self._on_state, LOOP_QOS)
        self.create_subscription(Bool, 'wheeled/bumper', self._on_bumper, LOOP_QOS)
        self.create_timer(0.05, self._on_wall_timer, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.create_subscription(String, 'wheeled/manifold/model', self._on_model, LATCHED_QOS)
        self.create_subscription(SensorGoal, 'wheeled/goal', self._on_goal_topic, LATCHED_QOS)
        self.create_service(SetSensorGoal, 'wheeled/set_goal', self._on_set_goal)

    def _on_set_parameters(self, params) -> SetParametersResult:
        result = reject_non_finite(params)
        if result.successful:
            for p in params:
                if p.name in ('tolerance', 'max_reach_steps', 'max_wheel_speed', 'bumper_wait'):
                    setattr(self, p.name, p.value)
        return result

    # --- phase bookkeeping ----------------------------------------------------------------------------------------
    def _set_phase(self, phase: int, detail: str) -> None:
        """Enter `phase` (its step count restarts); a new detail in the same phase (another goal) is logged too."""
        if phase != self.phase or detail != self.detail:
            self.get_logger().info(f'{PHASE_NAMES[self.phase]} -> {PHASE_NAMES[phase]}: {detail}')
        if phase != self.phase:
            self.phase, self.phase_step = phase, 0
        self.detail = detail

    def _status(self, error: float = math.nan, target=()) -> None:
        msg = ControllerStatus()
        # Stamped with the state it answers (the sim clock on /clock may lag behind the state that just arrived).
        msg.header.stamp = self.state_stamp if self.state_stamp is not None else self.get_clock().now().to_msg()
        msg.phase, msg.phase_name, msg.detail = self.phase, PHASE_NAMES[self.phase], self.detail
        msg.error, msg.target, msg.step = float(error), [float(v) for v in target], self.phase_step
        msg.goal_stamp = self.goal_stamp
        self.status_pub.publish(msg)

    # --- inputs ---------------------------------------------------------------------------------------------------
    def _on_model(self, msg: String) -> None:
        if not msg.data:
            self.get_logger().warn('the manifold node keeps its model in memory only (no model_path): cannot control')
            return
        try:
            self.model = SensorManifoldModel.load(msg.data)
        except ValueError as exc:
            self.get_logger().error(str(exc))
            return
        self.get_logger().info(f'model loaded from {msg.data}')
        if not self.model.ready:
            if self.phase == ControllerStatus.PHASE_LEARNING:
                extra = max(self.exploration_steps // 4, 1)
                self.exploration_budget = self.explored + extra
                self._set_phase(ControllerStatus.PHASE_EXPLORING, f'the model has not seen sensor 2: exploring '
                                                                  f'{extra} more steps')
                if self.pending is not None:
                    self._answer(self.pending)
        elif self.phase in (ControllerStatus.PHASE_LEARNING, ControllerStatus.PHASE_EXPLORING):
            skipped = self.phase == ControllerStatus.PHASE_EXPLORING and self.explored < self.exploration_budget
            self._set_phase(ControllerStatus.PHASE_WAITING_FOR_GOAL,
                            'a learned model exists: exploration skipped' if skipped else 'model ready')
            self._start_goal()
        self._status()

    def _on_goal_topic(self, msg: SensorGoal) -> None:
        accepted, reason = self._accept_goal(msg)
        if not accepted:
            self.get_logger().warn(f'goal rejected: {reason}')

    def _on_set_goal(self, request: SetSensorGoal.Request, response: SetSensorGoal.Response):
        response.accepted, response.message = self._accept_goal(request.goal)
        return response

    def _accept_goal(self, goal: SensorGoal):
        reading = np.asarray(goal.reading, dtype=float)
        if goal.sensor_group != SensorGoal.SENSOR2 or reading.shape != (2,):
            return False, 'the goal must be a sensor-2 reading (sensor_group=2, two values)'
        if not np.all(np.isfinite(reading)) or np.any(reading <= 0):
            return False, f'goal reading must be positive and finite, got {list(reading)}'
        if not (goal.tolerance == 0.0 or (math.isfinite(goal.tolerance) and 0 < goal.tolerance < 0.2)):
            return False, f'tolerance {goal.tolerance} out of (0, 0.2) m'
        self.goal = goal
        problem = self._start_goal()
        self._status()
        return (False, problem) if problem else (True, 'accepted')

    def _start_goal(self) -> Optional[str]:
        """Begin reaching once there is both a goal and a model; answer a state that is already waiting. A goal the
        model cannot map ends FAILED under that goal's stamp (so whoever sent it sees the outcome); returns why."""
        if self.goal is None or self.model is None or self.phase in (ControllerStatus.PHASE_EXPLORING,
                                                                     ControllerStatus.PHASE_LEARNING):
            return None
        tolerance = self.goal.tolerance or self.tolerance
        reading = np.asarray(self.goal.reading, dtype=float)
        self.controller = SwitchingController(self.dt, max_wheel_speed=self.max_wheel_speed, tolerance=tolerance)
        try:
            self.controller.set_goal_from_routes(self.model.virtual_, reading, self.model.sensor2_noise_)
        except ValueError as exc:
            self.goal_stamp = self.goal.header.stamp
            self.goal = None
            self._set_phase(ControllerStatus.PHASE_FAILED, f'cannot map the goal: {exc}')
            return self.detail
        self.goal_stamp = self.goal.header.stamp
        self.goal = None
        self.reach_steps = 0
        self._set_phase(ControllerStatus.PHASE_REACHING_SENSOR1, f'goal {list(reading)} (tolerance {tolerance} m)')
        if self.pending is not None:
            self._answer(self.pending)
        return None

    def _on_bumper(self, msg: Bool) -> None:
        self.bumped = bool(msg.data)
        self.bumper_since_command = True
        if self.pending is not None and self.phase == ControllerStatus.PHASE_EXPLORING:
            self._answer(self.pending)

    def _on_wall_timer(self) -> None:
        """A state whose bumper reading never came (a lost message) is answered after bumper_wait."""
        if (self.pending is not None and self.phase == ControllerStatus.PHASE_EXPLORING
                and time.monotonic() - self.state_wall > self.bumper_wait):
            self.bumper_since_command = True
            self._answer(self.pending)

    def _on_state(self, msg: ManifoldState) -> None:
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        if stamp <= self.last_answered:
            return
        self.state_stamp = msg.header.stamp
        self.pending = msg
        self.state_wall = time.monotonic()
        if self.phase == ControllerStatus.PHASE_EXPLORING and not self.bumper_since_command:
            return
        self._answer(msg)

    # --- control ------------------------------------------------------------------------------------------------
    def _answer(self, msg: ManifoldState) -> None:
        command = None
        error, target = math.nan, ()
        if self.phase == ControllerStatus.PHASE_EXPLORING:
            if self.explored >= self.exploration_budget:
                self._set_phase(ControllerStatus.PHASE_LEARNING, f'{self.explored} exploration steps done')
            else:
                readings = np.array(list(msg.sensor1) + list(msg.sensor2), dtype=float)
                command = self.explorer.command(readings, self.bumped)
                self.explored += 1
        elif self.phase in REACHING.values():
            command, error, target = self._reach(msg)
        self.phase_step += 1
        if command is not None:
            self.last_answered = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            self.pending = None
            self.bumper_since_command = False
            self.command_pub.publish(Float64MultiArray(data=[float(v) for v in command]))
        self._status(error, target)

    def _reach(self, msg: ManifoldState):
        m, c = self.model, self.controller
        space = int(msg.active_space)
        coords = np.asarray(msg.coordinates, dtype=float) if len(msg.coordinates) else None
        s2 = np.asarray(msg.sensor2_estimate, dtype=float) if len(msg.sensor2_estimate) else None
        if space in REACHING:
            self._set_phase(REACHING[space], f'{PHASE_NAMES[REACHING[space]].lower()} active')
        J1 = m.regions1_.interpolate(coords) if space == SPACE_SENSOR1 and coords is not None else None
        u, done, error = c.command(space, coords, s2, m.virtual_.field_, m.field2_, J1, m.virtual_bounds(),
                                   m.sensor2_box_, sensor2_measured=all(msg.in_range[3:5]))
        target = c.goal_sensor2 if space == SPACE_SENSOR2 else (c.target if c.target is not None else ())
        if done:
            self._set_phase(ControllerStatus.PHASE_GOAL_REACHED, f'sensor-2 error {error:.4f} m')
            return None, error, target
        self.reach_steps += 1
        if self.reach_steps > self.max_reach_steps:
            self._set_phase(ControllerStatus.PHASE_FAILED, f'not reached within {self.max_reach_steps} steps')
            return None, error, target
        return u, error, target


def main(args=None):
    run_node(SwitchingControllerNode, args)


if __name__ == '__main__':
    main()
