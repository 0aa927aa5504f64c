"""Recorder and player parameters in-process: start-up-only parameters are read-only, runtime ones reject NaN,
bad regexes and a missing bag are clear errors, and the in-process recorder writes with the time-based commit."""
import pytest
from mm_common.rosbag import BagError, BagWriter, McapScan, QosSummary, iter_messages, read_metadata
from mm_common.ros_harness import RosHarness
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from mm_bringup.player_node import Player
from mm_bringup.recorder_node import Recorder, RecorderConfigError

QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)


@pytest.fixture
def ros():
    harness = RosHarness()
    yield harness
    harness.close()


def test_recorder_start_up_parameters_are_read_only_and_runtime_ones_checked(ros, tmp_path):
    recorder = ros.add(Recorder(context=ros.context, parameter_overrides=[
        Parameter('output', value=str(tmp_path / 'bag')), Parameter('topics', value=['/params_test/.*']),
        Parameter('flush_period', value=0.05)]))
    for name, value in (('discovery_period', 1.0), ('flush_period', 1.0), ('chunk_size', 10), ('output', 'x'),
                        ('topics', ['.*']), ('max_bag_size', 5), ('compression', 'zstd')):
        assert not recorder.set_parameters([Parameter(name, value=value)])[0].successful, name
    assert not recorder.set_parameters([Parameter('drain_period', value=float('nan'))])[0].successful
    assert not recorder.set_parameters([Parameter('drain_period', value=-1.0)])[0].successful
    assert recorder.set_parameters([Parameter('drain_period', value=1.0)])[0].successful
    assert recorder.get_parameter('drain_period').value == 1.0     # main() reads it when the stop signal comes

    pub = ros.node('params_test_pub').create_publisher(String, '/params_test/text', QOS)
    assert ros.spin_until(lambda: pub.get_subscription_count() > 0, timeout=10)
    for i in range(5):
        pub.publish(String(data=str(i)))
    # committed by the writer thread's idle flush: readable by a scan before the bag is closed
    assert ros.spin_until(lambda: McapScan(tmp_path / 'bag' / 'bag_0.mcap').scan().message_count == 5, timeout=10)
    recorder.close()
    assert read_metadata(tmp_path / 'bag')['message_count'] == 5
    assert [bytes(m.data[8:9]).decode() for m in iter_messages(tmp_path / 'bag')] == list('01234')


@pytest.mark.parametrize('name, value, problem', [
    ('topics', ['(unclosed'], 'not a valid regular expression'),
    ('exclude', ['*bad'], 'not a valid regular expression'),
])
def test_recorder_rejects_bad_regexes_by_name(ros, tmp_path, name, value, problem):
    with pytest.raises(RecorderConfigError, match=f'{name}: .*{problem}'):
        Recorder(context=ros.context, parameter_overrides=[Parameter('output', value=str(tmp_path / 'bag')),
                                                           Parameter(name, value=value)])
    assert not (tmp_path / 'bag').exists()


def test_player_parameters_are_read_only_and_a_missing_bag_is_a_clear_error(ros, tmp_path):
    with pytest.raises(BagError, match='parameter bag is empty'):
        Player(context=ros.context)
    with pytest.raises(BagError, match='no such bag directory'):
        Player(context=ros.context, parameter_overrides=[Parameter('bag', value=str(tmp_path / 'nothing'))])
    writer = BagWriter(tmp_path / 'bag')
    writer.add_topic('/params_test/text', 'std_msgs/msg/String', [QosSummary()])
    writer.close()
    player = ros.add(Player(context=ros.context, parameter_overrides=[Parameter('bag', value=str(tmp_path / 'bag'))]))
    for name, value in (('bag', 'x'), ('rate', 2.0), ('topics', ['/a']), ('publish_clock', True),
                        ('start_delay', 0.0), ('wait_for_subscribers', 1)):
        assert not player.set_parameters([Parameter(name, value=value)])[0].successful, name
