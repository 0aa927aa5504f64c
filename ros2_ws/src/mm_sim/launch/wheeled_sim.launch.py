"""Start the wheeled-robot simulator alone (paper Section 2.5).

    ros2 launch mm_sim wheeled_sim.launch.py                              # lockstep, config/wheeled_sim.yaml
    ros2 launch mm_sim wheeled_sim.launch.py lockstep:=false              # free-running at real_time_factor
    ros2 launch mm_sim wheeled_sim.launch.py params_file:=/path/to/my_wheeled_sim.yaml

The simulator owns /clock; start every other node with use_sim_time:=true.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

_TRUE = ('true', '1', 'yes', 'on')
_FALSE = ('false', '0', 'no', 'off')


def _bool_or_none(text: str):
    """'' -> None (keep the params file's value); true/false -> bool; anything else is an error."""
    value = text.strip().lower()
    if not value:
        return None
    if value in _TRUE:
        return True
    if value in _FALSE:
        return False
    raise ValueError(f'expected true or false, got {text!r}')


def _launch_sim(context, *args, **kwargs):
    params_file = LaunchConfiguration('params_file').perform(context)
    if not os.path.isfile(params_file):
        raise FileNotFoundError(f'wheeled_sim params_file not found: {params_file}')
    overrides = {}
    lockstep = _bool_or_none(LaunchConfiguration('lockstep').perform(context))
    if lockstep is not None:
        overrides['lockstep'] = lockstep
    rtf = LaunchConfiguration('real_time_factor').perform(context).strip()
    if rtf:
        overrides['real_time_factor'] = float(rtf)
    return [Node(
        package='mm_sim',
        executable='wheeled_sim',
        output='screen',
        parameters=[params_file, overrides] if overrides else [params_file],
    )]


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory('mm_sim'), 'config', 'wheeled_sim.yaml')
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='YAML parameter file of the wheeled_sim node'),
        DeclareLaunchArgument('lockstep', default_value='',
                              description='true: one step per command (deterministic); false: free-running; '
                                          'empty: as in params_file'),
        DeclareLaunchArgument('real_time_factor', default_value='',
                              description='Free-running speed relative to wall time; empty: as in params_file'),
        OpaqueFunction(function=_launch_sim),
    ])
