"""The arm simulator node in-process: camera frames, lockstep stepping, command rejection, reset via parameters."""
import math

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from mm_common.ros_harness import RosHarness
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image, JointState
from mm_msgs.msg import ArmGroundTruth, Contact
from std_msgs.msg import Float64MultiArray

from mm_sim.arm_model import ArmModel
from mm_sim.arm_sim_node import ArmSim

QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)


@pytest.fixture
def rig():
    ros = RosHarness()
    sim = ros.add(ArmSim(context=ros.context, parameter_overrides=[
        Parameter('republish_period', value=0.2), Parameter('object_seed', value=5)]))
    client = ros.node('arm_sim_test_client')
    seen = {'image': [], 'joints': [], 'contact': [], 'pose': [], 'truth': []}
    client.create_subscription(Image, 'arm/camera/image_raw', seen['image'].append, QOS)
    client.create_subscription(JointState, 'arm/joint_states', seen['joints'].append, QOS)
    client.create_subscription(Contact, 'arm/contact', seen['contact'].append, QOS)
    client.create_subscription(PoseStamped, 'arm/ground_truth/object_pose', seen['pose'].append, QOS)
    client.create_subscription(ArmGroundTruth, 'arm/ground_truth/state', seen['truth'].append, QOS)
    cmd = client.create_publisher(Float64MultiArray, 'arm/joint_position_controller/commands', QOS)
    # Before the first command the current step is re-published: wait until every topic has delivered once.
    assert ros.spin_until(lambda: cmd.get_subscription_count() > 0 and all(seen.values()), timeout=10)
    yield ros, sim, cmd, seen
    ros.close()


def stamp_ns(msg):
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def test_publishes_rgb8_frames_of_the_model_with_joint_states_and_ground_truth(rig):
    _, sim, _, seen = rig
    img = seen['image'][-1]
    assert (img.width, img.height, img.encoding, img.step) == (400, 400, 'rgb8', 1200)
    assert len(img.data) == 400 * 1200
    frame = np.frombuffer(bytes(img.data), np.uint8).reshape(400, 400, 3)
    model = ArmModel(random_state=5)
    np.testing.assert_array_equal(frame, model.render([-2.0, 1.1]))
    js = seen['joints'][-1]
    assert list(js.name) == ['shoulder_roll', 'shoulder_pitch']
    assert list(js.position) == pytest.approx([-2.0, 1.1])
    truth, contact = seen['truth'][-1], seen['contact'][-1]
    assert stamp_ns(js) == stamp_ns(img) == stamp_ns(seen['pose'][-1]) == stamp_ns(truth) == stamp_ns(contact)
    assert seen['pose'][-1].pose.position.x == pytest.approx(model.object_position_[0])
    assert truth.object_position.x == pytest.approx(model.object_position_[0])
    assert truth.hand_object_distance == pytest.approx(model.hand_object_distance([-2.0, 1.1]))
    assert contact.in_contact is contact.in_contact_at_frame is model.in_contact([-2.0, 1.1])


def test_lockstep_moves_toward_the_target_at_the_speed_limit(rig):
    ros, sim, cmd, seen = rig
    target = [-1.0, 0.5]
    for k in range(1, 5):
        cmd.publish(Float64MultiArray(data=target))
        assert ros.spin_until(lambda: stamp_ns(seen['joints'][-1]) == k * int(round(sim.dt * 1e9))
                              and stamp_ns(seen['image'][-1]) == stamp_ns(seen['joints'][-1]))
    ros.spin_for(0.3)          # re-sends of the last step only (same stamp), no extra steps
    assert sim.step_index == 4
    by_stamp = {stamp_ns(m): m for m in seen['joints']}
    stamps = sorted(by_stamp)
    assert stamps == [k * int(round(sim.dt * 1e9)) for k in range(5)]
    q = [np.array(by_stamp[s].position) for s in stamps]
    max_step = sim.max_joint_speed * sim.dt
    for a, b in zip(q, q[1:]):
        assert np.max(np.abs(b - a)) <= max_step + 1e-12
    # straight line toward the target: 1.0 rad in joint 0 takes 3 steps of 0.4 rad (the last one shorter)
    np.testing.assert_allclose(q[-1], target, atol=1e-12)
    np.testing.assert_allclose(q[1], np.array([-2.0, 1.1]) + 0.4 * (np.array(target) - [-2.0, 1.1]), atol=1e-12)
    frame = np.frombuffer(bytes(seen['image'][-1].data), np.uint8).reshape(400, 400, 3)
    np.testing.assert_array_equal(frame, sim.model.render(target))


