"""The arm simulator in-process: object modes and the arm/place_object service, stamped ground truth with contact of
any part checked along the motion, re-sending the last step at any step, and hostile inputs."""
import math

import numpy as np
import pytest
from mm_common.ros_harness import RosHarness
from mm_msgs.msg import ArmGroundTruth, Contact
from mm_msgs.srv import PlaceObject
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import Float64MultiArray

from mm_sim.arm_model import ArmModel
from mm_sim.arm_sim_node import ArmSim

QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
SEED = 5


def stamp_ns(msg):
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


class Rig:
    """One simulator and a client that records every frame topic and can command and call the service."""

    def __init__(self, **params):
        params = {'republish_period': 0.2, 'object_seed': SEED, **params}
        self.ros = RosHarness()
        self.sim = self.ros.add(ArmSim(context=self.ros.context, parameter_overrides=[
            Parameter(k, value=v) for k, v in params.items()]))
        client = self.ros.node('arm_sim_objects_client')
        self.seen = {'image': [], 'joints': [], 'contact': [], 'truth': []}
        # a free-running camera publishes best effort (sensor data); a reliable subscription would not match it
        image_qos = QOS if params.get('lockstep', True) else qos_profile_sensor_data
        for key, kind, topic, qos in (('image', Image, 'arm/camera/image_raw', image_qos),
                                      ('joints', JointState, 'arm/joint_states', QOS),
                                      ('contact', Contact, 'arm/contact', QOS),
                                      ('truth', ArmGroundTruth, 'arm/ground_truth/state', QOS)):
            client.create_subscription(kind, topic, self.seen[key].append, qos)
        self.cmd = client.create_publisher(Float64MultiArray, 'arm/joint_position_controller/commands', QOS)
        self.place_client = client.create_client(PlaceObject, 'arm/place_object')
        assert self.ros.spin_until(lambda: self.cmd.get_subscription_count() > 0 and all(self.seen.values())
                                   and self.place_client.service_is_ready(), timeout=10)

    def latest(self, key):
        return self.seen[key][-1]

    def command(self, target):
        """Send one command and wait for the frame of the next step on every topic."""
        step = self.sim.step_index + 1
        self.cmd.publish(Float64MultiArray(data=[float(v) for v in target]))
        self.wait_step(step)

    def wait_step(self, step):
        t = int(round(step * self.sim.dt * 1e9))
        assert self.ros.spin_until(lambda: all(v and stamp_ns(v[-1]) == t for v in self.seen.values())), \
            f'no complete frame for step {step}'

    def place(self, position=(), random=False):
        future = self.place_client.call_async(PlaceObject.Request(random=random, position=list(position)))
        assert self.ros.spin_until(future.done)
        return future.result()

    def truth_by_stamp(self):
        return {stamp_ns(m): m for m in self.seen['truth']}

    def close(self):
        self.ros.close()


@pytest.fixture
def on_request():
    rig = Rig(object_mode='on_request')
    yield rig
    rig.close()


def test_fixed_mode_keeps_the_object_and_refuses_to_move_it():
    rig = Rig()
    try:
        where = rig.sim.model.object_position_.copy()
        for _ in range(3):
            rig.command([-1.5, 0.5])
        reply = rig.place(random=True)
        assert not reply.accepted and 'fixed' in reply.message
        assert list(reply.position) == pytest.approx(where.tolist())
        assert {m.placement for m in rig.seen['truth']} == {0}
        assert all(m.object_position.x == where[0] and m.object_position.y == where[1] for m in rig.seen['truth'])
    finally:
        rig.close()


def run_every_n(placement_seed, steps=10):
    rig = Rig(object_mode='every_n_frames', object_period_frames=3, placement_seed=placement_seed)
    try:
        rng = np.random.default_rng(0)
        for _ in range(steps):
            rig.command(rig.sim.model.sample_joints(1, rng)[0])
        return [(m.step, m.placement, m.object_placed, m.object_position.x, m.object_position.y)
                for m in sorted(rig.truth_by_stamp().values(), key=lambda m: m.step)]
    finally:
        rig.close()


