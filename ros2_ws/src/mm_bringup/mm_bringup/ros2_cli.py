"""usage: ros2 <command> [<verb>] [args...]

This `ros2` is mm's own subset of ros2cli, written because ros2cli is not pip-installable (the venv gets ROS 2
from PyPI wheels). It mirrors ros2cli's argument syntax and output layout for the verbs below; anything else is not
implemented. On a machine with a real ROS 2 installation (apt or source), source it and use the real `ros2`.
There is no ros2 daemon: every command discovers the graph afresh (about a second).

Commands:
  run <package> <executable> [args...]    start a node's executable (install/<pkg>/lib/<pkg>/<exe>)
  pkg executables [package]               list the executables of the installed packages
  node list | info <node>                 nodes in the graph; a node's topics and services
  topic list|info|type|echo|hz|pub        inspect and publish topics (ros2 topic <verb> -h)
  service list | call <service> [type] [values]
  param list|get|set|describe|dump        parameters through the rcl_interfaces services of a node
  interface show <pkg>/msg|srv/<Name>     an interface definition, nested types expanded
  bag info|play|record|...                rosbag2 MCAP bags (delegates to mm_bringup.bag_tool; ros2 bag -h)

Call `ros2 <command> -h` for more detailed usage.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import List, Optional

import rclpy
import yaml
from ament_index_python.packages import PackageNotFoundError, get_package_prefix, get_packages_with_prefixes
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType
from rclpy.action import get_action_client_names_and_types_by_node, get_action_server_names_and_types_by_node
from rclpy.node import Node
from rclpy.parameter import get_parameter_value, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient

from mm_bringup import bag_tool, topic_tool
from mm_bringup.message_yaml import interface_class, interface_lines, parse_values, set_message_fields
from mm_bringup.topic_tool import absolute, cli_node, run_cli, settle_graph, silence_stdout

PARAMETER_TYPES = {
    ParameterType.PARAMETER_NOT_SET: ('not set', 'Parameter not set.'),
    ParameterType.PARAMETER_BOOL: ('boolean', 'Boolean value is:'),
    ParameterType.PARAMETER_INTEGER: ('integer', 'Integer value is:'),
    ParameterType.PARAMETER_DOUBLE: ('double', 'Double value is:'),
    ParameterType.PARAMETER_STRING: ('string', 'String value is:'),
    ParameterType.PARAMETER_BYTE_ARRAY: ('byte array', 'Byte values are:'),
    ParameterType.PARAMETER_BOOL_ARRAY: ('boolean array', 'Boolean values are:'),
    ParameterType.PARAMETER_INTEGER_ARRAY: ('integer array', 'Integer values are:'),
    ParameterType.PARAMETER_DOUBLE_ARRAY: ('double array', 'Double values are:'),
    ParameterType.PARAMETER_STRING_ARRAY: ('string array', 'String values are:'),
}
_FIELD_OF_TYPE = {ParameterType.PARAMETER_BOOL: 'bool_value', ParameterType.PARAMETER_INTEGER: 'integer_value',
                  ParameterType.PARAMETER_DOUBLE: 'double_value', ParameterType.PARAMETER_STRING: 'string_value',
                  ParameterType.PARAMETER_BYTE_ARRAY: 'byte_array_value',
                  ParameterType.PARAMETER_BOOL_ARRAY: 'bool_array_value',
                  ParameterType.PARAMETER_INTEGER_ARRAY: 'integer_array_value',
                  ParameterType.PARAMETER_DOUBLE_ARRAY: 'double_array_value',
                  ParameterType.PARAMETER_STRING_ARRAY: 'string_array_value'}


COMMANDS = ('run', 'pkg', 'node', 'topic', 'service', 'param', 'interface', 'bag')


class CliError(Exception):
    """A failure reported as one line on stderr with exit status 1 (ros2cli returns such a string from main)."""


# --- graph helpers ---------------------------------------------------------------------------------------------------
def _full_name(name: str, namespace: str) -> str:
    return f'{namespace.rstrip("/")}/{name}'


def node_names(node: Node, include_hidden: bool = False) -> List[str]:
    settle_graph(node)
    names = [_full_name(n, ns) for n, ns in node.get_node_names_and_namespaces()]
    return sorted(n for n in names if include_hidden or not n.rsplit('/', 1)[1].startswith('_'))


def _require_node(node: Node, name: str, timeout: float = 5.0) -> tuple:
    """(full name, name, namespace) of a node once discovered; CliError if it does not appear within `timeout` s."""
    full = absolute(name)
    deadline = time.monotonic() + timeout
    while full not in [_full_name(n, ns) for n, ns in node.get_node_names_and_namespaces()]:
        if time.monotonic() >= deadline:
            raise CliError(f"Unable to find node '{full}'")
        rclpy.spin_once(node, timeout_sec=0.05)
    namespace, _, base = full.rpartition('/')
    return full, base, namespace or '/'


def _wait(node: Node, future, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while not future.done():
        if time.monotonic() >= deadline:
            raise CliError(f'No answer from {what} within {timeout} s')
        rclpy.spin_once(node, timeout_sec=0.05)
    if future.exception() is not None:
        raise CliError(f'{what} failed: {future.exception()}')
    return future.result()


# --- verbs -----------------------------------------------------------------------------------------------------------
def _run(args) -> int:
    try:
        prefix = Path(get_package_prefix(args.package))
    except PackageNotFoundError:
        raise CliError(f"Package '{args.package}' not found") from None
    path = prefix / 'lib' / args.package / args.executable
    if not (path.is_file() and os.access(path, os.X_OK)):
        raise CliError('No executable found')
    cmd = [str(path), *args.argv]
    if args.prefix:
        cmd = [*args.prefix.split(), *cmd]
    sys.stdout.flush()
    os.execvp(cmd[0], cmd)
    return 0  # not reached


def _package_executables(prefix: str, package: str) -> List[Path]:
    lib = Path(prefix) / 'lib' / package
    if not lib.is_dir():
        return []
    return sorted(p for p in lib.iterdir() if p.is_file() and os.access(p, os.X_OK))


def _pkg(args) -> int:
    packages = get_packages_with_prefixes()
    if args.package_name:
        if args.package_name not in packages:
            raise CliError('Package not found')
        packages = {args.package_name: packages[args.package_name]}
    for package in sorted(packages):
        for path in _package_executables(packages[package], package):
            print(str(path) if args.full_path else f'{package} {path.name}')
    return 0


def _node(args) -> int:
    node = cli_node()
    try:
        if args.verb == 'list':
            names = node_names(node, args.all)
            if args.count_nodes:
                print(len(names))
            else:
                for name in names:
                    print(name)
            return 0
        full, base, namespace = _require_node(node, args.node_name, args.timeout)
        settle_graph(node)                      # its endpoints are discovered after the node itself
        print(full)
        sections = (
            ('Subscribers', node.get_subscriber_names_and_types_by_node(base, namespace)),
            ('Publishers', node.get_publisher_names_and_types_by_node(base, namespace)),
            ('Service Servers', node.get_service_names_and_types_by_node(base, namespace)),
            ('Service Clients', node.get_client_names_and_types_by_node(base, namespace)),
            ('Action Servers', get_action_server_names_and_types_by_node(node, base, namespace)),
            ('Action Clients', get_action_client_names_and_types_by_node(node, base, namespace)))
        for title, names_and_types in sections:
            print(f'  {title}:')
            print(*[f'    {name}: {", ".join(types)}' for name, types in sorted(names_and_types)
                    if args.include_hidden or not any(p.startswith('_') for p in name.split('/'))], sep='\n')
        return 0
    finally:
        node.destroy_node()


def _service(args) -> int:
    node = cli_node()
    try:
        if args.verb == 'list':
            settle_graph(node)
            for name, types in sorted(node.get_service_names_and_types()):
                if args.include_hidden_services or not any(p.startswith('_') for p in name.split('/')):
                    print(f"{name} [{', '.join(types)}]" if args.show_types else name)
            return 0
        service = absolute(args.service_name)
        type_name = args.service_type
        if not type_name:
            settle_graph(node)
            types = dict(node.get_service_names_and_types()).get(service)
            if not types:
                raise CliError(f"Unknown service '{service}' (give its type to wait for it)")
            type_name = types[0]
        try:
            srv_class = interface_class(type_name)
            request = srv_class.Request()
            set_message_fields(request, parse_values(args.values), now=lambda: node.get_clock().now().to_msg())
        except (LookupError, ValueError) as exc:
            raise CliError(str(exc)) from None
        client = node.create_client(srv_class, service)
        if not client.wait_for_service(timeout_sec=0.5):
            print('waiting for service to become available...')
            if not client.wait_for_service(timeout_sec=args.timeout):
                raise CliError(f"Service '{service}' is not available (waited {args.timeout} s)")
        period = 1.0 / args.rate if args.rate else None
        while True:
            print(f'requester: making request: {request!r}\n')
            response = _wait(node, client.call_async(request), args.timeout, f"service '{service}'")
            print(f'response:\n{response!r}\n', flush=True)
            if period is None:
                return 0
            time.sleep(period)
    finally:
        node.destroy_node()


def _param_value_text(value) -> str:
    """The ros2cli text of a ParameterValue's payload (arrays print as rclpy holds them, e.g. array('d', [...]))."""
    field = _FIELD_OF_TYPE.get(value.type)
    return str(getattr(value, field)) if field else ''


