"""`ros2 topic` / `./mm topic` list|info|type|echo|hz|pub: mm's stand-in for ros2cli's (not pip-installable).

    ros2 topic list -t
    ros2 topic info /wheeled/range/front_left -v
    ros2 topic echo /wheeled/manifold/state --once
    ros2 topic hz /wheeled/range/front_center
    ros2 topic pub --once /wheeled/wheel_velocity_controller/commands std_msgs/msg/Float64MultiArray "{data: [1, 1]}"

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
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from mm_bringup.message_yaml import (interface_class, message_to_yaml, parse_values, set_message_fields, to_plain,
                                     to_yaml)
from mm_bringup.recorder_node import message_class
from mm_common.rosbag import QosSummary, adapt_offered_qos

_DISCOVERY_WAIT = 1.0
_SETTLE = 0.5                       # [s] graph unchanged this long before `info` reports the endpoints
# What the rmw reports for an endpoint whose participant's node list has not been discovered yet (rmw_dds_common).
_UNKNOWN_NAMES = ('_NODE_NAME_UNKNOWN_', '_NODE_NAMESPACE_UNKNOWN_')


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


def _matching_qos(node: Node, topic: str) -> QoSProfile:
    """QoS that matches the topic's publishers (as rosbag2 adapts); best effort while none is known, since a best
    effort subscription matches publishers of either reliability."""
    offered = [QosSummary(int(p.qos_profile.reliability), int(p.qos_profile.durability))
               for p in node.get_publishers_info_by_topic(topic)]
    if not offered:
        return QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
    reliability, durability = adapt_offered_qos(offered)
    return QoSProfile(depth=100, reliability=ReliabilityPolicy(reliability), durability=DurabilityPolicy(durability))


def cli_node() -> Node:
    """The command's own node: hidden (leading underscore, as ros2cli's), so `node list` and `param list` skip it."""
    return Node(f'_ros2cli_{os.getpid()}', start_parameter_services=False, enable_rosout=False)


def settle_graph(node: Node, timeout: float = 8.0) -> None:
    """Spin until at least _DISCOVERY_WAIT s have passed, some other node has been seen, and the node and topic lists
    have not changed for _SETTLE s; at most `timeout` s (an empty graph costs the full timeout). There is no ros2
    daemon caching the graph: every command discovers it afresh. The bound is generous because a graph usually
    appears within 0.3-3 s but a fresh-clone test once saw nothing after 3 s; a busy graph returns as soon as it has
    settled."""
    start = time.monotonic()
    last_key, stable_since = None, start
    while True:
        nodes = tuple(sorted(node.get_node_names_and_namespaces()))
        key = (nodes, tuple(sorted((n, tuple(t)) for n, t in node.get_topic_names_and_types())))
        now = time.monotonic()
        if key != last_key:
            last_key, stable_since = key, now
        others = [n for n, _ in nodes if n != node.get_name()]
        if (others and now - start >= _DISCOVERY_WAIT and now - stable_since >= _SETTLE) or now - start >= timeout:
            return
        rclpy.spin_once(node, timeout_sec=0.05)


def absolute(name: str) -> str:
    return name if name.startswith('/') else '/' + name


def _hidden(name: str) -> bool:
    return any(part.startswith('_') for part in name.split('/'))


def run(args) -> int:
    node = cli_node()
    try:
        return {'list': _list, 'info': _info, 'type': _type, 'echo': _echo, 'hz': _hz, 'pub': _pub}[args.command](
            node, args)
    finally:
        node.destroy_node()


def _list(node: Node, args) -> int:
    settle_graph(node)
    for name, types in sorted(node.get_topic_names_and_types()):
        if _hidden(name) and not args.include_hidden_topics:
            continue
        print(f"{name} [{', '.join(types)}]" if args.show_types else name)
    return 0


def _type(node: Node, args) -> int:
    topic = absolute(args.topic)
    deadline = time.monotonic() + args.timeout
    while not dict(node.get_topic_names_and_types()).get(topic):
        if time.monotonic() >= deadline:
            print(f"Unknown topic '{topic}'", file=sys.stderr)
            return 1
        rclpy.spin_once(node, timeout_sec=0.05)
    print('\n'.join(dict(node.get_topic_names_and_types())[topic]))
    return 0


def _info(node: Node, args) -> int:
    topic = absolute(args.topic)
    type_name, pubs, subs, known = _wait_for_endpoints(node, topic, args.timeout)
    if type_name is None:
        print(f"Unknown topic '{topic}'", file=sys.stderr)
        return 1
    if not args.verbose:
        print(f'Type: {type_name}\nPublisher count: {len(pubs)}\nSubscription count: {len(subs)}')
    else:
        print(f'Type: {type_name}\n\nPublisher count: {len(pubs)}\n')
        for e in pubs:
            print(e, end='\n\n')
        print(f'Subscription count: {len(subs)}\n')
        for e in subs:
            print(e, end='\n\n')
    if not known:
        print(f'Note: the node names of some endpoints were not discovered within {args.timeout} s '
              f'(try a longer --timeout)', file=sys.stderr)
    return 0


def _subscription_type(node: Node, args) -> Optional[str]:
    """The topic's type: the one given on the command line (no need to wait for a publisher, as in ros2cli), else
    the graph's once a publisher is seen."""
    topic = absolute(args.topic)
    if args.message_type:
        return args.message_type
    type_name = _wait_for_topic(node, topic, args.timeout)
    if type_name is None:
        print(f"Unknown topic '{topic}': no publisher within {args.timeout} s", file=sys.stderr)
    return type_name


