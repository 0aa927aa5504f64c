"""The switching controller node in-process: one command per manifold state while exploring (with the bumper reflex),
then learning; goals through the set_goal service are validated; a model announced on the latched topic is loaded
(an unreadable one is reported, not fatal) and a valid goal then starts reaching; bad parameter updates are refused."""
import math

import numpy as np
import pytest
from mm_common.testing import RosHarness
from mm_msgs.msg import ControllerStatus, ManifoldState, SensorGoal
from mm_msgs.srv import SetSensorGoal
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Bool, Float64MultiArray, String

from mm_bringup.wall_experiment import explore, sensor2_goal_reading
from mm_manifold.sensor_manifold import SPACE_SENSOR1, SensorManifoldModel
from mm_planner.switching_controller_node import SwitchingControllerNode
from mm_sim.wheeled_model import WheeledRobot

QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
DT = 0.05
INF = math.inf


@pytest.fixture(scope='module')
def model_file(tmp_path_factory):
    log = explore(WheeledRobot(), 5000, random_state=0, dt=DT)
    model = SensorManifoldModel(DT).fit(log.readings, log.commands, log.continuous)
    assert model.ready
    path = tmp_path_factory.mktemp('controller') / 'wall_model.npz'
    model.save(path)
    return path, model


class Rig:
    def __init__(self, params):
        self.ros = RosHarness()
        try:
            self.node = self.ros.add(SwitchingControllerNode(context=self.ros.context, parameter_overrides=[
                Parameter(k, value=v) for k, v in params.items()]))
            self.client = self.ros.node('controller_test_client')
            self.commands, self.status = [], []
            self.client.create_subscription(Float64MultiArray, 'wheeled/wheel_velocity_controller/commands',
                                            self.commands.append, QOS)
            self.client.create_subscription(ControllerStatus, 'wheeled/controller/status', self.status.append, QOS)
            self.state_pub = self.client.create_publisher(ManifoldState, 'wheeled/manifold/state', QOS)
            self.bumper = self.client.create_publisher(Bool, 'wheeled/bumper', QOS)
            self.model_pub = self.client.create_publisher(String, 'wheeled/manifold/model', LATCHED)
            self.set_goal = self.client.create_client(SetSensorGoal, 'wheeled/set_goal')
            pubs = [self.state_pub, self.bumper, self.model_pub]
            assert self.ros.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs)
                                       and self.node.command_pub.get_subscription_count() > 0
                                       and self.node.status_pub.get_subscription_count() > 0, timeout=10)
            assert self.set_goal.wait_for_service(timeout_sec=10)
        except BaseException:
            self.ros.close()
            raise

    def state(self, sec, sensor1=(0.6, 0.5, 0.6), sensor2=(INF, INF), space=0, coordinates=()):
        msg = ManifoldState(sensor1=[float(v) for v in sensor1], sensor2=[float(v) for v in sensor2],
                            in_range=[math.isfinite(v) for v in list(sensor1) + list(sensor2)],
                            active_space=space, coordinates=[float(v) for v in coordinates])
        msg.header.stamp.sec = sec
        self.state_pub.publish(msg)

    def call(self, reading, group=SensorGoal.SENSOR2, tolerance=0.0, stamp_sec=0):
        goal = SensorGoal(sensor_group=group, reading=[float(v) for v in reading], tolerance=float(tolerance))
        goal.header.stamp.sec = stamp_sec
        future = self.set_goal.call_async(SetSensorGoal.Request(goal=goal))
        assert self.ros.spin_until(future.done, timeout=10)
        return future.result()

    def phase(self):
        return self.status[-1].phase_name if self.status else None