def _nested(params: dict) -> dict:
    """`a.b: 1` -> `{a: {b: 1}}`, the layout of `ros2 param dump`."""
    tree: dict = {}
    for name in sorted(params):
        *parents, leaf = name.split('.')
        branch = tree
        for part in parents:
            branch = branch.setdefault(part, {})
        branch[leaf] = params[name]
    return tree


def _param(args) -> int:
    node = cli_node()
    try:
        if args.verb == 'list' and not args.node_name:
            targets = node_names(node)
        else:
            targets = [_require_node(node, args.node_name, args.timeout)[0]]
        for target in targets:
            client = AsyncParameterClient(node, target)
            if not client.wait_for_services(timeout_sec=args.timeout):
                if args.verb == 'list' and not args.node_name:
                    continue                    # a node without parameter services (e.g. started without them)
                raise CliError(f"Node '{target}' offers no parameter services (waited {args.timeout} s)")
            what = f'{target} parameter services'
            if args.verb == 'list':
                names = sorted(_wait(node, client.list_parameters(args.param_prefixes or None), args.timeout,
                                     what).result.names)
                types = {}
                if args.param_type and names:
                    types = {d.name: PARAMETER_TYPES[d.type][0] for d in _wait(
                        node, client.describe_parameters(names), args.timeout, what).descriptors}
                if not args.node_name:
                    print(f'{target}:')
                for name in names:
                    print(f'  {name} (type: {types[name]})' if args.param_type else f'  {name}')
            elif args.verb == 'get':
                values = _wait(node, client.get_parameters([args.parameter_name]), args.timeout, what).values
                if not values or values[0].type == ParameterType.PARAMETER_NOT_SET:
                    raise CliError('Parameter not set.')
                label = PARAMETER_TYPES.get(values[0].type, ('', f"Unknown parameter type '{values[0].type}'"))[1]
                print(_param_value_text(values[0]) if args.hide_type else f'{label} {_param_value_text(values[0])}')
            elif args.verb == 'set':
                msg = ParameterMsg(name=args.parameter_name, value=get_parameter_value(args.value))
                result = _wait(node, client.set_parameters([msg]), args.timeout, what).results[0]
                if not result.successful:
                    raise CliError('Set parameter failed' + (f': {result.reason}' if result.reason else ''))
                print('Set parameter successful')
            elif args.verb == 'describe':
                for d in _wait(node, client.describe_parameters(args.parameter_names), args.timeout,
                               what).descriptors:
                    _print_descriptor(d)
            else:  # dump
                names = sorted(_wait(node, client.list_parameters(), args.timeout, what).result.names)
                values = _wait(node, client.get_parameters(names), args.timeout, what).values if names else []
                params = {n: parameter_value_to_python(v) for n, v in zip(names, values)}
                params = {n: list(v) if hasattr(v, 'tolist') or isinstance(v, tuple) else v
                          for n, v in params.items()}
                print(yaml.safe_dump({target: {'ros__parameters': _nested(params)}}, default_flow_style=False),
                      end='')
        return 0
    finally:
        node.destroy_node()


