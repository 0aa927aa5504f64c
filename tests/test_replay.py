"""Replay: the player re-publishes a recorded bag and a subscriber receives the same bytes in the same order."""
import math

import pytest
from mm_bringup.process_graph import ProcessGraph
from mm_common.rosbag import BagWriter, QosSummary, iter_messages
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Range
from std_msgs.msg import Bool

QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


@pytest.fixture
def bag(tmp_path):
    writer = BagWriter(tmp_path / 'bag')
    writer.add_topic('/wheeled/range/front_center', 'sensor_msgs/msg/Range', [QosSummary()])
    writer.add_topic('/wheeled/bumper', 'std_msgs/msg/Bool', [QosSummary()])
    for i in range(200):
        t = 1_000_000_000 + i * 5_000_000
        r = Range(range=0.5 + 0.001 * i if i % 7 else math.inf)
        r.header.stamp.nanosec = i
        writer.write('/wheeled/range/front_center', serialize_message(r), t)
        writer.write('/wheeled/bumper', serialize_message(Bool(data=i % 2 == 0)), t + 1)
    writer.close()
    return tmp_path / 'bag'


@pytest.mark.parametrize('rate', [0.0, 2.0])
def test_player_replays_the_same_messages_in_order(ros, bag, rate):
    node = ros.node('replay_listener')
    received = []
    node.create_subscription(Range, '/wheeled/range/front_center',
                             lambda data: received.append(('/wheeled/range/front_center', data)), QOS, raw=True)
    node.create_subscription(Bool, '/wheeled/bumper', lambda data: received.append(('/wheeled/bumper', data)),
                             QOS, raw=True)
    with ProcessGraph(log_dir=bag.parent / 'logs') as graph:
        # start once our subscriptions matched (a fixed delay lost the first messages when discovery was slow)
        player = graph.start('mm_bringup', 'player', {'bag': str(bag), 'rate': rate, 'start_delay': 30.0,
                                                      'wait_for_subscribers': 1})
        assert ros.spin_until(lambda: len(received) == 400, timeout=30), (len(received), graph.log_tail(player))
        assert ros.spin_until(lambda: player.process.poll() is not None, timeout=10)
        assert player.process.returncode == 0
    recorded = [(m.topic, m.data) for m in iter_messages(bag)]
    for topic in ('/wheeled/range/front_center', '/wheeled/bumper'):
        assert [d for t, d in received if t == topic] == [d for t, d in recorded if t == topic]


def test_player_reports_a_corrupt_bag_and_exits_non_zero(tmp_path):
    (tmp_path / 'broken').mkdir()
    (tmp_path / 'broken' / 'metadata.yaml').write_text('rosbag2_bagfile_information: {storage_identifier: sqlite3}')
    with ProcessGraph(log_dir=tmp_path / 'logs') as graph:
        player = graph.start('mm_bringup', 'player', {'bag': str(tmp_path / 'broken')})
        assert player.process.wait(timeout=20) != 0
        assert 'not supported' in graph.log_tail(player)