def test_every_n_frames_replaces_the_object_on_schedule_deterministically_for_a_seed():
    first = run_every_n(placement_seed=11)
    # frames 0-2 show the initial place, each later group of 3 frames a new one, placed at the start of its motion
    assert [placement for _, placement, _, _, _ in first] == [0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3]
    assert [step for step, _, placed, _, _ in first if placed] == [0, 3, 6, 9]
    places = {(x, y) for _, _, _, x, y in first}
    assert len(places) == 4
    model = ArmModel(random_state=SEED)
    for x, y in places:      # every place is one the hand can reach, inside the image
        assert model.inverse_kinematics([x, y]) is not None
        assert 20.0 <= x <= 380.0 and 20.0 <= y <= 380.0
    assert run_every_n(placement_seed=11) == first
    assert run_every_n(placement_seed=12) != first


def test_place_object_service_moves_the_object_and_publishes_a_stamped_frame(on_request):
    rig = on_request
    rig.command([-1.6, 0.9])
    before = np.frombuffer(bytes(rig.latest('image').data), np.uint8).reshape(400, 400, 3)
    reply = rig.place(random=True)
    assert reply.accepted, reply.message
    assert reply.stamp.sec * 10**9 + reply.stamp.nanosec == 2 * int(round(rig.sim.dt * 1e9))
    rig.wait_step(2)
    truth = rig.latest('truth')
    assert truth.object_placed and truth.placement == 1 and truth.contact_steps == 0
    assert [truth.object_position.x, truth.object_position.y] == pytest.approx(list(reply.position))
    assert list(rig.latest('joints').position) == pytest.approx([-1.6, 0.9])       # the arm stays
    after = np.frombuffer(bytes(rig.latest('image').data), np.uint8).reshape(400, 400, 3)
    model = ArmModel(random_state=SEED)
    model.set_object_position(reply.position)
    np.testing.assert_array_equal(after, model.render([-1.6, 0.9]))    # same scene, object moved
    assert np.any(after != before)
    explicit = model.hand_position([-2.2, 1.4])
    reply = rig.place(position=explicit)
    assert reply.accepted, reply.message
    rig.wait_step(3)
    assert rig.latest('truth').placement == 2
    assert rig.latest('truth').object_position.x == pytest.approx(explicit[0])


@pytest.mark.parametrize('request_args, reason', [
    (dict(position=[25.0, 25.0]), 'reach'),                     # inside the image, too far from the shoulder
    (dict(position=[5.0, 200.0]), 'image'),                     # the disc would leave the image
    (dict(position=[200.0]), 'expected 2'),
    (dict(position=[200.0, 150.0, 1.0]), 'expected 2'),
    (dict(position=[math.nan, 150.0]), 'finite'),
    (dict(position=[math.inf, 150.0]), 'finite'),
    (dict(position=[]), 'expected 2'),
    (dict(position=[200.0, 150.0], random=True), 'one or the other'),
    ('arm', 'overlap'),                                         # on top of the arm's current pose
])
def test_invalid_places_are_rejected_with_the_reason_and_a_valid_one_follows(on_request, request_args, reason):
    rig = on_request
    where, steps = rig.sim.model.object_position_.copy(), rig.sim.step_index
    if request_args == 'arm':
        request_args = dict(position=rig.sim.model.hand_position(rig.sim.joints))
    reply = rig.place(**request_args)
    assert not reply.accepted and reason in reply.message, reply.message
    assert rig.sim.step_index == steps and np.array_equal(rig.sim.model.object_position_, where)
    assert rig.place(random=True).accepted


