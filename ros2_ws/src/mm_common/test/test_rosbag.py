"""rosbag2 layout rules: schema text, QoS YAML, metadata, splitting, corrupt input; crash safety: time-based chunk
commits, recovery of cut files (reindex), a full disk, overwrite, malformed metadata and what the files really hold."""
import errno
import io
import os
import shutil

import yaml
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Range
from std_msgs.msg import String

from mm_common.rosbag import (SCHEMA_SEPARATOR, BagDiskFull, BagError, BagWriter, McapScan, QosSummary,
                              adapt_offered_qos, bag_owned_files, iter_messages, parse_qos_profiles, qos_profiles_yaml,
                              read_metadata, reindex, schema_text, summarize_file)


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


# --- crash safety, recovery and honest reading ----------------------------------------------------------------


class FakeClock:
    """A monotonic clock the test advances, so the time-based commit is checked without sleeping."""

    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def text_messages(writer, clock, n, start=0, period=0.1, size=10):
    for i in range(start, start + n):
        clock.now = i * period
        writer.write('/text', serialize_message(String(data=f'{i:06d}' + 'x' * size)), 10**9 + i * 10**8)


def recorded_indices(bag_dir):
    return [int(bytes(m.data[8:14]).decode()) for m in iter_messages(bag_dir)]


def copy_as_crashed(src_dir, dst_dir):
    """What kill -9 leaves: the storage file as it is on disk now, no metadata.yaml."""
    dst_dir.mkdir()
    for f in src_dir.glob('*.mcap'):
        shutil.copy(f, dst_dir / f.name.replace(src_dir.name, dst_dir.name))


def test_chunks_are_committed_after_flush_period_without_waiting_for_size(tmp_path):
    clock = FakeClock()
    writer = BagWriter(tmp_path / 'bag', clock=clock, flush_period=0.5, chunk_size=1 << 30)
    writer.add_topic('/text', 'std_msgs/msg/String', [QosSummary()])
    text_messages(writer, clock, 5, period=0.1)                 # 0.4 s: still one open chunk
    assert writer.topics['/text'].message_count == 0 and writer.seconds_until_flush() == pytest.approx(0.1)
    clock.now = 0.5
    writer.flush_if_due()                                       # the idle path of the recorder's writer thread
    assert writer.topics['/text'].message_count == 5 and writer.seconds_until_flush() is None
    text_messages(writer, clock, 30, start=5, period=0.1)
    committed = writer.topics['/text'].message_count
    assert 35 - committed <= 5                                  # uncommitted: at most flush_period (5 x 0.1 s)
    copy_as_crashed(tmp_path / 'bag', tmp_path / 'crash')
    writer.close()
    assert McapScan(tmp_path / 'crash' / 'crash_0.mcap').scan().message_count == committed
    assert 'without a summary' in McapScan(tmp_path / 'crash' / 'crash_0.mcap').scan().error


@pytest.mark.parametrize('compression', ['none', 'zstd'])
def test_reindex_recovers_the_intact_prefix_at_every_cut(tmp_path, compression):
    clock = FakeClock()
    writer = BagWriter(tmp_path / 'bag', clock=clock, flush_period=0.25, chunk_size=1 << 30, compression=compression)
    writer.add_topic('/text', 'std_msgs/msg/String', [QosSummary(reliability=2)], 'RIHS01_t')
    text_messages(writer, clock, 40)
    writer.close()
    data = (tmp_path / 'bag' / 'bag_0.mcap').read_bytes()
    recovered = []
    for cut in range(0, len(data), 97):
        bag = tmp_path / f'cut{cut}'
        bag.mkdir()
        (bag / f'cut{cut}_0.mcap').write_bytes(data[:cut])
        meta, report = reindex(bag)
        indices = recorded_indices(bag) if meta['files'] else []
        assert indices == list(range(len(indices))), f'cut at {cut}: not the intact prefix'
        assert meta['message_count'] == len(indices)
        recovered.append(len(indices))
        if cut == 0:
            assert meta['files'] == [] and 'empty (0 bytes), left out' in report[0]
        else:
            topic = meta['topics_with_message_count']
            assert not topic or (topic[0]['topic_metadata']['type_description_hash'] == 'RIHS01_t' and
                                 topic[0]['topic_metadata']['offered_qos_profiles'][0]['reliability'] ==
                                 'best_effort')
            with open(bag / f'cut{cut}_0.mcap', 'rb') as f:      # a complete, indexed file for the standard reader
                reader = make_reader(f)
                assert reader.get_summary().statistics.message_count == len(indices)
                assert {c.compression for c in reader.get_summary().chunk_indexes} <= {compression.replace('none', '')}
                assert len(list(reader.iter_messages())) == len(indices)
    assert recovered == sorted(recovered) and recovered[-1] == 40   # a cut in the summary loses no message


