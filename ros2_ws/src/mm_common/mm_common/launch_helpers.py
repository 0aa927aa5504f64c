"""Helpers shared by the mm launch files (mm_sim/launch, mm_bringup/launch).

`launch`, `launch_ros` and `ament_index_python` are imported inside the functions that need them, never at module
level, so the pure helpers (parse_bool, resolve_params_file, node_parameters) import and test without a ROS install.
"""
import os

TRUE = ('true', '1', 'yes', 'on')
FALSE = ('false', '0', 'no', 'off')


def parse_bool(text: str, default=None):
    """true/false (and 1/0, yes/no, on/off) -> bool; '' -> default; anything else is an error.

    With default=None, '' means "keep the node's or params file's value".
    """
    value = text.strip().lower()
    if not value:
        return default
    if value in TRUE:
        return True
    if value in FALSE:
        return False
    raise ValueError(f'expected true or false, got {text!r}')


def resolve_params_file(given: str, arg_name: str, default=None, required: bool = False):
    """`given` (stripped) when non-empty, which must be an existing file; else `default` when it is an existing file;
    else None, or FileNotFoundError when `required`."""
    given = given.strip()
    if given:
        if not os.path.isfile(given):
            raise FileNotFoundError(f'{arg_name} not found: {given}')
        return given
    if default and os.path.isfile(default):
        return default
    if required:
        raise FileNotFoundError(f'{arg_name} not found: {given}')
    return None


def node_parameters(params_file, overrides):
    """The `parameters` list of a Node: the params file (if any), then the overrides dict (if non-empty)."""
    return ([params_file] if params_file else []) + ([overrides] if overrides else [])


# --- helpers that need a ROS install (imports deferred) ---------------------------------------------------------------

def package_config(package: str, filename: str) -> str:
    """<package share>/config/<filename> (whether or not the file exists); the package must be installed."""
    from ament_index_python.packages import get_package_share_directory
    return os.path.join(get_package_share_directory(package), 'config', filename)


def launch_arg(context, name: str) -> str:
    """The value of launch argument `name` in an OpaqueFunction's context."""
    from launch.substitutions import LaunchConfiguration
    return LaunchConfiguration(name).perform(context)


def launch_bool(context, name: str, default=None):
    """parse_bool of launch argument `name`."""
    return parse_bool(launch_arg(context, name), default=default)


def params_file(context, arg_name: str, package: str, filename: str):
    """The file named by the launch argument, else <package share>/config/<filename> when installed, else None."""
    given = launch_arg(context, arg_name).strip()
    if given:
        return resolve_params_file(given, arg_name)
    return resolve_params_file('', arg_name, default=package_config(package, filename))


def lockstep_overrides(context, arg_name: str = 'lockstep') -> dict:
    """{'lockstep': bool} when the launch argument is true/false, {} when it is empty (keep the configured value)."""
    lockstep = launch_bool(context, arg_name)
    return {} if lockstep is None else {'lockstep': lockstep}


def screen_node(context, package: str, executable: str, params_arg: str, overrides=None, filename=None):
    """Node(package, executable, output='screen') with the parameters file chosen by params_file(params_arg,
    default <package>/config/<executable>.yaml) followed by `overrides`."""
    from launch_ros.actions import Node
    params = params_file(context, params_arg, package, filename or f'{executable}.yaml')
    return Node(package=package, executable=executable, output='screen',
                parameters=node_parameters(params, overrides))


def params_argument(name: str, package: str, executable: str):
    """DeclareLaunchArgument `name` (default ''): YAML parameter file of `executable` (empty: the installed one)."""
    from launch.actions import DeclareLaunchArgument
    return DeclareLaunchArgument(name, default_value='',
                                 description=f'YAML parameter file of {executable} '
                                             f'(empty: {package}/config/{executable}.yaml if installed)')


def recorder_arguments(default_bag: str):
    """The record, bag, overwrite and compression launch arguments read by recorder_actions."""
    from launch.actions import DeclareLaunchArgument
    return [
        DeclareLaunchArgument('record', default_value='false',
                              description='Also start the mm recorder (rosbag2 layout, MCAP storage)'),
        DeclareLaunchArgument('bag', default_value=default_bag,
                              description='Bag directory the recorder creates (relative to the working directory)'),
        DeclareLaunchArgument('overwrite', default_value='false',
                              description='Replace an existing bag directory'),
        DeclareLaunchArgument('compression', default_value='none',
                              description='MCAP chunk compression: none, zstd or lz4'),
    ]


def recorder_actions(context):
    """[the mm_bringup recorder Node] when record:=true, else []."""
    if not launch_bool(context, 'record', default=False):
        return []
    from launch_ros.actions import Node
    from launch_ros.parameter_descriptions import ParameterValue
    # The recorder stamps messages with their wall receive time, as `ros2 bag record` does by default.
    return [Node(
        package='mm_bringup', executable='recorder', output='screen',
        parameters=[{
            # ParameterValue(..., value_type=str): a bag named e.g. '2024' must stay a string.
            'output': ParameterValue(launch_arg(context, 'bag'), value_type=str),
            'overwrite': launch_bool(context, 'overwrite', default=False),
            'compression': ParameterValue(launch_arg(context, 'compression'), value_type=str),
        }])]
