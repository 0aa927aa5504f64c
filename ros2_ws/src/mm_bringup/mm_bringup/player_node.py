"""Player node: re-publishes a recorded bag (raw CDR), preserving order and, by default, the recorded timing.

    ./mm run mm_bringup player --ros-args -p bag:=results/demo_bag -p rate:=2.0
    ./mm bag play results/demo_bag --rate 0      # as fast as possible, order preserved

Each topic is published with its recorded type and the QoS its recorders saw offered (reliable only if every
recorded publisher was reliable, transient-local only if every one was). Exits when the bag is done: status 0
when every selected message was played (or SIGINT/SIGTERM/SIGHUP stopped it), 1 when a file was damaged, a topic's
type is unavailable or fewer messages were found than metadata.yaml lists.
"""
from __future__ import annotations

import signal
import sys
import threading
import time
from typing import Dict, List, Optional

import rclpy
from mm_common.node_utils import declare, dump_stacks_on_request
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from mm_common.rosbag import BagError, adapt_offered_qos, iter_messages, read_metadata, topic_qos
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from builtin_interfaces.msg import Time

from mm_bringup.recorder_node import message_class


class Player(Node):
    def __init__(self, stop: Optional[threading.Event] = None, **node_kwargs):
        super().__init__('player', **node_kwargs)
        self.stop = stop or threading.Event()
        self.bag = declare(self, 'bag', '', 'Bag directory to play', read_only=True)
        self.rate = declare(self, 'rate', 1.0, 'Playback speed factor; 0 = as fast as possible (order kept)',
                            min_value=0.0, max_value=1000.0, read_only=True)
        self.topics: List[str] = [t for t in declare(self, 'topics', [''], 'Topics to play (empty = all)',
                                                      read_only=True) if t]
        self.publish_clock = declare(self, 'publish_clock', False,
                                     'Publish /clock from the recorded log times', read_only=True)
        self.start_delay = declare(self, 'start_delay', 0.5,
                                   'Wall seconds to wait after creating publishers so subscribers can match',
                                   min_value=0.0, max_value=60.0, read_only=True)
        self.wait_for_subscribers = declare(
            self, 'wait_for_subscribers', 0, 'Start as soon as every topic to play has this many matched '
            'subscriptions (still at most start_delay seconds); 0 = always wait start_delay',
            min_value=0, max_value=1000, read_only=True)
        self.played = 0
        self.problems: List[str] = []
        if not self.bag:
            raise BagError('parameter bag is empty: set it to the bag directory to play')
        self.info = read_metadata(self.bag)
        self.publishers_by_topic: Dict[str, object] = {}
        self.expected = 0     # messages metadata.yaml lists on the topics to play
        for entry in self.info.get('topics_with_message_count', []):
            name = entry['topic_metadata']['name']
            if (not self.topics or name in self.topics) and not (self.publish_clock and name == '/clock'):
                self.expected += int(entry.get('message_count', 0))
        for topic, (type_name, offered) in topic_qos(self.info).items():
            if self.topics and topic not in self.topics:
                continue
            if self.publish_clock and topic == '/clock':
                continue  # the player's own clock replaces the recorded one
            reliability, durability = adapt_offered_qos(offered)
            qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                             reliability=ReliabilityPolicy(reliability), durability=DurabilityPolicy(durability))
            try:
                self.publishers_by_topic[topic] = self.create_publisher(message_class(type_name), topic, qos)
            except (ImportError, AttributeError, ValueError) as exc:
                self.problems.append(f'skipped {topic}: type {type_name} unavailable ({exc})')
                self.get_logger().error(self.problems[-1])
        self.clock_pub = self.create_publisher(Clock, '/clock', 10) if self.publish_clock else None

    def run(self) -> bool:
        """Give subscribers `start_delay` to match, play the bag, wait until reliable readers acked.
        True when everything selected was played or a stop signal ended playback early."""
        deadline = time.monotonic() + self.start_delay
        while time.monotonic() < deadline and not self.stop.is_set() and not self._subscribers_ready():
            rclpy.spin_once(self, timeout_sec=0.02)
        if self.wait_for_subscribers and not self._subscribers_ready():
            self.get_logger().warn(f'starting without {self.wait_for_subscribers} subscriber(s) on every topic '
                                   f'after {self.start_delay} s')
        try:
            self.play()
        except BagError as exc:
            self.problems.append(f'playback stopped: {exc}')
            self.get_logger().error(self.problems[-1])
        for pub in self.publishers_by_topic.values():
            pub.wait_for_all_acked(Duration(seconds=0.2 if self.stop.is_set() else 5.0))
        if self.stop.is_set():
            self.get_logger().info(f'stopped after {self.played} of {self.expected} messages from {self.bag}')
            return True
        if not self.problems and self.played != self.expected:
            self.problems.append(f'played {self.played} messages but metadata.yaml lists {self.expected}')
            self.get_logger().error(self.problems[-1])
        self.get_logger().info(f'played {self.played} messages from {self.bag}')
        return not self.problems

    def _subscribers_ready(self) -> bool:
        return bool(self.wait_for_subscribers) and all(
            pub.get_subscription_count() >= self.wait_for_subscribers for pub in self.publishers_by_topic.values())

    def play(self) -> None:
        first_log = None
        wall_start = time.monotonic()
        wanted = list(self.publishers_by_topic) or None
        for msg in iter_messages(self.bag, wanted):
            if self.stop.is_set():
                return
            pub = self.publishers_by_topic.get(msg.topic)
            if pub is None:
                continue
            if first_log is None:
                first_log = msg.log_time_ns
            if self.rate > 0:
                due = wall_start + (msg.log_time_ns - first_log) / 1e9 / self.rate
                delay = due - time.monotonic()
                if delay > 0 and self.stop.wait(delay):
                    return
            if self.clock_pub is not None:
                self.clock_pub.publish(Clock(clock=Time(sec=msg.log_time_ns // 10**9,
                                                        nanosec=msg.log_time_ns % 10**9)))
            pub.publish(msg.data)    # rclpy publishes bytes as an already serialized message
            self.played += 1


def main(args=None):
    """Own SIGINT/SIGTERM/SIGHUP handling (a flag the playback loop checks), so a signal mid-publish never meets a
    context that rclpy's handler already shut down; the exit status says whether everything was played."""
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, lambda *_: stop.set())
    dump_stacks_on_request()
    node = None
    ok = False
    try:
        node = Player(stop)
        ok = node.run()
    except (KeyboardInterrupt, ExternalShutdownException):
        ok = True
    except (BagError, ParameterException) as exc:
        rclpy.logging.get_logger('player').error(f'cannot play: {exc}')
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    sys.exit(0 if ok else 1)


if __name__ == '__main__':
    main()
