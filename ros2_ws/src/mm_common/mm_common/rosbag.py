"""rosbag2-compatible MCAP bags without rosbag2: schema texts, QoS YAML, metadata.yaml, a splitting writer, a reader.

Layout written (what `ros2 bag info/play` with rosbag2_storage_mcap expect, Jazzy, metadata version 9):
  <bag>/metadata.yaml           rosbag2_bagfile_information
  <bag>/<bag>_0.mcap, _1 ...    profile "ros2", schema encoding "ros2msg", message encoding "cdr",
                                channel metadata offered_qos_profiles (YAML) + topic_type_hash,
                                a "rosbag2" metadata record holding the serialized bag metadata.
No rclpy import: tools and tests use this module offline.
"""
from __future__ import annotations

import os
import re
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Sequence, Tuple

import yaml
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

ROS_DISTRO = 'jazzy'
METADATA_VERSION = 9
SCHEMA_SEPARATOR = '=' * 80
# rmw's "infinite" duration as rosbag2 serialises it.
INFINITE_DURATION = {'sec': 9223372036, 'nsec': 854775807}


class BagError(RuntimeError):
    """A bag directory or file that cannot be read or written as asked."""


# --- message definitions ------------------------------------------------------------------------------------------
def _default_share_dirs() -> List[Path]:
    dirs = []
    for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        if prefix:
            dirs.append(Path(prefix) / 'share')
    return dirs


def find_definition(type_name: str, share_dirs: Optional[Sequence[Path]] = None) -> str:
    """Text of the installed `pkg/msg/Type.msg` (from share/<pkg>/msg/ of the ament prefixes)."""
    pkg, kind, name = _split_type(type_name)
    for share in share_dirs or _default_share_dirs():
        path = Path(share) / pkg / kind / f'{name}.{kind}'
        if path.is_file():
            return path.read_text()
    raise BagError(f'no definition for {type_name}: {pkg}/{kind}/{name}.{kind} not found in the ament prefixes')


def _split_type(type_name: str) -> Tuple[str, str, str]:
    parts = type_name.split('/')
    if len(parts) == 3:
        return parts[0], parts[1], parts[2]
    if len(parts) == 2:
        return parts[0], 'msg', parts[1]
    raise BagError(f'not a ROS type name: {type_name!r} (expected pkg/msg/Type)')


# rosbag2_storage_mcap's dependency scan: the first token of each line that is followed by whitespace (optionally
# after an array suffix) is a field type; primitives are skipped, bare names belong to the message's own package.
_FIELD_TYPE = re.compile(r'(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+')
_PRIMITIVES = {'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16', 'int32', 'uint32',
               'int64', 'uint64', 'string'}


def _dependencies(text: str, own_package: str) -> List[str]:
    """Types a .msg text refers to, as `pkg/Type`, sorted (rosbag2 keeps them in a std::set)."""
    deps = set()
    for match in _FIELD_TYPE.finditer(text):
        name = match.group(1)
        if name in _PRIMITIVES:
            continue
        deps.add(name if '/' in name else f'{own_package}/{name}')
    return sorted(deps)


def schema_text(type_name: str, share_dirs: Optional[Sequence[Path]] = None) -> str:
    """The `ros2msg` schema text exactly as rosbag2 builds it: the .msg text, then for each not yet seen
    dependency (sorted, depth first) a newline, a line of 80 '=', `MSG: pkg/Type` and that type's full text."""
    seen = set()

    def full_text(name: str) -> str:
        pkg = _split_type(name)[0]
        text = find_definition(name, share_dirs)
        for dep in _dependencies(text, pkg):
            if dep not in seen:
                seen.add(dep)
                text += f'\n{SCHEMA_SEPARATOR}\nMSG: {dep}\n' + full_text(dep)
        return text

    return full_text(type_name)


# --- QoS ----------------------------------------------------------------------------------------------------------
_HISTORY = {0: 'system_default', 1: 'keep_last', 2: 'keep_all', 3: 'unknown'}
_RELIABILITY = {0: 'system_default', 1: 'reliable', 2: 'best_effort', 3: 'unknown', 4: 'best_available'}
_DURABILITY = {0: 'system_default', 1: 'transient_local', 2: 'volatile', 3: 'unknown', 4: 'best_available'}
_LIVELINESS = {0: 'system_default', 1: 'automatic', 3: 'manual_by_topic', 4: 'unknown', 5: 'best_available'}