def _echo(node: Node, args) -> int:
    type_name = _subscription_type(node, args)
    if type_name is None:
        return 1
    topic = absolute(args.topic)
    fields = [f for f in (args.field or '').split('.') if f]
    received: List = []
    limit = 1 if args.once else args.times

    def on_msg(msg):
        received.append(1)
        value = msg
        for f in fields:
            value = getattr(value, f)
        if hasattr(value, 'get_fields_and_field_types'):
            text = message_to_yaml(value, args.no_arr, args.no_str, args.flow_style)
        else:
            text = to_yaml(to_plain(value, args.no_arr, args.no_str), args.flow_style)
            text = text[:-len('...\n')] if text.endswith('\n...\n') else text
        print(text, end='')
        print('---', flush=True)

    try:
        msg_class = interface_class(type_name)
    except LookupError as exc:
        print(exc, file=sys.stderr)
        return 1
    try:
        current = msg_class()
        for f in fields:
            current = getattr(current, f)
    except AttributeError:
        print(f"Invalid field '{args.field}' for {type_name}", file=sys.stderr)
        return 1
    node.create_subscription(msg_class, topic, on_msg, _matching_qos(node, topic))
    while not limit or len(received) < limit:
        rclpy.spin_once(node, timeout_sec=0.1)
    return 0


def _hz(node: Node, args) -> int:
    if _subscription_type(node, args) is None:
        return 1
    topic = absolute(args.topic)
    type_name = dict(node.get_topic_names_and_types())[topic][0]
    stamps: List[float] = []
    node.create_subscription(message_class(type_name), topic, lambda _m: stamps.append(time.monotonic()),
                             _matching_qos(node, topic), raw=True)
    next_report = time.monotonic() + 1.0
    reports = 0
    while not args.reports or reports < args.reports:
        rclpy.spin_once(node, timeout_sec=0.05)
        if time.monotonic() < next_report:
            continue
        next_report += 1.0
        if len(stamps) < 2:
            print('no new messages', flush=True)
            continue
        window = stamps[-args.window:]
        periods = [b - a for a, b in zip(window, window[1:])]
        mean = sum(periods) / len(periods)
        std = math.sqrt(sum((p - mean) ** 2 for p in periods) / len(periods))
        print(f'average rate: {1.0 / mean:.3f}\n\tmin: {min(periods):.3f}s max: {max(periods):.3f}s '
              f'std dev: {std:.5f}s window: {len(window)}', flush=True)
        reports += 1
    return 0


_RELIABILITY = {'reliable': ReliabilityPolicy.RELIABLE, 'best_effort': ReliabilityPolicy.BEST_EFFORT}
_DURABILITY = {'volatile': DurabilityPolicy.VOLATILE, 'transient_local': DurabilityPolicy.TRANSIENT_LOCAL}


def _pub(node: Node, args) -> int:
    topic = absolute(args.topic)
    try:
        msg_class = interface_class(args.message_type)
        msg = msg_class()
        set_message_fields(msg, parse_values(args.values), now=lambda: node.get_clock().now().to_msg())
    except (LookupError, ValueError) as exc:
        print(f'Failed to populate field: {exc}' if isinstance(exc, ValueError) else str(exc), file=sys.stderr)
        return 1
    qos = QoSProfile(depth=args.qos_depth, reliability=_RELIABILITY[args.qos_reliability],
                     durability=_DURABILITY[args.qos_durability])
    publisher = node.create_publisher(msg_class, topic, qos)
    times = 1 if args.once else args.times
    wait = args.wait_matching_subscriptions
    if wait is None:
        wait = 1 if times else 0
    deadline = time.monotonic() + args.timeout
    while publisher.get_subscription_count() < wait:
        if args.timeout and time.monotonic() >= deadline:
            print(f'No {wait} matching subscription(s) on {topic} within {args.timeout} s', file=sys.stderr)
            return 1
        rclpy.spin_once(node, timeout_sec=0.05)
    print('publisher: beginning loop')
    count = 0
    period = 1.0 / args.rate
    next_time = time.monotonic()
    while not times or count < times:
        count += 1
        publisher.publish(msg)
        if args.print_nth and count % args.print_nth == 0:
            print(f'publishing #{count}: {msg!r}\n', flush=True)
        next_time += period
        if times and count >= times:
            break
        while time.monotonic() < next_time:
            rclpy.spin_once(node, timeout_sec=max(0.0, min(0.05, next_time - time.monotonic())))
    # Reliable delivery of the last message before the publisher goes away (ros2cli keeps it alive briefly too).
    if qos.reliability == ReliabilityPolicy.RELIABLE:
        publisher.wait_for_all_acked(Duration(seconds=args.keep_alive))
    return 0


