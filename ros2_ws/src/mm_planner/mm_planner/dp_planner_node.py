"""DP planner node: the thin ROS driver of mm_planner.arm_agent.ArmAgent (paper Section 3.3): explore the arm's joint
space, wait for the learned collision map, then - for every goal - plan with value iteration on the joint grid on a
map of the current frame, before moving, and drive the arm cell by cell.

    ./mm run mm_planner dp_planner --ros-args -p use_sim_time:=true -p exploration_steps:=500

Subscribes `arm/joint_states`, `arm/contact` (mm_msgs/Contact: the hand's touch sensor, stamped with its frame),
`arm/embedding/state` (pacing only), `arm/embedding/collision_map` (mm_msgs/CollisionMap, TRANSIENT_LOCAL, stamped
with the frame it was built from) and `arm/robot_description` (std_msgs/String URDF, TRANSIENT_LOCAL: the joint box;
nothing is explored or planned before it comes, and a map or topic goal that came earlier is acted on then); goal as
joint angles on `arm/goal` (std_msgs/Float64MultiArray [shoulder_roll, shoulder_pitch] rad, TRANSIENT_LOCAL) or
through the `arm/set_goal` service (mm_msgs/SetJointGoal).
Either kind of goal is stamped with the node's clock (sim time) when accepted; the service's reply says
`goal_stamp=<sec>.<nanosec>` and every ControllerStatus on `arm/planner/status` carries it in `goal_stamp`.
Publishes joint targets on `arm/joint_position_controller/commands`, its phase on `arm/planner/status`, and
`arm/embedding/map_request` (std_msgs/Header: stamp = the frame a collision map is needed of; the image_embedding
node answers with a map of that frame).

Phases and planning: see mm_planner.arm_agent. Timeouts are wall-clock (sim time stands still while the loop
waits): `learning_timeout` in LEARNING explores more; `map_timeout` without a map of the current frame FAILS the goal.

Lockstep: one command per frame, given once the frame's joint state and touch reading are in (and, with
`wait_for_embedding`, its embedding, at most `embedding_timeout` wall seconds). Every input is validated; a bad one
is dropped with a throttled log line and the node keeps running.
"""
from __future__ import annotations

import math
import time
from typing import Optional

import numpy as np
from builtin_interfaces.msg import Time
from mm_common.node_utils import check_parameters, declare, reject_input, run_node
from mm_common.robot_description import joint_box
from mm_msgs.msg import CollisionMap, Contact, ControllerStatus, EmbeddingState
from mm_msgs.srv import SetJointGoal
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, Header, String

from mm_planner.arm_agent import (EXPLORATION_STEPS, PHASE_LEARNING, PHASE_NAMES, PHASE_PLANNING, ArmAgent,
                                  ArmObservation)

# Lockstep loop: RELIABLE, a lost joint state or command would stall the loop.
LOOP_QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
# Goals, the collision map and the robot description are latched state: TRANSIENT_LOCAL so whoever starts later
# still gets the latest.
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                         history=HistoryPolicy.KEEP_LAST)
# Map requests: RELIABLE (the planner waits for the answer), volatile (a request is about the present frame only).
REQUEST_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
MAX_PENDING_FRAMES = 200
# A frame stamped further ahead of the node's clock than this is rejected (a bogus stamp would otherwise make every
# later, valid frame look old); with sim time the clock trails the simulator's frames by one /clock message at most.
FUTURE_MARGIN_NS = 60 * 1_000_000_000


def stamp_ns(stamp: Time) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def ns_to_time(ns: int) -> Time:
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def cells_problem(rows: int, cols: int, lim0, lim1, tolerance: float) -> str:
    """'' if a rows x cols grid over the joint limits leaves cells wider than the arrival tolerance, else why not."""
    step = min((lim0[1] - lim0[0]) / rows, (lim1[1] - lim1[0]) / cols)
    if not step > 2 * tolerance:
        return f'grid cells of {step:.4g} rad are not wider than twice arrival_tolerance={tolerance}'
    return ''


