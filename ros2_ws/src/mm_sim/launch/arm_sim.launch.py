"""Start the 2-joint arm and camera simulator alone (paper Section 3).

    ros2 launch mm_sim arm_sim.launch.py                          # parameters: mm_sim/config/arm_sim.yaml if installed
    ros2 launch mm_sim arm_sim.launch.py lockstep:=false          # free-running camera
    ros2 launch mm_sim arm_sim.launch.py object_mode:=on_request  # the object moves through arm/place_object
    ros2 launch mm_sim arm_sim.launch.py params_file:=/path/to/my_arm_sim.yaml

The simulator owns /clock; start every other node with use_sim_time:=true.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch_ros.actions import Node

from mm_common.launch_helpers import launch_arg, lockstep_overrides, node_parameters, params_file


def _launch_sim(context, *args, **kwargs):
    # Empty params_file: mm_sim/config/arm_sim.yaml if installed, else the node's defaults; empty lockstep: no override.
    params = params_file(context, 'params_file', 'mm_sim', 'arm_sim.yaml')
    overrides = lockstep_overrides(context)
    object_mode = launch_arg(context, 'object_mode').strip()
    if object_mode:                 # checked by the node (fixed | every_n_frames | on_request)
        overrides['object_mode'] = object_mode
    return [Node(package='mm_sim', executable='arm_sim', output='screen',
                 parameters=node_parameters(params, overrides))]


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value='',
                              description='YAML parameter file of the arm_sim node '
                                          '(empty: mm_sim/config/arm_sim.yaml if installed, else node defaults)'),
        DeclareLaunchArgument('lockstep', default_value='',
                              description='true: one frame per command (deterministic); false: free-running; '
                                          'empty: as configured'),
        DeclareLaunchArgument('object_mode', default_value='',
                              description='fixed | every_n_frames | on_request; empty: as configured'),
        OpaqueFunction(function=_launch_sim),
    ])
