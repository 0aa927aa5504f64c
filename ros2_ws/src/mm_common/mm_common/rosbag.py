"""rosbag2-compatible MCAP bags without rosbag2: schema texts, QoS YAML, metadata.yaml, a splitting writer, a reader.

Layout written (what `ros2 bag info/play` with rosbag2_storage_mcap expect, Jazzy, metadata version 9):
  <bag>/metadata.yaml           rosbag2_bagfile_information
  <bag>/<bag>_0.mcap, _1 ...    profile "ros2", schema encoding "ros2msg", message encoding "cdr",
                                channel metadata offered_qos_profiles (YAML) + topic_type_hash,
                                a "rosbag2" metadata record holding the serialized bag metadata.
No rclpy import: tools and tests use this module offline.
"""
from __future__ import annotations

import errno
import io
import math
import os
import re
import struct
import tempfile
import time
import zlib
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, Iterator, List, Optional, Sequence, Tuple

import yaml
from mcap._chunk_builder import ChunkBuilder
from mcap.data_stream import RecordBuilder
from mcap.exceptions import EndOfFile
from mcap.opcode import Opcode
from mcap.reader import SeekingReader, make_reader
from mcap.records import (Channel, Chunk, ChunkIndex, DataEnd, Footer, Header, Message, Metadata, MetadataIndex,
                          Schema, Statistics, SummaryOffset)
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.summary import Summary
from mcap.writer import MCAP0_MAGIC

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


# --- MCAP file layer ----------------------------------------------------------------------------------------------
class BagDiskFull(BagError):
    """The disk filled up (ENOSPC) while writing; what was committed before stays readable."""


_COMPRESSORS = {'none': ('', lambda data: data),
                'zstd': ('zstd', lambda data: _zstd().compress(data)),
                'lz4': ('lz4', lambda data: _lz4_frame().compress(data))}


def _zstd():
    import zstandard
    return zstandard


def _lz4_frame():
    import lz4.frame
    return lz4.frame


