"""Start the 2-joint arm and camera simulator alone (paper Section 3).

    ros2 launch mm_sim arm_sim.launch.py                          # parameters: mm_sim/config/arm_sim.yaml if installed
    ros2 launch mm_sim arm_sim.launch.py lockstep:=false          # free-running camera
    ros2 launch mm_sim arm_sim.launch.py params_file:=/path/to/my_arm_sim.yaml

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
    """'' -> None (keep the node's or params file's value); true/false -> bool; anything else is an error."""
    value = text.strip().lower()
    if not value:
        return None
    if value in _TRUE:
        return True
    if value in _FALSE:
        return False
    raise ValueError(f'expected true or false, got {text!r}')


def _params_file(context, arg_name: str, package: str, filename: str):
    """The file named by the launch argument, else <package share>/config/<filename> when installed, else None."""
    given = LaunchConfiguration(arg_name).perform(context).strip()
    if given:
        if not os.path.isfile(given):
            raise FileNotFoundError(f'{arg_name} not found: {given}')
        return given
    default = os.path.join(get_package_share_directory(package), 'config', filename)
    return default if os.path.isfile(default) else None


def _launch_sim(context, *args, **kwargs):
    parameters = []
    params_file = _params_file(context, 'params_file', 'mm_sim', 'arm_sim.yaml')
    if params_file:
        parameters.append(params_file)
    lockstep = _bool_or_none(LaunchConfiguration('lockstep').perform(context))
    if lockstep is not None:
        parameters.append({'lockstep': lockstep})
    return [Node(package='mm_sim', executable='arm_sim', output='screen', parameters=parameters)]


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value='',
                              description='YAML parameter file of the arm_sim node '
                                          '(empty: mm_sim/config/arm_sim.yaml if installed, else node defaults)'),
        DeclareLaunchArgument('lockstep', default_value='',
                              description='true: one frame per command (deterministic); false: free-running; '
                                          'empty: as configured'),
        OpaqueFunction(function=_launch_sim),
    ])