@dataclass(frozen=True)
class QosSummary:
    """The parts of an offered QoS profile that rosbag2 records (enum values as in rmw)."""

    reliability: int = 1
    durability: int = 2
    history: int = 3
    depth: int = 0
    liveliness: int = 1

    def to_yaml_dict(self) -> dict:
        return {
            'history': _HISTORY.get(self.history, 'unknown'),
            'depth': int(self.depth),
            'reliability': _RELIABILITY.get(self.reliability, 'unknown'),
            'durability': _DURABILITY.get(self.durability, 'unknown'),
            'deadline': dict(INFINITE_DURATION),
            'lifespan': dict(INFINITE_DURATION),
            'liveliness': _LIVELINESS.get(self.liveliness, 'unknown'),
            'liveliness_lease_duration': dict(INFINITE_DURATION),
            'avoid_ros_namespace_conventions': False,
        }

    @classmethod
    def from_yaml_dict(cls, d: dict) -> 'QosSummary':
        inverse = lambda table, v: next((k for k, name in table.items() if name == v), v if isinstance(v, int) else 0)  # noqa: E731
        return cls(reliability=inverse(_RELIABILITY, d.get('reliability', 1)),
                   durability=inverse(_DURABILITY, d.get('durability', 2)),
                   history=inverse(_HISTORY, d.get('history', 3)), depth=int(d.get('depth', 0)),
                   liveliness=inverse(_LIVELINESS, d.get('liveliness', 1)))


def qos_profiles_yaml(profiles: Sequence[QosSummary]) -> str:
    """offered_qos_profiles as the YAML string rosbag2 puts into MCAP channel metadata."""
    return yaml.safe_dump([p.to_yaml_dict() for p in profiles], sort_keys=False, default_flow_style=False)


def parse_qos_profiles(text_or_list) -> List[QosSummary]:
    data = yaml.safe_load(text_or_list) if isinstance(text_or_list, str) else text_or_list
    return [QosSummary.from_yaml_dict(d) for d in (data or [])]


def adapt_offered_qos(profiles: Sequence[QosSummary]) -> Tuple[int, int]:
    """(reliability, durability) a recorder/player should use, the way rosbag2 adapts to offers:
    reliable only if every publisher is reliable, transient-local only if every publisher is."""
    if not profiles:
        return 1, 2
    reliability = 1 if all(p.reliability == 1 for p in profiles) else 2
    durability = 1 if all(p.durability == 1 for p in profiles) else 2
    return reliability, durability


# --- writing ------------------------------------------------------------------------------------------------------
@dataclass
class TopicInfo:
    name: str
    type: str
    offered_qos: List[QosSummary] = field(default_factory=list)
    type_hash: str = ''
    message_count: int = 0


@dataclass
class _FileStats:
    path: str
    start_ns: Optional[int] = None
    end_ns: Optional[int] = None
    count: int = 0