class McapFile:
    """One MCAP file written so that a crash or a full disk loses at most the chunk being built.

    Schema and channel records go into the data section outside chunks; messages are grouped into a chunk that
    `commit()` hands to the OS together with its message indexes in one unbuffered write (what a killed process
    wrote survives it); `sync()` forces it to the disk, `finish()` does so when `fsync` is set. The summary is built
    from committed state only: after a failed write the file is cut back to the last commit and `finish()` still
    appends a consistent summary, so a killed or starved recorder leaves a readable prefix.
    """

    def __init__(self, path: os.PathLike, *, compression: str = 'none', profile: str = 'ros2',
                 library: str = 'mm rosbag2-compatible writer', fsync: bool = True,
                 open_file: Callable[[Path], io.FileIO] = lambda path: open(path, 'wb', buffering=0)):
        if compression not in _COMPRESSORS:
            raise BagError(f'compression must be none, zstd or lz4, got {compression!r}')
        self.path = Path(path)
        self.compression = compression
        self.fsync = fsync
        self.size = 0                         # bytes committed
        self.message_count = 0
        self.start_ns: Optional[int] = None
        self.end_ns: Optional[int] = None
        self._schemas: Dict[int, Schema] = {}
        self._channels: Dict[int, Channel] = {}
        self._pending_records: List = []      # schemas and channels not committed yet
        self._chunk = ChunkBuilder()
        self._chunk_indexes: List[ChunkIndex] = []
        self._counts: Dict[int, int] = defaultdict(int)
        self._metadata: List[Tuple[str, Dict[str, str]]] = []
        self._next_id = {'schema': 1, 'channel': 1}
        self._file: Optional[io.FileIO] = open_file(self.path)   # unbuffered: a commit is on disk or cut back
        builder = RecordBuilder()
        Header(profile=profile, library=library).write(builder)
        try:
            self._append(MCAP0_MAGIC + builder.end())
        except OSError:
            self.abandon()
            raise

    @property
    def pending_bytes(self) -> int:
        return self._chunk.count

    @property
    def pending_messages(self) -> int:
        return self._chunk.num_messages

    def add_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema = Schema(id=self._next_id['schema'], name=name, encoding=encoding, data=data)
        self._next_id['schema'] += 1
        self._pending_records.append(schema)
        return schema.id

    def add_channel(self, topic: str, message_encoding: str, schema_id: int, metadata: Dict[str, str]) -> int:
        channel = Channel(id=self._next_id['channel'], topic=topic, message_encoding=message_encoding,
                          schema_id=schema_id, metadata=metadata)
        self._next_id['channel'] += 1
        self._pending_records.append(channel)
        return channel.id

    def add_message(self, channel_id: int, log_time: int, publish_time: int, data: bytes, sequence: int = 0) -> None:
        self._chunk.add_message(Message(channel_id=channel_id, sequence=sequence, log_time=log_time,
                                        publish_time=publish_time, data=data))

    def add_metadata(self, name: str, data: Dict[str, str]) -> None:
        """A metadata record written by `finish()` (rosbag2 keeps the bag metadata there)."""
        self._metadata.append((name, data))

    def _append(self, data: bytes) -> None:
        """Write `data` at the committed end; on any OSError cut the file back to the committed end and re-raise."""
        try:
            view = memoryview(data)
            while view:
                view = view[self._file.write(view):]
        except OSError:
            try:
                self._file.truncate(self.size)
                self._file.seek(self.size)
            except OSError:
                pass
            raise
        self.size += len(data)

    def commit(self) -> None:
        """Write pending schemas, channels and the chunk in progress (raises OSError; nothing of it is kept then)."""
        if not self._pending_records and not self._chunk.num_messages:
            return
        builder = RecordBuilder()
        for record in self._pending_records:
            record.write(builder)
        chunk_index = None
        chunk = self._chunk
        if chunk.num_messages:
            raw = chunk.record_writer.end()
            name, compress = _COMPRESSORS[self.compression]
            compressed = compress(raw)
            chunk_start = self.size + builder.count
            Chunk(compression=name, data=compressed, message_start_time=chunk.message_start_time,
                  message_end_time=chunk.message_end_time, uncompressed_crc=zlib.crc32(raw),
                  uncompressed_size=len(raw)).write(builder)
            index_start = self.size + builder.count
            offsets = {}
            for channel_id, index in chunk.message_indices.items():
                offsets[channel_id] = self.size + builder.count
                index.write(builder)
            chunk_index = ChunkIndex(
                message_start_time=chunk.message_start_time, message_end_time=chunk.message_end_time,
                chunk_start_offset=chunk_start, chunk_length=index_start - chunk_start,
                message_index_offsets=offsets, message_index_length=self.size + builder.count - index_start,
                compression=name, compressed_size=len(compressed), uncompressed_size=len(raw))
        self._append(builder.end())
        for record in self._pending_records:
            (self._schemas if isinstance(record, Schema) else self._channels)[record.id] = record
        self._pending_records = []
        if chunk_index is not None:
            self._chunk_indexes.append(chunk_index)
            for channel_id, index in chunk.message_indices.items():
                self._counts[channel_id] += len(index.records)
            self.message_count += chunk.num_messages
            self.start_ns = chunk.message_start_time if self.start_ns is None else min(self.start_ns,
                                                                                       chunk.message_start_time)
            self.end_ns = chunk.message_end_time if self.end_ns is None else max(self.end_ns, chunk.message_end_time)
        chunk.reset()

    def sync(self) -> None:
        """Force what was committed to the disk (power loss, not only a killed process)."""
        os.fsync(self._file.fileno())

    def discard_pending(self) -> int:
        """Drop the chunk in progress (after a failed commit); returns how many messages it held."""
        lost = self._chunk.num_messages
        self._chunk.reset()
        return lost

    def _closing_bytes(self, with_summary: bool) -> bytes:
        builder = RecordBuilder()
        metadata_indexes = []
        if with_summary:
            for name, data in self._metadata:
                offset = self.size + builder.count
                Metadata(name=name, metadata=data).write(builder)
                metadata_indexes.append(MetadataIndex(offset=offset, length=self.size + builder.count - offset,
                                                      name=name))
        DataEnd(data_section_crc=0).write(builder)
        summary_start = self.size + builder.count
        summary = RecordBuilder()
        summary_offset_start = 0
        if with_summary:
            groups = [(Opcode.SCHEMA, list(self._schemas.values())),
                      (Opcode.CHANNEL, list(self._channels.values())),
                      (Opcode.STATISTICS, [Statistics(
                          message_count=self.message_count, schema_count=len(self._schemas),
                          channel_count=len(self._channels), attachment_count=0,
                          metadata_count=len(metadata_indexes), chunk_count=len(self._chunk_indexes),
                          message_start_time=self.start_ns or 0, message_end_time=self.end_ns or 0,
                          channel_message_counts=dict(self._counts))]),
                      (Opcode.CHUNK_INDEX, self._chunk_indexes),
                      (Opcode.METADATA_INDEX, metadata_indexes)]
            offsets = []
            for opcode, records in groups:
                start = summary.count
                for record in records:
                    record.write(summary)
                if summary.count > start:
                    offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + start,
                                                 group_length=summary.count - start))
            summary_offset_start = summary_start + summary.count
            for offset in offsets:
                offset.write(summary)
        summary_data = summary.end()
        footer_start = summary_start if summary_data else 0
        crc = zlib.crc32(struct.pack('<BQQQ', Opcode.FOOTER, 20, footer_start, summary_offset_start),
                         zlib.crc32(summary_data))
        Footer(summary_start=footer_start, summary_offset_start=summary_offset_start,
               summary_crc=crc).write(summary)
        return builder.end() + summary_data + summary.end() + MCAP0_MAGIC

    def finish(self) -> str:
        """Close the file: 'summary' (complete, indexed), else 'footer' (no summary: readers scan it, still valid),
        else 'truncated' (the disk had no room even for a footer: a clean prefix that `reindex` completes)."""
        if self._file is None:
            raise BagError(f'{self.path} already finished')
        outcome = 'truncated'
        for with_summary in (True, False):
            try:
                self._append(self._closing_bytes(with_summary))
                outcome = 'summary' if with_summary else 'footer'
                if self.fsync:
                    self.sync()
                break
            except OSError:
                continue
        self._file.close()
        self._file = None
        return outcome

    def abandon(self) -> None:
        """Close without a summary (the file stays a clean prefix of committed records)."""
        if self._file is not None:
            self._file.close()
            self._file = None