def build_parser(prog: str = 'mm topic') -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest='command', required=True)
    p_list = sub.add_parser('list', help='Output a list of available topics')
    p_list.add_argument('-t', '--show-types', action='store_true', help='Additionally show the topic type')
    p_list.add_argument('--include-hidden-topics', action='store_true', help='Consider hidden topics as well')
    helps = {'info': 'Print information about a topic', 'type': 'Print a topic\'s type',
             'echo': 'Output messages from a topic', 'hz': 'Print the average publishing rate to screen'}
    for name in ('info', 'type', 'echo', 'hz'):
        p = sub.add_parser(name, help=helps[name])
        p.add_argument('topic', metavar='topic_name')
        p.add_argument('--timeout', type=float, default=5.0,
                       help='seconds to wait for the topic (info: for its endpoints and their node names)')
        if name == 'info':
            p.add_argument('-v', '--verbose', action='store_true',
                           help='Print detailed information like the node name, QoS profile and GID')
        if name == 'echo':
            p.add_argument('message_type', nargs='?', help='Type of the ROS message (e.g. std_msgs/msg/String)')
            p.add_argument('--once', action='store_true', help='Print the first message received and then exit')
            p.add_argument('--times', '-n', '--count', type=int, default=0, dest='times',
                           help='Print N messages and then exit (0 = never)')
            p.add_argument('--field', help='Echo a selected field of a message (e.g. header.stamp)')
            p.add_argument('--no-arr', action='store_true', help="Don't print array fields of messages")
            p.add_argument('--no-str', action='store_true', help="Don't print string fields of messages")
            p.add_argument('--flow-style', action='store_true', help='Print collections in the block style')
        if name == 'hz':
            p.set_defaults(message_type=None)
            p.add_argument('-w', '--window', type=int, default=10000,
                           help='window size, in # of messages, for calculating rate')
            p.add_argument('--reports', type=int, default=0, help='stop after N reports (0 = never; mm extension)')
    p_pub = sub.add_parser('pub', help='Publish a message to a topic')
    p_pub.add_argument('topic', metavar='topic_name')
    p_pub.add_argument('message_type', help='Type of the ROS message (e.g. std_msgs/msg/String)')
    p_pub.add_argument('values', nargs='?', default='{}', help='Values to fill the message with in YAML format')
    p_pub.add_argument('-r', '--rate', type=float, default=1.0, help='Publishing rate in Hz (default: 1)')
    p_pub.add_argument('-p', '--print', type=int, default=1, dest='print_nth',
                       help='Only print every N-th published message (0 = never)')
    group = p_pub.add_mutually_exclusive_group()
    group.add_argument('-1', '--once', action='store_true', help='Publish one message and exit')
    group.add_argument('-t', '--times', type=int, default=0, help='Publish this number of times and then exit')
    p_pub.add_argument('-w', '--wait-matching-subscriptions', type=int, default=None,
                       help='Wait until finding the specified number of matching subscriptions (default: 1 with '
                            '--once or --times, else 0)')
    p_pub.add_argument('--timeout', type=float, default=0.0,
                       help='give up waiting for subscriptions after this many seconds (0 = wait forever)')
    p_pub.add_argument('--keep-alive', type=float, default=2.0,
                       help='seconds to wait for reliable subscribers to acknowledge the last message')
    p_pub.add_argument('--qos-depth', type=int, default=10)
    p_pub.add_argument('--qos-reliability', choices=sorted(_RELIABILITY), default='reliable')
    p_pub.add_argument('--qos-durability', choices=sorted(_DURABILITY), default='volatile')
    return parser


def run_cli(function, args) -> int:
    """Run `function(args)` inside rclpy init/shutdown; Ctrl-C and a closed output pipe end quietly with 0."""
    rclpy.init()
    try:
        rc = function(args)
        sys.stdout.flush()          # inside the try: a closed pipe surfaces here, not at interpreter exit
        return rc
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    except BrokenPipeError:
        # The reader of our output went away (`| head`): stop quietly, as ros2cli does. Point stdout at /dev/null so
        # the interpreter's final flush of the buffered rest does not raise again.
        silence_stdout()
        return 0
    finally:
        rclpy.try_shutdown()


def main(argv: Optional[List[str]] = None, prog: str = 'mm topic') -> int:
    return run_cli(run, build_parser(prog).parse_args(argv))


def silence_stdout() -> None:
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass


if __name__ == '__main__':
    sys.exit(main())
