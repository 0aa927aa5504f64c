"""Recorder node: writes every (or every selected) topic into a rosbag2-compatible MCAP bag directory.

    ./mm run mm_bringup recorder --ros-args -p output:=results/my_bag -p overwrite:=true
    ./mm bag record -o results/my_bag -a                  # the same through the bag tool
    ros2 run mm_bringup recorder --ros-args -p output:=my_bag -p topics:="['/wheeled/.*']"

Subscribes with raw serialized messages (no deserialize/serialize round trip), one subscription per topic with the
reliability/durability adapted to the publishers' offered QoS like rosbag2 (reliable only if every publisher is
reliable, transient-local only if every publisher is), discovers topics that appear later, takes every message
already delivered at each wake (Recorder.take_delivered) and hands them to a writer thread so disk I/O never blocks
DDS callbacks. SIGINT, SIGTERM and SIGHUP finalise the MCAP summary and
metadata.yaml. Crash safety: the writer commits a chunk (written, flushed, fsynced) at the latest `flush_period`
seconds after its first message, so kill -9 loses at most that much; `./mm bag reindex <bag>` completes such a bag.
A full disk stops the recording at once with one error line and leaves the bag closed with what was written.
"""
from __future__ import annotations

import importlib
import queue
import re
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Dict, List

import rclpy
from mm_common.node_utils import declare, dump_stacks_on_request, reject_non_finite
from mm_common.rosbag import BagError, BagWriter, QosSummary, adapt_offered_qos
from rclpy.exceptions import InvalidHandle, ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

_STOP = object()


class RecorderConfigError(ValueError):
    """A start-up parameter the recorder cannot work with (reported as one line, exit status 1)."""


def compile_patterns(name: str, patterns: List[str]) -> List['re.Pattern']:
    """The non-empty regexes of a list parameter, compiled; RecorderConfigError names the one that is invalid."""
    compiled = []
    for pattern in patterns:
        if not pattern:
            continue
        try:
            compiled.append(re.compile(pattern))
        except re.error as exc:
            raise RecorderConfigError(f'{name}: {pattern!r} is not a valid regular expression ({exc})') from exc
    return compiled


def message_class(type_name: str):
    """The Python class of `pkg/msg/Type` (rosidl_runtime_py is not available in the pip install)."""
    pkg, kind, name = type_name.split('/')
    return getattr(importlib.import_module(f'{pkg}.{kind}'), name)