# --- bags ---------------------------------------------------------------------------------------------------------
@dataclass
class TopicInfo:
    name: str
    type: str
    offered_qos: List[QosSummary] = field(default_factory=list)
    type_hash: str = ''
    message_count: int = 0


@dataclass
class FileStats:
    path: str
    start_ns: Optional[int] = None
    end_ns: Optional[int] = None
    count: int = 0


def bag_metadata(files: Sequence[FileStats], topics: Sequence[TopicInfo]) -> dict:
    """rosbag2_bagfile_information (version 9) for these files and topics."""
    starts = [f.start_ns for f in files if f.start_ns is not None]
    ends = [f.end_ns for f in files if f.end_ns is not None]
    start = min(starts) if starts else 0
    duration = (max(ends) - start) if ends else 0
    return {
        'version': METADATA_VERSION,
        'storage_identifier': 'mcap',
        'duration': {'nanoseconds': int(duration)},
        'starting_time': {'nanoseconds_since_epoch': int(start)},
        'message_count': int(sum(t.message_count for t in topics)),
        'topics_with_message_count': [
            {'topic_metadata': {'name': t.name, 'type': t.type, 'serialization_format': 'cdr',
                                'offered_qos_profiles': [q.to_yaml_dict() for q in t.offered_qos],
                                'type_description_hash': t.type_hash},
             'message_count': int(t.message_count)}
            for t in topics],
        'compression_format': '',
        'compression_mode': '',
        'relative_file_paths': [f.path for f in files],
        'files': [{'path': f.path,
                   'starting_time': {'nanoseconds_since_epoch': int(f.start_ns or 0)},
                   'duration': {'nanoseconds': int((f.end_ns or 0) - (f.start_ns or 0))},
                   'message_count': int(f.count)} for f in files],
        'custom_data': {},
        'ros_distro': ROS_DISTRO,
    }


RESERVE_NAME = '.mm_recording_reserve'
RESERVE_BYTES = 256 * 1024


def _bag_file_name(bag_name: str, index: int) -> str:
    return f'{bag_name}_{index}.mcap'


def bag_owned_files(directory: os.PathLike) -> List[Path]:
    """The files of the bag in `directory`: metadata.yaml, the files it lists (inside the directory only),
    `<name>_<n>.mcap` storage files, the recorder's disk reserve and leftover temp files of metadata.yaml / reindex.
    Anything else in the directory is not the bag's and is never touched."""
    directory = Path(directory)
    owned = set()
    meta = directory / 'metadata.yaml'
    if meta.is_file():
        owned.add(meta)
        try:
            owned.update(bag_file_paths(directory, read_metadata(directory)))
        except BagError:
            pass   # unreadable metadata: fall back to the naming pattern
    pattern = re.compile(re.escape(directory.name) + r'_\d+\.mcap')
    for child in directory.iterdir():
        if pattern.fullmatch(child.name) or child.name == RESERVE_NAME or \
                (child.name.startswith('.metadata.') and child.name.endswith('.yaml')) or \
                (child.name.startswith('.') and child.name.endswith('.mcap.reindex')):
            owned.add(child)
    return sorted(p for p in owned if p.is_file())


