"""Player node: re-publishes a recorded bag (raw CDR), preserving order and, by default, the recorded timing.

    ./mm run mm_bringup player --ros-args -p bag:=results/demo_bag -p rate:=2.0
    ./mm bag play results/demo_bag --rate 0      # as fast as possible, order preserved

Each topic is published with its recorded type and the QoS its recorders saw offered (reliable only if every
recorded publisher was reliable, transient-local only if every one was). Exits when the bag is done.
"""
from __future__ import annotations

import time
from typing import Dict, List

import rclpy
from mm_common.node_utils import declare
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException
from mm_common.rosbag import BagError, adapt_offered_qos, iter_messages, read_metadata, topic_qos
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from builtin_interfaces.msg import Time

from mm_bringup.recorder_node import message_class


class Player(Node):
    def __init__(self, **node_kwargs):
        super().__init__('player', **node_kwargs)
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
        self.played = 0
        try:
            self.info = read_metadata(self.bag)
        except BagError as exc:
            self.get_logger().error(str(exc))
            raise
        self.publishers_by_topic: Dict[str, object] = {}
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
                self.get_logger().error(f'skipping {topic}: type {type_name} unavailable ({exc})')
        self.clock_pub = self.create_publisher(Clock, '/clock', 10) if self.publish_clock else None

    def run(self) -> None:
        """Give subscribers `start_delay` to match, play the bag, then wait until reliable readers acked."""
        deadline = time.monotonic() + self.start_delay
        while time.monotonic() < deadline:
            rclpy.spin_once(self, timeout_sec=0.02)
        try:
            self.play()
        except BagError as exc:
            self.get_logger().error(f'playback stopped: {exc}')
        for pub in self.publishers_by_topic.values():
            pub.wait_for_all_acked(Duration(seconds=2.0))
        self.get_logger().info(f'played {self.played} messages from {self.bag}')

    def play(self) -> None:
        first_log = None
        wall_start = time.monotonic()
        wanted = list(self.publishers_by_topic) or None
        for msg in iter_messages(self.bag, wanted):
            pub = self.publishers_by_topic.get(msg.topic)
            if pub is None:
                continue
            if first_log is None:
                first_log = msg.log_time_ns
            if self.rate > 0:
                due = wall_start + (msg.log_time_ns - first_log) / 1e9 / self.rate
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            if self.clock_pub is not None:
                self.clock_pub.publish(Clock(clock=Time(sec=msg.log_time_ns // 10**9,
                                                        nanosec=msg.log_time_ns % 10**9)))
            pub.publish(msg.data)    # rclpy publishes bytes as an already serialized message
            self.played += 1


def main(args=None):
    rclpy.init(args=args)
    node = None
    try:
        node = Player()
        node.run()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except BagError:
        raise SystemExit(1)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
