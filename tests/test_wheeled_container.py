"""mm_bringup wheeled_container: the wheeled loop's three nodes in one process. They are the usual nodes on the usual
topics (the learning is identical to three processes: tests/test_determinism_under_load.py); here: the simulator keeps
its own clock whatever `use_sim_time` the command line gives, the two others take it from the simulator in the process
(no /clock subscription of their own; they cannot leave it), node-specific parameters reach their node only, and a
parameter a node refuses ends the process with one error line and status 2, as a single node's does (the nodes created
before it log as usual)."""
import subprocess

from mm_common.ros_harness import RosHarness
from rcl_interfaces.srv import GetParameters
from rclpy.parameter import Parameter
from mm_sim.wheeled_sim_node import WheeledSim
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64MultiArray

from mm_bringup.process_graph import ProcessGraph, executable_path
from mm_bringup.wheeled_container import SimClock, _fixed_clock

NODES = ('wheeled_sim', 'switching_controller', 'sensor_manifold')


def parameter(ros, node, target, name):
    client = node.create_client(GetParameters, f'/{target}/get_parameters')
    assert ros.spin_until(client.service_is_ready, 20.0), f'{target} offers no parameter service'
    future = client.call_async(GetParameters.Request(names=[name]))
    assert ros.spin_until(future.done, 10.0)
    node.destroy_client(client)
    return future.result().values[0]


def test_three_nodes_in_one_process_on_the_simulators_clock(tmp_path):
    ros = RosHarness()
    try:
        with ProcessGraph(log_dir=tmp_path) as graph:
            container = graph.start('mm_bringup', 'wheeled_container',
                                    {'use_sim_time': True, 'wheeled_sim:dt': 0.1, 'sensor_manifold:dt': 0.1,
                                     'switching_controller:dt': 0.1, 'switching_controller:exploration_steps': 50})
            node = ros.node('container_probe')
            clock = []
            node.create_subscription(Clock, '/clock', clock.append, 10)
            assert ros.spin_until(lambda: all(n in node.get_node_names() for n in NODES), 30.0), \
                graph.log_tail(container)
            # the loop runs: the simulator is not waiting for a clock of its own
            assert ros.spin_until(lambda: len(clock) > 20, 30.0), graph.log_tail(container)
            assert parameter(ros, node, 'wheeled_sim', 'use_sim_time').bool_value is False
            assert parameter(ros, node, 'sensor_manifold', 'use_sim_time').bool_value is True
            assert parameter(ros, node, 'switching_controller', 'exploration_steps').integer_value == 50
            assert parameter(ros, node, 'wheeled_sim', 'dt').double_value == 0.1
            # the nodes on the simulator's clock take it in the process: none of them subscribes to /clock
            clock_takers = [i.node_name for i in node.get_subscriptions_info_by_topic('/clock')]
            assert not [n for n in clock_takers if n in NODES], clock_takers
            assert container.process.poll() is None
    finally:
        ros.close()


def test_a_refused_parameter_ends_the_container_with_one_line():
    result = subprocess.run([str(executable_path('mm_bringup', 'wheeled_container')), '--ros-args',
                             '-p', 'sensor_manifold:learn_after:=-5'], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip() and not line.startswith('[INFO]')]
    assert len(lines) == 1 and 'SensorManifold: cannot start' in lines[0] and 'learn_after' in lines[0], \
        result.stderr


def test_composed_nodes_run_on_the_simulators_clock_without_a_subscription_and_keep_it():
    """SimClock: the nodes' clocks read the simulator's time from the moment they are attached and follow each step
    it publishes, with no /clock subscription; use_sim_time cannot be switched off."""
    ros = RosHarness()
    try:
        sim = ros.add(WheeledSim(context=ros.context, parameter_overrides=[Parameter('republish_period', value=60.0)]))
        shared = SimClock()
        shared.follow(sim)
        sim_time = [Parameter('use_sim_time', value=True)]
        first, second = (ros.node(name, sim_time) for name in ('first', 'second'))
        for node in (first, second):
            shared.share(node)
            node.add_on_set_parameters_callback(_fixed_clock)
        probe = ros.node('probe')
        assert not probe.get_subscriptions_info_by_topic('/clock')
        assert first.get_clock().now().nanoseconds == second.get_clock().now().nanoseconds == sim.sim_time_ns
        command = probe.create_publisher(Float64MultiArray, 'wheeled/wheel_velocity_controller/commands', 10)
        before = sim.step_index
        for step in range(1, 4):
            command.publish(Float64MultiArray(data=[1.0, 1.0]))
            assert ros.spin_until(lambda: sim.step_index == before + step, 10.0)
            assert first.get_clock().now().nanoseconds == second.get_clock().now().nanoseconds == sim.sim_time_ns > 0
        result = second.set_parameters([Parameter('use_sim_time', value=False)])[0]
        assert not result.successful and 'fixed' in result.reason
        command.publish(Float64MultiArray(data=[1.0, 1.0]))
        assert ros.spin_until(lambda: sim.step_index == before + 4, 10.0)
        assert second.get_clock().now().nanoseconds == sim.sim_time_ns
    finally:
        ros.close()
