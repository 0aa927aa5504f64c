"""DP planner node: explores the arm's joint space, waits for the learned collision map, then plans with value
iteration on the joint grid and drives the arm cell by cell (paper Section 3.3).

    ./mm run mm_planner dp_planner --ros-args -p use_sim_time:=true -p exploration_steps:=500

Subscribes `arm/joint_states`, `arm/contact` (touch sensor), `arm/embedding/state` (pacing only) and
`arm/embedding/collision_map` (TRANSIENT_LOCAL); goal as joint angles on `arm/goal` (std_msgs/Float64MultiArray
[shoulder_roll, shoulder_pitch] rad, TRANSIENT_LOCAL) or through the `arm/set_goal` service (mm_msgs/SetJointGoal).
Publishes joint targets on `arm/joint_position_controller/commands` and its phase on `arm/planner/status`
(mm_msgs/ControllerStatus).

Phases: EXPLORING (random joint targets from mm_planner.arm_exploration, `exploration_steps` commands) -> LEARNING
(no commands until a collision map arrives; after `learning_timeout` wall seconds without one it explores
`exploration_steps // 4` more steps) -> WAITING_FOR_GOAL -> PLANNING (mm_planner.value_iteration.DPPlanner: reward 0
at the goal cell, -100 for predicted collision cells, -1 per step, plus down to `clearance_reward` for entering a free
cell by its closeness to the contact region in the map, so paths keep clear of it when they can) -> EXECUTING
(command the centre of the next cell until the arm is there, then the next; a changed map replans at once) ->
GOAL_REACHED, or FAILED when no collision-free path exists on the predicted map or `max_execution_steps` pass. A new
goal restarts planning.

Lockstep: one command per received joint state; with `wait_for_embedding` the command for step k waits until the
embedding of frame k is out too (so the learner sees every frame), at most `embedding_timeout` wall seconds.
"""
from __future__ import annotations

import math
import time
from typing import Optional

import numpy as np
from mm_common.node_utils import declare, reject_non_finite, run_node
from mm_msgs.msg import CollisionMap, Contact, ControllerStatus, EmbeddingState
from mm_msgs.srv import SetJointGoal
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from mm_planner.arm_exploration import ArmExplorer
from mm_planner.value_iteration import DPPlanner, JointGrid

# Lockstep loop: RELIABLE, a lost joint state or command would stall the loop.
LOOP_QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
# Goals and the collision map are latched state: TRANSIENT_LOCAL so whoever starts later still gets the latest.
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                         history=HistoryPolicy.KEEP_LAST)
P = ControllerStatus
PHASE_NAMES = {P.PHASE_IDLE: 'IDLE', P.PHASE_EXPLORING: 'EXPLORING', P.PHASE_LEARNING: 'LEARNING',
               P.PHASE_WAITING_FOR_GOAL: 'WAITING_FOR_GOAL', P.PHASE_PLANNING: 'PLANNING',
               P.PHASE_EXECUTING: 'EXECUTING', P.PHASE_GOAL_REACHED: 'GOAL_REACHED', P.PHASE_FAILED: 'FAILED'}


def stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