class BagWriter:
    """Writes a rosbag2 bag directory with MCAP storage; splits files at `max_bag_size` bytes.

    Not thread-safe: the recorder calls it from a single writer thread.
    """

    def __init__(self, directory: os.PathLike, *, compression: str = 'none', max_bag_size: int = 0,
                 chunk_size: int = 1024 * 1024, overwrite: bool = False,
                 share_dirs: Optional[Sequence[Path]] = None):
        self.directory = Path(directory)
        if compression not in ('none', 'zstd', 'lz4'):
            raise BagError(f'compression must be none, zstd or lz4, got {compression!r}')
        if max_bag_size < 0:
            raise BagError('max_bag_size must be >= 0 (0 = no splitting)')
        if self.directory.exists():
            if not overwrite:
                raise BagError(f'{self.directory} exists (pass overwrite to replace it)')
            if (self.directory / 'metadata.yaml').exists() or any(self.directory.glob('*.mcap')) \
                    or not any(self.directory.iterdir()):
                for child in self.directory.iterdir():
                    if child.is_file() and (child.suffix in ('.mcap', '.yaml')):
                        child.unlink()
            else:
                raise BagError(f'{self.directory} exists and is not a bag; refusing to overwrite it')
        self.directory.mkdir(parents=True, exist_ok=True)
        self.compression = compression
        self.max_bag_size = int(max_bag_size)
        self.chunk_size = int(chunk_size)
        self.share_dirs = share_dirs
        self.topics: Dict[str, TopicInfo] = {}
        self._schema_texts: Dict[str, bytes] = {}
        self._files: List[_FileStats] = []
        self._writer: Optional[Writer] = None
        self._stream = None
        self._schema_ids: Dict[str, int] = {}
        self._channel_ids: Dict[str, int] = {}
        self._sequence = 0
        self._closed = False
        self._open_next_file()

    @property
    def name(self) -> str:
        return self.directory.name

    def _open_next_file(self) -> None:
        path = f'{self.name}_{len(self._files)}.mcap'
        self._stream = open(self.directory / path, 'wb')
        self._writer = Writer(self._stream, chunk_size=self.chunk_size,
                              compression={'none': CompressionType.NONE, 'zstd': CompressionType.ZSTD,
                                           'lz4': CompressionType.LZ4}[self.compression])
        self._writer.start(profile='ros2', library='mm rosbag2-compatible writer (python mcap)')
        self._files.append(_FileStats(path))
        self._schema_ids.clear()
        self._channel_ids.clear()
        for topic in self.topics.values():
            self._register_channel(topic)

    def _register_channel(self, topic: TopicInfo) -> None:
        if topic.type not in self._schema_ids:
            if topic.type not in self._schema_texts:
                self._schema_texts[topic.type] = schema_text(topic.type, self.share_dirs).encode()
            self._schema_ids[topic.type] = self._writer.register_schema(
                name=topic.type, encoding='ros2msg', data=self._schema_texts[topic.type])
        self._channel_ids[topic.name] = self._writer.register_channel(
            topic=topic.name, message_encoding='cdr', schema_id=self._schema_ids[topic.type],
            metadata={'offered_qos_profiles': qos_profiles_yaml(topic.offered_qos),
                      'topic_type_hash': topic.type_hash})

    def add_topic(self, name: str, type_name: str, offered_qos: Sequence[QosSummary] = (),
                  type_hash: str = '') -> TopicInfo:
        """Register a topic (idempotent). Raises BagError if the type's .msg definition is not installed."""
        if name in self.topics:
            return self.topics[name]
        topic = TopicInfo(name, type_name, list(offered_qos), type_hash)
        self._register_channel(topic)   # resolves the schema first, so an unknown type is not half-registered
        self.topics[name] = topic
        return topic

    def write(self, topic: str, data: bytes, log_time_ns: int, publish_time_ns: Optional[int] = None) -> None:
        if self._closed:
            raise BagError('bag already closed')
        info = self.topics.get(topic)
        if info is None:
            raise BagError(f'topic {topic} was not added')
        current = self._files[-1]
        if self.max_bag_size and current.count and self._stream.tell() >= self.max_bag_size:
            self._finish_file()
            self._open_next_file()
            current = self._files[-1]
        self._writer.add_message(channel_id=self._channel_ids[topic], log_time=int(log_time_ns),
                                 publish_time=int(publish_time_ns if publish_time_ns is not None else log_time_ns),
                                 data=bytes(data), sequence=self._sequence)
        self._sequence += 1
        info.message_count += 1
        current.count += 1
        current.start_ns = log_time_ns if current.start_ns is None else min(current.start_ns, log_time_ns)
        current.end_ns = log_time_ns if current.end_ns is None else max(current.end_ns, log_time_ns)

    def metadata(self) -> dict:
        starts = [f.start_ns for f in self._files if f.start_ns is not None]
        ends = [f.end_ns for f in self._files if f.end_ns is not None]
        start = min(starts) if starts else 0
        duration = (max(ends) - start) if ends else 0
        info = {
            'version': METADATA_VERSION,
            'storage_identifier': 'mcap',
            'duration': {'nanoseconds': int(duration)},
            'starting_time': {'nanoseconds_since_epoch': int(start)},
            'message_count': int(sum(t.message_count for t in self.topics.values())),
            'topics_with_message_count': [
                {'topic_metadata': {'name': t.name, 'type': t.type, 'serialization_format': 'cdr',
                                    'offered_qos_profiles': [q.to_yaml_dict() for q in t.offered_qos],
                                    'type_description_hash': t.type_hash},
                 'message_count': int(t.message_count)}
                for t in self.topics.values()],
            'compression_format': '',
            'compression_mode': '',
            'relative_file_paths': [f.path for f in self._files],
            'files': [{'path': f.path,
                       'starting_time': {'nanoseconds_since_epoch': int(f.start_ns or 0)},
                       'duration': {'nanoseconds': int((f.end_ns or 0) - (f.start_ns or 0))},
                       'message_count': int(f.count)} for f in self._files],
            'custom_data': {},
            'ros_distro': ROS_DISTRO,
        }
        return info

    def _finish_file(self) -> None:
        # rosbag2_storage_mcap stores the bag metadata in a "rosbag2" metadata record of each file.
        self._writer.add_metadata('rosbag2', {'serialized_metadata': yaml.safe_dump(self.metadata(), sort_keys=False),
                                              'ROS_DISTRO': ROS_DISTRO})
        self._writer.finish()
        self._stream.close()

    def close(self) -> dict:
        """Finish the current MCAP file (summary, indexes) and write metadata.yaml atomically."""
        if self._closed:
            return self.metadata()
        self._finish_file()
        self._closed = True
        meta = self.metadata()
        write_metadata(self.directory, meta)
        return meta


