"""Helpers every mm node shares: the Jazzy main() pattern and parameter declaration with descriptors."""
from __future__ import annotations

import math
from typing import Any, Callable, Optional, Sequence

import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node


def run_node(node_factory: Callable[[], Node], args: Optional[Sequence[str]] = None) -> None:
    """Spin one node until Ctrl-C or external shutdown, then clean up (the Jazzy main() pattern)."""
    rclpy.init(args=args)
    node = None
    try:
        node = node_factory()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


def declare(node: Node, name: str, default: Any, description: str, *,
            min_value: Optional[float] = None, max_value: Optional[float] = None,
            step: float = 0.0, read_only: bool = False, additional_constraints: str = '') -> Any:
    """Declare a parameter with a descriptor (description and, for numbers, an inclusive range); return its value.

    rclpy itself rejects set requests outside the declared range, so nodes only need an on-set callback for
    constraints a range cannot express (see `reject_non_finite`).
    """
    descriptor = ParameterDescriptor(description=description, read_only=read_only,
                                     additional_constraints=additional_constraints)
    if min_value is not None or max_value is not None:
        lo = -math.inf if min_value is None else min_value
        hi = math.inf if max_value is None else max_value
        if isinstance(default, bool):
            raise TypeError(f'parameter {name}: a range makes no sense for a bool')
        if isinstance(default, int):
            descriptor.integer_range = [IntegerRange(from_value=int(max(lo, -2**63)),
                                                     to_value=int(min(hi, 2**63 - 1)), step=int(step))]
        else:
            descriptor.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi),
                                                                  step=float(step))]
    return node.declare_parameter(name, default, descriptor).value


def reject_non_finite(params) -> SetParametersResult:
    """On-set callback: refuse NaN/inf in any float or float-array parameter update."""
    for p in params:
        values = p.value if isinstance(p.value, (list, tuple)) else [p.value]
        for v in values:
            if isinstance(v, float) and not math.isfinite(v):
                return SetParametersResult(successful=False, reason=f'{p.name}: value must be finite, got {v}')
    return SetParametersResult(successful=True)
