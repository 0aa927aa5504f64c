"""Messages <-> YAML and interface text, for the `ros2` command (rosidl_runtime_py is not pip-installable here).

Built on what the wheels do ship: generated message classes (get_fields_and_field_types(), SLOT_TYPES from
rosidl_parser.definition) and the installed interface files (share/<pkg>/msg|srv/<Name>.msg|srv), parsed line by
line with rosidl_adapter like `ros2 interface show` does. The YAML layout is rosidl_runtime_py's message_to_yaml.
"""
from __future__ import annotations

import array
import importlib
import re
import sys
from collections import OrderedDict
from pathlib import Path
from typing import Callable, Iterator, List, Optional

import yaml
from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
from rosidl_parser.definition import AbstractNestedType, NamespacedType

INTERFACE_KINDS = ('msg', 'srv')


def interface_class(type_name: str):
    """The Python class of `pkg/msg/Name` or `pkg/srv/Name` (`pkg/Name` means a message)."""
    parts = type_name.split('/')
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3 or parts[1] not in INTERFACE_KINDS or not all(parts):
        raise LookupError(f"Invalid interface type '{type_name}': expected <package>/msg|srv/<Name>")
    pkg, kind, name = parts
    try:
        module = importlib.import_module(f'{pkg}.{kind}')
    except ImportError:
        raise LookupError(f"Unknown package '{pkg}' (no Python module {pkg}.{kind})") from None
    cls = getattr(module, name, None)
    if cls is None:
        raise LookupError(f"Unknown interface '{type_name}'")
    return cls


# --- message -> YAML -------------------------------------------------------------------------------------------------
def message_to_ordereddict(msg, no_arr: bool = False, no_str: bool = False) -> OrderedDict:
    """Field name -> plain Python value, in declaration order (nested messages become nested dicts)."""
    return OrderedDict((name, to_plain(getattr(msg, name), no_arr, no_str, field_type))
                       for name, field_type in msg.get_fields_and_field_types().items())


def to_plain(value, no_arr: bool, no_str: bool, field_type: str = ''):
    """A field's value as plain Python; with no_arr/no_str, arrays/strings become ros2cli's placeholders."""
    if hasattr(value, 'get_fields_and_field_types'):
        return message_to_ordereddict(value, no_arr, no_str)
    if isinstance(value, str):
        return '<string length: <{}>>'.format(len(value)) if no_str else value
    if isinstance(value, (bytes, bytearray)):
        value = list(value)
    if isinstance(value, (list, tuple, array.array)) or type(value).__name__ == 'ndarray':
        items = value.tolist() if hasattr(value, 'tolist') else list(value)
        if no_arr:
            element = re.sub(r'^sequence<|[,>\[].*$', '', field_type) or 'unknown'
            return f'<sequence type: {element}, length: {len(items)}>'
        return [to_plain(v, no_arr, no_str) for v in items]
    if hasattr(value, 'item'):                  # numpy scalar
        return value.item()
    return value


class _Dumper(yaml.SafeDumper):
    """SafeDumper that keeps field order (the representer is registered on this class only)."""


_Dumper.add_representer(OrderedDict, lambda dumper, data: dumper.represent_mapping(
    'tag:yaml.org,2002:map', data.items()))


def message_to_yaml(msg, no_arr: bool = False, no_str: bool = False, flow_style: bool = False) -> str:
    """The text `ros2 topic echo` prints for one message (without the `---` separator)."""
    return to_yaml(message_to_ordereddict(msg, no_arr, no_str), flow_style)


def to_yaml(data, flow_style: bool = False) -> str:
    return yaml.dump(data, Dumper=_Dumper, allow_unicode=True, width=sys.maxsize, default_flow_style=flow_style)


# --- YAML -> message -------------------------------------------------------------------------------------------------
def set_message_fields(msg, values, now: Optional[Callable[[], object]] = None) -> None:
    """Fill `msg` from a dict (the parsed YAML of `ros2 topic pub` / `ros2 service call`).

    Unknown fields and values of the wrong kind raise ValueError naming the field. With `now` (a function returning a
    builtin_interfaces/Time), a Time field given as 'now' gets the current time and a Header given as 'auto' gets
    the current time and an empty frame, as in ros2cli."""
    if values is None:
        return
    if not isinstance(values, dict):
        raise ValueError(f'{type(msg).__name__}: expected a mapping of field names, got {values!r}')
    fields = list(msg.get_fields_and_field_types())
    for name, value in values.items():
        if name not in fields:
            raise ValueError(f"{type(msg).__name__} has no field named '{name}' (fields: {', '.join(fields)})")
        slot = msg.SLOT_TYPES[fields.index(name)]
        try:
            setattr(msg, name, _from_plain(slot, value, now))
        except ValueError as exc:
            raise ValueError(f"field '{name}': {exc}") from None
        except (AssertionError, TypeError) as exc:
            raise ValueError(f"field '{name}' cannot take {value!r}: {exc or 'wrong type'}") from None


