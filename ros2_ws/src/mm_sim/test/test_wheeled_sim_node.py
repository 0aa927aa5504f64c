"""The simulator node in-process: lockstep stepping, command rejection, reset service, bumper, markers."""
import math

import pytest
from mm_common.ros_harness import RosHarness
from mm_msgs.srv import ResetPose
from nav_msgs.msg import Odometry
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Range
from std_msgs.msg import Bool, Float64MultiArray
from visualization_msgs.msg import MarkerArray

from mm_common.wheeled_sensors import SENSOR_NAMES
from mm_sim.wheeled_sim_node import WheeledSim

QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)


@pytest.fixture
def rig():
    ros = RosHarness()
    sim = ros.add(WheeledSim(context=ros.context, parameter_overrides=[
        Parameter('republish_period', value=5.0), Parameter('initial_pose', value=[0.0, 0.5, -math.pi / 2])]))
    client = ros.node('sim_test_client')
    seen = {'odom': [], 'bumper': [], 'markers': [], 'ranges': {n: [] for n in SENSOR_NAMES}}
    client.create_subscription(Odometry, 'wheeled/ground_truth/odom', seen['odom'].append, QOS)
    client.create_subscription(Bool, 'wheeled/bumper', seen['bumper'].append, QOS)
    client.create_subscription(MarkerArray, 'wheeled/markers', seen['markers'].append, QOS)
    for name in SENSOR_NAMES:
        client.create_subscription(Range, f'wheeled/range/{name}', seen['ranges'][name].append, QOS)
    cmd = client.create_publisher(Float64MultiArray, 'wheeled/wheel_velocity_controller/commands', QOS)
    assert ros.spin_until(lambda: cmd.get_subscription_count() > 0)
    # The first step was published before our subscriptions matched: ask for it again through a reset.
    reset = client.create_client(ResetPose, 'wheeled/reset')
    assert reset.wait_for_service(timeout_sec=5.0)
    future = reset.call_async(ResetPose.Request(x=0.0, y=0.5, theta=-math.pi / 2))
    assert ros.spin_until(lambda: future.done() and len(seen['odom']) >= 1)
    yield ros, sim, cmd, reset, seen
    ros.close()


def stamp_ns(msg):
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def test_lockstep_advances_exactly_one_step_per_command(rig):
    ros, sim, cmd, _, seen = rig
    start = len(seen['odom'])
    for k in range(1, 6):
        cmd.publish(Float64MultiArray(data=[5.0, 5.0]))
        assert ros.spin_until(lambda: len(seen['odom']) == start + k)
    ros.spin_for(0.2)
    assert len(seen['odom']) == start + 5
    stamps = [stamp_ns(m) for m in seen['odom'][-6:]]
    assert all(b - a == int(sim.dt * 1e9) for a, b in zip(stamps, stamps[1:]))
    # 5 steps of 0.05 s at v = 0.1 m/s straight toward the wall.
    assert seen['odom'][-1].pose.pose.position.y == pytest.approx(0.5 - 5 * 0.05 * 0.1)
    # All five readings of one step carry the same stamp.
    assert len({stamp_ns(seen['ranges'][n][-1]) for n in SENSOR_NAMES}) == 1
    centre = seen['ranges']['front_center'][-1]
    assert centre.radiation_type == Range.INFRARED
    assert centre.range == pytest.approx(0.5 - 0.025 - 0.025, abs=1e-6)


@pytest.mark.parametrize('bad', [[math.nan, 1.0], [1.0], [1.0, 2.0, 3.0], [1e6, 0.0], [math.inf, 0.0]])
def test_bad_commands_are_rejected_without_advancing(rig, bad):
    ros, sim, cmd, _, seen = rig
    start = len(seen['odom'])
    cmd.publish(Float64MultiArray(data=bad))
    assert ros.spin_until(lambda: sim.commands_rejected == 1)
    ros.spin_for(0.1)
    assert len(seen['odom']) == start
    cmd.publish(Float64MultiArray(data=[1.0, 1.0]))       # still alive and stepping
    assert ros.spin_until(lambda: len(seen['odom']) == start + 1)


def test_reset_service_moves_the_robot_and_rejects_the_wall(rig):
    ros, _, _, reset, seen = rig
    future = reset.call_async(ResetPose.Request(x=1.0, y=0.2, theta=0.0))
    assert ros.spin_until(lambda: future.done())
    assert future.result().success
    assert ros.spin_until(lambda: seen['odom'][-1].pose.pose.position.x == pytest.approx(1.0))
    assert seen['ranges']['side_front'][-1].range == pytest.approx(0.2 - 0.025, abs=1e-6)
    bad = reset.call_async(ResetPose.Request(x=0.0, y=-1.0, theta=0.0))
    assert ros.spin_until(lambda: bad.done())
    assert not bad.result().success