class BagWriter:
    """Writes a rosbag2 bag directory with MCAP storage; splits files at `max_bag_size` bytes.

    A chunk is committed (written to the OS) when it reaches `chunk_size` bytes or when its oldest message is
    `flush_period` seconds old (`flush_if_due()` covers quiet periods), so a killed recorder loses at most that much;
    with `fsync`, committed data is forced to the disk at most once per `flush_period` (every commit would cost
    about 60 % of the throughput for camera images).
    metadata.yaml is written at every split and at close; a crashed bag is completed by `reindex()`.
    On a full disk the writer frees its reserve, closes the current file with what was committed, writes
    metadata.yaml and raises BagDiskFull once; later writes raise BagError. Not thread-safe: one writer thread.
    """

    def __init__(self, directory: os.PathLike, *, compression: str = 'none', max_bag_size: int = 0,
                 chunk_size: int = 1024 * 1024, flush_period: float = 0.5, fsync: bool = True,
                 overwrite: bool = False, share_dirs: Optional[Sequence[Path]] = None,
                 clock: Callable[[], float] = time.monotonic,
                 open_file: Optional[Callable[[Path], io.FileIO]] = None):
        self.directory = Path(directory)
        if compression not in _COMPRESSORS:
            raise BagError(f'compression must be none, zstd or lz4, got {compression!r}')
        if max_bag_size < 0:
            raise BagError('max_bag_size must be >= 0 (0 = no splitting)')
        if chunk_size < 0:
            raise BagError('chunk_size must be >= 0')
        if not flush_period > 0 or not math.isfinite(flush_period):
            raise BagError(f'flush_period must be a positive number of seconds, got {flush_period}')
        if self.directory.exists():
            if not self.directory.is_dir():
                raise BagError(f'{self.directory} exists and is not a directory')
            if not overwrite:
                raise BagError(f'{self.directory} exists (pass overwrite to replace it)')
            owned = bag_owned_files(self.directory)
            if not owned and any(self.directory.iterdir()):
                raise BagError(f'{self.directory} exists and is not a bag; refusing to overwrite it')
            for path in owned:
                path.unlink()
        self.directory.mkdir(parents=True, exist_ok=True)
        self.compression = compression
        self.max_bag_size = int(max_bag_size)
        self.chunk_size = int(chunk_size)
        self.flush_period = float(flush_period)
        self.fsync = fsync
        self.share_dirs = share_dirs
        self._clock = clock
        self._open_file = open_file
        self.topics: Dict[str, TopicInfo] = {}
        self.lost_messages = 0                # written to the bag but never committed (failed write)
        self.failure: Optional[str] = None
        self.closing_outcomes: List[str] = []
        self._schema_texts: Dict[str, bytes] = {}
        self._files: List[FileStats] = []
        self._current: Optional[McapFile] = None
        self._schema_ids: Dict[str, int] = {}
        self._channel_ids: Dict[str, int] = {}
        self._pending: Dict[str, int] = defaultdict(int)
        self._pending_since: Optional[float] = None
        self._last_sync = -math.inf
        self._sequence = 0
        self._closed = False
        self._reserve = self.directory / RESERVE_NAME
        try:
            self._reserve.write_bytes(bytes(RESERVE_BYTES))
            self._open_next_file()
        except OSError as exc:
            self._reserve.unlink(missing_ok=True)
            raise BagError(f'cannot create {self.directory}: {exc.strerror or exc}') from exc

    @property
    def name(self) -> str:
        return self.directory.name

    @property
    def closed(self) -> bool:
        return self._closed

    def _open_next_file(self) -> None:
        path = _bag_file_name(self.name, len(self._files))
        extra = {'open_file': self._open_file} if self._open_file else {}
        self._current = McapFile(self.directory / path, compression=self.compression, fsync=self.fsync,
                                 library='mm rosbag2-compatible writer (python mcap records)', **extra)
        self._files.append(FileStats(path))
        self._schema_ids.clear()
        self._channel_ids.clear()
        for topic in self.topics.values():
            self._register_channel(topic)

    def _register_channel(self, topic: TopicInfo) -> None:
        if topic.type not in self._schema_ids:
            if topic.type not in self._schema_texts:
                self._schema_texts[topic.type] = schema_text(topic.type, self.share_dirs).encode()
            self._schema_ids[topic.type] = self._current.add_schema(topic.type, 'ros2msg', self._schema_texts[topic.type])
        self._channel_ids[topic.name] = self._current.add_channel(
            topic.name, 'cdr', self._schema_ids[topic.type],
            {'offered_qos_profiles': qos_profiles_yaml(topic.offered_qos), 'topic_type_hash': topic.type_hash})

    def add_topic(self, name: str, type_name: str, offered_qos: Sequence[QosSummary] = (),
                  type_hash: str = '') -> TopicInfo:
        """Register a topic (idempotent). Raises BagError if the type's .msg definition is not installed."""
        if name in self.topics:
            return self.topics[name]
        self._check_open()
        topic = TopicInfo(name, type_name, list(offered_qos), type_hash)
        self._register_channel(topic)   # resolves the schema first, so an unknown type is not half-registered
        self.topics[name] = topic
        return topic

    def _check_open(self) -> None:
        if self.failure:
            raise BagError(f'recording stopped: {self.failure}')
        if self._closed:
            raise BagError('bag already closed')

    def write(self, topic: str, data: bytes, log_time_ns: int, publish_time_ns: Optional[int] = None) -> None:
        self._check_open()
        if topic not in self.topics:
            raise BagError(f'topic {topic} was not added')
        if self.max_bag_size and (self._current.message_count or self._current.pending_messages) and \
                self._current.size + self._current.pending_bytes >= self.max_bag_size:
            self._split()
        self._current.add_message(self._channel_ids[topic], int(log_time_ns),
                                  int(publish_time_ns if publish_time_ns is not None else log_time_ns),
                                  bytes(data), self._sequence)
        self._sequence += 1
        self._pending[topic] += 1
        if self._pending_since is None:
            self._pending_since = self._clock()
        if self._current.pending_bytes >= self.chunk_size or self.seconds_until_flush() == 0.0:
            self._commit()

    def seconds_until_flush(self) -> Optional[float]:
        """Seconds until the chunk in progress is due to be committed; None when nothing is pending."""
        if self._pending_since is None:
            return None
        return max(0.0, self._pending_since + self.flush_period - self._clock())

    def flush_if_due(self) -> None:
        """Commit the chunk in progress if its oldest message waited `flush_period` (call when idle)."""
        if not self._closed and self.failure is None and self.seconds_until_flush() == 0.0:
            self._commit()

    def flush(self) -> None:
        """Commit the chunk in progress now."""
        self._check_open()
        self._commit()

    def _commit(self) -> None:
        file, stats = self._current, self._files[-1]
        try:
            file.commit()
        except OSError as exc:
            self._fail(exc)
        stats.count, stats.start_ns, stats.end_ns = file.message_count, file.start_ns, file.end_ns
        for topic, n in self._pending.items():
            self.topics[topic].message_count += n
        self._pending.clear()
        self._pending_since = None
        if self.fsync and self._clock() - self._last_sync >= self.flush_period:
            try:
                file.sync()
            except OSError as exc:
                self._fail(exc)
            self._last_sync = self._clock()

    def _split(self) -> None:
        """Finish the current file and continue in `<name>_<n+1>.mcap`; metadata.yaml lists both from now on."""
        self._commit()
        self._finish_file()
        try:
            self._open_next_file()
        except OSError as exc:
            self._closed = True      # every file so far is finished: only metadata.yaml is left to write
            self._stop(exc, self.directory / _bag_file_name(self.name, len(self._files)), 1)  # the message at hand
        self._write_metadata_file()

    def _fail(self, exc: OSError) -> None:
        """Stop recording after a failed write: keep everything committed, close the bag as well as the disk allows."""
        lost = self._current.discard_pending()
        self._pending.clear()
        self._pending_since = None
        self._stop(exc, self._current.path, lost)

    def _stop(self, exc: OSError, path: Path, lost: int) -> None:
        self.lost_messages += lost
        full = exc.errno in (errno.ENOSPC, errno.EDQUOT)
        self.failure = (f"{'disk full' if full else 'write failed'} writing {path} ({exc.strerror or exc}); "
                        f'recording stopped, {lost} messages of the last chunk lost')
        self._reserve.unlink(missing_ok=True)   # room for the summary and metadata.yaml
        if self._closed:
            self._write_metadata_file()
        else:
            self.close()
        raise (BagDiskFull if full else BagError)(self.failure) from exc

    def metadata(self) -> dict:
        return bag_metadata(self._files, list(self.topics.values()))

    def _finish_file(self) -> None:
        # rosbag2_storage_mcap stores the bag metadata in a "rosbag2" metadata record of each file.
        self._current.add_metadata('rosbag2', {'serialized_metadata': yaml.safe_dump(self.metadata(), sort_keys=False),
                                            'ROS_DISTRO': ROS_DISTRO})
        self.closing_outcomes.append(self._current.finish())

    def _write_metadata_file(self) -> None:
        try:
            write_metadata(self.directory, self.metadata())
        except OSError as exc:
            note = f'metadata.yaml not written ({exc.strerror or exc}); run `bag reindex {self.directory}`'
            self.failure = f'{self.failure}; {note}' if self.failure else note

    def close(self) -> dict:
        """Commit and finish the current MCAP file (summary, indexes), write metadata.yaml atomically."""
        if self._closed:
            return self.metadata()
        if self.failure is None:
            try:
                self._commit()
            except BagError:
                return self.metadata()   # _fail() closed the bag with what was committed
        self._closed = True
        self._finish_file()
        self._write_metadata_file()
        self._reserve.unlink(missing_ok=True)
        return self.metadata()


