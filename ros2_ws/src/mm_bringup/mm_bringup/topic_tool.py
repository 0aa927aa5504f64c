"""`./mm topic list|info|echo|hz`: the venv stand-in for `ros2 topic` (ros2cli is not pip-installable).

    ./mm topic list -t
    ./mm topic info /wheeled/range/front_left
    ./mm topic echo /wheeled/manifold/state --once
    ./mm topic hz /wheeled/range/front_center

Output can be piped (`| head -3`): when the reader goes away the tool stops quietly with exit status 0.
"""
from __future__ import annotations

import argparse
import math
import os
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
_SETTLE = 0.5                       # [s] graph unchanged this long before `info` reports the endpoints
# What the rmw reports for an endpoint whose participant's node list has not been discovered yet (rmw_dds_common).
_UNKNOWN_NAMES = ('_NODE_NAME_UNKNOWN_', '_NODE_NAMESPACE_UNKNOWN_')


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


def _endpoints(node: Node, topic: str):
    return node.get_publishers_info_by_topic(topic), node.get_subscriptions_info_by_topic(topic)


def _name_known(endpoint) -> bool:
    return endpoint.node_name not in _UNKNOWN_NAMES and endpoint.node_namespace not in _UNKNOWN_NAMES


def _wait_for_endpoints(node: Node, topic: str, timeout: float):
    """Publishers and subscriptions of a topic once discovery has settled: wait (up to `timeout` s) until the topic
    has an endpoint, every endpoint's node name is known, at least _DISCOVERY_WAIT s have passed (peers are found
    one by one) and neither the node list nor the topic's endpoints have changed for _SETTLE s.
    Returns (type name or None, publishers, subscriptions, all node names known)."""
    start = time.monotonic()
    deadline = start + timeout
    last_key, stable_since = None, start
    while True:
        types = dict(node.get_topic_names_and_types()).get(topic)
        pubs, subs = _endpoints(node, topic)
        known = all(_name_known(e) for e in list(pubs) + list(subs))
        key = (tuple(sorted(node.get_node_names_and_namespaces())),
               tuple(sorted((str(e.endpoint_gid), e.node_namespace, e.node_name) for e in list(pubs) + list(subs))))
        now = time.monotonic()
        if key != last_key:
            last_key, stable_since = key, now
        if (types and (pubs or subs) and known and now - start >= _DISCOVERY_WAIT
                and now - stable_since >= _SETTLE):
            break
        if now >= deadline:
            break
        rclpy.spin_once(node, timeout_sec=0.05)
    return (types[0] if types else None), pubs, subs, known


def _node_label(endpoint) -> str:
    if not _name_known(endpoint):
        return '<unknown: not discovered yet>'
    return f'{endpoint.node_namespace.rstrip("/")}/{endpoint.node_name}'


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
        if args.command == 'info':
            type_name, pubs, subs, known = _wait_for_endpoints(node, topic, args.timeout)
            if type_name is None:
                print(f'mm topic: no publisher or subscription on {topic} within {args.timeout} s', file=sys.stderr)
                return 1
            print(f'Type: {type_name}\nPublisher count: {len(pubs)}\nSubscription count: {len(subs)}')
            for kind, endpoints in (('Publisher', pubs), ('Subscription', subs)):
                for e in endpoints:
                    print(f'  {kind}: node {_node_label(e)}, '
                          f'reliability={e.qos_profile.reliability.name}, durability={e.qos_profile.durability.name}, '
                          f'depth={e.qos_profile.depth}')
            if not known:
                print(f'Note: the node names of some endpoints were not discovered within {args.timeout} s '
                      f'(try a longer --timeout)', file=sys.stderr)
            return 0
        type_name = _wait_for_topic(node, topic, args.timeout)
        if type_name is None:
            print(f'mm topic: no publisher on {topic} within {args.timeout} s', file=sys.stderr)
            return 1
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
    p_list = sub.add_parser('list', help='names (and types with -t) of the topics in the graph')
    p_list.add_argument('-t', '--show-types', action='store_true')
    helps = {'info': 'type, publishers and subscriptions (node, QoS) of a topic',
             'echo': 'print the messages of a topic as YAML', 'hz': 'measure the publishing rate of a topic'}
    for name in ('info', 'echo', 'hz'):
        p = sub.add_parser(name, help=helps[name])
        p.add_argument('topic')
        p.add_argument('--timeout', type=float, default=5.0,
                       help='seconds to wait for a publisher (info: for the endpoints and their node names)')
        if name == 'echo':
            p.add_argument('--once', action='store_true')
            p.add_argument('-n', '--count', type=int, default=0, help='stop after N messages (0 = never)')
        if name == 'hz':
            p.add_argument('--window', type=int, default=100)
    args = parser.parse_args(argv)
    rclpy.init()
    try:
        rc = run(args)
        sys.stdout.flush()          # inside the try: a closed pipe surfaces here, not at interpreter exit
        return rc
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    except BrokenPipeError:
        # The reader of our output went away (`| head`): stop quietly, as ros2cli does. Point stdout at /dev/null so
        # the interpreter's final flush of the buffered rest does not raise again.
        _silence_stdout()
        return 0
    finally:
        rclpy.try_shutdown()


def _silence_stdout() -> None:
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass


if __name__ == '__main__':
    sys.exit(main())