class DiskWithRoom(io.FileIO):
    """A real file on a pretend disk with `room` bytes: writes beyond it are cut short and then fail with ENOSPC,
    as on a full filesystem; truncating gives the bytes back."""

    room = 0

    def write(self, data):
        fits = max(0, DiskWithRoom.room - os.fstat(self.fileno()).st_size)
        if fits == 0 and len(data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return super().write(bytes(data[:fits]))


def test_full_disk_stops_once_and_leaves_a_readable_bag(tmp_path):
    DiskWithRoom.room = 12_000
    clock = FakeClock()
    writer = BagWriter(tmp_path / 'bag', clock=clock, flush_period=0.3, chunk_size=1 << 30,
                       open_file=lambda path: DiskWithRoom(path, 'wb'))
    writer.add_topic('/text', 'std_msgs/msg/String', [QosSummary()])
    with pytest.raises(BagDiskFull, match='disk full') as failure:
        text_messages(writer, clock, 1000, size=100)
    assert 'messages of the last chunk lost' in str(failure.value)
    with pytest.raises(BagError, match='recording stopped'):
        text_messages(writer, clock, 1, start=1000)
    kept = writer.topics['/text'].message_count
    assert kept > 0 and writer.closed and not (tmp_path / 'bag' / '.mm_recording_reserve').exists()
    assert read_metadata(tmp_path / 'bag')['message_count'] == kept
    assert recorded_indices(tmp_path / 'bag') == list(range(kept))
    summary = summarize_file(tmp_path / 'bag' / 'bag_0.mcap')
    assert not summary.error and summary.message_count == kept
    with open(tmp_path / 'bag' / 'bag_0.mcap', 'rb') as f:   # the standard reader reads it too (footer present)
        assert len(list(make_reader(f).iter_messages())) == kept


def test_overwrite_removes_only_the_replaced_bags_files(tmp_path):
    bag = tmp_path / 'bag'
    write_bag(bag, n=5)
    (bag / 'notes.yaml').write_text('mine: true\n')
    (bag / 'other.mcap').write_bytes(b'not ours')
    (bag / 'bag_7.mcap').write_bytes(b'')                     # a split file of this bag (by name): replaced
    assert [p.name for p in bag_owned_files(bag)] == ['bag_0.mcap', 'bag_7.mcap', 'metadata.yaml']
    write_bag(bag, n=2, overwrite=True)
    assert sorted(p.name for p in bag.iterdir()) == ['bag_0.mcap', 'metadata.yaml', 'notes.yaml', 'other.mcap']
    assert (bag / 'notes.yaml').read_text() == 'mine: true\n' and read_metadata(bag)['message_count'] == 4
    plain = tmp_path / 'plain'
    plain.mkdir()
    (plain / 'config.yaml').write_text('x: 1\n')
    with pytest.raises(BagError, match='not a bag'):
        BagWriter(plain, overwrite=True)
    assert (plain / 'config.yaml').exists()


@pytest.mark.parametrize('text, problem', [
    ('- just\n- a list\n', 'no rosbag2_bagfile_information'),
    ('rosbag2_bagfile_information: {storage_identifier: mcap, relative_file_paths: 3}', 'relative_file_paths'),
    ('rosbag2_bagfile_information: {storage_identifier: mcap, relative_file_paths: [a.mcap], '
     'topics_with_message_count: [{topic_metadata: {name: /a}}]}', 'name and a type'),
    ('rosbag2_bagfile_information: {storage_identifier: mcap, relative_file_paths: [a.mcap], message_count: many}',
     'message_count'),
    ('rosbag2_bagfile_information: {storage_identifier: mcap, relative_file_paths: [../outside.mcap]}',
     'leaves the bag directory'),
    ('rosbag2_bagfile_information: {storage_identifier: mcap, relative_file_paths: [/etc/hostname]}',
     'leaves the bag directory'),
    ('rosbag2_bagfile_information: {storage_identifier: mcap\n  bad: [', 'not valid YAML'),
])
def test_malformed_metadata_is_one_clear_error(tmp_path, text, problem):
    (tmp_path / 'metadata.yaml').write_text(text)
    with pytest.raises(BagError, match=problem) as error:
        read_metadata(tmp_path)
    assert '\n' not in str(error.value)


def test_file_summaries_count_what_the_files_hold(tmp_path):
    write_bag(tmp_path / 'bag', n=20)
    path = tmp_path / 'bag' / 'bag_0.mcap'
    summary = summarize_file(path)
    assert summary.counts == {'/range': 20, '/text': 20} and not summary.scanned and not summary.error
    assert summary.types['/range'] == 'sensor_msgs/msg/Range'
    assert summarize_file(tmp_path / 'bag' / 'nothing.mcap').error == 'file missing'
    data = path.read_bytes()
    path.write_bytes(b'')
    assert summarize_file(path).error == 'empty file (0 bytes)'
    path.write_bytes(data[:len(data) // 2])
    truncated = summarize_file(path)
    assert truncated.scanned and truncated.error.startswith('truncated')
    with pytest.raises(BagError, match='truncated'):
        list(iter_messages(tmp_path / 'bag'))


def test_no_room_for_the_next_split_file_keeps_the_finished_ones(tmp_path):
    def open_file(path):
        if path.name == 'bag_2.mcap':
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return open(path, 'wb', buffering=0)

    clock = FakeClock()
    writer = BagWriter(tmp_path / 'bag', clock=clock, max_bag_size=3000, chunk_size=500, open_file=open_file)
    writer.add_topic('/text', 'std_msgs/msg/String', [QosSummary()])
    with pytest.raises(BagDiskFull, match='bag_2.mcap'):
        text_messages(writer, clock, 1000, size=100)
    meta = read_metadata(tmp_path / 'bag')
    assert meta['relative_file_paths'] == ['bag_0.mcap', 'bag_1.mcap'] and writer.lost_messages == 1
    assert recorded_indices(tmp_path / 'bag') == list(range(meta['message_count']))
    assert meta['message_count'] == writer.topics['/text'].message_count > 10