class Recorder(Node):
    def __init__(self, **node_kwargs):
        super().__init__('recorder', **node_kwargs)
        output = declare(self, 'output', '', 'Bag directory to create (default: rosbag2_<date>_<time>)',
                         read_only=True)
        overwrite = declare(self, 'overwrite', False, 'Replace an existing bag directory', read_only=True)
        self.include = compile_patterns('topics', declare(
            self, 'topics', [''], 'Regexes of topics to record (full match); empty string = all topics',
            read_only=True))
        self.exclude = compile_patterns('exclude', declare(
            self, 'exclude', ['/rosout', '/parameter_events'], 'Regexes of topics never recorded (full match)',
            read_only=True))
        self.discovery_period = declare(self, 'discovery_period', 0.1, 'Seconds between topic discovery polls',
                                        min_value=0.01, max_value=60.0, read_only=True)
        compression = declare(self, 'compression', 'none', 'MCAP chunk compression: none, zstd or lz4',
                              read_only=True, additional_constraints='one of none, zstd, lz4')
        max_bag_size = declare(self, 'max_bag_size', 0, 'Split into a new .mcap file past this many bytes (0 = never)',
                               min_value=0, max_value=2**62, read_only=True)
        chunk_size = declare(self, 'chunk_size', 1024 * 1024,
                             'MCAP chunk size in bytes: a chunk is written to the file when it reaches this size',
                             min_value=0, max_value=2**31, read_only=True)
        flush_period = declare(self, 'flush_period', 0.5,
                               'Seconds after which a chunk is written to the file even if not full: '
                               'the most data a kill -9 can lose', min_value=0.01, max_value=60.0, read_only=True)
        declare(self, 'drain_period', 0.3, 'Seconds spent taking already-delivered messages after a stop signal',
                min_value=0.0, max_value=10.0)
        self.batch_period = declare(self, 'batch_period', 0.01,
                                    'Seconds messages gather in the subscriptions after the recorder took some, so '
                                    'that one executor wake takes many (each wake costs CPU the recorded graph '
                                    'needs); queue_depth messages per topic wait meanwhile',
                                    min_value=0.0, max_value=1.0, read_only=True)
        # as deep as the wheeled loop's own history (mm_common.qos): a recorder that lags keeps what the writer keeps
        self.queue_depth = declare(self, 'queue_depth', 10000, 'Subscription history depth per topic',
                                   min_value=1, max_value=100000, read_only=True)
        if not output:
            output = time.strftime('rosbag2_%Y_%m_%d-%H_%M_%S')
        self.writer = BagWriter(Path(output), compression=compression, max_bag_size=max_bag_size,
                                chunk_size=chunk_size, flush_period=flush_period, overwrite=overwrite)
        self.add_on_set_parameters_callback(reject_non_finite)
        self._queue: 'queue.Queue' = queue.Queue()
        self._writer_lock = threading.Lock()   # discovery (executor thread) adds topics while the writer thread writes
        self._failed_topics: Dict[str, str] = {}
        self._recorded_subscriptions: Dict[str, object] = {}
        # DDS matches each writer to our reader on its own schedule: the log says when a topic's recording begins
        self._topics_with_data: set = set()
        self.received = 0
        self.dropped = 0          # arrived after the recording stopped (write failure)
        self._writer_thread = threading.Thread(target=self._write_loop, name='bag_writer', daemon=True)
        self._writer_thread.start()
        self._closed = False
        self.create_timer(self.discovery_period, self._discover)
        self._discover()
        self.get_logger().info(f'recording into {self.writer.directory}')

    # --- discovery ------------------------------------------------------------------------------------------
    def _selected(self, topic: str) -> bool:
        if any(p.fullmatch(topic) for p in self.exclude):
            return False
        return not self.include or any(p.fullmatch(topic) for p in self.include)

    def _discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if topic in self._recorded_subscriptions or topic in self._failed_topics or not self._selected(topic):
                continue
            publishers = self.get_publishers_info_by_topic(topic)
            if not publishers:
                continue  # only subscribers so far: wait until someone offers data
            type_name = types[0]
            offered = [QosSummary(int(p.qos_profile.reliability), int(p.qos_profile.durability),
                                  int(p.qos_profile.history), int(p.qos_profile.depth),
                                  int(p.qos_profile.liveliness)) for p in publishers]
            try:
                msg_type = message_class(type_name)
                with self._writer_lock:
                    self.writer.add_topic(topic, type_name, offered, str(publishers[0].topic_type_hash))
            except (ImportError, AttributeError, ValueError, BagError) as exc:
                self._failed_topics[topic] = str(exc)
                self.get_logger().error(f'cannot record {topic} ({type_name}): {exc}')
                continue
            reliability, durability = adapt_offered_qos(offered)
            qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self.queue_depth,
                             reliability=ReliabilityPolicy(reliability), durability=DurabilityPolicy(durability))
            self._recorded_subscriptions[topic] = self.create_subscription(
                msg_type, topic, lambda data, info, t=topic: self._on_message(t, data, info), qos, raw=True)
            self.get_logger().info(f'subscribed to {topic} [{type_name}] '
                                   f"({'reliable' if reliability == 1 else 'best effort'}, "
                                   f"{'transient local' if durability == 1 else 'volatile'})")

    # --- data path ------------------------------------------------------------------------------------------
    def _on_message(self, topic: str, data: bytes, info: dict) -> None:
        self.received += 1
        if topic not in self._topics_with_data:
            self._topics_with_data.add(topic)
            self.get_logger().info(f'first message on {topic}: recording it from here')
        if self.writer.failure is not None:
            self.dropped += 1
            return
        received = info.get('received_timestamp') or time.time_ns()
        self._queue.put((topic, data, received, info.get('source_timestamp') or received))

    def take_delivered(self) -> int:
        """Take every message DDS has already delivered to the recorded subscriptions, oldest first, and return how
        many. The SingleThreadedExecutor takes one message per wake and rebuilds its wait set from every handle each
        time: in the demo that cost the recorder 13.9 s of CPU, more than the three wheeled nodes together, on a
        machine with two cores. Taken here, one wake serves all that arrived meanwhile. (The EventsExecutor, which the
        other nodes use, delivers nothing to a callback that takes the message info, and the bag needs its
        timestamps.)"""
        batch = []
        for topic, subscription in list(self._recorded_subscriptions.items()):
            try:
                with subscription.handle:
                    while (taken := subscription.handle.take_message(subscription.msg_type, True)) is not None:
                        batch.append((topic, *taken))
            except InvalidHandle:
                continue        # destroyed meanwhile (close())
        batch.sort(key=lambda item: item[2].get('received_timestamp') or 0)
        for item in batch:
            self._on_message(*item)
        return len(batch)

    def _write_loop(self) -> None:
        """Write queued messages; when idle, commit a chunk that has waited `flush_period`."""
        while True:
            try:
                item = self._queue.get(timeout=self.writer.seconds_until_flush())
            except queue.Empty:
                item = None
            if item is _STOP:
                return
            try:
                with self._writer_lock:
                    if item is None:
                        self.writer.flush_if_due()
                    elif self.writer.failure is None:
                        self.writer.write(*item)
                    else:
                        self.dropped += 1
            except (BagError, OSError) as exc:
                # reported at once (the writer has already closed the bag with what was committed)
                self.get_logger().error(f'{exc}; the bag in {self.writer.directory} stays readable')

    def close(self) -> dict:
        """Stop subscriptions, drain the queue, finalise the MCAP file(s) and metadata.yaml."""
        if self._closed:
            return self.writer.metadata()
        self._closed = True
        for sub in self._recorded_subscriptions.values():
            self.destroy_subscription(sub)
        self._queue.put(_STOP)
        self._writer_thread.join()
        with self._writer_lock:
            meta = self.writer.close()
        if self.writer.failure is not None:
            self.get_logger().error(f'recording incomplete: {self.writer.failure}; '
                                    f'{self.dropped} later messages not recorded')
        self.get_logger().info(f"bag closed: {meta['message_count']} messages on "
                               f"{len(meta['topics_with_message_count'])} topics in {self.writer.directory}")
        return meta

    def destroy_node(self):
        self.close()
        return super().destroy_node()


def main(args=None):
    """Own SIGINT/SIGTERM/SIGHUP handling: stop spinning, take what DDS already delivered, then finalise the bag.

    With rclpy's default handlers the context is shut down inside the signal handler and messages still queued in
    the subscriptions would be lost; rosbag2 likewise flushes before it exits. A closed terminal (SIGHUP) is a stop
    request too. A start-up problem (bad regex or parameter value, existing directory) is one error line and exit
    status 1.
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, lambda *_: stop.set())
    dump_stacks_on_request()
    node = None
    status = 0
    try:
        node = Recorder()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=0.05)
            if node.take_delivered():
                stop.wait(node.batch_period)
        drain_until = time.monotonic() + node.get_parameter('drain_period').value   # settable until the end
        while time.monotonic() < drain_until and rclpy.ok():
            executor.spin_once(timeout_sec=0.01)
            node.take_delivered()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (BagError, RecorderConfigError, ParameterException) as exc:
        rclpy.logging.get_logger('recorder').error(f'cannot record: {exc}')
        status = 1
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    if status:
        sys.exit(status)


if __name__ == '__main__':
    main()