class DpPlannerNode(Node):
    def __init__(self, **node_kwargs):
        super().__init__('dp_planner', **node_kwargs)
        rows = declare(self, 'grid_rows', 8, 'Joint grid rows (joint 0)', min_value=1, max_value=200, read_only=True)
        cols = declare(self, 'grid_cols', 12, 'Joint grid cols (joint 1)', min_value=1, max_value=200,
                       read_only=True)
        agent_params = dict(
            exploration_steps=declare(self, 'exploration_steps', EXPLORATION_STEPS, 'Random-motion commands before '
                                      'learning (0 = none: use a map that is already there)', min_value=0,
                                      max_value=1000000, read_only=True),
            exploration_seed=declare(self, 'exploration_seed', 0, 'Seed of the exploration targets', min_value=0,
                                     max_value=2**31 - 1, read_only=True),
            contact_share=declare(self, 'contact_share', 0.25, 'Share of exploration targets drawn near '
                                  'configurations where contact was felt', min_value=0.0, max_value=1.0,
                                  read_only=True),
            contact_spread=declare(self, 'contact_spread', 0.08, 'Spread of those targets [rad]', min_value=0.0,
                                   max_value=1.0, read_only=True),
            max_execution_steps=declare(self, 'max_execution_steps', 300, 'Steps before an execution FAILS',
                                        min_value=1, max_value=1000000),
            arrival_tolerance=declare(self, 'arrival_tolerance', 1e-3, 'A cell centre is reached within this [rad]',
                                      min_value=1e-9, max_value=0.5),
            step_reward=declare(self, 'step_reward', -1.0, 'Reward per step (paper: -1)', min_value=-1000.0,
                                max_value=0.0, read_only=True),
            collision_reward=declare(self, 'collision_reward', -100.0, 'Reward for entering a predicted collision '
                                     'cell (paper: -100)', min_value=-1e6, max_value=0.0, read_only=True),
            goal_reward=declare(self, 'goal_reward', 0.0, 'Reward for reaching the goal cell (paper: 0)',
                                min_value=-1e6, max_value=1e6, read_only=True),
            clearance_reward=declare(self, 'clearance_reward', -5.0, 'Extra reward for entering a free cell on the '
                                     'contact region\'s surface (0 = the paper\'s rewards only)', min_value=-1000.0,
                                     max_value=0.0, read_only=True),
            clearance=declare(self, 'clearance', 1.0, 'Closeness below -clearance costs nothing extra',
                              min_value=1e-3, max_value=100.0, read_only=True),
            through_predicted_collision=declare(self, 'through_predicted_collision', False, 'When no '
                                                'collision-free path exists on the map, follow the DP policy through '
                                                'predicted collision cells (paper rewards) instead of FAILING',
                                                read_only=True))
        self.use_blocked_moves = declare(self, 'use_blocked_moves', True, "Plan on the map's blocked moves when it "
                                         "has them (a cell is crossed along its free moves); false: on the per-cell "
                                         "map only, as the paper (chosen by mm_bringup.tune_arm_reach)",
                                         read_only=True)
        self.wait_for_embedding = declare(self, 'wait_for_embedding', True,
                                          'Pace commands on arm/embedding/state of the same frame')
        self.embedding_timeout = declare(self, 'embedding_timeout', 5.0, 'Wall seconds to wait for an embedding '
                                         'before commanding anyway', min_value=0.0, max_value=600.0)
        self.learning_timeout = declare(self, 'learning_timeout', 120.0, 'Wall seconds in LEARNING before exploring '
                                        'more', min_value=1.0, max_value=3600.0)
        self.map_timeout = declare(self, 'map_timeout', 60.0, 'Wall seconds a goal waits for a collision map of the '
                                   'current frame before it FAILS', min_value=0.1, max_value=3600.0)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        # The agent needs the robot's joint box: it is built when arm/robot_description comes.
        self.grid_shape = (rows, cols)
        self.agent_params = agent_params
        self.agent: Optional[ArmAgent] = None
        self.grid = None
        self.waiting_latched: dict = {}   # the latest map / topic goal that came before the robot description
        self.joints: dict = {}            # frame stamp -> joints, until the frame is acted on
        self.contacts: dict = {}          # frame stamp -> touch reading
        self.embedded = set()
        self.latest_stamp: Optional[int] = None
        self.acted_stamp: Optional[int] = None
        self.frame_wall = {}
        self.phase_since = time.monotonic()
        self.contacts_while_executing = 0

        self.cmd_pub = self.create_publisher(Float64MultiArray, 'arm/joint_position_controller/commands', LOOP_QOS)
        self.status_pub = self.create_publisher(ControllerStatus, 'arm/planner/status', LOOP_QOS)
        self.request_pub = self.create_publisher(Header, 'arm/embedding/map_request', REQUEST_QOS)
        self.create_subscription(JointState, 'arm/joint_states', self._on_joints, LOOP_QOS)
        self.create_subscription(Contact, 'arm/contact', self._on_contact, LOOP_QOS)
        self.create_subscription(EmbeddingState, 'arm/embedding/state', self._on_embedding, LOOP_QOS)
        self.create_subscription(CollisionMap, 'arm/embedding/collision_map', self._on_map, LATCHED_QOS)
        self.create_subscription(Float64MultiArray, 'arm/goal', self._on_goal_msg, LATCHED_QOS)
        self.create_service(SetJointGoal, 'arm/set_goal', self._on_set_goal)
        self.create_subscription(String, 'arm/robot_description', self._on_robot_description, LATCHED_QOS)
        # Wall-clock timer: embedding, learning and map timeouts must fire while sim time stands still.
        self.create_timer(0.2, self._on_wall_timer, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f'dp_planner ready: {rows}x{cols} grid, exploring '
                               f'{agent_params["exploration_steps"]} steps once arm/robot_description gives the '
                               'joint box')

    # --- the robot --------------------------------------------------------------------------------------------
    def _on_robot_description(self, msg: String) -> None:
        """Build the agent over the robot's joint box (once: a description with another box is refused, restart the
        node for a new robot); then act on a map or goal that came earlier."""
        try:
            limits = joint_box(msg.data, 2)
        except ValueError as exc:
            reject_input(self, 'arm/robot_description', str(exc))
            return
        if self.agent is not None:
            if not np.allclose(limits, self.grid.limits):
                reject_input(self, 'arm/robot_description', f'joint box {limits.tolist()} differs from the one this '
                                                            f'node plans over, {self.grid.limits.tolist()}; restart '
                                                            'the node for a new robot')
            return
        problem = cells_problem(*self.grid_shape, limits[0], limits[1], self.agent_params['arrival_tolerance'])
        if problem:
            reject_input(self, 'arm/robot_description', problem)
            return
        self.agent = ArmAgent(limits, self.grid_shape, **self.agent_params)
        self.grid = self.agent.grid
        self.get_logger().info(f'joint box from arm/robot_description: {limits.tolist()} rad')
        self._publish_transitions()
        waiting, self.waiting_latched = self.waiting_latched, {}
        if 'map' in waiting:
            self._on_map(waiting['map'])
        if 'goal' in waiting:
            self._on_goal_msg(waiting['goal'])
        self._try_act()

    # --- parameters -------------------------------------------------------------------------------------------
    def _on_set_parameters(self, params) -> SetParametersResult:
        result = check_parameters(self, params, [lambda v: '' if self.grid is None else cells_problem(
            self.grid.rows, self.grid.cols, self.grid.limits[0], self.grid.limits[1], v.get('arrival_tolerance'))])
        if not result.successful:
            return result
        for name in ('max_execution_steps', 'arrival_tolerance'):
            value = next((p.value for p in params if p.name == name), None)
            if value is not None:
                self.agent_params[name] = value           # for an agent built later
        for p in params:
            if p.name == 'wait_for_embedding':
                self.wait_for_embedding = bool(p.value)
            elif p.name == 'embedding_timeout':
                self.embedding_timeout = float(p.value)
            elif p.name == 'learning_timeout':
                self.learning_timeout = float(p.value)
            elif p.name == 'map_timeout':
                self.map_timeout = float(p.value)
            elif p.name == 'max_execution_steps' and self.agent is not None:
                self.agent.max_execution_steps = int(p.value)
            elif p.name == 'arrival_tolerance' and self.agent is not None:
                self.agent.arrival_tolerance = float(p.value)
        return SetParametersResult(successful=True)

    # --- inputs -----------------------------------------------------------------------------------------------
    def _frame_stamp(self, header, source: str) -> Optional[int]:
        stamp = stamp_ns(header.stamp)
        now = self.get_clock().now().nanoseconds
        if self.acted_stamp is not None and now + FUTURE_MARGIN_NS < self.acted_stamp:
            # the clock itself went back (the simulator restarted): the loop starts again from its frames
            self.get_logger().warn('the clock went back before the last frame acted on: restarting the loop')
            self.acted_stamp = self.latest_stamp = None
            self.joints.clear()
            self.contacts.clear()
            self.frame_wall.clear()
        if stamp > now + FUTURE_MARGIN_NS:
            reject_input(self, source, f'stamp {stamp * 1e-9:.3f} s is more than {FUTURE_MARGIN_NS * 1e-9:.0f} s '
                                       f'ahead of the clock ({now * 1e-9:.3f} s)')
            return None
        if self.acted_stamp is not None and stamp < self.acted_stamp:
            reject_input(self, source, f'stamp {stamp} ns is older than the frame already acted on '
                                       f'({self.acted_stamp} ns)')
            return None
        return stamp

    def _forget_old(self) -> None:
        for store in (self.joints, self.contacts, self.frame_wall):
            if len(store) > MAX_PENDING_FRAMES:
                for old in sorted(store)[:len(store) - MAX_PENDING_FRAMES]:
                    del store[old]
        if len(self.embedded) > 2 * MAX_PENDING_FRAMES:
            self.embedded = set(sorted(self.embedded)[-MAX_PENDING_FRAMES:])

    def _on_joints(self, msg: JointState) -> None:
        if len(msg.position) != 2 or not all(math.isfinite(v) for v in msg.position):
            reject_input(self, 'arm/joint_states', f'need 2 finite positions, got {list(msg.position)}')
            return
        stamp = self._frame_stamp(msg.header, 'arm/joint_states')
        if stamp is None or stamp in self.joints or stamp == self.acted_stamp:
            return            # a re-published frame
        self.joints[stamp] = np.asarray(msg.position, dtype=float)
        self.frame_wall[stamp] = time.monotonic()
        self.latest_stamp = max(stamp, self.latest_stamp or stamp)
        self._forget_old()
        self._try_act()

    def _on_contact(self, msg: Contact) -> None:
        stamp = self._frame_stamp(msg.header, 'arm/contact')
        if stamp is None:
            return
        self.contacts[stamp] = bool(msg.in_contact)
        if msg.in_contact and self.agent is not None and self.agent.phase_name == 'EXECUTING':
            self.contacts_while_executing += 1
            self.get_logger().warn(f'contact while executing ({self.contacts_while_executing} so far)',
                                   throttle_duration_sec=1.0)
        self._forget_old()
        self._try_act()

    def _on_embedding(self, msg: EmbeddingState) -> None:
        self.embedded.add(stamp_ns(msg.header.stamp))
        self._forget_old()
        self._try_act()

    def map_problem(self, msg: CollisionMap) -> str:
        """'' if the map fits this planner's grid, else what is wrong with it."""
        if (msg.rows, msg.cols) != self.grid.shape:
            return f'map is {msg.rows}x{msg.cols}, the planner grid is {self.grid.shape[0]}x{self.grid.shape[1]}'
        if len(msg.collision) != msg.rows * msg.cols:
            return f'{len(msg.collision)} collision cells for a {msg.rows}x{msg.cols} map'
        if len(msg.closeness) not in (0, len(msg.collision)):
            return f'{len(msg.closeness)} closeness values for {len(msg.collision)} cells'
        if any(math.isnan(v) or v == math.inf for v in msg.closeness):
            return 'closeness values must be finite or -inf'
        if len(msg.blocked_moves) not in (0, 4 * len(msg.collision)):
            return f'{len(msg.blocked_moves)} blocked_moves for {len(msg.collision)} cells (need 4 per cell or none)'
        limits = [list(msg.joint0_limits), list(msg.joint1_limits)]
        if [len(v) for v in limits] != [2, 2] or not all(math.isfinite(v) for pair in limits for v in pair):
            return f'joint limits must be two finite [min, max] pairs, got {limits}'
        if not np.allclose(limits, self.grid.limits):
            return f'joint limits {limits} differ from the planner\'s {self.grid.limits.tolist()}'
        return ''

    def _on_map(self, msg: CollisionMap) -> None:
        if self.agent is None:
            self.waiting_latched['map'] = msg           # checked once the joint box is known
            return
        problem = self.map_problem(msg)
        now = self.get_clock().now().nanoseconds
        if not problem and stamp_ns(msg.header.stamp) > now + FUTURE_MARGIN_NS:
            problem = f'map stamped {stamp_ns(msg.header.stamp) * 1e-9:.3f} s, ahead of the clock ({now * 1e-9:.3f} s)'
        if problem:
            reject_input(self, 'arm/embedding/collision_map', problem)
            return
        closeness = np.array(msg.closeness, float).reshape(self.grid.shape) if len(msg.closeness) else None
        collision = np.array(msg.collision, bool).reshape(self.grid.shape)
        moves = (np.array(msg.blocked_moves, bool).reshape(*self.grid.shape, 4).transpose(2, 0, 1)
                 if len(msg.blocked_moves) and self.use_blocked_moves else None)   # (row*cols + col)*4 + move
        stamp = stamp_ns(msg.header.stamp)
        changed = self.agent.set_map(collision, closeness, stamp, moves)
        blocked = '' if moves is None else f', {int(moves.sum())} blocked moves'
        self.get_logger().info(f'collision map of frame {stamp * 1e-9:.3f} s: {int(collision.sum())} collision '
                               f'cells{blocked}{" (changed)" if changed else ""}')
        self._publish_transitions()
        self._try_act()

    def _accept_goal(self, values, source: str) -> str:
        problem = ('no robot description yet (arm/robot_description): the joint box is unknown' if self.agent is None
                   else self.agent.validate_goal(values))
        if problem:
            reject_input(self, source, problem)
            return problem
        stamp = self.get_clock().now().nanoseconds
        self.agent.set_goal(values, stamp)
        self.get_logger().info(f'goal {list(values)} -> cell {self.agent.goal_cell_} (goal_stamp {stamp * 1e-9:.3f} '
                               f's, phase {self.agent.phase_name})')
        self._on_phase_change()
        self._publish_transitions()
        self._try_act()
        return ''

    def _on_goal_msg(self, msg: Float64MultiArray) -> None:
        if self.agent is None:
            self.waiting_latched['goal'] = msg          # latched: it is meant for when the planner can plan
            return
        self._accept_goal(list(msg.data), 'arm/goal')

    def _on_set_goal(self, request: SetJointGoal.Request, response: SetJointGoal.Response):
        problem = self._accept_goal(list(request.positions), 'arm/set_goal')
        response.accepted = not problem
        if problem:
            response.message = problem
        else:
            t = ns_to_time(self.agent.goal_stamp_)
            response.message = (f'goal_stamp={t.sec}.{t.nanosec:09d} cell {self.agent.goal_cell_}, phase '
                                f'{self.agent.phase_name}')
        return response

    def _on_wall_timer(self) -> None:
        if self.agent is None:
            self.get_logger().warn('waiting for arm/robot_description (the joint box) before exploring',
                                   throttle_duration_sec=10.0)
            return
        waited = time.monotonic() - self.phase_since
        if self.agent.phase_ == PHASE_LEARNING and waited > self.learning_timeout:
            self.agent.explore_more(f'no collision map after {self.learning_timeout:.0f} s: exploring more')
        elif self.agent.phase_ == PHASE_PLANNING and waited > self.map_timeout:
            self.agent.fail(f'no collision map of the current frame after {self.map_timeout:.0f} s')
        self._publish_transitions()
        self._try_act(timer=True)

    # --- output -----------------------------------------------------------------------------------------------
    def _on_phase_change(self) -> None:
        self.phase_since = time.monotonic()

    def _status(self, phase: int, detail: str, goal_stamp: Optional[int]) -> ControllerStatus:
        s = self.agent.status()
        msg = ControllerStatus(phase=phase, phase_name=PHASE_NAMES[phase], detail=detail,
                               step=s['step'])
        msg.header.stamp = self.get_clock().now().to_msg()
        if s['error'] is not None:
            msg.error = s['error']
        if s['target'] is not None:
            msg.target = s['target']
        if goal_stamp is not None:
            msg.goal_stamp = ns_to_time(goal_stamp)
        return msg

    def _publish_transitions(self) -> None:
        if self.agent is None:
            return
        transitions = self.agent.pop_transitions()
        for t in transitions:
            self.get_logger().info(f'-> {PHASE_NAMES[t.phase]}: {t.detail}')
            self.status_pub.publish(self._status(t.phase, t.detail, t.goal_stamp))
        if transitions:
            self._on_phase_change()

    # --- acting once per frame --------------------------------------------------------------------------------
    def _try_act(self, timer: bool = False) -> None:
        stamp = self.latest_stamp
        if self.agent is None or stamp is None or stamp == self.acted_stamp or stamp not in self.joints:
            return
        waited = time.monotonic() - self.frame_wall.get(stamp, time.monotonic()) > self.embedding_timeout
        if stamp not in self.contacts:
            if not (timer and waited):
                return
            self.get_logger().warn(f'no touch reading for frame {stamp * 1e-9:.3f} s after {self.embedding_timeout} '
                                   's; taking it as no contact', throttle_duration_sec=5.0)
        if self.wait_for_embedding and stamp not in self.embedded:
            if not (timer and waited):
                return
            self.get_logger().warn(f'no embedding for the frame after {self.embedding_timeout} s; commanding anyway',
                                   throttle_duration_sec=5.0)
        command = self.agent.step(ArmObservation(stamp, self.joints[stamp], self.contacts.get(stamp, False)))
        request = self.agent.take_map_request()
        if request is not None:
            header = Header(stamp=ns_to_time(request), frame_id='joint_grid')
            self.request_pub.publish(header)
            self.get_logger().info(f'requested a collision map of frame {request * 1e-9:.3f} s')
        self._publish_transitions()
        if command is None:
            return
        self.acted_stamp = stamp
        for store in (self.joints, self.contacts, self.frame_wall):
            for old in [s for s in store if s <= stamp]:
                del store[old]
        self.cmd_pub.publish(Float64MultiArray(data=[float(v) for v in command]))
        s = self.agent.status()
        self.status_pub.publish(self._status(s['phase'], s['detail'], s['goal_stamp']))


def main(args=None):
    run_node(DpPlannerNode, args)


if __name__ == '__main__':
    main()
