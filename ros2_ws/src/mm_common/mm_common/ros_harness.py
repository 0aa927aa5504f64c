"""In-process ROS harness: nodes run in their own rclpy Context and executor, polled with deadlines (node tests, and
the benchmarks' experimenter nodes that drive a graph from one process)."""
from __future__ import annotations

import time
from typing import Callable, List, Optional, Sequence

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node


class RosHarness:
    """A private Context + executor; `spin_until` polls instead of sleeping for a fixed time."""

    def __init__(self, domain_id: Optional[int] = None):
        self.context = Context()
        kwargs = {} if domain_id is None else {'domain_id': domain_id}
        rclpy.init(context=self.context, **kwargs)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.nodes: List[Node] = []

    def add(self, node: Node) -> Node:
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def node(self, name: str, parameter_overrides: Sequence = ()) -> Node:
        return self.add(Node(name, context=self.context, parameter_overrides=list(parameter_overrides)))

    def spin_until(self, predicate: Callable[[], bool], timeout: float = 5.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return True
            self.executor.spin_once(timeout_sec=0.01)
        return predicate()

    def sim_clock(self, publisher_node: Node, listener: Node, timeout: float = 10.0) -> Callable[[int], None]:
        """A setter of simulated time for a node under test with use_sim_time: `set(sec)` publishes /clock from
        `publisher_node` and returns once `listener`'s clock reads it."""
        from rosgraph_msgs.msg import Clock
        pub = publisher_node.create_publisher(Clock, '/clock', 10)
        if not self.spin_until(lambda: pub.get_subscription_count() > 0, timeout):
            raise TimeoutError('/clock has no subscriber')

        def set_time(sec: int) -> None:
            msg = Clock()
            msg.clock.sec = sec
            pub.publish(msg)
            if not self.spin_until(lambda: listener.get_clock().now().nanoseconds == sec * 10 ** 9, timeout):
                raise TimeoutError(f'{listener.get_name()} never read /clock {sec} s')
        return set_time

    def spin_for(self, seconds: float) -> None:
        """Process callbacks for a while: for asserting that something does NOT happen."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.01)

    def close(self) -> None:
        for node in self.nodes:
            self.executor.remove_node(node)
            node.destroy_node()
        self.executor.shutdown()
        rclpy.try_shutdown(context=self.context)
