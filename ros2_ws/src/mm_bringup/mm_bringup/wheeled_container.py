"""The wheeled loop's three nodes - wheeled_sim, sensor_manifold, switching_controller - composed in one process
(`./mm run mm_bringup wheeled_container`), like rclcpp's component_container with the three loaded.

They are the same node classes as `ros2 run mm_sim wheeled_sim` etc. and still meet only through their topics,
which any other process sees, records and may publish on as before; what composition saves is the loop's hops
between processes: one step of the lockstep loop (simulator -> learner -> controller -> simulator) runs in one
thread instead of waking three processes in turn (graph rate in README, issue 14; it also leaves the second core
to whatever else runs, e.g. the demo's arm). Parameters: the nodes' own files with `--params-file` (keyed by node
name, as wheeled_sim.yaml is) or `-p <node>:<name>:=<value>`; a bare `-p name:=value` reaches all three. The
simulator owns `/clock` and the two others run on it: use_sim_time is false for wheeled_sim and true for the others
whatever the arguments say, and cannot be changed while they run. They take the simulator's clock from it in this
process as it publishes /clock (what rclcpp's intra-process delivery would do), not through /clock subscriptions of
their own: no delivery of /clock per step, and their clocks never lag behind the readings (README, issue 14). /clock
is published as before for every other process.

`--wait-for-subscriber NODE` (before `--ros-args`): the nodes are created in the loop's order (simulator,
controller, learner, which closes the loop), each once the node NODE (e.g. a recorder in another process)
subscribes to every topic the nodes before it publish (or to those of them named by `--wait-topics`), so that a bag
holds the loop from its first step, as when the nodes start one by one.
"""
from __future__ import annotations

import argparse
import sys
from typing import Sequence

from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSCompatibility, qos_check_compatible
from rclpy.time_source import TimeSource
from rclpy.utilities import remove_ros_args

from mm_common.node_utils import run_nodes
from mm_manifold.sensor_manifold_node import SensorManifold
from mm_planner.switching_controller_node import SwitchingControllerNode
from mm_sim.wheeled_sim_node import WheeledSim


def _fixed_clock(params) -> SetParametersResult:
    """On-set callback: the clock a composed node runs on is fixed (the simulator sets it in this process)."""
    if any(p.name == 'use_sim_time' for p in params):
        return SetParametersResult(successful=False, reason='use_sim_time is fixed in wheeled_container')
    return SetParametersResult(successful=True)


class SimClock:
    """The composed nodes on the simulator's clock: one time source, subscribed to nothing, set by the simulator in
    this process each time it publishes /clock (WheeledSim.clock_listeners); each node's own time source drops its
    /clock subscription and the node's clock is attached to the shared one. (rclpy has no public handle on a node's
    time source: this is the one place that reaches `Node._time_source`.)"""

    def __init__(self):
        self.source = TimeSource()
        self.source.ros_time_is_active = True       # with no node it subscribes to nothing

    def follow(self, sim: WheeledSim) -> None:
        """Run on `sim`'s clock: from its current time on, set each time it publishes /clock."""
        self.source.clock_callback(sim.clock_msg)
        sim.clock_listeners.append(self.source.clock_callback)

    def share(self, node: Node) -> None:
        node._time_source.detach_node()             # drops its /clock subscription
        self.source.attach_clock(node.get_clock())


def _on_clock(node_class, sim_time: bool, sim_clock: SimClock):
    def factory():
        node = node_class(parameter_overrides=[Parameter('use_sim_time', value=sim_time)])
        if isinstance(node, WheeledSim):
            sim_clock.follow(node)
        if sim_time:
            sim_clock.share(node)
        # Runs before the time source's own callback (rclpy calls the newest first) and refuses the change, so no
        # node's clock leaves the shared source.
        node.add_on_set_parameters_callback(_fixed_clock)
        return node
    factory.__name__ = node_class.__name__
    return factory


def _subscribed_by(name: str, only: Sequence[str] = ()):
    """True once the node `name` subscribes to every topic the given nodes publish (/rosout and parameter events
    aside; only those in `only` when given) and each of those publishers has matched every subscription it can serve:
    a subscription is seen on the graph a little before the middleware has matched it, and a step published in
    between never reaches it (seen in a demo bag, 100-150 messages short on some topics)."""
    def subscribed(nodes: Sequence[Node]) -> bool:
        publishers = [p for n in nodes for p in n.publishers if p.topic_name not in ('/rosout', '/parameter_events')
                      and (not only or p.topic_name in only)]
        for publisher in publishers:
            readers = nodes[0].get_subscriptions_info_by_topic(publisher.topic_name)
            if not any(info.node_name == name for info in readers):
                return False
            servable = [info for info in readers if qos_check_compatible(
                publisher.qos_profile, info.qos_profile)[0] != QoSCompatibility.ERROR]
            if publisher.get_subscription_count() < len(servable):
                return False
        return True
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
    sim_clock = SimClock()
    run_nodes([_on_clock(WheeledSim, False, sim_clock), _on_clock(SwitchingControllerNode, True, sim_clock),
               _on_clock(SensorManifold, True, sim_clock)], argv, create_when=gate)


if __name__ == '__main__':
    main()
