"""Message <-> YAML for the venv's `ros2` command, on rosidl introspection only (no rosidl_runtime_py)."""
import math

import pytest
import yaml
from builtin_interfaces.msg import Time
from mm_bringup.message_yaml import (interface_class, interface_lines, message_to_yaml, parse_values,
                                     set_message_fields)
from mm_msgs.msg import SensorGoal
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Range
from std_msgs.msg import Float64MultiArray
from visualization_msgs.msg import MarkerArray


def test_yaml_round_trip_keeps_field_order_nesting_and_arrays():
    msg = Odometry()
    set_message_fields(msg, {'header': {'frame_id': 'world', 'stamp': {'sec': 3, 'nanosec': 7}},
                             'pose': {'pose': {'position': {'x': 1, 'y': -2.5}}, 'covariance': [0.5] * 36}})
    text = message_to_yaml(msg)
    assert text.startswith('header:\n  stamp:\n    sec: 3\n    nanosec: 7\n  frame_id: world\nchild_frame_id: \'\'\n')
    back = Odometry()
    set_message_fields(back, yaml.safe_load(text))
    assert back == msg
    assert message_to_yaml(Float64MultiArray(data=[1.0, 2.5]), flow_style=True) == \
        '{layout: {dim: [], data_offset: 0}, data: [1.0, 2.5]}\n'
    assert message_to_yaml(Range(range=math.inf)).endswith('range: .inf\nvariance: 0.0\n')
    assert "data: '<sequence type: double, length: 2>'" in message_to_yaml(Float64MultiArray(data=[1.0, 2.0]),
                                                                          no_arr=True)


def test_sequences_of_messages_and_now_auto_stamps():
    markers = MarkerArray()
    set_message_fields(markers, {'markers': [{'ns': 'a', 'id': 1}, {'ns': 'b', 'points': [{'x': 1.0}]}]})
    assert [m.ns for m in markers.markers] == ['a', 'b'] and markers.markers[1].points[0].x == 1.0
    goal = SensorGoal()
    set_message_fields(goal, {'header': 'auto', 'sensor_group': 2, 'reading': [0.3, 0.3]}, now=lambda: Time(sec=9))
    assert goal.header.stamp.sec == 9 and list(goal.reading) == [0.3, 0.3]


@pytest.mark.parametrize('values, message', [
    ({'rang': 1.0}, "Range has no field named 'rang'"),
    ({'range': 'far'}, "field 'range': expected a number"),
    ({'radiation_type': 1.5}, "field 'radiation_type': expected an integer"),
    ({'radiation_type': 300}, r"field 'radiation_type': 300 is outside the range of uint8 \[0, 255\]"),
    ({'header': {'frame_id': 3}}, "field 'header': field 'frame_id': expected a string"),
    ({'header': [1]}, 'expected a mapping'),
])
def test_bad_values_name_the_field(values, message):
    with pytest.raises(ValueError, match=message):
        set_message_fields(Range(), values)


def test_parse_values_and_lookup_errors():
    assert parse_values('{data: [1, 2]}') == {'data': [1, 2]} and parse_values('') == {} and parse_values('{}') == {}
    with pytest.raises(ValueError, match='mapping'):
        parse_values('[1, 2]')
    with pytest.raises(ValueError, match='not valid YAML'):
        parse_values('{a: [}')
    assert interface_class('std_msgs/String').__name__ == 'String'
    for bad, match in (('nope/msg/X', "Unknown package 'nope'"), ('std_msgs/msg/Nope', 'Unknown interface'),
                       ('std_msgs', 'Invalid interface type')):
        with pytest.raises(LookupError, match=match):
            interface_class(bad)


def test_interface_show_expands_nested_types_like_ros2cli():
    lines = list(interface_lines('std_msgs/msg/Float64MultiArray', show_comments=False))
    assert lines == ['MultiArrayLayout  layout', '\tMultiArrayDimension[] dim', '\t\tstring label',
                     '\t\tuint32 size', '\t\tuint32 stride', '\tuint32 data_offset', 'float64[]         data']
    srv = list(interface_lines('mm_msgs/srv/ResetPose', show_comments=False))
    assert srv[:4] == ['float64 x', 'float64 y', 'float64 theta', '---']
    commented = list(interface_lines('sensor_msgs/msg/Range'))
    assert commented[0].startswith('#') and '\tbuiltin_interfaces/Time stamp' in commented
