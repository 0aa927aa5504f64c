"""Simulator + recorder as separate processes; the recorder is stopped with SIGINT and the bag is read back with the
mcap and mcap-ros2-support readers: counts, schema text, QoS metadata and decoded values."""
import math

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mm_bringup.process_graph import ProcessGraph
from mm_common.rosbag import read_metadata, schema_text
from mm_msgs.srv import ResetPose
from mm_sim.wheeled_model import WheeledRobot
from nav_msgs.msg import Odometry
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray

QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
SIM_TOPICS = ['/clock', '/wheeled/bumper', '/wheeled/ground_truth/odom', '/wheeled/markers'] + [
    f'/wheeled/range/{n}' for n in ('front_left', 'front_center', 'front_right', 'side_front', 'side_rear')]
STAMPED_TOPICS = [t for t in SIM_TOPICS if t not in ('/clock', '/wheeled/markers', '/wheeled/bumper')]
STEPS = 100
# DDS matches each writer to the recorder's reader on its own schedule, after the recorder sees the topic (on a
# loaded machine dozens of steps later): steps made before every match are not the recorder's to keep. The measured
# window starts once the recorder's log says every topic has delivered its first message.
MAX_WARMUP_STEPS = 2000
DT = 0.05


def recorder_subscribed(node, topics):
    return all(any(e.node_name == 'recorder' for e in node.get_subscriptions_info_by_topic(t)) for t in topics)


@pytest.fixture(scope='module')
def recorded_bag(tmp_path_factory):
    from mm_common.ros_harness import RosHarness
    bag = tmp_path_factory.mktemp('graph') / 'bag'
    ros = RosHarness()
    with ProcessGraph(log_dir=bag.parent / 'logs') as graph:
        recorder = graph.start('mm_bringup', 'recorder', {'output': str(bag), 'discovery_period': 0.05})
        graph.start('mm_sim', 'wheeled_sim', {'republish_period': 30.0, 'dt': DT, 'marker_period': 10})
        node = ros.node('graph_test_driver')
        odom = []
        node.create_subscription(Odometry, 'wheeled/ground_truth/odom', odom.append, QOS)
        cmd = node.create_publisher(Float64MultiArray, 'wheeled/wheel_velocity_controller/commands', QOS)
        assert ros.spin_until(lambda: recorder_subscribed(node, SIM_TOPICS), timeout=20), graph.log_tail(recorder)
        reset = node.create_client(ResetPose, 'wheeled/reset')
        assert reset.wait_for_service(timeout_sec=10)
        future = reset.call_async(ResetPose.Request(x=0.0, y=0.6, theta=-math.pi / 2 + 0.3))
        assert ros.spin_until(lambda: future.done() and odom, timeout=10)
        rng = np.random.default_rng(0)

        def step():
            before = len(odom)
            cmd.publish(Float64MultiArray(data=list(rng.uniform(-8.0, 8.0, size=2))))
            assert ros.spin_until(lambda: len(odom) > before, timeout=5)

        for _ in range(MAX_WARMUP_STEPS):
            step()
            log = graph.log_tail(recorder, lines=200)
            if all(f'first message on {t}:' in log for t in SIM_TOPICS):
                break
        else:
            pytest.fail(f'the recorder never received every topic:\n{graph.log_tail(recorder)}')
        for _ in range(STEPS):
            step()
        last_stamp = odom[-1].header.stamp
        code = graph.stop(recorder)
        assert code == 0, graph.log_tail(recorder)
    ros.close()
    return bag, last_stamp.sec * 10**9 + last_stamp.nanosec


def decoded(bag_dir, topics=None):
    info = read_metadata(bag_dir)
    out = []
    for rel in info['relative_file_paths']:
        with open(bag_dir / rel, 'rb') as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            out += [(ch.topic, msg) for _, ch, _, msg in reader.iter_decoded_messages(topics=topics)]
    return out