def test_contact_of_a_link_along_a_fast_motion_that_the_end_poses_miss():
    start, end = np.array([-3.15, 0.5]), np.array([-2.25, 0.5])
    model = ArmModel(random_state=SEED)
    pts = model.link_points([-2.7, 0.5])
    obstacle = (pts[1] + pts[2]) / 2              # the forearm's middle, half-way through the motion
    assert model.part_clearances(start, object_position=obstacle).min() > 0
    assert model.part_clearances(end, object_position=obstacle).min() > 0
    rig = Rig(object_mode='on_request', max_joint_speed=10.0, initial_joints=start.tolist())
    try:
        assert rig.place(position=obstacle).accepted
        rig.wait_step(1)
        rig.command(end)                          # 0.9 rad in one step: through the object
        truth, touch = rig.latest('truth'), rig.latest('contact')
        assert list(rig.latest('joints').position) == pytest.approx(end.tolist())
        assert truth.link_clearance > 0 and not model.in_contact(end)     # the frame itself shows no contact
        assert truth.link_contact and 'forearm' in truth.contact_parts and truth.min_link_clearance < 0
        assert truth.contact_steps == 1 and truth.contact_events == 1
        assert touch.in_contact == truth.hand_contact == ('hand' in truth.contact_parts)
        assert not touch.in_contact_at_frame
        assert touch.arm_in_contact and not touch.arm_in_contact_at_frame      # the forearm felt it on the way
        assert truth.min_hand_object_distance < truth.hand_object_distance
        rig.command(end + [0.1, 0.0])             # clear of the object: counts stay, no new event
        truth = rig.latest('truth')
        assert not truth.link_contact and truth.contact_steps == 1 and truth.contact_events == 1
        rig.command(start)                        # back through it: a second event
        assert rig.latest('truth').contact_steps == 2 and rig.latest('truth').contact_events == 2
        rig.command(model.inverse_kinematics(obstacle))     # the hand ends on the object
        assert rig.latest('contact').in_contact and rig.latest('contact').in_contact_at_frame
        assert rig.latest('contact').arm_in_contact_at_frame
    finally:
        rig.close()


def test_every_message_of_a_frame_carries_the_frame_stamp(on_request):
    rig = on_request
    rng = np.random.default_rng(3)
    for k in range(6):
        if k == 3:
            assert rig.place(random=True).accepted
            rig.wait_step(rig.sim.step_index)
        else:
            rig.command(rig.sim.model.sample_joints(1, rng)[0])
    stamps = {key: {stamp_ns(m) for m in msgs} for key, msgs in rig.seen.items()}
    expected = {int(round(k * rig.sim.dt * 1e9)) for k in range(7)}
    assert all(s == expected for s in stamps.values()), stamps
    joints = {stamp_ns(m): np.array(m.position) for m in rig.seen['joints']}
    for stamp, truth in rig.truth_by_stamp().items():
        hand = rig.sim.model.link_points(joints[stamp])[2]
        assert truth.step * int(round(rig.sim.dt * 1e9)) == stamp
        assert [truth.hand_position.x, truth.hand_position.y] == pytest.approx(hand.tolist())
        assert truth.header.frame_id == 'camera'


def test_the_last_step_is_re_sent_until_the_next_command_at_any_step(on_request):
    rig = on_request
    for _ in range(3):
        rig.command([-1.5, 0.5])
    t3 = stamp_ns(rig.latest('joints'))
    n = {key: len(v) for key, v in rig.seen.items()}
    # The next command is "lost": nothing comes. The simulator re-sends step 3 (same stamp) every 0.2 s.
    assert rig.ros.spin_until(lambda: all(len(v) >= n[key] + 2 for key, v in rig.seen.items()), timeout=3)
    assert rig.sim.step_index == 3
    assert all(stamp_ns(m) == t3 for key, v in rig.seen.items() for m in v[n[key]:])
    resent = rig.seen['truth'][n['truth']:]
    assert all(m.contact_steps == rig.seen['truth'][n['truth'] - 1].contact_steps for m in resent)
    rig.command([-1.5, 0.5])                      # the loop goes on from step 3
    assert rig.sim.step_index == 4


