"""The demo's check that its bag holds every step of the wheeled loop (mm_bringup.demo.bag_completeness)."""
from rclpy.serialization import serialize_message
from mm_msgs.msg import RangeGroup
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Range
from std_msgs.msg import Bool

from mm_bringup.demo import PER_STEP_TOPICS, STAMPED_PER_STEP_TOPICS, bag_completeness, header_stamp_ns
from mm_common.rosbag import BagWriter, QosSummary

DT_NS = 50_000_000
TYPES = {'/wheeled/ranges': ('mm_msgs/msg/RangeGroup', RangeGroup),
         '/wheeled/ground_truth/odom': ('nav_msgs/msg/Odometry', Odometry),
         '/wheeled/bumper': ('std_msgs/msg/Bool', Bool)}


def message(topic, step):
    _, cls = TYPES.get(topic, ('sensor_msgs/msg/Range', Range))
    msg = cls()
    if topic != '/wheeled/bumper':
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(step * DT_NS, 1_000_000_000)
    return serialize_message(msg)


def write_bag(path, published, truncated=None):
    """`published`: (topic, step) in the order the simulator sent them; the `truncated` one cut to 6 bytes."""
    writer = BagWriter(path)
    for topic in PER_STEP_TOPICS:
        writer.add_topic(topic, TYPES.get(topic, ('sensor_msgs/msg/Range',))[0], [QosSummary()])
    for n, (topic, step) in enumerate(published):
        data = message(topic, step)
        writer.write(topic, data[:6] if (topic, step) == truncated else data, 1_000_000_000 + n)
    writer.close()
    return path


def steps(n, topics=PER_STEP_TOPICS):
    return [(topic, step) for step in range(n) for topic in topics]


def test_the_header_stamp_is_read_from_the_serialized_bytes():
    assert header_stamp_ns(message('/wheeled/range/side_rear', 41)) == 41 * DT_NS
    assert header_stamp_ns(message('/wheeled/ground_truth/odom', 7)) == 7 * DT_NS


def test_a_step_re_sent_to_some_topics_only_is_no_loss(tmp_path):
    """At start-up the simulator re-sends step 0 while the recorder has matched some of its topics and not yet the
    others (seen in one demo of four: three topics one message ahead): every step is still on every topic."""
    early = ['/wheeled/range/front_left', '/wheeled/range/front_center', '/wheeled/bumper']
    result = bag_completeness(write_bag(tmp_path / 'bag', [(t, 0) for t in early] + steps(5)))
    assert result['complete'] and result['steps'] == 5
    assert result['per_step_topic_counts']['/wheeled/range/front_left'] == 6
    assert set(result['per_step_topic_steps'].values()) == {5}


def test_a_step_missing_from_one_topic_is_a_loss(tmp_path):
    published = [(t, s) for t, s in steps(5) if (t, s) != ('/wheeled/range/side_rear', 3)]
    assert not bag_completeness(write_bag(tmp_path / 'a', published))['complete']
    # a step replaced by a re-sent one: the counts agree, the steps do not
    published = [(t, 2 if (t, s) == ('/wheeled/ranges', 3) else s) for t, s in steps(5)]
    result = bag_completeness(write_bag(tmp_path / 'b', published))
    assert len(set(result['per_step_topic_counts'].values())) == 1 and not result['complete']
    # a truncated message holds no step
    assert not bag_completeness(write_bag(tmp_path / 'd', steps(3), truncated=('/wheeled/ranges', 1)))['complete']
    # the bumper has no stamp: fewer of its messages than steps is a loss
    published = [(t, s) for t, s in steps(5) if (t, s) != ('/wheeled/bumper', 4)]
    assert not bag_completeness(write_bag(tmp_path / 'c', published))['complete']
    assert set(STAMPED_PER_STEP_TOPICS) | {'/wheeled/bumper'} == set(PER_STEP_TOPICS)
