"""Section 2 graph on a real install: wheeled_sim + sensor_manifold + switching_controller, optionally recorded.

    ros2 launch mm_bringup wheeled_experiment.launch.py
    ros2 launch mm_bringup wheeled_experiment.launch.py record:=true bag:=results/wheeled_bag overwrite:=true
    ros2 launch mm_bringup wheeled_experiment.launch.py lockstep:=false       # simulator free-running
    ros2 launch mm_bringup wheeled_experiment.launch.py composed:=true        # the three nodes in one process

The simulator owns /clock; the learning and control nodes run with use_sim_time:=true. Parameter files: the
simulator reads mm_sim/config/wheeled_sim.yaml; the other nodes read <pkg>/config/<executable>.yaml when that file is
installed, or the file given by their *_params argument, else their built-in defaults. Ctrl-C (SIGINT) stops every
node; the recorder finalises metadata.yaml and the MCAP file on the way out. With composed:=true the three nodes
run in one process (mm_bringup wheeled_container: same nodes and topics, a faster loop); it reads the same three
parameter files (each keyed by its node's name) and keeps the simulator on its own clock whatever use_sim_time says.
sensor_manifold takes the simulator's grouped readings (range_input:=grouped, one message per step) unless
range_input:=per_sensor (the five Range topics).
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction

from mm_common.launch_helpers import (launch_arg, launch_bool, lockstep_overrides, package_config, params_argument,
                                      params_file, recorder_actions, recorder_arguments, screen_node)


def _launch_graph(context, *args, **kwargs):
    use_sim_time = launch_bool(context, 'use_sim_time', default=True)
    range_input = {'range_input': launch_arg(context, 'range_input')}
    if launch_bool(context, 'composed', default=False):
        from launch_ros.actions import Node
        files = [params_file(context, 'sim_params', 'mm_sim', 'wheeled_sim.yaml'),
                 params_file(context, 'manifold_params', 'mm_manifold', 'sensor_manifold.yaml'),
                 params_file(context, 'controller_params', 'mm_planner', 'switching_controller.yaml')]
        # a dict of parameters reaches every node of the process: only lockstep, which only the simulator has, and
        # range_input, which only the learner has. Recording, the container creates each node once the recorder
        # (every topic) subscribes to what the nodes before it publish: the bag holds the loop from its first step.
        wait = ['--wait-for-subscriber', 'recorder'] if launch_bool(context, 'record', default=False) else []
        return [Node(package='mm_bringup', executable='wheeled_container', output='screen', arguments=wait,
                     parameters=[f for f in files if f] + [range_input] + ([lockstep_overrides(context)]
                                                                          if lockstep_overrides(context) else []))
                ] + recorder_actions(context)
    return [
        screen_node(context, 'mm_sim', 'wheeled_sim', 'sim_params', lockstep_overrides(context)),
        screen_node(context, 'mm_manifold', 'sensor_manifold', 'manifold_params',
                    {'use_sim_time': use_sim_time, **range_input}),
        screen_node(context, 'mm_planner', 'switching_controller', 'controller_params',
                    {'use_sim_time': use_sim_time}),
    ] + recorder_actions(context)


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument('sim_params', default_value=package_config('mm_sim', 'wheeled_sim.yaml'),
                              description='YAML parameter file of wheeled_sim'),
        params_argument('manifold_params', 'mm_manifold', 'sensor_manifold'),
        params_argument('controller_params', 'mm_planner', 'switching_controller'),
        DeclareLaunchArgument('lockstep', default_value='',
                              description='Simulator timing: true = lockstep, false = free-running, '
                                          'empty = as in sim_params'),
        DeclareLaunchArgument('composed', default_value='false',
                              description='Run the three nodes in one process (mm_bringup wheeled_container)'),
        DeclareLaunchArgument('range_input', default_value='grouped',
                              description="sensor_manifold's readings: grouped (wheeled_sim's wheeled/ranges, one "
                                          'message per step) or per_sensor (the five wheeled/range/<name> topics)'),
        DeclareLaunchArgument('use_sim_time', default_value='true',
                              description='Learning and control nodes follow the simulator /clock'),
        *recorder_arguments('results/wheeled_experiment_bag'),
        OpaqueFunction(function=_launch_graph),
    ])