class DpPlannerNode(Node):
    def __init__(self, **node_kwargs):
        super().__init__('dp_planner', **node_kwargs)
        lim0 = declare(self, 'joint0_limits', [-3.2, -0.8], 'shoulder_roll [min, max] rad', read_only=True)
        lim1 = declare(self, 'joint1_limits', [0.0, 2.2], 'shoulder_pitch [min, max] rad', read_only=True)
        rows = declare(self, 'grid_rows', 8, 'Joint grid rows (joint 0)', min_value=1, max_value=200, read_only=True)
        cols = declare(self, 'grid_cols', 12, 'Joint grid cols (joint 1)', min_value=1, max_value=200,
                       read_only=True)
        self.exploration_steps = declare(self, 'exploration_steps', 500, 'Random-motion commands before learning '
                                         '(0 = none: use a map that is already there)', min_value=0,
                                         max_value=1000000)
        seed = declare(self, 'exploration_seed', 0, 'Seed of the exploration targets', min_value=0,
                       max_value=2**31 - 1)
        contact_share = declare(self, 'contact_share', 0.25, 'Share of exploration targets drawn near configurations '
                                'where contact was felt', min_value=0.0, max_value=1.0, read_only=True)
        spread = declare(self, 'contact_spread', 0.08, 'Spread of those targets [rad]', min_value=0.0, max_value=1.0,
                         read_only=True)
        self.wait_for_embedding = declare(self, 'wait_for_embedding', True,
                                          'Pace commands on arm/embedding/state of the same frame')
        self.embedding_timeout = declare(self, 'embedding_timeout', 5.0, 'Wall seconds to wait for an embedding '
                                         'before commanding anyway', min_value=0.0, max_value=600.0)
        self.learning_timeout = declare(self, 'learning_timeout', 120.0, 'Wall seconds in LEARNING before exploring '
                                        'more', min_value=1.0, max_value=3600.0)
        self.max_execution_steps = declare(self, 'max_execution_steps', 300, 'Steps before an execution FAILS',
                                           min_value=1, max_value=1000000)
        self.tolerance = declare(self, 'arrival_tolerance', 1e-3, 'A cell centre is reached within this [rad]',
                                 min_value=1e-9, max_value=0.5)
        rewards = [declare(self, 'step_reward', -1.0, 'Reward per step', max_value=0.0, read_only=True),
                   declare(self, 'collision_reward', -100.0, 'Reward for entering a predicted collision cell',
                           max_value=0.0, read_only=True),
                   declare(self, 'goal_reward', 0.0, 'Reward for reaching the goal cell', read_only=True)]
        clearance = dict(
            clearance_reward=declare(self, 'clearance_reward', -5.0, 'Extra reward for entering a free cell on the '
                                     'contact region\'s surface (0 = the paper\'s rewards only)', max_value=0.0,
                                     read_only=True),
            clearance=declare(self, 'clearance', 1.0, 'Closeness below -clearance costs nothing extra',
                              min_value=1e-3, max_value=100.0, read_only=True))
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.grid = JointGrid(lim0, lim1, rows, cols)
        self.planner = DPPlanner(self.grid, *rewards, **clearance)
        self.explorer = ArmExplorer(self.grid.limits, contact_share=contact_share, spread=spread, random_state=seed)
        self.phase = P.PHASE_EXPLORING if self.exploration_steps > 0 else P.PHASE_LEARNING
        self.phase_step = 0
        self.detail = 'start'
        self.explored = 0
        self.explore_budget = self.exploration_steps
        self.have_map = False
        self.map_updates = 0
        self.goal_joints: Optional[np.ndarray] = None
        self.goal_cell = None
        self.target: Optional[np.ndarray] = None
        self.joints: Optional[np.ndarray] = None
        self.joints_stamp: Optional[int] = None
        self.acted_stamp: Optional[int] = None
        self.joints_wall = 0.0
        self.embedded_stamps = set()
        self.last_contact = False
        # The touch reading of a step travels on its own topic and may arrive after the joint state: in lockstep the
        # first contact message after a command belongs to the step that command produced, so act only once it came.
        self.contact_since_command = False
        self.contacts_while_executing = 0
        self.commands_sent = 0
        self.learning_since = time.monotonic()

        self.cmd_pub = self.create_publisher(Float64MultiArray, 'arm/joint_position_controller/commands', LOOP_QOS)
        self.status_pub = self.create_publisher(ControllerStatus, 'arm/planner/status', LOOP_QOS)
        self.create_subscription(JointState, 'arm/joint_states', self._on_joints, LOOP_QOS)
        self.create_subscription(Contact, 'arm/contact', self._on_contact, LOOP_QOS)
        self.create_subscription(EmbeddingState, 'arm/embedding/state', self._on_embedding, LOOP_QOS)
        self.create_subscription(CollisionMap, 'arm/embedding/collision_map', self._on_map, LATCHED_QOS)
        self.create_subscription(Float64MultiArray, 'arm/goal', self._on_goal_msg, LATCHED_QOS)
        self.create_service(SetJointGoal, 'arm/set_goal', self._on_set_goal)
        # Wall-clock timer: embedding and learning timeouts must fire while sim time stands still.
        self.create_timer(0.2, self._on_wall_timer, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f'dp_planner ready: {rows}x{cols} grid, exploring {self.exploration_steps} steps')

    # --- parameters -------------------------------------------------------------------------------------------
    def _on_set_parameters(self, params) -> SetParametersResult:
        result = reject_non_finite(params)
        if not result.successful:
            return result
        for p in params:
            if p.name == 'wait_for_embedding':
                self.wait_for_embedding = bool(p.value)
            elif p.name == 'embedding_timeout':
                self.embedding_timeout = float(p.value)
            elif p.name == 'learning_timeout':
                self.learning_timeout = float(p.value)
            elif p.name == 'max_execution_steps':
                self.max_execution_steps = int(p.value)
            elif p.name == 'arrival_tolerance':
                self.tolerance = float(p.value)
            elif p.name in ('exploration_steps', 'exploration_seed'):
                return SetParametersResult(successful=False, reason=f'{p.name} can only be set at start-up')
        return SetParametersResult(successful=True)

    # --- inputs -----------------------------------------------------------------------------------------------
    def _on_joints(self, msg: JointState) -> None:
        if len(msg.position) != 2 or not all(math.isfinite(v) for v in msg.position):
            self.get_logger().warn('ignoring joint state without 2 finite positions', throttle_duration_sec=2.0)
            return
        stamp = stamp_ns(msg.header)
        if stamp == self.joints_stamp:
            return            # re-published step
        self.joints = np.asarray(msg.position, dtype=float)
        self.joints_stamp = stamp
        self.joints_wall = time.monotonic()
        self._try_act()

    def _on_contact(self, msg: Contact) -> None:
        if self.acted_stamp is not None and stamp_ns(msg.header) <= self.acted_stamp:
            return            # a re-sent reading of a step already acted on
        self.last_contact = bool(msg.in_contact)
        self.contact_since_command = True
        self._try_act()
        if msg.in_contact and self.phase == P.PHASE_EXECUTING:
            self.contacts_while_executing += 1
            self.get_logger().warn(f'contact while executing ({self.contacts_while_executing} so far)',
                                   throttle_duration_sec=1.0)

    def _on_embedding(self, msg: EmbeddingState) -> None:
        self.embedded_stamps.add(stamp_ns(msg.header))
        if len(self.embedded_stamps) > 1000:
            self.embedded_stamps = set(sorted(self.embedded_stamps)[-500:])
        self._try_act()

    def _on_map(self, msg: CollisionMap) -> None:
        if (msg.rows, msg.cols) != self.grid.shape or len(msg.collision) != msg.rows * msg.cols:
            self.get_logger().error(f'collision map {msg.rows}x{msg.cols} with {len(msg.collision)} cells does not '
                                    f'match the {self.grid.shape} grid; ignored', throttle_duration_sec=5.0)
            return
        if not np.allclose([*msg.joint0_limits, *msg.joint1_limits], self.grid.limits.ravel()):
            self.get_logger().error('collision map joint limits differ from ours; ignored', throttle_duration_sec=5.0)
            return
        closeness = None                  # none sent: the paper's rewards only
        if len(msg.closeness) == len(msg.collision):
            closeness = np.array(msg.closeness, float).reshape(self.grid.shape)
        elif len(msg.closeness):
            self.get_logger().warn(f'collision map closeness has {len(msg.closeness)} values for '
                                   f'{len(msg.collision)} cells; planning without clearance',
                                   throttle_duration_sec=5.0)
        try:
            changed = self.planner.update_collision(np.array(msg.collision, bool).reshape(self.grid.shape), closeness)
        except ValueError as exc:
            self.get_logger().error(f'collision map rejected: {exc}', throttle_duration_sec=5.0)
            return
        self.have_map = True
        self.map_updates += 1
        self.get_logger().info(f'collision map {self.map_updates}: {sum(msg.collision)} collision cells'
                               f"{' (changed: replanned)' if changed and self.goal_cell is not None else ''}")
        if self.phase == P.PHASE_LEARNING:
            self._set_phase(P.PHASE_WAITING_FOR_GOAL, 'collision map received')
            if self.goal_cell is not None:
                self._start_planning('goal given before learning finished')
        elif self.phase == P.PHASE_EXECUTING and changed:
            self._check_path('map changed')
        self._try_act()

    def _validate_goal(self, values) -> str:
        if len(values) != 2 or not all(math.isfinite(v) for v in values):
            return 'goal must be 2 finite joint angles [shoulder_roll, shoulder_pitch]'
        lim = self.grid.limits
        if any(v < lo or v > hi for v, (lo, hi) in zip(values, lim)):
            return f'goal {list(values)} outside the joint limits {lim.tolist()}'
        return ''

    def _accept_goal(self, values) -> str:
        problem = self._validate_goal(values)
        if problem:
            self.get_logger().warn(f'rejected goal: {problem}', throttle_duration_sec=1.0)
            return problem
        self.goal_joints = np.asarray(values, dtype=float)
        self.goal_cell = self.grid.cell_of(self.goal_joints)
        self.get_logger().info(f'goal {self.goal_joints.tolist()} -> cell {self.goal_cell}')
        if self.phase in (P.PHASE_WAITING_FOR_GOAL, P.PHASE_GOAL_REACHED, P.PHASE_FAILED, P.PHASE_PLANNING,
                          P.PHASE_EXECUTING):
            self._start_planning('new goal')
            self._try_act()
        return ''

    def _on_goal_msg(self, msg: Float64MultiArray) -> None:
        self._accept_goal(list(msg.data))

    def _on_set_goal(self, request: SetJointGoal.Request, response: SetJointGoal.Response):
        problem = self._accept_goal(list(request.positions))
        response.accepted = not problem
        response.message = problem or f'goal cell {self.goal_cell}, phase {PHASE_NAMES[self.phase]}'
        return response

    def _on_wall_timer(self) -> None:
        now = time.monotonic()
        if self.phase == P.PHASE_LEARNING and now - self.learning_since > self.learning_timeout:
            self.explore_budget = self.explored + max(50, self.exploration_steps // 4)
            self._set_phase(P.PHASE_EXPLORING, f'no collision map after {self.learning_timeout:.0f} s: exploring more')
        self._try_act(timer=True)

    # --- phases -----------------------------------------------------------------------------------------------
    def _set_phase(self, phase: int, detail: str) -> None:
        if phase != self.phase:
            self.get_logger().info(f'{PHASE_NAMES[self.phase]} -> {PHASE_NAMES[phase]}: {detail}')
        self.phase, self.detail, self.phase_step = phase, detail, 0
        if phase == P.PHASE_LEARNING:
            self.learning_since = time.monotonic()
        self._publish_status()

    def _start_planning(self, why: str) -> None:
        self._set_phase(P.PHASE_PLANNING, why)
        self.planner.set_goal(self.goal_cell)
        self.target = None
        self._set_phase(P.PHASE_EXECUTING, f'planned to cell {self.goal_cell} ({why})')
        self._check_path('planned')

    def _check_path(self, why: str) -> None:
        if self.joints is None:
            return
        path = self.planner.plan(self.grid.cell_of(self.joints), allow_collision=False)
        if path is None:
            self._set_phase(P.PHASE_FAILED, f'no collision-free path to cell {self.goal_cell} on the predicted map '
                                            f'({why})')

    def _publish_status(self) -> None:
        s = ControllerStatus(phase=self.phase, phase_name=PHASE_NAMES[self.phase], detail=self.detail,
                             step=self.phase_step)
        s.header.stamp = self.get_clock().now().to_msg()
        if self.goal_joints is not None and self.joints is not None:
            s.error = float(np.linalg.norm(self.joints - self.goal_joints))
        if self.target is not None:
            s.target = [float(v) for v in self.target]
        self.status_pub.publish(s)

    # --- acting once per step ---------------------------------------------------------------------------------
    def _try_act(self, timer: bool = False) -> None:
        if self.joints is None or self.acted_stamp == self.joints_stamp:
            return
        waited = timer and time.monotonic() - self.joints_wall > self.embedding_timeout
        if not self.contact_since_command and not waited:
            return
        if self.wait_for_embedding and self.joints_stamp not in self.embedded_stamps:
            if not (timer and time.monotonic() - self.joints_wall > self.embedding_timeout):
                return
            self.get_logger().warn(f'no embedding for the frame after {self.embedding_timeout} s; commanding anyway',
                                   throttle_duration_sec=5.0)
        command = self._decide()
        if command is None:
            return
        self.acted_stamp = self.joints_stamp
        self.contact_since_command = False
        self.phase_step += 1
        self.commands_sent += 1
        self.cmd_pub.publish(Float64MultiArray(data=[float(v) for v in command]))
        self._publish_status()

    def _decide(self) -> Optional[np.ndarray]:
        """Command for the current step, or None to send nothing (the lockstep simulator then waits)."""
        q = self.joints
        if self.phase == P.PHASE_EXPLORING:
            if self.explored >= self.explore_budget:
                self._set_phase(P.PHASE_LEARNING if not self.have_map else P.PHASE_WAITING_FOR_GOAL,
                                f'explored {self.explored} steps')
                if self.have_map and self.goal_cell is not None:
                    self._start_planning('exploration finished')
                    return self._decide()
                return None
            self.explored += 1
            self.target = self.explorer.next_command(q, self.last_contact)
            return self.target
        if self.phase != P.PHASE_EXECUTING:
            return None
        if self.phase_step >= self.max_execution_steps:
            self._set_phase(P.PHASE_FAILED, f'goal not reached in {self.max_execution_steps} steps')
            return None
        cell = self.grid.cell_of(q)
        if self.target is None:
            self.target = self.grid.centre(cell)       # first settle in the centre of the current cell
        if np.max(np.abs(q - self.target)) <= self.tolerance:
            if cell == self.goal_cell:
                self._set_phase(P.PHASE_GOAL_REACHED, f'at the centre of goal cell {cell}')
                return None
            nxt = self.planner.next_cell(cell)
            if nxt is None:
                self._set_phase(P.PHASE_FAILED, f'no move from cell {cell}')
                return None
            if self.planner.collision_[nxt]:
                self._set_phase(P.PHASE_FAILED, f'next cell {nxt} is predicted as collision')
                return None
            self.target = self.grid.centre(nxt)
        return self.target


def main(args=None):
    run_node(DpPlannerNode, args)


if __name__ == '__main__':
    main()
