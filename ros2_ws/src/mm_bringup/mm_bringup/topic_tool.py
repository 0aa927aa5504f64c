"""`./mm topic list|info|echo|hz`: the venv stand-in for `ros2 topic` (ros2cli is not pip-installable).

    ./mm topic list -t
    ./mm topic info /wheeled/range/front_left
    ./mm topic echo /wheeled/manifold/state --once
    ./mm topic hz /wheeled/range/front_center
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from typing import List, Optional

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from mm_bringup.recorder_node import message_class
from mm_common.rosbag import QosSummary, adapt_offered_qos

_DISCOVERY_WAIT = 1.0


def to_yaml(msg, indent: int = 0) -> str:
    """Message -> YAML-like text in the style of `ros2 topic echo` (arrays of numbers on one line)."""
    pad = '  ' * indent
    lines = []
    for name in msg.get_fields_and_field_types():
        value = getattr(msg, name)
        if hasattr(value, 'get_fields_and_field_types'):
            lines.append(f'{pad}{name}:')
            lines.append(to_yaml(value, indent + 1))
        elif isinstance(value, (list, tuple)) or type(value).__name__ in ('ndarray', 'array'):
            items = list(value)
            if items and hasattr(items[0], 'get_fields_and_field_types'):
                lines.append(f'{pad}{name}:')
                for item in items:
                    body = to_yaml(item, indent + 2).lstrip()
                    lines.append(f'{pad}- {body}')
            else:
                if len(items) > 32:
                    lines.append(f"{pad}{name}: '<sequence of {len(items)} values>'")
                else:
                    lines.append(f'{pad}{name}: [{", ".join(_scalar(v) for v in items)}]')
        else:
            lines.append(f'{pad}{name}: {_scalar(value)}')
    return '\n'.join(lines)


def _scalar(v) -> str:
    if isinstance(v, float):
        if math.isnan(v):
            return '.nan'
        if math.isinf(v):
            return '.inf' if v > 0 else '-.inf'
    if isinstance(v, str):
        return repr(v)
    if isinstance(v, bytes):
        return str(list(v))
    return str(v)


def _wait_for_topic(node: Node, topic: str, timeout: float) -> Optional[str]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        types = dict(node.get_topic_names_and_types()).get(topic)
        if types and node.get_publishers_info_by_topic(topic):
            return types[0]
        rclpy.spin_once(node, timeout_sec=0.05)
    return None


def _matching_qos(node: Node, topic: str) -> QoSProfile:
    offered = [QosSummary(int(p.qos_profile.reliability), int(p.qos_profile.durability))
               for p in node.get_publishers_info_by_topic(topic)]
    reliability, durability = adapt_offered_qos(offered)
    return QoSProfile(depth=100, reliability=ReliabilityPolicy(reliability), durability=DurabilityPolicy(durability))


def run(args) -> int:
    node = Node('mm_topic_tool', start_parameter_services=False)
    try:
        if args.command == 'list':
            deadline = time.monotonic() + _DISCOVERY_WAIT
            while time.monotonic() < deadline:
                rclpy.spin_once(node, timeout_sec=0.05)
            for name, types in sorted(node.get_topic_names_and_types()):
                print(f"{name} [{', '.join(types)}]" if args.show_types else name)
            return 0
        topic = args.topic if args.topic.startswith('/') else '/' + args.topic
        type_name = _wait_for_topic(node, topic, args.timeout)
        if type_name is None:
            print(f'mm topic: no publisher on {topic} within {args.timeout} s', file=sys.stderr)
            return 1
        if args.command == 'info':
            pubs = node.get_publishers_info_by_topic(topic)
            subs = node.get_subscriptions_info_by_topic(topic)
            print(f'Type: {type_name}\nPublisher count: {len(pubs)}\nSubscription count: {len(subs)}')
            for kind, endpoints in (('Publisher', pubs), ('Subscription', subs)):
                for e in endpoints:
                    print(f'  {kind}: node {e.node_namespace.rstrip("/")}/{e.node_name}, '
                          f'reliability={e.qos_profile.reliability.name}, durability={e.qos_profile.durability.name}, '
                          f'depth={e.qos_profile.depth}')
            return 0
        received: List = []
        msg_class = message_class(type_name)
        if args.command == 'echo':
            limit = 1 if args.once else args.count

            def on_msg(msg):
                received.append(1)
                print(to_yaml(msg))
                print('---', flush=True)
            node.create_subscription(msg_class, topic, on_msg, _matching_qos(node, topic))
            while not limit or len(received) < limit:
                rclpy.spin_once(node, timeout_sec=0.1)
            return 0
        # hz
        stamps: List[float] = []
        node.create_subscription(msg_class, topic, lambda _m: stamps.append(time.monotonic()),
                                 _matching_qos(node, topic), raw=True)
        next_report = time.monotonic() + 1.0
        while True:
            rclpy.spin_once(node, timeout_sec=0.05)
            if time.monotonic() >= next_report and len(stamps) > 1:
                window = stamps[-args.window:]
                periods = [b - a for a, b in zip(window, window[1:])]
                mean = sum(periods) / len(periods)
                print(f'average rate: {1.0 / mean:.3f}\n\tmin: {min(periods):.4f}s max: {max(periods):.4f}s '
                      f'window: {len(window)}', flush=True)
                next_report += 1.0
    finally:
        node.destroy_node()


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog='mm topic', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest='command', required=True)
    p_list = sub.add_parser('list')
    p_list.add_argument('-t', '--show-types', action='store_true')
    for name in ('info', 'echo', 'hz'):
        p = sub.add_parser(name)
        p.add_argument('topic')
        p.add_argument('--timeout', type=float, default=5.0, help='seconds to wait for a publisher')
        if name == 'echo':
            p.add_argument('--once', action='store_true')
            p.add_argument('-n', '--count', type=int, default=0, help='stop after N messages (0 = never)')
        if name == 'hz':
            p.add_argument('--window', type=int, default=100)
    args = parser.parse_args(argv)
    rclpy.init()
    try:
        return run(args)
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    finally:
        rclpy.try_shutdown()


if __name__ == '__main__':
    sys.exit(main())