def _print_descriptor(d) -> None:
    print('Parameter name:', d.name)
    print('  Type:', PARAMETER_TYPES.get(d.type, ('unknown',))[0])
    if d.description:
        print('  Description:', d.description)
    if d.read_only or d.additional_constraints or d.floating_point_range or d.integer_range:
        print('  Constraints:')
        if d.read_only:
            print('    Read only: true')
        if d.additional_constraints:
            print('    Additional constraints:', d.additional_constraints)
        for r in list(d.floating_point_range) + list(d.integer_range):
            print('    Min value:', r.from_value)
            print('    Max value:', r.to_value)
            if r.step:
                print('    Step:', r.step)


def _interface(args) -> int:
    try:
        for line in interface_lines(args.type, show_comments=args.all_comments or not args.no_comments,
                                    show_nested_comments=args.all_comments):
            print(line)
    except (LookupError, ValueError) as exc:
        raise CliError(str(exc)) from None
    return 0


def _bag(argv: List[str]) -> int:
    """ros2 bag's option names for play and record, translated to mm_bringup.bag_tool's CLI; every other verb
    (info, reindex, ...) goes to bag_tool unchanged."""
    if not argv or argv[0] not in ('play', 'record'):
        return bag_tool.main(argv, prog='ros2 bag')
    parser = argparse.ArgumentParser(prog=f'ros2 bag {argv[0]}')
    if argv[0] == 'play':
        parser.add_argument('bag_path')
        parser.add_argument('-r', '--rate', type=float, default=1.0)
        parser.add_argument('--clock', nargs='?', const=True, default=False,
                            help='publish /clock from the recorded times (a frequency is accepted and ignored: '
                                 'mm publishes one per message)')
        parser.add_argument('--topics', nargs='+', default=[])
        args = parser.parse_args(argv[1:])
        return bag_tool.main(['play', args.bag_path, '--rate', str(args.rate), *(['--clock'] if args.clock else []),
                              *(['--topics', *args.topics] if args.topics else [])], prog='ros2 bag')
    parser.add_argument('topics', nargs='*')
    parser.add_argument('-a', '--all', action='store_true')
    parser.add_argument('-o', '--output', default='')
    parser.add_argument('-e', '--regex', default='')
    parser.add_argument('-x', '--exclude-regex', default='')
    parser.add_argument('--exclude-topics', nargs='+', default=[])
    parser.add_argument('--compression-mode', choices=['none', 'file', 'message'], default='none')
    parser.add_argument('--compression-format', choices=['zstd', 'lz4'], default='zstd')
    parser.add_argument('-b', '--max-bag-size', type=int, default=0)
    args = parser.parse_args(argv[1:])
    translated = ['record', *(['-o', args.output] if args.output else []), *(['-a'] if args.all else []),
                  *args.topics, *([args.regex] if args.regex else []),
                  '--max-bag-size', str(args.max_bag_size),
                  '--compression', args.compression_format if args.compression_mode != 'none' else 'none']
    excludes = [args.exclude_regex] if args.exclude_regex else []
    excludes += [f'^{t}$' for t in args.exclude_topics]
    if excludes:
        translated += ['--exclude', *excludes]
    return bag_tool.main(translated, prog='ros2 bag')


