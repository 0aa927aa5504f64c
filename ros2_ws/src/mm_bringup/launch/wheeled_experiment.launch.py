"""Section 2 graph on a real install: wheeled_sim + sensor_manifold + switching_controller, optionally recorded.

    ros2 launch mm_bringup wheeled_experiment.launch.py
    ros2 launch mm_bringup wheeled_experiment.launch.py record:=true bag:=results/wheeled_bag overwrite:=true
    ros2 launch mm_bringup wheeled_experiment.launch.py lockstep:=false       # simulator free-running

The simulator owns /clock; the learning and control nodes run with use_sim_time:=true. Parameter files: the
simulator reads mm_sim/config/wheeled_sim.yaml; the other nodes read <pkg>/config/<executable>.yaml when that file is
installed, or the file given by their *_params argument, else their built-in defaults. Ctrl-C (SIGINT) stops every
node; the recorder finalises metadata.yaml and the MCAP file on the way out.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

_TRUE = ('true', '1', 'yes', 'on')
_FALSE = ('false', '0', 'no', 'off')


def _bool(text: str, default=None):
    """true/false (and 1/0, yes/no, on/off) -> bool; '' -> default; anything else is an error."""
    value = text.strip().lower()
    if not value:
        return default
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


def _node_parameters(params_file, overrides):
    return ([params_file] if params_file else []) + ([overrides] if overrides else [])


def _launch_graph(context, *args, **kwargs):
    use_sim_time = _bool(LaunchConfiguration('use_sim_time').perform(context), default=True)

    sim_overrides = {}
    lockstep = _bool(LaunchConfiguration('lockstep').perform(context))
    if lockstep is not None:
        sim_overrides['lockstep'] = lockstep
    actions = [
        Node(package='mm_sim', executable='wheeled_sim', output='screen',
             parameters=_node_parameters(_params_file(context, 'sim_params', 'mm_sim', 'wheeled_sim.yaml'),
                                         sim_overrides)),
        Node(package='mm_manifold', executable='sensor_manifold', output='screen',
             parameters=_node_parameters(
                 _params_file(context, 'manifold_params', 'mm_manifold', 'sensor_manifold.yaml'),
                 {'use_sim_time': use_sim_time})),
        Node(package='mm_planner', executable='switching_controller', output='screen',
             parameters=_node_parameters(
                 _params_file(context, 'controller_params', 'mm_planner', 'switching_controller.yaml'),
                 {'use_sim_time': use_sim_time})),
    ]
    if _bool(LaunchConfiguration('record').perform(context), default=False):
        # The recorder stamps messages with their wall receive time, as `ros2 bag record` does by default.
        actions.append(Node(
            package='mm_bringup', executable='recorder', output='screen',
            parameters=[{
                # ParameterValue(..., value_type=str): a bag named e.g. '2024' must stay a string.
                'output': ParameterValue(LaunchConfiguration('bag').perform(context), value_type=str),
                'overwrite': _bool(LaunchConfiguration('overwrite').perform(context), default=False),
                'compression': ParameterValue(LaunchConfiguration('compression').perform(context), value_type=str),
            }]))
    return actions


def generate_launch_description():
    sim_params = os.path.join(get_package_share_directory('mm_sim'), 'config', 'wheeled_sim.yaml')
    return LaunchDescription([
        DeclareLaunchArgument('sim_params', default_value=sim_params,
                              description='YAML parameter file of wheeled_sim'),
        DeclareLaunchArgument('manifold_params', default_value='',
                              description='YAML parameter file of sensor_manifold '
                                          '(empty: mm_manifold/config/sensor_manifold.yaml if installed)'),
        DeclareLaunchArgument('controller_params', default_value='',
                              description='YAML parameter file of switching_controller '
                                          '(empty: mm_planner/config/switching_controller.yaml if installed)'),
        DeclareLaunchArgument('lockstep', default_value='',
                              description='Simulator timing: true = lockstep, false = free-running, '
                                          'empty = as in sim_params'),
        DeclareLaunchArgument('use_sim_time', default_value='true',
                              description='Learning and control nodes follow the simulator /clock'),
        DeclareLaunchArgument('record', default_value='false',
                              description='Also start the mm recorder (rosbag2 layout, MCAP storage)'),
        DeclareLaunchArgument('bag', default_value='results/wheeled_experiment_bag',
                              description='Bag directory the recorder creates (relative to the working directory)'),
        DeclareLaunchArgument('overwrite', default_value='false',
                              description='Replace an existing bag directory'),
        DeclareLaunchArgument('compression', default_value='none',
                              description='MCAP chunk compression: none, zstd or lz4'),
        OpaqueFunction(function=_launch_graph),
    ])