def write_metadata(directory: os.PathLike, info: dict) -> None:
    directory = Path(directory)
    text = yaml.safe_dump({'rosbag2_bagfile_information': info}, sort_keys=False, default_flow_style=False)
    fd, tmp = tempfile.mkstemp(dir=directory, prefix='.metadata.', suffix='.yaml')
    with os.fdopen(fd, 'w') as f:
        f.write(text)
    os.chmod(tmp, 0o644)
    os.replace(tmp, directory / 'metadata.yaml')


# --- reading ------------------------------------------------------------------------------------------------------
def read_metadata(directory: os.PathLike) -> dict:
    path = Path(directory) / 'metadata.yaml'
    if not path.is_file():
        raise BagError(f'{directory} is not a bag directory: metadata.yaml missing')
    try:
        data = yaml.safe_load(path.read_text())
        info = data['rosbag2_bagfile_information']
    except (yaml.YAMLError, KeyError, TypeError) as exc:
        raise BagError(f'{path}: not a rosbag2 metadata file ({exc})') from exc
    if info.get('storage_identifier') != 'mcap':
        raise BagError(f"{path}: storage {info.get('storage_identifier')!r} is not supported (mcap only)")
    return info


@dataclass
class BagMessage:
    topic: str
    type: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int


def iter_messages(directory: os.PathLike, topics: Optional[Sequence[str]] = None) -> Iterator[BagMessage]:
    """Messages of every file of a bag in log-time order within each file, raw CDR bytes."""
    directory = Path(directory)
    info = read_metadata(directory)
    wanted = set(topics) if topics else None
    for rel in info.get('relative_file_paths', []):
        path = directory / rel
        if not path.is_file():
            raise BagError(f'{path} listed in metadata.yaml is missing')
        with open(path, 'rb') as stream:
            try:
                reader = make_reader(stream)
                for schema, channel, message in reader.iter_messages(topics=list(wanted) if wanted else None,
                                                                      log_time_order=True):
                    yield BagMessage(channel.topic, schema.name if schema else '', message.data,
                                     message.log_time, message.publish_time)
            except BagError:
                raise
            except Exception as exc:  # mcap raises several exception types for damaged files
                raise BagError(f'{path}: corrupt or truncated MCAP file ({exc})') from exc


def topic_qos(info: dict) -> Dict[str, Tuple[str, List[QosSummary]]]:
    """topic -> (type, offered QoS profiles) from bag metadata."""
    out = {}
    for entry in info.get('topics_with_message_count', []):
        meta = entry['topic_metadata']
        out[meta['name']] = (meta['type'], parse_qos_profiles(meta.get('offered_qos_profiles', [])))
    return out
