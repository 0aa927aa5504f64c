"""rosbag2 layout rules: schema text, QoS YAML, metadata, splitting, corrupt input."""
import yaml
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Range
from std_msgs.msg import String

from mm_common.rosbag import (SCHEMA_SEPARATOR, BagError, BagWriter, QosSummary, adapt_offered_qos, iter_messages,
                              parse_qos_profiles, qos_profiles_yaml, read_metadata, schema_text)


def test_schema_text_appends_dependencies_like_rosbag2():
    text = schema_text('sensor_msgs/msg/Range')
    blocks = text.split('\n' + SCHEMA_SEPARATOR + '\n')
    assert blocks[0].startswith('# Single range reading')
    assert [b.splitlines()[0] for b in blocks[1:]] == ['MSG: std_msgs/Header', 'MSG: builtin_interfaces/Time']
    assert 'int32 sec' in blocks[2] and 'string frame_id' in blocks[1]


def test_schema_text_lists_each_dependency_once_sorted_depth_first():
    names = [line for line in schema_text('nav_msgs/msg/Odometry').splitlines() if line.startswith('MSG: ')]
    assert names == ['MSG: geometry_msgs/PoseWithCovariance', 'MSG: geometry_msgs/Pose', 'MSG: geometry_msgs/Point',
                     'MSG: geometry_msgs/Quaternion', 'MSG: geometry_msgs/TwistWithCovariance',
                     'MSG: geometry_msgs/Twist', 'MSG: geometry_msgs/Vector3', 'MSG: std_msgs/Header',
                     'MSG: builtin_interfaces/Time']


def test_unknown_type_is_a_clear_error():
    with pytest.raises(BagError, match='no definition'):
        schema_text('no_such_pkg/msg/Nothing')


def test_qos_yaml_round_trip_and_adaptation():
    profiles = [QosSummary(reliability=1, durability=1, history=1, depth=5), QosSummary(reliability=2)]
    data = yaml.safe_load(qos_profiles_yaml(profiles))
    assert data[0]['reliability'] == 'reliable' and data[0]['durability'] == 'transient_local'
    assert data[1]['reliability'] == 'best_effort'
    assert data[0]['deadline'] == {'sec': 9223372036, 'nsec': 854775807}
    assert parse_qos_profiles(qos_profiles_yaml(profiles)) == profiles
    assert adapt_offered_qos(profiles) == (2, 2)          # one best-effort publisher -> best effort
    assert adapt_offered_qos(profiles[:1]) == (1, 1)


def write_bag(path, n=50, **kwargs):
    writer = BagWriter(path, **kwargs)
    writer.add_topic('/range', 'sensor_msgs/msg/Range', [QosSummary()], 'RIHS01_abc')
    writer.add_topic('/text', 'std_msgs/msg/String', [QosSummary(reliability=2)])
    for i in range(n):
        writer.write('/range', serialize_message(Range(range=float(i))), 1000 + 10 * i, 900 + 10 * i)
        writer.write('/text', serialize_message(String(data=f'msg {i}' * 50)), 1005 + 10 * i)
    return writer.close()


def test_bag_directory_layout_and_mcap_contents(tmp_path):
    meta = write_bag(tmp_path / 'bag')
    info = read_metadata(tmp_path / 'bag')
    assert info == meta
    assert info['version'] == 9 and info['storage_identifier'] == 'mcap' and info['ros_distro'] == 'jazzy'
    assert info['message_count'] == 100 and info['relative_file_paths'] == ['bag_0.mcap']
    assert info['duration']['nanoseconds'] == 1005 + 490 - 1000
    counts = {t['topic_metadata']['name']: t['message_count'] for t in info['topics_with_message_count']}
    assert counts == {'/range': 50, '/text': 50}
    with open(tmp_path / 'bag' / 'bag_0.mcap', 'rb') as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        summary = reader.get_summary()
        assert header.profile == 'ros2'
        assert summary.statistics.message_count == 100 and summary.chunk_indexes
        assert {s.encoding for s in summary.schemas.values()} == {'ros2msg'}
        channel = next(c for c in summary.channels.values() if c.topic == '/range')
        assert channel.message_encoding == 'cdr'
        assert channel.metadata['topic_type_hash'] == 'RIHS01_abc'
        assert yaml.safe_load(channel.metadata['offered_qos_profiles'])[0]['reliability'] == 'reliable'
        assert 'rosbag2' in {m.name for m in reader.iter_metadata()}
        values = [m.range for _, ch, _, m in reader.iter_decoded_messages(topics=['/range'])]
    assert values == [float(i) for i in range(50)]
    publish = [m.publish_time_ns for m in iter_messages(tmp_path / 'bag', ['/range'])]
    assert publish[:2] == [900, 910]


def test_size_based_splitting_lists_every_file(tmp_path):
    meta = write_bag(tmp_path / 'split', n=400, max_bag_size=20_000, chunk_size=4096)
    assert len(meta['files']) > 1
    assert sum(f['message_count'] for f in meta['files']) == 800
    assert len(list(iter_messages(tmp_path / 'split'))) == 800


def test_zstd_compression_reads_back(tmp_path):
    write_bag(tmp_path / 'z', compression='zstd')
    assert len(list(iter_messages(tmp_path / 'z'))) == 100


def test_existing_directory_needs_overwrite(tmp_path):
    write_bag(tmp_path / 'bag')
    with pytest.raises(BagError, match='exists'):
        BagWriter(tmp_path / 'bag')
    write_bag(tmp_path / 'bag', n=3, overwrite=True)
    assert read_metadata(tmp_path / 'bag')['message_count'] == 6


def test_corrupt_bags_give_clear_errors(tmp_path):
    with pytest.raises(BagError, match='metadata.yaml missing'):
        read_metadata(tmp_path)
    write_bag(tmp_path / 'bag')
    mcap_path = tmp_path / 'bag' / 'bag_0.mcap'
    mcap_path.write_bytes(mcap_path.read_bytes()[:200])
    with pytest.raises(BagError, match='corrupt'):
        list(iter_messages(tmp_path / 'bag'))
    (tmp_path / 'bag' / 'metadata.yaml').write_text('not: [valid')
    with pytest.raises(BagError):
        read_metadata(tmp_path / 'bag')
