"""Start the wheeled-robot simulator alone (paper Section 2.5).

    ros2 launch mm_sim wheeled_sim.launch.py                              # lockstep, config/wheeled_sim.yaml
    ros2 launch mm_sim wheeled_sim.launch.py lockstep:=false              # free-running at real_time_factor
    ros2 launch mm_sim wheeled_sim.launch.py params_file:=/path/to/my_wheeled_sim.yaml

The simulator owns /clock; start every other node with use_sim_time:=true.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch_ros.actions import Node

from mm_common.launch_helpers import (launch_arg, lockstep_overrides, node_parameters, package_config,
                                      resolve_params_file)


def _launch_sim(context, *args, **kwargs):
    # params_file is required here (its default is the installed config/wheeled_sim.yaml): no fallback.
    params_file = resolve_params_file(launch_arg(context, 'params_file'), 'wheeled_sim params_file', required=True)
    overrides = lockstep_overrides(context)
    rtf = launch_arg(context, 'real_time_factor').strip()
    if rtf:
        overrides['real_time_factor'] = float(rtf)
    return [Node(package='mm_sim', executable='wheeled_sim', output='screen',
                 parameters=node_parameters(params_file, overrides))]


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=package_config('mm_sim', 'wheeled_sim.yaml'),
                              description='YAML parameter file of the wheeled_sim node'),
        DeclareLaunchArgument('lockstep', default_value='',
                              description='true: one step per command (deterministic); false: free-running; '
                                          'empty: as in params_file'),
        DeclareLaunchArgument('real_time_factor', default_value='',
                              description='Free-running speed relative to wall time; empty: as in params_file'),
        OpaqueFunction(function=_launch_sim),
    ])