@pytest.mark.parametrize('bad', [[], [math.nan, 1.0], [1e308, 0.5], [-2.0, 1.0, 0.0], [-math.inf, 0.5], [-9.0, 1.0]])
def test_malformed_commands_are_rejected_and_the_next_valid_one_steps(on_request, bad):
    rig = on_request
    rig.cmd.publish(Float64MultiArray(data=bad))
    assert rig.ros.spin_until(lambda: rig.sim.commands_rejected == 1)
    assert rig.sim.step_index == 0
    rig.command([-1.8, 1.0])
    assert rig.sim.step_index == 1


def test_parameters_are_checked_and_start_up_ones_are_read_only(on_request):
    sim = on_request.sim
    for name, value in (('object_mode', 'sometimes'), ('object_position', [1.0, 2.0, 3.0]),
                        ('object_position', [500.0, 10.0]), ('initial_joints', [math.nan, 0.0]),
                        ('initial_joints', [0.5]), ('object_period_frames', 0), ('contact_resolution', 0.0),
                        ('dt', 0.05), ('lockstep', False), ('republish_period', 1.0), ('image_size', 200)):
        assert not sim.set_parameters([Parameter(name, value=value)])[0].successful, (name, value)
    assert sim.object_mode == 'on_request' and sim.step_index == 0
    assert sim.set_parameters([Parameter('object_mode', value='every_n_frames'),
                               Parameter('object_period_frames', value=2)])[0].successful
    assert (sim.object_mode, sim.object_period_frames) == ('every_n_frames', 2)
    with pytest.raises(ValueError, match='object_mode'):
        ArmSim(context=on_request.ros.context, parameter_overrides=[Parameter('object_mode', value='bogus')])


def test_the_sweep_matches_a_fine_brute_force_along_random_motions():
    from mm_sim.arm_motion import sweep
    model = ArmModel(random_state=SEED)
    rng = np.random.default_rng(7)
    agree = 0
    for _ in range(200):
        a = model.sample_joints(1, rng)[0]
        b = np.clip(a + rng.uniform(-0.4, 0.4, 2), model.joint_limits[:, 0], model.joint_limits[:, 1])
        coarse, fine = sweep(model, a, b), sweep(model, a, b, resolution=5e-4)
        # near and outside the surface the sampled minimum is exact to a fraction of a pixel (deep inside it is not
        # smooth and matters less: contact is certain there)
        if fine.min_hand_object_distance > model.contact_distance - 5.0:
            assert coarse.min_hand_object_distance == pytest.approx(fine.min_hand_object_distance, abs=0.2)
        for gap, fine_gap in zip(coarse.min_part_clearance, fine.min_part_clearance):
            if fine_gap > -5.0:
                assert gap == pytest.approx(fine_gap, abs=0.2)
        # contact agrees unless the deepest overlap is a graze thinner than that tolerance
        for hit, fine_hit, gap in zip(coarse.part_contact, fine.part_contact, fine.min_part_clearance):
            assert hit == fine_hit or abs(gap) < 0.2
        agree += coarse.part_contact == fine.part_contact
    assert agree >= 195


def test_free_running_steps_on_its_own_and_re_places_the_object_every_n_frames():
    rig = Rig(lockstep=False, real_time_factor=20.0, object_mode='every_n_frames', object_period_frames=2)
    try:
        rig.cmd.publish(Float64MultiArray(data=[-1.2, 0.6]))
        assert rig.ros.spin_until(lambda: rig.sim.step_index >= 8, timeout=10)
        assert rig.ros.spin_until(lambda: len(rig.truth_by_stamp()) >= 7)
        truths = sorted(rig.truth_by_stamp().values(), key=lambda m: m.step)
        assert all(m.placement == m.step // 2 for m in truths)      # a new place every second frame
        assert all(m.object_placed == (m.step % 2 == 0) for m in truths)
        assert list(rig.sim.target) == [-1.2, 0.6]
    finally:
        rig.close()