def write_metadata(directory: os.PathLike, info: dict) -> None:
    directory = Path(directory)
    text = yaml.safe_dump({'rosbag2_bagfile_information': info}, sort_keys=False, default_flow_style=False)
    fd, tmp = tempfile.mkstemp(dir=directory, prefix='.metadata.', suffix='.yaml')
    with os.fdopen(fd, 'w') as f:
        f.write(text)
    os.chmod(tmp, 0o644)
    os.replace(tmp, directory / 'metadata.yaml')


# --- reading ------------------------------------------------------------------------------------------------------
def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _check(condition: bool, path: Path, what: str) -> None:
    if not condition:
        raise BagError(f'{path}: malformed metadata ({what})')


def read_metadata(directory: os.PathLike) -> dict:
    """The bag's rosbag2_bagfile_information, checked field by field (BagError with one line otherwise)."""
    path = Path(directory) / 'metadata.yaml'
    if not Path(directory).is_dir():
        raise BagError(f'{directory}: no such bag directory')
    if not path.is_file():
        hint = ' (a recording that did not finish? `bag reindex` rebuilds it)' if any(Path(directory).glob('*.mcap')) \
            else ''
        raise BagError(f'{directory} is not a bag directory: metadata.yaml missing{hint}')
    try:
        data = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError, OSError) as exc:
        raise BagError(f'{path}: not valid YAML ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})') \
            from exc
    _check(isinstance(data, dict) and isinstance(data.get('rosbag2_bagfile_information'), dict), path,
           'no rosbag2_bagfile_information mapping')
    info = data['rosbag2_bagfile_information']
    if info.get('storage_identifier') != 'mcap':
        raise BagError(f"{path}: storage {info.get('storage_identifier')!r} is not supported (mcap only)")
    files = info.get('relative_file_paths')
    _check(isinstance(files, list) and all(isinstance(f, str) and f for f in files), path,
           'relative_file_paths must be a list of file names')
    topics = info.get('topics_with_message_count', [])
    _check(isinstance(topics, list), path, 'topics_with_message_count must be a list')
    for entry in topics:
        meta = entry.get('topic_metadata') if isinstance(entry, dict) else None
        _check(isinstance(meta, dict) and isinstance(meta.get('name'), str) and isinstance(meta.get('type'), str),
               path, 'each topic needs topic_metadata with a name and a type')
        _check(_is_int(entry.get('message_count', 0)) and entry.get('message_count', 0) >= 0, path,
               f"message_count of {meta['name']} must be an integer >= 0")
        _check(isinstance(meta.get('offered_qos_profiles', []), (list, str)), path,
               f"offered_qos_profiles of {meta['name']} must be a list")
    _check(_is_int(info.get('message_count', 0)), path, 'message_count must be an integer')
    for key, sub in (('starting_time', 'nanoseconds_since_epoch'), ('duration', 'nanoseconds')):
        value = info.get(key, {})
        _check(isinstance(value, dict) and _is_int(value.get(sub, 0)), path, f'{key}.{sub} must be an integer')
    bag_file_paths(directory, info)
    return info


