"""Section 3 graph on a real install: arm_sim + image_embedding + dp_planner, optionally recorded.

    ros2 launch mm_bringup arm_experiment.launch.py
    ros2 launch mm_bringup arm_experiment.launch.py record:=true bag:=results/arm_bag compression:=zstd
    ros2 launch mm_bringup arm_experiment.launch.py lockstep:=false           # free-running camera

The simulator owns /clock; the learning and planning nodes run with use_sim_time:=true. Parameter files: each node
reads <pkg>/config/<executable>.yaml when that file is installed, or the file given by its *_params argument, else
its built-in defaults. Ctrl-C (SIGINT) stops every node; the recorder finalises metadata.yaml and the MCAP file on
the way out. 400x400 rgb8 frames are 480 kB each: zstd compression keeps long recordings small.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction

from mm_common.launch_helpers import (launch_bool, lockstep_overrides, params_argument, recorder_actions,
                                      recorder_arguments, screen_node)


def _launch_graph(context, *args, **kwargs):
    use_sim_time = launch_bool(context, 'use_sim_time', default=True)
    return [
        screen_node(context, 'mm_sim', 'arm_sim', 'sim_params', lockstep_overrides(context)),
        screen_node(context, 'mm_manifold', 'image_embedding', 'embedding_params', {'use_sim_time': use_sim_time}),
        screen_node(context, 'mm_planner', 'dp_planner', 'planner_params', {'use_sim_time': use_sim_time}),
    ] + recorder_actions(context)


def generate_launch_description():
    return LaunchDescription([
        params_argument('sim_params', 'mm_sim', 'arm_sim'),
        params_argument('embedding_params', 'mm_manifold', 'image_embedding'),
        params_argument('planner_params', 'mm_planner', 'dp_planner'),
        DeclareLaunchArgument('lockstep', default_value='',
                              description='Simulator timing: true = lockstep, false = free-running, '
                                          'empty = as configured'),
        DeclareLaunchArgument('use_sim_time', default_value='true',
                              description='Learning and planning nodes follow the simulator /clock'),
        *recorder_arguments('results/arm_experiment_bag'),
        OpaqueFunction(function=_launch_graph),
    ])
