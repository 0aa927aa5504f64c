"""The dp_planner node in-process (own Context): the thin driver of ArmAgent. A goal asks for a collision map of the
current frame and nothing moves before it arrives; every status names its goal (goal_stamp); malformed joint states,
touch readings, maps and goals are rejected with the node still answering the next valid input; parameters that
only take effect at start-up are read-only and cross-parameter constraints hold."""
import math

import numpy as np
import pytest
from mm_common.node_utils import rejected_inputs
from mm_common.ros_harness import RosHarness
from mm_msgs.msg import CollisionMap, Contact, ControllerStatus, EmbeddingState
from mm_msgs.srv import SetJointGoal
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from mm_common.robot_description import planar_chain_urdf
from std_msgs.msg import Float64MultiArray, Header, String

from mm_planner.dp_planner_node import DpPlannerNode
from mm_planner.value_iteration import JointGrid

QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
GRID = JointGrid((-3.2, -0.8), (0.0, 2.2), 8, 12)


def urdf(box=((-3.2, -0.8), (0.0, 2.2))):
    return planar_chain_urdf('test_arm', [(f'joint{i}', lo, hi, 0.1) for i, (lo, hi) in enumerate(box)], 4.0)
P = ControllerStatus


class Rig:
    def __init__(self, describe=True, **params):
        self.ros = RosHarness()
        try:
            defaults = dict(exploration_steps=0, wait_for_embedding=False)
            self.node = self.ros.add(DpPlannerNode(context=self.ros.context, parameter_overrides=[
                Parameter(k, value=v) for k, v in {**defaults, **params}.items()]))
            self.client = self.ros.node('dp_planner_test_client')
            self.commands, self.status, self.requests = [], [], []
            self.client.create_subscription(Float64MultiArray, 'arm/joint_position_controller/commands',
                                            self.commands.append, QOS)
            self.client.create_subscription(ControllerStatus, 'arm/planner/status', self.status.append, QOS)
            self.client.create_subscription(Header, 'arm/embedding/map_request', self.requests.append, QOS)
            self.joints = self.client.create_publisher(JointState, 'arm/joint_states', QOS)
            self.contact = self.client.create_publisher(Contact, 'arm/contact', QOS)
            self.embedding = self.client.create_publisher(EmbeddingState, 'arm/embedding/state', QOS)
            self.map = self.client.create_publisher(CollisionMap, 'arm/embedding/collision_map', LATCHED)
            self.goal = self.client.create_publisher(Float64MultiArray, 'arm/goal', LATCHED)
            self.set_goal = self.client.create_client(SetJointGoal, 'arm/set_goal')
            self.description = self.client.create_publisher(String, 'arm/robot_description', LATCHED)
            pubs = [self.joints, self.contact, self.map, self.goal]
            assert self.ros.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs)
                                       and self.node.cmd_pub.get_subscription_count() > 0
                                       and self.node.request_pub.get_subscription_count() > 0, timeout=10)
            assert self.set_goal.wait_for_service(timeout_sec=10)
            if describe:
                self.description.publish(String(data=urdf()))
                assert self.ros.spin_until(lambda: self.node.agent is not None, timeout=10)
        except BaseException:
            self.ros.close()
            raise

    def frame(self, sec, q, contact=False):
        js = JointState(name=['shoulder_roll', 'shoulder_pitch'], position=[float(v) for v in q])
        js.header.stamp.sec = sec
        c = Contact(in_contact=contact)
        c.header.stamp.sec = sec
        self.joints.publish(js)
        self.contact.publish(c)

    def send_map(self, sec, blocked=None, **overrides):
        m = CollisionMap(rows=8, cols=12, joint0_limits=[-3.2, -0.8], joint1_limits=[0.0, 2.2])
        m.header.stamp.sec = sec
        m.collision = [bool(v) for v in (np.zeros((8, 12), bool) if blocked is None else blocked).ravel()]
        m.closeness = [-2.0] * 96
        for k, v in overrides.items():
            setattr(m, k, v)
        self.map.publish(m)

    def call_goal(self, q):
        future = self.set_goal.call_async(SetJointGoal.Request(positions=[float(v) for v in q]))
        assert self.ros.spin_until(future.done, timeout=10)
        return future.result()

    def close(self):
        self.ros.close()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def test_plans_before_moving_on_a_map_of_the_current_frame_and_names_the_goal(rig):
    start, goal = (4, 1), (4, 10)
    blocked = np.zeros((8, 12), bool)
    blocked[2:7, 5] = True
    rig.send_map(0)
    assert rig.ros.spin_until(lambda: rig.status and rig.status[-1].phase == P.PHASE_WAITING_FOR_GOAL)
    q = GRID.centre(start)
    rig.frame(1, q)
    reply = rig.call_goal(GRID.centre(goal))
    assert reply.accepted and 'goal_stamp=' in reply.message
    # a map request for frame 1, and no command before its map
    assert rig.ros.spin_until(lambda: rig.requests and rig.requests[-1].stamp.sec == 1)
    rig.ros.spin_for(0.3)
    assert not rig.commands and rig.status[-1].phase == P.PHASE_PLANNING
    rig.send_map(1, blocked)
    sec = 1
    while rig.status[-1].phase not in (P.PHASE_GOAL_REACHED, P.PHASE_FAILED) and sec < 60:
        n = len(rig.commands)
        assert rig.ros.spin_until(lambda: len(rig.commands) > n or rig.status[-1].phase == P.PHASE_GOAL_REACHED)
        if len(rig.commands) > n:
            q = np.array(rig.commands[-1].data)
            assert not blocked[GRID.cell_of(q)]
            sec += 1
            rig.frame(sec, q)
    assert rig.status[-1].phase == P.PHASE_GOAL_REACHED
    stamps = {(s.goal_stamp.sec, s.goal_stamp.nanosec) for s in rig.status
              if s.phase in (P.PHASE_PLANNING, P.PHASE_EXECUTING, P.PHASE_GOAL_REACHED)}
    assert len(stamps) == 1
    sec_s, nsec = stamps.pop()
    assert reply.message.startswith(f'goal_stamp={sec_s}.{nsec:09d}')
    # a topic goal gets its own stamp too, and the failure names it
    walled = np.zeros((8, 12), bool)
    walled[:, 6] = True
    rig.frame(sec + 1, q)
    rig.goal.publish(Float64MultiArray(data=[float(v) for v in GRID.centre((4, 2))]))
    assert rig.ros.spin_until(lambda: rig.requests[-1].stamp.sec == sec + 1)
    rig.send_map(sec + 1, walled)
    assert rig.ros.spin_until(lambda: rig.status[-1].phase == P.PHASE_FAILED)
    failed = rig.status[-1]
    assert 'no collision-free path' in failed.detail
    assert (failed.goal_stamp.sec, failed.goal_stamp.nanosec) not in {(0, 0), (sec_s, nsec)}