def bag_file_paths(directory: os.PathLike, info: dict) -> List[Path]:
    """The storage files metadata.yaml lists; each must stay inside the bag directory."""
    directory = Path(directory)
    root = directory.resolve()
    paths = []
    for rel in info.get('relative_file_paths', []):
        path = (directory / rel)
        if Path(rel).is_absolute() or not path.resolve().is_relative_to(root) or path.resolve() == root:
            raise BagError(f'{directory}/metadata.yaml: file path {rel!r} leaves the bag directory')
        paths.append(path)
    return paths


class McapScan:
    """Reads an MCAP file front to back without its summary, stopping cleanly at a truncated or damaged tail
    (what a killed recorder leaves). After iterating `messages()`: `good_bytes` ends the last intact record,
    `complete` says whether the footer was reached, `error` says what stopped the scan."""

    def __init__(self, path: os.PathLike):
        self.path = Path(path)
        self.size = self.path.stat().st_size
        self.profile = ''
        self.schemas: Dict[int, Schema] = {}
        self.channels: Dict[int, Channel] = {}
        self.counts: Dict[int, int] = defaultdict(int)
        self.start_ns: Optional[int] = None
        self.end_ns: Optional[int] = None
        self.good_bytes = 0
        self.complete = False
        self.error = ''
        self.orphans = 0   # messages whose channel record was lost
        self.compression = 'none'   # of the chunks read (a rebuilt file keeps it)

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())

    def messages(self) -> Iterator[Tuple[Channel, Message]]:
        if self.size == 0:
            self.error = 'empty file (0 bytes)'
            return
        with open(self.path, 'rb') as stream:
            # a record longer than the file can only be a truncation or garbage: stop instead of reading it
            reader = StreamReader(stream, emit_chunks=True, record_size_limit=self.size)
            try:
                for record in reader.records:
                    inner = [record]
                    if isinstance(record, Chunk):
                        inner = breakup_chunk(record, validate_crc=True)
                        self.compression = record.compression or 'none'
                    for item in inner:
                        if isinstance(item, Header):
                            self.profile = item.profile
                        elif isinstance(item, Schema):
                            self.schemas[item.id] = item
                        elif isinstance(item, Channel):
                            self.channels[item.id] = item
                        elif isinstance(item, Message):
                            channel = self.channels.get(item.channel_id)
                            if channel is None:
                                self.orphans += 1
                                continue
                            self.counts[item.channel_id] += 1
                            self.start_ns = item.log_time if self.start_ns is None else min(self.start_ns,
                                                                                            item.log_time)
                            self.end_ns = item.log_time if self.end_ns is None else max(self.end_ns, item.log_time)
                            yield channel, item
                        elif isinstance(item, Footer):
                            self.complete = True
                    self.good_bytes = stream.tell()
            except EndOfFile:
                self.error = (f'ends after {self.size} bytes without a summary (the recording did not finish)'
                              if self.good_bytes == self.size else
                              f'truncated: {self.size - self.good_bytes} bytes of an unfinished record after byte '
                              f'{self.good_bytes}')
            except Exception as exc:  # noqa: BLE001 - mcap raises many types (struct, CRC, decompression) on damage
                self.error = f'damaged at byte {self.good_bytes} of {self.size} ({type(exc).__name__}: {exc})'

    def scan(self) -> 'McapScan':
        for _ in self.messages():
            pass
        return self


