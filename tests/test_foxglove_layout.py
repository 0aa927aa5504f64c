"""The Foxglove layout shipped with the demo (mm_bringup/config/foxglove_layout.json) is a well-formed layout whose
panels name only topics the demo bag holds, and message paths whose fields exist in those topics' types.

The topics come from results/demo_bag/metadata.yaml when `make demo` has run, otherwise from the topic table of
docs/DESIGN.md (the names and types the nodes are held to).
"""
import importlib
import json
import re
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
LAYOUT = ROOT / 'ros2_ws' / 'src' / 'mm_bringup' / 'config' / 'foxglove_layout.json'
PANEL_TYPES = {'Plot', 'Image', '3D', 'StateTransitions', 'RawMessages'}


def demo_topics() -> dict:
    """Topic name -> type (pkg/msg/Name) of the demo bag."""
    metadata = ROOT / 'results' / 'demo_bag' / 'metadata.yaml'
    if metadata.exists():
        info = yaml.safe_load(metadata.read_text())['rosbag2_bagfile_information']
        return {t['topic_metadata']['name']: t['topic_metadata']['type'] for t in info['topics_with_message_count']}
    topics = {}
    for line in (ROOT / 'docs' / 'DESIGN.md').read_text().splitlines():
        row = re.match(r'\| `([^`]+)` \| ([\w/]+)', line)
        if not row or '(service)' in line.split('|')[1]:
            continue
        name, type_name = row.groups()
        group = re.search(r'\{([^}]*)\}', name)
        pkg, _, msg = type_name.partition('/')
        for variant in (group.group(1).split(',') if group else ['']):
            full = name.replace(group.group(0), variant) if group else name
            topics['/' + full.lstrip('/')] = f'{pkg}/msg/{msg}'
    return topics


def panel_ids(node) -> list:
    if isinstance(node, str):
        return [node]
    assert set(node) >= {'first', 'second', 'direction'} and node['direction'] in ('row', 'column'), node
    assert 0 < node.get('splitPercentage', 50) < 100
    return panel_ids(node['first']) + panel_ids(node['second'])


def referenced(config_by_id: dict) -> list:
    """(topic, field path or '') of every topic a panel reads."""
    refs = []
    for panel_id, config in config_by_id.items():
        kind = panel_id.split('!')[0]
        for path in config.get('paths', []):
            topic, _, fields = path['value'].partition('.')
            refs.append((topic, fields))
        if kind == 'Image':
            refs.append((config['imageMode']['imageTopic'], ''))
        if kind == '3D':
            refs += [(topic, '') for topic in config['topics']]
        if kind == 'RawMessages':
            refs.append((config['topicPath'], ''))
    return refs


def field_exists(type_name: str, fields: str) -> bool:
    pkg, kind, name = type_name.split('/')
    cls = getattr(importlib.import_module(f'{pkg}.{kind}'), name)
    for field in fields.split('.'):
        types = cls.get_fields_and_field_types()
        if field not in types:
            return False
        nested = types[field]
        if '/' in nested:
            p, n = nested.split('/')
            cls = getattr(importlib.import_module(f'{p}.msg'), n)
    return True


def test_layout_is_a_foxglove_layout():
    layout = json.loads(LAYOUT.read_text())
    assert set(layout) >= {'configById', 'layout', 'globalVariables', 'userNodes', 'playbackConfig'}
    ids = panel_ids(layout['layout'])
    assert sorted(ids) == sorted(layout['configById']) and len(set(ids)) == len(ids)
    assert {i.split('!')[0] for i in ids} == PANEL_TYPES
    for path in (p for c in layout['configById'].values() for p in c.get('paths', [])):
        assert path['timestampMethod'] in ('receiveTime', 'headerStamp') and path.get('enabled', True) is True


def test_layout_shows_the_demo_and_names_only_its_topics():
    layout = json.loads(LAYOUT.read_text())
    topics = demo_topics()
    refs = referenced(layout['configById'])
    for topic, fields in refs:
        assert topic in topics, f'{topic} is not in the demo bag'
        assert not fields or field_exists(topics[topic], fields), f'{topic}.{fields}'
    plotted = {t for t, f in refs if f == 'range'}
    assert plotted == {f'/wheeled/range/{s}' for s in
                       ('front_left', 'front_center', 'front_right', 'side_front', 'side_rear')}
    assert topics[layout['configById']['Image!camera']['imageMode']['imageTopic']] == 'sensor_msgs/msg/Image'
    assert {topics[t] for t in layout['configById']['3D!markers']['topics']} == {'visualization_msgs/msg/MarkerArray'}
    assert {'/wheeled/controller/status', '/arm/planner/status'} <= {t for t, _ in refs}