def test_a_map_with_blocked_moves_is_planned_on_its_moves(rig):
    # every cell is on the per-cell map, but the moves along row 4 are free: the node crosses along them
    moves = np.zeros((8, 12, 4), bool)                     # the message's layout: (row * cols + col) * 4 + move
    moves[:, :, :2] = True                                 # no move up or down anywhere
    rig.send_map(0, np.ones((8, 12), bool), blocked_moves=[bool(v) for v in moves.ravel()])
    assert rig.ros.spin_until(lambda: rig.status and rig.status[-1].phase == P.PHASE_WAITING_FOR_GOAL)
    q = GRID.centre((4, 1))
    rig.frame(1, q)
    assert rig.call_goal(GRID.centre((4, 4))).accepted
    assert rig.ros.spin_until(lambda: rig.requests and rig.requests[-1].stamp.sec == 1)
    rig.send_map(1, np.ones((8, 12), bool), blocked_moves=[bool(v) for v in moves.ravel()])
    sec = 1
    while rig.status[-1].phase not in (P.PHASE_GOAL_REACHED, P.PHASE_FAILED) and sec < 30:
        n = len(rig.commands)
        assert rig.ros.spin_until(lambda: len(rig.commands) > n or rig.status[-1].phase in (
            P.PHASE_GOAL_REACHED, P.PHASE_FAILED))
        if len(rig.commands) > n:
            q = np.array(rig.commands[-1].data)
            assert GRID.cell_of(q)[0] == 4                 # never up or down
            sec += 1
            rig.frame(sec, q)
    assert rig.status[-1].phase == P.PHASE_GOAL_REACHED, rig.status[-1].detail


