"""The house rule of docs/DESIGN.md ("Package layers"), checked on the sources: the learning, control and simulation
packages import only mm_msgs, mm_common and themselves, package tests import only their package and below, mm_common
imports no other mm package, and no mm module imports itself back through others (no cycles)."""
import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / 'ros2_ws' / 'src'
BASE = {'mm_msgs', 'mm_common'}
ALLOWED = {'mm_common': {'mm_msgs', 'mm_common'}, 'mm_sim': BASE | {'mm_sim'}, 'mm_manifold': BASE | {'mm_manifold'},
           'mm_planner': BASE | {'mm_planner'}}


def python_files(package: str):
    return sorted(p for p in (SRC / package).rglob('*.py') if '__pycache__' not in p.parts)


def mm_imports(path: Path):
    """(line, module) of every import of an mm_* module in the file, at any depth (also inside functions)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names if a.name.startswith('mm_')]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or '').startswith('mm_'):
            out.append((node.lineno, node.module))
    return out


def module_name(path: Path, package: str) -> str:
    rel = path.relative_to(SRC / package).with_suffix('')
    parts = [p for p in rel.parts if p != '__init__']
    return '.'.join(parts)


@pytest.mark.parametrize('package', sorted(ALLOWED))
def test_a_package_and_its_tests_import_only_itself_and_below(package):
    wrong = [f'{path.relative_to(SRC)}:{line} imports {module}'
             for path in python_files(package) for line, module in mm_imports(path)
             if module.split('.')[0] not in ALLOWED[package]]
    assert not wrong, '\n'.join(wrong)


def test_no_import_cycles_between_mm_modules():
    graph = {}
    for package_dir in sorted(p for p in SRC.iterdir() if (p / p.name).is_dir()):
        for path in python_files(package_dir.name):
            if 'test' in path.relative_to(package_dir).parts[:1]:
                continue
            graph[module_name(path, package_dir.name)] = {m for _, m in mm_imports(path)}
    known = set(graph)

    def targets(module):
        # `from pkg import name` may name a submodule: count it when one exists
        return {m for m in graph[module] if m in known and m != module}

    state = {}

    def visit(module, stack):
        state[module] = 'open'
        for target in sorted(targets(module)):
            if state.get(target) == 'open':
                cycle = stack[stack.index(target):] + [target]
                pytest.fail('import cycle: ' + ' -> '.join(cycle))
            if target not in state:
                visit(target, stack + [target])
        state[module] = 'done'

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])
    assert len(graph) > 40            # the scan found the sources