def test_bumper_reports_contact_and_markers_are_published(rig):
    ros, _, cmd, reset, seen = rig
    future = reset.call_async(ResetPose.Request(x=0.0, y=0.04, theta=-math.pi / 2))
    assert ros.spin_until(lambda: future.done())
    n = len(seen['bumper'])
    cmd.publish(Float64MultiArray(data=[20.0, 20.0]))
    assert ros.spin_until(lambda: len(seen['bumper']) > n)
    assert seen['bumper'][-1].data is True
    assert ros.spin_until(lambda: len(seen['markers']) > 0)
    namespaces = {m.ns for m in seen['markers'][-1].markers}
    assert {'wall', 'robot', 'beams'} <= namespaces


def test_invalid_parameter_updates_are_refused(rig):
    _, sim, _, _, _ = rig
    assert not sim.set_parameters([Parameter('noise_std', value=-1.0)])[0].successful
    assert not sim.set_parameters([Parameter('noise_std', value=math.nan)])[0].successful
    assert sim.set_parameters([Parameter('noise_std', value=0.01)])[0].successful
    assert sim.robot.noise_std == 0.01


def test_runtime_array_nan_and_start_up_parameters_are_refused(rig):
    _, sim, _, _, _ = rig
    for name, value in (('dt', 0.1), ('lockstep', False), ('initial_pose', [0.0, 2.0, 0.0]),
                        ('real_time_factor', 2.0)):
        result = sim.set_parameters([Parameter(name, value=value)])[0]
        assert not result.successful and 'read-only' in result.reason.lower(), (name, result.reason)
    assert sim.dt == 0.05


def test_parameters_take_effect_at_runtime(rig):
    ros, sim, cmd, _, seen = rig
    assert sim.set_parameters([Parameter('marker_period', value=1)])[0].successful
    n = len(seen['markers'])
    cmd.publish(Float64MultiArray(data=[1.0, 1.0]))
    assert ros.spin_until(lambda: len(seen['markers']) > n)
    # The same seed restarts the same noise sequence.
    assert sim.set_parameters([Parameter('noise_std', value=0.01), Parameter('random_seed', value=7)])[0].successful
    first = sim.robot.read(sim.pose)
    assert sim.set_parameters([Parameter('random_seed', value=7)])[0].successful
    assert list(sim.robot.read(sim.pose)) == list(first)


def test_lockstep_republishes_the_current_step_at_any_step_until_the_next_command(rig):
    """A lost command mid-run must not stall the loop: the step is re-sent with its own stamp."""
    ros, sim, cmd, _, seen = rig
    assert sim.set_parameters([Parameter('republish_period', value=0.1)])[0].successful
    for _ in range(3):
        cmd.publish(Float64MultiArray(data=[2.0, 2.0]))
    assert ros.spin_until(lambda: sim.step_index >= 4)
    step, republished = sim.step_index, sim.republished
    assert ros.spin_until(lambda: sim.republished >= republished + 2, timeout=3.0)
    assert sim.step_index == step           # re-sent, not advanced
    stamps = {stamp_ns(m) for m in seen['odom'][-2:]}
    assert stamps == {sim.sim_time_ns}
    cmd.publish(Float64MultiArray(data=[2.0, 2.0]))
    assert ros.spin_until(lambda: sim.step_index == step + 1)


@pytest.mark.parametrize('request_args', [dict(x=math.nan, y=0.5), dict(x=0.0, y=math.inf), dict(x=1e308, y=0.5),
                                          dict(x=0.0, y=1e308), dict(x=0.0, y=0.5, theta=-math.inf)])
def test_reset_rejects_non_finite_and_far_poses_and_keeps_serving(rig, request_args):
    ros, sim, _, reset, _ = rig
    bad = reset.call_async(ResetPose.Request(**request_args))
    assert ros.spin_until(lambda: bad.done())
    assert not bad.result().success and bad.result().message
    assert sim.resets_rejected == 1
    good = reset.call_async(ResetPose.Request(x=0.0, y=0.5, theta=0.0))
    assert ros.spin_until(lambda: good.done())
    assert good.result().success


def test_matched_command_publishers_are_counted(rig):
    ros, sim, cmd, _, _ = rig
    assert ros.spin_until(lambda: sim.command_publishers_matched == 1)
    ros.nodes[1].destroy_publisher(cmd)
    assert ros.spin_until(lambda: sim.command_publishers_matched == 0)


def test_initial_step_continues_a_predecessors_time():
    ros = RosHarness()
    try:
        sim = ros.add(WheeledSim(context=ros.context, parameter_overrides=[
            Parameter('initial_step', value=123), Parameter('republish_period', value=5.0)]))
        assert sim.step_index == 123 and sim.sim_time_ns == round(123 * sim.dt * 1e9)
        assert not sim.set_parameters([Parameter('initial_step', value=0)])[0].successful
    finally:
        ros.close()
