"""The wheeled loop's three nodes - wheeled_sim, sensor_manifold, switching_controller - composed in one process
(`./mm run mm_bringup wheeled_container`), like rclcpp's component_container with the three loaded.

They are the same node classes as `ros2 run mm_sim wheeled_sim` etc. and still meet only through their topics,
which any other process sees, records and may publish on as before; what composition saves is the loop's hops
between processes: one step of the lockstep loop (simulator -> learner -> controller -> simulator) runs in one
thread instead of waking three processes in turn (graph rate in README, issue 14; it also leaves the second core
to whatever else runs, e.g. the demo's arm). Parameters: the nodes' own files with `--params-file` (keyed by node
name, as wheeled_sim.yaml is) or `-p <node>:<name>:=<value>`; a bare `-p name:=value` reaches all three. The
simulator owns `/clock` and the two others run on it: use_sim_time is false for wheeled_sim and true for the others
whatever the arguments say.

`--wait-for-subscriber NODE` (before `--ros-args`): the nodes are created in the loop's order (simulator,
controller, learner, which closes the loop), each once the node NODE (e.g. a recorder in another process)
subscribes to every topic the nodes before it publish (or to those of them named by `--wait-topics`), so that a bag
holds the loop from its first step, as when the nodes start one by one.
"""
from __future__ import annotations

import argparse
import sys
from typing import Sequence

from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.utilities import remove_ros_args

from mm_common.node_utils import run_nodes
from mm_manifold.sensor_manifold_node import SensorManifold
from mm_planner.switching_controller_node import SwitchingControllerNode
from mm_sim.wheeled_sim_node import WheeledSim


def _on_clock(node_class, sim_time: bool):
    def factory():
        return node_class(parameter_overrides=[Parameter('use_sim_time', value=sim_time)])
    factory.__name__ = node_class.__name__
    return factory


def _subscribed_by(name: str, only: Sequence[str] = ()):
    """True once the node `name` subscribes to every topic the given nodes publish (/rosout and parameter events
    aside; only those in `only` when given)."""
    def subscribed(nodes: Sequence[Node]) -> bool:
        topics = {p.topic_name for n in nodes for p in n.publishers} - {'/rosout', '/parameter_events'}
        if only:
            topics &= set(only)
        return all(any(info.node_name == name for info in nodes[0].get_subscriptions_info_by_topic(topic))
                   for topic in topics)
    return subscribed


def main(args=None):
    argv = sys.argv if args is None else list(args)
    parser = argparse.ArgumentParser(prog='wheeled_container', description=__doc__.split('\n\n')[0])
    parser.add_argument('--wait-for-subscriber', metavar='NODE', default='',
                        help='create each node once NODE subscribes to the topics of the nodes before it')
    parser.add_argument('--wait-topics', metavar='TOPIC', nargs='+', default=[],
                        help='the topics (absolute names) NODE must subscribe to (default: all of them)')
    options = parser.parse_args(remove_ros_args(argv)[1:])
    gate = _subscribed_by(options.wait_for_subscriber, options.wait_topics) if options.wait_for_subscriber else None
    run_nodes([_on_clock(WheeledSim, False), _on_clock(SwitchingControllerNode, True),
               _on_clock(SensorManifold, True)], argv, create_when=gate)


if __name__ == '__main__':
    main()