@dataclass
class FileSummary:
    """What one storage file holds, from its MCAP summary or (`scanned`) by reading it through."""

    path: Path
    counts: Dict[str, int]
    types: Dict[str, str]
    start_ns: Optional[int]
    end_ns: Optional[int]
    scanned: bool
    error: str = ''

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())


def _summary_of(stream) -> Optional[Summary]:
    """The MCAP summary (None when the file has none); raises on a file without a valid footer."""
    return SeekingReader(stream).get_summary()


def summarize_file(path: os.PathLike) -> FileSummary:
    """Real message counts per topic of one storage file; `error` is set for missing, empty or damaged files."""
    path = Path(path)
    if not path.is_file():
        return FileSummary(path, {}, {}, None, None, False, 'file missing')
    if path.stat().st_size == 0:
        return FileSummary(path, {}, {}, None, None, False, 'empty file (0 bytes)')
    try:
        with open(path, 'rb') as stream:
            summary = _summary_of(stream)
    except Exception:  # noqa: BLE001 - no valid footer: fall through to a scan, which says what is wrong
        summary = None
    if summary is not None and summary.statistics is not None:
        counts, types = defaultdict(int), {}
        for channel_id, n in summary.statistics.channel_message_counts.items():
            channel = summary.channels.get(channel_id)
            if channel is not None:
                counts[channel.topic] += n
        for channel in summary.channels.values():
            schema = summary.schemas.get(channel.schema_id)
            types[channel.topic] = schema.name if schema else ''
            counts.setdefault(channel.topic, 0)
        stats = summary.statistics
        return FileSummary(path, dict(counts), types, stats.message_start_time if stats.message_count else None,
                           stats.message_end_time if stats.message_count else None, False)
    scan = McapScan(path).scan()
    counts, types = defaultdict(int), {}
    for channel in scan.channels.values():
        schema = scan.schemas.get(channel.schema_id)
        types[channel.topic] = schema.name if schema else ''
        counts[channel.topic] += scan.counts.get(channel.id, 0)
    error = scan.error if scan.error else ('' if scan.complete else 'no footer')
    return FileSummary(path, dict(counts), types, scan.start_ns, scan.end_ns, True, error)


@dataclass
class BagMessage:
    topic: str
    type: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int


def iter_messages(directory: os.PathLike, topics: Optional[Sequence[str]] = None) -> Iterator[BagMessage]:
    """Messages of every file of a bag, raw CDR bytes: in log-time order within each indexed file, in file order
    in a file without a summary. Raises BagError after the last readable message of a damaged file."""
    directory = Path(directory)
    info = read_metadata(directory)
    wanted = set(topics) if topics else None
    for path in bag_file_paths(directory, info):
        if not path.is_file():
            raise BagError(f'{path} listed in metadata.yaml is missing')
        if path.stat().st_size == 0:
            raise BagError(f'{path}: empty file (0 bytes); `bag reindex {directory}` recovers a crashed recording')
        with open(path, 'rb') as stream:
            try:
                summary = _summary_of(stream)
            except Exception:  # noqa: BLE001 - no valid footer: read it through below
                summary = None
            if summary is not None and summary.chunk_indexes:
                try:
                    reader = make_reader(stream)
                    for schema, channel, message in reader.iter_messages(topics=list(wanted) if wanted else None,
                                                                          log_time_order=True):
                        yield BagMessage(channel.topic, schema.name if schema else '', message.data,
                                         message.log_time, message.publish_time)
                except Exception as exc:  # noqa: BLE001 - mcap raises several exception types for damaged files
                    raise BagError(f'{path}: corrupt MCAP file ({type(exc).__name__}: {exc})') from exc
                continue
        scan = McapScan(path)
        for channel, message in scan.messages():
            if wanted is None or channel.topic in wanted:
                schema = scan.schemas.get(channel.schema_id)
                yield BagMessage(channel.topic, schema.name if schema else '', message.data, message.log_time,
                                 message.publish_time)
        if scan.error:
            raise BagError(f'{path}: {scan.error}; `bag reindex {directory}` keeps what is readable')


def topic_qos(info: dict) -> Dict[str, Tuple[str, List[QosSummary]]]:
    """topic -> (type, offered QoS profiles) from bag metadata."""
    out = {}
    for entry in info.get('topics_with_message_count', []):
        meta = entry['topic_metadata']
        try:
            out[meta['name']] = (meta['type'], parse_qos_profiles(meta.get('offered_qos_profiles', [])))
        except (yaml.YAMLError, AttributeError, TypeError, ValueError) as exc:
            raise BagError(f"metadata.yaml: offered_qos_profiles of {meta['name']} unreadable ({exc})") from exc
    return out