def _class_of(namespaced: NamespacedType):
    return getattr(importlib.import_module('.'.join(namespaced.namespaces)), namespaced.name)


def _from_plain(slot, value, now):
    if isinstance(slot, NamespacedType):
        cls = _class_of(slot)
        if now is not None and value == 'now' and slot.namespaced_name() == ('builtin_interfaces', 'msg', 'Time'):
            return now()
        if now is not None and value == 'auto' and slot.namespaced_name() == ('std_msgs', 'msg', 'Header'):
            return cls(stamp=now())
        msg = cls()
        set_message_fields(msg, value, now)
        return msg
    if isinstance(slot, AbstractNestedType):
        if not isinstance(value, (list, tuple)):
            raise ValueError(f'expected a list, got {value!r}')
        return [_from_plain(slot.value_type, v, now) for v in value]
    return _coerce(slot, value)


def _coerce(slot, value):
    typename = getattr(slot, 'typename', 'string')
    if typename in ('float', 'double'):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f'expected a number, got {value!r}')
        return float(value)
    if typename == 'boolean':
        if not isinstance(value, bool):
            raise ValueError(f'expected true or false, got {value!r}')
        return value
    if typename in ('char', 'octet') or 'int' in typename:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f'expected an integer, got {value!r}')
        bits = int(re.sub(r'\D', '', typename) or 8)
        low, high = (-2 ** (bits - 1), 2 ** (bits - 1) - 1) if typename.startswith('int') else (0, 2 ** bits - 1)
        if not low <= value <= high:
            raise ValueError(f'{value} is outside the range of {typename} [{low}, {high}]')
        return bytes([value]) if typename == 'octet' else value
    if not isinstance(value, str):
        raise ValueError(f'expected a string, got {value!r}')
    return value


def parse_values(text: str) -> dict:
    """The YAML argument of `ros2 topic pub` / `ros2 service call` ('{}' or empty = all defaults)."""
    try:
        values = yaml.safe_load(text) if text else {}
    except yaml.YAMLError as exc:
        raise ValueError(f'the values are not valid YAML: {exc}') from None
    if values is None:
        return {}
    if not isinstance(values, dict):
        raise ValueError(f'the values must be a YAML mapping (e.g. "{{data: 1.0}}"), got {text!r}')
    return values


# --- interface text (`ros2 interface show`) --------------------------------------------------------------------------
def interface_path(type_name: str) -> Path:
    parts = type_name.split('/')
    if len(parts) != 3 or parts[1] not in INTERFACE_KINDS:
        raise LookupError(f"Invalid name '{type_name}'. Expected three parts separated by '/'")
    pkg, kind, name = parts
    try:
        share = Path(get_package_share_directory(pkg))
    except PackageNotFoundError:
        raise LookupError(f"Unknown package '{pkg}'") from None
    path = share / kind / f'{name}.{kind}'
    if not path.is_file():
        raise LookupError(f"Could not find the interface '{path}'")
    return path


def interface_lines(type_name: str, show_comments: bool = True, show_nested_comments: bool = False,
                    indent: int = 0) -> Iterator[str]:
    """The lines `ros2 interface show` prints: the file's text, each nested message's definition below its field
    indented by one tab (comments and blank lines of nested definitions only with show_nested_comments)."""
    from rosidl_adapter.parser import parse_message_string
    pkg, kind, name = type_name.split('/')
    sections: List = [interface_class(type_name)]
    if kind == 'srv':
        sections = [sections[0].Request, sections[0].Response]
    section = 0
    for raw in interface_path(type_name).read_text().splitlines():
        text = raw.rstrip()
        if text == '---':
            section += 1
            yield '\t' * indent + text
            continue
        spec = parse_message_string(pkg, name, text)
        field = spec.fields[0] if spec.fields else None
        is_comment = not spec.fields and not spec.constants and text.lstrip().startswith('#')
        if not show_comments:
            if not text or is_comment:
                continue
            trailing = (field or (spec.constants[0] if spec.constants else None))
            comment = trailing.annotations.get('comment') if trailing is not None else None
            if comment:
                text = text[:text.find(comment[0]) - 1].strip().rstrip('#').rstrip()
        yield ('\t' * indent + text) if text else ''
        if field is not None:
            cls = sections[min(section, len(sections) - 1)]
            names = list(cls.get_fields_and_field_types())
            slot = cls.SLOT_TYPES[names.index(field.name)] if field.name in names else None
            if isinstance(slot, AbstractNestedType):
                slot = slot.value_type
            if isinstance(slot, NamespacedType):
                yield from interface_lines('/'.join(slot.namespaced_name()), show_nested_comments,
                                           show_nested_comments, indent + 1)