def test_explores_one_command_per_state_then_learns():
    rig = Rig({'exploration_steps': 6, 'random_seed': 1})
    try:
        for k in range(1, 5):
            rig.state(k)
            assert rig.ros.spin_until(lambda: len(rig.commands) == k), f'no command for state {k}'
            u = np.array(rig.commands[-1].data)
            assert u.shape == (2,) and np.all(np.isfinite(u)) and np.max(np.abs(u)) <= 7.0
        assert rig.phase() == 'EXPLORING'
        rig.state(4)                                               # the same state again: already answered
        rig.ros.spin_for(0.3)
        assert len(rig.commands) == 4
        # The bumper reflex: back off, whatever the readings say.
        rig.bumper.publish(Bool(data=True))
        assert rig.ros.spin_until(lambda: rig.node.bumped)
        rig.state(5)
        assert rig.ros.spin_until(lambda: len(rig.commands) == 5)
        u = rig.commands[-1].data
        assert u[0] < 0 and u[1] < 0 and u[0] == pytest.approx(u[1])
        rig.bumper.publish(Bool(data=False))
        rig.state(6)
        assert rig.ros.spin_until(lambda: len(rig.commands) == 6)
        # Exploration budget spent: the next state gets no command, the loop pauses for learning.
        rig.state(7)
        assert rig.ros.spin_until(lambda: rig.phase() == 'LEARNING')
        rig.ros.spin_for(0.3)
        assert len(rig.commands) == 6 and rig.node.explored == 6
    finally:
        rig.ros.close()


def test_a_model_that_has_not_seen_sensor2_sends_it_exploring_again(model_file, tmp_path):
    """Some noisy explorations never see sensor 2 during an excursion: that model cannot map any goal, so the
    controller explores exploration_steps // 4 more steps (the manifold node refits after them) instead of waiting
    for goals it would fail; a model that has seen sensor 2 then ends the exploration."""
    path, _ = model_file
    blind = SensorManifoldModel.load(path)
    blind.virtual_.overlap_coordinates_ = blind.virtual_.overlap_exits_ = np.zeros((0, 2))
    blind.virtual_.overlap_sensor2_, blind.virtual_.overlap_travel_ = np.zeros((0, 2)), np.zeros(0)
    assert not blind.ready
    blind_path = tmp_path / 'blind_model.npz'
    blind.save(blind_path)
    rig = Rig({'exploration_steps': 8, 'random_seed': 1})
    try:
        for k in range(1, 10):
            rig.state(k)
            assert rig.ros.spin_until(lambda: rig.phase() == 'LEARNING' or len(rig.commands) == k)
        assert rig.phase() == 'LEARNING' and len(rig.commands) == 8
        rig.model_pub.publish(String(data=str(blind_path)))
        # Exploring again, and the state that was waiting is answered at once.
        assert rig.ros.spin_until(lambda: rig.phase() == 'EXPLORING' and len(rig.commands) == 9)
        assert 'not seen sensor 2' in rig.status[-1].detail
        rig.state(10)
        assert rig.ros.spin_until(lambda: len(rig.commands) == 10)
        rig.state(11)                                              # 2 more steps (8 // 4) spent: learning again
        assert rig.ros.spin_until(lambda: rig.phase() == 'LEARNING')
        rig.model_pub.publish(String(data=str(path)))
        assert rig.ros.spin_until(lambda: rig.phase() == 'WAITING_FOR_GOAL')
        assert len(rig.commands) == 10
    finally:
        rig.ros.close()


def test_invalid_goals_are_rejected_with_a_reason():
    rig = Rig({'exploration_steps': 0})
    try:
        for reading, group, tolerance in (([0.2, 0.2], SensorGoal.SENSOR1, 0.0),       # wrong sensor group
                                          ([0.2, 0.2, 0.2], SensorGoal.SENSOR2, 0.0),  # wrong size
                                          ([0.2], SensorGoal.SENSOR2, 0.0),
                                          ([math.nan, 0.2], SensorGoal.SENSOR2, 0.0),
                                          ([0.2, INF], SensorGoal.SENSOR2, 0.0),
                                          ([-0.1, 0.2], SensorGoal.SENSOR2, 0.0),
                                          ([0.2, 0.2], SensorGoal.SENSOR2, math.nan),
                                          ([0.2, 0.2], SensorGoal.SENSOR2, 0.5)):
            response = rig.call(reading, group, tolerance)
            assert not response.accepted, (reading, group, tolerance)
            assert response.message and response.message != 'accepted'
        assert rig.node.goal is None and rig.node.controller is None
    finally:
        rig.ros.close()