# --- recovery -----------------------------------------------------------------------------------------------------
def _storage_files(directory: Path) -> List[Path]:
    """The bag's .mcap files in split order (`<name>_<n>.mcap` by n, then any other .mcap by name)."""
    def key(path: Path):
        match = re.fullmatch(re.escape(directory.name) + r'_(\d+)\.mcap', path.name)
        return (0, int(match.group(1)), '') if match else (1, 0, path.name)
    return sorted((p for p in directory.glob('*.mcap') if p.is_file()), key=key)


def reindex(directory: os.PathLike, chunk_size: int = 1024 * 1024) -> Tuple[dict, List[str]]:
    """Rebuild a crashed bag (the `ros2 bag reindex` counterpart): every .mcap without a valid summary is read as
    far as it is intact and rewritten as a complete, indexed MCAP (atomically, through a temporary file); empty
    files are left out; metadata.yaml is written from what the files really hold. Returns (metadata, report lines).
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise BagError(f'{directory}: no such bag directory')
    files = _storage_files(directory)
    if not files:
        raise BagError(f'{directory}: no .mcap files to reindex')
    topics: Dict[str, TopicInfo] = {}
    stats: List[FileStats] = []
    report = []
    for path in files:
        summary = summarize_file(path)
        if summary.error == 'empty file (0 bytes)':
            report.append(f'{path.name}: empty (0 bytes), left out')
            continue
        if summary.scanned or summary.error:
            summary = _rebuild(path, chunk_size, report)
        else:
            report.append(f'{path.name}: complete, {summary.message_count} messages')
        channels = _channel_records(path)
        for topic, count in summary.counts.items():
            channel = channels.get(topic)
            metadata = channel.metadata if channel is not None else {}
            try:
                qos = parse_qos_profiles(metadata.get('offered_qos_profiles', ''))
            except (yaml.YAMLError, AttributeError, TypeError, ValueError):
                qos = []
            info = topics.setdefault(topic, TopicInfo(topic, summary.types.get(topic, ''), qos,
                                                      metadata.get('topic_type_hash', '')))
            info.message_count += count
        stats.append(FileStats(path.name, summary.start_ns, summary.end_ns, summary.message_count))
    meta = bag_metadata(stats, list(topics.values()))
    write_metadata(directory, meta)
    (directory / RESERVE_NAME).unlink(missing_ok=True)
    report.append(f"metadata.yaml: {meta['message_count']} messages on {len(topics)} topics in {len(stats)} files")
    return meta, report


def _channel_records(path: Path) -> Dict[str, Channel]:
    with open(path, 'rb') as stream:
        summary = _summary_of(stream)
    return {c.topic: c for c in summary.channels.values()} if summary else {}


def _rebuild(path: Path, chunk_size: int, report: List[str]) -> FileSummary:
    """Rewrite the intact part of `path` as a complete MCAP file and replace `path` with it."""
    scan = McapScan(path)
    tmp = path.with_name(f'.{path.name}.reindex')
    out = McapFile(tmp, fsync=True, profile='ros2', library='mm bag reindex')
    schema_ids: Dict[int, int] = {}
    channel_ids: Dict[int, int] = {}

    def copy_channel(channel) -> None:
        if channel.id not in channel_ids:
            schema = scan.schemas.get(channel.schema_id)
            if schema is not None and schema.id not in schema_ids:
                schema_ids[schema.id] = out.add_schema(schema.name, schema.encoding, schema.data)
            channel_ids[channel.id] = out.add_channel(channel.topic, channel.message_encoding,
                                                      schema_ids.get(channel.schema_id, 0), channel.metadata)

    try:
        for channel, message in scan.messages():
            copy_channel(channel)
            out.add_message(channel_ids[channel.id], message.log_time, message.publish_time, message.data,
                            message.sequence)
            if out.pending_bytes >= chunk_size:
                out.compression = scan.compression if scan.compression in _COMPRESSORS else 'none'
                out.commit()
        for channel in scan.channels.values():   # channels without messages still describe the recording
            copy_channel(channel)
        out.compression = scan.compression if scan.compression in _COMPRESSORS else 'none'
        out.commit()
        if out.finish() != 'summary':
            raise OSError(errno.ENOSPC, 'no room for the summary')
        os.replace(tmp, path)
    except OSError as exc:
        out.abandon()
        tmp.unlink(missing_ok=True)
        raise BagError(f'{path}: cannot write the rebuilt file ({exc.strerror or exc})') from exc
    dropped = scan.size - scan.good_bytes
    what = scan.error or 'no summary'
    report.append(f'{path.name}: rebuilt, {scan.message_count} messages kept'
                  + (f', {dropped} unreadable bytes at the end dropped' if dropped and scan.error else '')
                  + f' ({what})' + (f', {scan.orphans} messages without a channel record dropped'
                                    if scan.orphans else ''))
    return summarize_file(path)