@pytest.mark.parametrize('bad', [[math.nan, 1.0], [1.0], [-2.0, 1.0, 0.0], [-2.0, 3.0], [math.inf, 0.5], [-5.0, 1.0]])
def test_bad_commands_are_rejected_and_the_node_keeps_running(rig, bad):
    ros, sim, cmd, seen = rig
    start = len(seen['joints'])
    cmd.publish(Float64MultiArray(data=bad))
    assert ros.spin_until(lambda: sim.commands_rejected == 1)
    ros.spin_for(0.1)
    assert sim.step_index == 0                                  # no step taken (step 0 may be re-published)
    assert all(stamp_ns(m) == 0 for m in seen['joints'][start:])
    cmd.publish(Float64MultiArray(data=[-2.0, 2.3]))           # within the margin above the limit: clipped
    assert ros.spin_until(lambda: sim.step_index == 1)
    assert sim.target[1] == 2.2 and sim.joints[1] == pytest.approx(1.1 + 0.4)


def test_reset_through_parameters_replaces_the_object_and_the_arm(rig):
    ros, sim, cmd, seen = rig
    before = seen['pose'][-1].pose.position.x
    n = len(seen['pose'])
    assert sim.set_parameters([Parameter('object_position', value=[150.0, 120.0])])[0].successful
    assert ros.spin_until(lambda: len(seen['pose']) > n)
    assert (seen['pose'][-1].pose.position.x, seen['pose'][-1].pose.position.y) == (150.0, 120.0)
    assert seen['pose'][-1].pose.position.x != before
    assert sim.set_parameters([Parameter('initial_joints', value=[-1.5, 0.4])])[0].successful
    assert ros.spin_until(lambda: list(seen['joints'][-1].position) == pytest.approx([-1.5, 0.4]))
    assert stamp_ns(seen['joints'][-1]) > stamp_ns(seen['joints'][0])        # sim time stays monotonic
    # invalid updates are refused and change nothing
    assert not sim.set_parameters([Parameter('object_position', value=[900.0, 10.0])])[0].successful
    assert not sim.set_parameters([Parameter('initial_joints', value=[math.nan, 0.0])])[0].successful
    assert not sim.set_parameters([Parameter('dt', value=0.5)])[0].successful
    assert sim.model.object_position_.tolist() == [150.0, 120.0]


def test_joint_motion_is_straight_limited_and_detects_contact_during_a_step():
    from mm_sim.arm_motion import JointMotion, move_towards, swept_contact
    model = ArmModel(random_state=5)
    lim = model.joint_limits
    q = move_towards([-2.0, 1.0], [-1.0, 1.5], 0.4, lim)
    np.testing.assert_allclose(q, [-1.6, 1.2])              # along the line, 0.4 rad in the larger joint
    np.testing.assert_allclose(move_towards([-2.0, 1.0], [-1.9, 5.0], 10.0, lim), [-1.9, 2.2])   # clipped
    # a step whose ends are both clear but that sweeps the hand across the object
    through = model.inverse_kinematics(model.object_position_)
    a, b = through - [0.35, 0.0], through + [0.35, 0.0]
    assert not model.in_contact(a) and not model.in_contact(b)
    assert swept_contact(model, a, b) and not swept_contact(model, a, a - [0.3, 0.0])
    motion = JointMotion(model, max_joint_speed=4.0, dt=0.1)
    new, touched = motion.step(through - [0.2, 0.0], through + [0.2, 0.0])
    assert touched and np.allclose(new, through + [0.2, 0.0])