def test_malformed_inputs_are_rejected_and_the_node_keeps_working(rig):
    bad_maps = [dict(joint0_limits=[-3.2]), dict(rows=3), dict(collision=[True] * 5),
                dict(closeness=[math.nan] * 96), dict(closeness=[0.0] * 7), dict(joint1_limits=[0.0, math.inf]),
                dict(joint0_limits=[-3.0, -0.8]), dict(blocked_moves=[False] * 95)]
    for i, bad in enumerate(bad_maps):
        rig.send_map(0, **bad)
        assert rig.ros.spin_until(lambda: rejected_inputs(rig.node).get('arm/embedding/collision_map', 0) == i + 1)
    assert rig.node.agent.maps_received_ == 0
    bad_joints = JointState(position=[math.nan, 1.0])
    rig.joints.publish(bad_joints)
    rig.joints.publish(JointState(position=[1.0, 2.0, 3.0]))
    assert rig.ros.spin_until(lambda: rejected_inputs(rig.node).get('arm/joint_states', 0) == 2)
    for goal in ([1.0], [math.nan, 1.0], [50.0, 50.0]):
        assert not rig.call_goal(goal).accepted
    rig.goal.publish(Float64MultiArray(data=[math.inf, 0.0]))
    assert rig.ros.spin_until(lambda: rejected_inputs(rig.node).get('arm/goal', 0) == 1)
    # still alive: a valid map ends learning, a valid goal is accepted
    rig.send_map(0)
    assert rig.ros.spin_until(lambda: rig.status and rig.status[-1].phase == P.PHASE_WAITING_FOR_GOAL)
    assert rig.call_goal(GRID.centre((2, 2))).accepted


def test_parameters_start_up_only_and_cross_checks():
    rig = Rig()
    try:
        for name, value in (('exploration_steps', 10), ('grid_rows', 4),
                            ('collision_reward', -50.0), ('exploration_seed', 3)):
            assert not rig.node.set_parameters([Parameter(name, value=value)])[0].successful, name
        assert not rig.node.set_parameters([Parameter('arrival_tolerance', value=0.2)])[0].successful   # > cells/2
        assert rig.node.set_parameters([Parameter('max_execution_steps', value=10)])[0].successful
        assert rig.node.agent.max_execution_steps == 10
    finally:
        rig.close()


def test_the_joint_box_comes_from_the_robot_description_and_a_bad_one_is_refused():
    rig = Rig(describe=False, exploration_steps=0)
    try:
        rig.send_map(0)                       # latched map before the robot is known: kept, not lost
        reply = rig.call_goal(GRID.centre((2, 2)))
        assert not reply.accepted and 'robot_description' in reply.message
        bad = ['', '<robot', '<!DOCTYPE robot [<!ENTITY a "b">]><robot/>', urdf(((-0.8, -3.2), (0.0, 2.2))),
               planar_chain_urdf('three', [('a', 0, 1, 0.1), ('b', 0, 1, 0.1), ('c', 0, 1, 0.1)], 1.0)]
        for i, text in enumerate(bad):
            rig.description.publish(String(data=text))
            assert rig.ros.spin_until(lambda: rejected_inputs(rig.node).get('arm/robot_description', 0) == i + 1)
        assert rig.node.agent is None and not rig.commands
        rig.description.publish(String(data=urdf()))
        assert rig.ros.spin_until(lambda: rig.status and rig.status[-1].phase == P.PHASE_WAITING_FOR_GOAL)
        assert np.allclose(rig.node.grid.limits, [(-3.2, -0.8), (0.0, 2.2)])
        assert rig.node.agent.maps_received_ == 1            # the map that came first was used
        n = rejected_inputs(rig.node).get('arm/robot_description', 0)
        rig.description.publish(String(data=urdf(((-3.0, -1.0), (0.0, 2.2)))))
        assert rig.ros.spin_until(lambda: rejected_inputs(rig.node).get('arm/robot_description', 0) == n + 1)
        assert np.allclose(rig.node.grid.limits, [(-3.2, -0.8), (0.0, 2.2)])
        assert rig.call_goal(GRID.centre((2, 2))).accepted
    finally:
        rig.close()
