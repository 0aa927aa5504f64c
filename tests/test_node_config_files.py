"""config/<executable>.yaml of every mm_manifold and mm_planner node lists exactly the node's declared parameters
(not those rclpy declares on every node), each with its built-in default and type, under the node's default name;
and the node starts with it as the launch files pass it (--params-file). So the files cannot drift from the code."""
from pathlib import Path

import pytest
import rclpy
import yaml
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter

from mm_manifold.image_embedding_node import ImageEmbeddingNode
from mm_manifold.sensor_manifold_node import SensorManifold
from mm_planner.dp_planner_node import DpPlannerNode
from mm_planner.switching_controller_node import SwitchingControllerNode

SRC = Path(__file__).resolve().parents[1] / 'ros2_ws' / 'src'
# (package, executable) -> node class, as in the packages' console_scripts
NODES = {('mm_manifold', 'sensor_manifold'): SensorManifold, ('mm_manifold', 'image_embedding'): ImageEmbeddingNode,
         ('mm_planner', 'switching_controller'): SwitchingControllerNode, ('mm_planner', 'dp_planner'): DpPlannerNode}


def start_node(node_class, params_file=None):
    """Node name, {parameter: (type, value)} and the overrides rcl gave it (from the file) of a node started in a
    Context of its own; without the parameters every rclpy node declares (use_sim_time,
    start_type_description_service)."""
    args = ['--ros-args', '--params-file', str(params_file)] if params_file else []
    context = Context()
    rclpy.init(args=args, context=context)
    node = None
    try:
        plain = Node('config_test_plain_node', context=context)
        builtin = set(plain.list_parameters([], 0).names)
        plain.destroy_node()
        assert 'use_sim_time' in builtin
        node = node_class(context=context)
        names = node.list_parameters([], 0).names
        overrides = node._parameter_overrides      # what rcl parsed from --params-file for this node's name
        return (node.get_name(), {n: as_plain(node.get_parameter(n)) for n in names if n not in builtin},
                {n: as_plain(p) for n, p in overrides.items() if n not in builtin})
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)


def as_plain(param: Parameter):
    value = param.value
    return param.type_, list(value) if param.type_.name.endswith('_ARRAY') else value


@pytest.mark.parametrize('package', sorted({package for package, _ in NODES}))
def test_there_is_one_file_per_node(package):
    assert (sorted(p.stem for p in (SRC / package / 'config').glob('*.yaml'))
            == sorted(exe for pkg, exe in NODES if pkg == package))


@pytest.mark.parametrize('package,executable', sorted(NODES))
def test_file_matches_the_declared_parameters_and_defaults(package, executable):
    path = SRC / package / 'config' / f'{executable}.yaml'
    content = yaml.safe_load(path.read_text())
    name, defaults, overrides = start_node(NODES[package, executable])
    assert not overrides
    assert list(content) == [name] and list(content[name]) == ['ros__parameters'], \
        f'{path.name}: top-level key must be the node name {name!r} with only ros__parameters under it'
    in_file = content[name]['ros__parameters']
    # (a) exactly the declared parameters
    assert sorted(in_file) == sorted(defaults), (f'{path.name}: missing {sorted(set(defaults) - set(in_file))}, '
                                                 f'not declared {sorted(set(in_file) - set(defaults))}')
    # (b) each with its built-in default, of the declared type
    file_values = {k: as_plain(Parameter(k, value=v)) for k, v in in_file.items()}
    differ = {k: (file_values[k], defaults[k]) for k in defaults if file_values[k] != defaults[k]}
    assert not differ, f'{path.name}: (file, built-in default) differ: {differ}'
    # The node starts with the file as the launch files pass it; rcl reads every value, typed as declared, from it.
    name_with_file, loaded, from_file = start_node(NODES[package, executable], path)
    assert name_with_file == name and from_file == defaults and loaded == defaults