# --- parser ----------------------------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog='ros2', description=__doc__, usage=argparse.SUPPRESS,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest='command', metavar='')

    p = sub.add_parser('run', help='Run a package specific executable')
    p.add_argument('--prefix', help='Prefix command, which should go before the executable (e.g. "gdb -ex run --args")')
    p.add_argument('package')
    p.add_argument('executable')
    p.add_argument('argv', nargs=argparse.REMAINDER, help='Pass arbitrary arguments to the executable')

    p = sub.add_parser('pkg', help='Various package related sub-commands')
    verbs = p.add_subparsers(dest='verb', required=True)
    v = verbs.add_parser('executables', help='Output a list of package specific executables')
    v.add_argument('package_name', nargs='?')
    v.add_argument('--full-path', action='store_true')

    p = sub.add_parser('node', help='Various node related sub-commands')
    verbs = p.add_subparsers(dest='verb', required=True)
    v = verbs.add_parser('list', help='Output a list of available nodes')
    v.add_argument('-a', '--all', action='store_true', help='Display all nodes even hidden ones')
    v.add_argument('-c', '--count-nodes', action='store_true', help='Only display the number of nodes discovered')
    v = verbs.add_parser('info', help='Output information about a node')
    v.add_argument('node_name')
    v.add_argument('--include-hidden', action='store_true')
    v.add_argument('--timeout', type=float, default=5.0, help='seconds to wait for the node to be discovered')

    sub.add_parser('topic', help='Various topic related sub-commands (ros2 topic -h)', add_help=False)
    sub.add_parser('bag', help='Various rosbag related sub-commands (ros2 bag -h)', add_help=False)

    p = sub.add_parser('service', help='Various service related sub-commands')
    verbs = p.add_subparsers(dest='verb', required=True)
    v = verbs.add_parser('list', help='Output a list of available services')
    v.add_argument('-t', '--show-types', action='store_true')
    v.add_argument('--include-hidden-services', action='store_true')
    v = verbs.add_parser('call', help='Call a service')
    v.add_argument('service_name')
    v.add_argument('service_type', nargs='?', help='Type of the service (e.g. std_srvs/srv/Empty)')
    v.add_argument('values', nargs='?', default='{}', help='Values to fill the request with in YAML format')
    v.add_argument('-r', '--rate', type=float, default=0.0, help='Repeat the call at a specific rate in Hz')
    v.add_argument('--timeout', type=float, default=10.0, help='seconds to wait for the service and its answer')

    p = sub.add_parser('param', help='Various param related sub-commands')
    verbs = p.add_subparsers(dest='verb', required=True)
    v = verbs.add_parser('list', help='Output a list of available parameters')
    v.add_argument('node_name', nargs='?')
    v.add_argument('--param-prefixes', nargs='+', default=[])
    v.add_argument('--param-type', action='store_true', help='Print parameter types with parameter names')
    v = verbs.add_parser('get', help='Get parameter')
    v.add_argument('node_name')
    v.add_argument('parameter_name')
    v.add_argument('--hide-type', action='store_true')
    v = verbs.add_parser('set', help='Set parameter')
    v.add_argument('node_name')
    v.add_argument('parameter_name')
    v.add_argument('value', help='Value of the parameter (YAML)')
    v = verbs.add_parser('describe', help='Show descriptive information about declared parameters')
    v.add_argument('node_name')
    v.add_argument('parameter_names', nargs='+')
    v = verbs.add_parser('dump', help='Show all of the parameters of a node in a YAML file format')
    v.add_argument('node_name')
    for v in verbs.choices.values():
        v.add_argument('--timeout', type=float, default=5.0, help='seconds to wait for the parameter services')

    p = sub.add_parser('interface', help='Show information about ROS interfaces')
    verbs = p.add_subparsers(dest='verb', required=True)
    v = verbs.add_parser('show', help='Output the interface definition')
    v.add_argument('type')
    group = v.add_mutually_exclusive_group()
    group.add_argument('--all-comments', action='store_true')
    group.add_argument('--no-comments', action='store_true')
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    if not argv or argv[0] in ('-h', '--help'):
        print(__doc__.strip())
        return 0
    # topic and bag have their own parsers (shared with ./mm topic and ./mm bag).
    if argv[0] == 'topic':
        return topic_tool.main(argv[1:], prog='ros2 topic')
    if argv[0] == 'bag':
        return _bag(argv[1:])
    if argv[0] not in COMMANDS:
        print(f"ros2: unknown command '{argv[0]}' (mm's ros2 implements only the commands below)\n", file=sys.stderr)
        print(__doc__.strip(), file=sys.stderr)
        return 2
    args = parser.parse_args(argv)
    handlers = {'run': _run, 'pkg': _pkg, 'node': _node, 'service': _service, 'param': _param,
                'interface': _interface}

    def guarded(parsed) -> int:
        try:
            return handlers[parsed.command](parsed)
        except CliError as exc:
            print(exc, file=sys.stderr)
            return 1

    if args.command in ('run', 'pkg', 'interface'):    # no graph needed
        try:
            rc = guarded(args)
            sys.stdout.flush()
            return rc
        except BrokenPipeError:                         # `| head`: stop quietly, as ros2cli does
            silence_stdout()
            return 0
    return run_cli(guarded, args)


if __name__ == '__main__':
    sys.exit(main())
