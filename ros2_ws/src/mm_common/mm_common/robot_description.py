"""The robot's joint box travels as a URDF on a latched robot_description topic, as in any ROS 2 robot: the simulator
(or a real robot's description publisher) writes it, learning and planning nodes read their joint limits from it, so
the limits have one home and no node carries a robot constant. No rclpy.

Only what the nodes need is read: the movable (revolute or prismatic) joints in document order with their
`<limit lower upper>`. Hostile input is refused with the reason (ValueError): oversized text, DTDs or entities (no
entity expansion), malformed XML, a movable joint without finite lower < upper.
"""
from __future__ import annotations

import math
import xml.etree.ElementTree as ElementTree
from typing import List, Sequence, Tuple

import numpy as np

MAX_DESCRIPTION_CHARS = 1_000_000
MOVABLE_TYPES = ('revolute', 'prismatic')


def joint_limits_from_urdf(urdf: str) -> Tuple[List[str], np.ndarray]:
    """(names, (n, 2) [lower, upper]) of the movable joints of a URDF, in document order; ValueError saying why not."""
    if not isinstance(urdf, str) or not urdf.strip():
        raise ValueError('the robot description is empty')
    if len(urdf) > MAX_DESCRIPTION_CHARS:
        raise ValueError(f'the robot description has {len(urdf)} characters (at most {MAX_DESCRIPTION_CHARS})')
    if '<!DOCTYPE' in urdf or '<!ENTITY' in urdf:
        raise ValueError('the robot description declares a DTD or entities, which are not accepted')
    try:
        root = ElementTree.fromstring(urdf)
    except ElementTree.ParseError as exc:
        raise ValueError(f'the robot description is not well-formed XML: {exc}') from None
    if root.tag != 'robot':
        raise ValueError(f'the robot description\'s root element is <{root.tag}>, expected <robot>')
    names, limits = [], []
    for joint in root.findall('joint'):
        if joint.get('type') not in MOVABLE_TYPES:
            continue
        name = joint.get('name') or f'joint {len(names)}'
        limit = joint.find('limit')
        try:
            lower, upper = float(limit.get('lower')), float(limit.get('upper'))
        except (AttributeError, TypeError, ValueError):
            raise ValueError(f'joint {name!r} has no numeric <limit lower= upper=>') from None
        if not (math.isfinite(lower) and math.isfinite(upper) and lower < upper):
            raise ValueError(f'joint {name!r} has limits [{lower}, {upper}]; finite lower < upper is required')
        names.append(name)
        limits.append((lower, upper))
    return names, np.array(limits, dtype=float).reshape(-1, 2)


def joint_box(urdf: str, n_joints: int) -> np.ndarray:
    """(n_joints, 2) [lower, upper] of a robot with exactly n_joints movable joints; ValueError saying why not."""
    names, limits = joint_limits_from_urdf(urdf)
    if len(names) != n_joints:
        raise ValueError(f'the robot description has {len(names)} movable joint(s) {names}, this node drives '
                         f'{n_joints}')
    return limits


def planar_chain_urdf(robot: str, joints: Sequence[Tuple[str, float, float, float]], velocity: float,
                      unit_note: str = '') -> str:
    """URDF of a serial chain of revolute joints about z: one (name, lower, upper [rad], length of the link it
    moves) per joint, each joint at the end of the previous link, every joint's speed limit `velocity` [rad/s]; the
    last link's end is the `tool` frame."""
    parts = ['<?xml version="1.0"?>', f'<robot name="{robot}">']
    if unit_note:
        parts.append(f'  <!-- {unit_note} -->')
    parts.append('  <link name="base"/>')
    parent, offset = 'base', 0.0
    for name, lower, upper, length in joints:
        child = f'{name}_link'
        parts += [f'  <link name="{child}"/>',
                  f'  <joint name="{name}" type="revolute">',
                  f'    <parent link="{parent}"/>', f'    <child link="{child}"/>',
                  f'    <origin xyz="{offset:.6g} 0 0" rpy="0 0 0"/>', '    <axis xyz="0 0 1"/>',
                  f'    <limit lower="{lower:.17g}" upper="{upper:.17g}" effort="0" velocity="{velocity:.6g}"/>',
                  '  </joint>']
        parent, offset = child, float(length)
    parts += ['  <link name="tool"/>', '  <joint name="tool_fixed" type="fixed">',
              f'    <parent link="{parent}"/>', '    <child link="tool"/>',
              f'    <origin xyz="{offset:.6g} 0 0" rpy="0 0 0"/>', '  </joint>', '</robot>', '']
    return '\n'.join(parts)