def test_loads_the_announced_model_and_reaches_for_a_valid_goal(model_file, tmp_path):
    path, model = model_file
    rig = Rig({'exploration_steps': 0, 'max_wheel_speed': 4.0})
    try:
        assert rig.node.phase == ControllerStatus.PHASE_LEARNING
        # An unreadable model file is reported and ignored; the node keeps running.
        broken = tmp_path / 'broken.npz'
        broken.write_bytes(path.read_bytes()[:1000])
        rig.model_pub.publish(String(data=str(broken)))
        rig.model_pub.publish(String(data=str(path)))
        assert rig.ros.spin_until(lambda: rig.node.model is not None, timeout=10)
        assert rig.ros.spin_until(lambda: rig.phase() == 'WAITING_FOR_GOAL')
        # A state while waiting: no command yet.
        reading = WheeledRobot().read((0.0, 0.6, -math.pi / 2), noisy=False)
        coordinates = model.grid_.transform(reading[:3][None])[0]
        rig.state(1, reading[:3], reading[3:], SPACE_SENSOR1, coordinates)
        assert rig.ros.spin_until(lambda: rig.node.pending is not None)
        assert not rig.commands
        # A valid goal: accepted, and the waiting state is answered at once with a command within the limit.
        goal = sensor2_goal_reading(WheeledRobot(), (0.0, 0.2, 0.0))
        response = rig.call(goal, tolerance=0.005)
        assert response.accepted, response.message
        assert rig.ros.spin_until(lambda: len(rig.commands) == 1)
        assert rig.ros.spin_until(lambda: rig.phase() == 'REACHING_SENSOR1')
        u = np.array(rig.commands[0].data)
        assert np.all(np.isfinite(u)) and 0 < np.max(np.abs(u)) <= 4.0 + 1e-9
        assert rig.node.controller.tolerance == 0.005
        np.testing.assert_allclose(rig.node.controller.goal_sensor2, goal)
        # The next state gets the next command.
        rig.state(2, reading[:3], reading[3:], SPACE_SENSOR1, coordinates)
        assert rig.ros.spin_until(lambda: len(rig.commands) == 2)
    finally:
        rig.ros.close()


def test_a_goal_the_model_cannot_map_fails_under_its_own_stamp(model_file):
    """A model that never saw sensor 2 (no overlap) cannot map a sensor-2 goal: the service says why, and the status
    reports FAILED for that goal's stamp - for every such goal, so a client waiting for its outcome is not left
    waiting."""
    path, _ = model_file
    rig = Rig({'exploration_steps': 0})
    try:
        rig.model_pub.publish(String(data=str(path)))
        assert rig.ros.spin_until(lambda: rig.phase() == 'WAITING_FOR_GOAL')
        virtual = rig.node.model.virtual_                # as learned from an exploration without sensor 2
        virtual.overlap_coordinates_ = virtual.overlap_exits_ = virtual.overlap_sensor2_ = np.zeros((0, 2))
        virtual.overlap_travel_ = np.zeros(0)
        goal = sensor2_goal_reading(WheeledRobot(), (0.0, 0.2, 0.0))
        for sec in (7, 8):
            response = rig.call(goal, stamp_sec=sec)
            assert not response.accepted and 'cannot map the goal' in response.message
            assert rig.ros.spin_until(lambda: rig.status[-1].goal_stamp.sec == sec)
            assert rig.status[-1].phase == ControllerStatus.PHASE_FAILED
            assert 'no overlap with sensor 2' in rig.status[-1].detail
    finally:
        rig.ros.close()


def test_parameter_updates_are_validated():
    rig = Rig({'exploration_steps': 0})
    try:
        node = rig.node
        for name in ('tolerance', 'max_wheel_speed', 'dt'):
            assert not node.set_parameters([Parameter(name, value=math.nan)])[0].successful, name
        assert not node.set_parameters([Parameter('max_wheel_speed', value=100.0)])[0].successful   # range
        assert not node.set_parameters([Parameter('max_reach_steps', value=0)])[0].successful
        assert node.max_wheel_speed == 6.0 and node.tolerance == 0.01
        assert node.set_parameters([Parameter('tolerance', value=0.02)])[0].successful
        assert node.tolerance == 0.02
        assert node.set_parameters([Parameter('max_reach_steps', value=200)])[0].successful
        assert node.max_reach_steps == 200
    finally:
        rig.ros.close()