def test_every_published_step_is_recorded_once(recorded_bag):
    bag, last_ns = recorded_bag
    info = read_metadata(bag)
    counts = {t['topic_metadata']['name']: t['message_count'] for t in info['topics_with_message_count']}
    assert set(SIM_TOPICS) <= set(counts)
    last_step = round(last_ns / (DT * 1e9))
    for topic in STAMPED_TOPICS:
        stamps = [round((m.header.stamp.sec * 10**9 + m.header.stamp.nanosec) / (DT * 1e9))
                  for _, m in decoded(bag, [topic])]
        assert len(stamps) == len(set(stamps)), f'{topic}: duplicated steps'
        # every step of the measured window is there, and nothing is lost once the topic is being recorded
        expected = set(range(last_step - STEPS, last_step + 1))
        assert expected <= set(stamps), f'{topic}: missing {sorted(expected - set(stamps))[:5]}'
        after_first = set(range(min(s for s in stamps if s > 0), last_step + 1))
        assert after_first <= set(stamps), f'{topic}: gap {sorted(after_first - set(stamps))[:5]}'
        assert counts[topic] == len(stamps)
    # /clock and the bumper have no header: the bumper of a step is published after its /clock, so the window's
    # bumper messages are those published after the /clock of the window's first step. Publish times (the writer's
    # source timestamps) keep that order; log (receive) times need not: a reliable sample a reader missed arrives
    # when it is sent again, after later messages of other topics (a fresh-clone `make test` under load logged 18
    # bumper messages of earlier steps after the window's first /clock).
    clock, bumper = [], []
    for rel in info['relative_file_paths']:
        with open(bag / rel, 'rb') as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            for _, ch, m, msg in reader.iter_decoded_messages(topics=['/clock', '/wheeled/bumper']):
                if ch.topic == '/clock':
                    clock.append((m.publish_time,
                                  round((msg.clock.sec * 10**9 + msg.clock.nanosec) / (DT * 1e9))))
                else:
                    bumper.append(m.publish_time)
    steps = [step for _, step in clock]
    assert len(steps) == len(set(steps)) and set(range(last_step - STEPS, last_step + 1)) <= set(steps)
    window_start = min(t for t, step in clock if step == last_step - STEPS)
    # ... and before the /clock of the step after the window, if one was recorded: the driver's last odometry can be
    # one step behind the simulator (a fresh-clone `make test` recorded step 109 of a window ending at 108, and its
    # bumper counted as the window's 102nd).
    window_end = min((t for t, step in clock if step == last_step + 1), default=math.inf)
    assert sum(window_start <= t < window_end for t in bumper) == STEPS + 1
    assert counts['/clock'] == len(clock) and counts['/wheeled/bumper'] == len(bumper)


def test_schema_qos_and_profile_follow_rosbag2(recorded_bag):
    bag, _ = recorded_bag
    info = read_metadata(bag)
    with open(bag / info['relative_file_paths'][0], 'rb') as f:
        reader = make_reader(f)
        assert reader.get_header().profile == 'ros2'
        summary = reader.get_summary()
        assert summary.chunk_indexes and summary.statistics.message_count == info['message_count']
        schemas = {s.name: s for s in summary.schemas.values()}
        assert schemas['sensor_msgs/msg/Range'].data.decode() == schema_text('sensor_msgs/msg/Range')
        assert schemas['nav_msgs/msg/Odometry'].encoding == 'ros2msg'
        for channel in summary.channels.values():
            assert channel.message_encoding == 'cdr'
            assert channel.metadata['topic_type_hash'].startswith('RIHS01_')
            assert yaml.safe_load(channel.metadata['offered_qos_profiles'])[0]['reliability'] == 'reliable'
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        assert yaml.safe_load(metadata['rosbag2']['serialized_metadata'])['message_count'] == info['message_count']


def test_decoded_ranges_match_the_sensor_model_at_the_recorded_pose(recorded_bag):
    bag, last_ns = recorded_bag
    first_in_window = last_ns - STEPS * round(DT * 1e9)
    robot = WheeledRobot()
    poses = {}
    for _, m in decoded(bag, ['/wheeled/ground_truth/odom']):
        q = m.pose.pose.orientation
        poses[(m.header.stamp.sec, m.header.stamp.nanosec)] = (
            m.pose.pose.position.x, m.pose.pose.position.y, 2 * math.atan2(q.z, q.w))
    names = ['front_left', 'front_center', 'front_right', 'side_front', 'side_rear']
    checked = 0
    for i, name in enumerate(names):
        for _, m in decoded(bag, [f'/wheeled/range/{name}']):
            if m.header.stamp.sec * 10**9 + m.header.stamp.nanosec < first_in_window:
                continue  # before the window the recorder may have matched the ranges before the odometry
            expected = robot.read(poses[(m.header.stamp.sec, m.header.stamp.nanosec)], noisy=False)[i]
            assert m.radiation_type == 1 and m.max_range > m.min_range
            if math.isinf(expected):
                assert math.isinf(m.range) and (m.range > 0) == (expected > 0)
            else:
                assert m.range == pytest.approx(expected, abs=1e-5)
            checked += 1
    assert checked >= 5 * (STEPS + 1)
