"""mm's `ros2` command (mm_bringup.ros2_cli) against real running nodes: a free-running wheeled_sim started with
`ros2 run`, and CLI processes talking to each other (pub -> echo, pub -> bag record, bag play -> echo).

Each check runs the installed `ros2` executable as a user would and compares the output layout with ros2cli's
(one fully-qualified node per line, "Double value is: 0.05", "Set parameter successful", the topic info block, the
service call request/response lines, ...); error paths must print a message and exit non-zero.
"""
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from mm_bringup.process_graph import executable_path, wait_for

ROOT = Path(__file__).resolve().parents[1]
ROS2 = str(executable_path('mm_bringup', 'ros2'))
SIM = '/wheeled_sim'


def ros2(*args, timeout=30.0):
    return subprocess.run([ROS2, *args], capture_output=True, text=True, timeout=timeout)


def start(*args) -> subprocess.Popen:
    return subprocess.Popen([ROS2, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def stop(proc: subprocess.Popen, sig=signal.SIGINT, timeout=15.0):
    if proc.poll() is None:
        os.killpg(proc.pid, sig)
    try:
        return proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        return proc.communicate()


@pytest.fixture(scope='module', autouse=True)
def sim():
    """The simulator, free running (it publishes without commands), started through `ros2 run`."""
    proc = start('run', 'mm_sim', 'wheeled_sim', '--ros-args', '-p', 'lockstep:=false', '-p', 'marker_period:=10')
    try:
        wait_for(lambda: SIM in ros2('node', 'list').stdout.split() or proc.poll() is not None, 60.0,
                 message='wheeled_sim on the graph')
        assert proc.poll() is None, stop(proc)
        yield proc
    finally:
        stop(proc)


def expect_error(result, pattern):
    assert result.returncode != 0, result
    assert re.search(pattern, result.stderr), result.stderr


def test_help_says_it_is_a_subset_and_ros2_is_on_path_after_mm_env():
    out = subprocess.run(['bash', '-c', 'eval "$(./mm env)" && command -v ros2 && ros2 --help'], cwd=ROOT,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    path, text = out.stdout.split('\n', 1)
    assert path == str(ROOT / 'scripts' / 'bin' / 'ros2')
    assert 'not pip-installable' in text and 'real `ros2`' in text
    for verb in ('run', 'pkg executables', 'node list', 'topic list', 'service list', 'param list',
                 'interface show', 'bag info'):
        assert verb in text
    expect_error(ros2('launch', 'x', 'y'), "unknown command 'launch'")


def test_run_and_pkg_executables():
    lines = ros2('pkg', 'executables', 'mm_sim').stdout.splitlines()
    assert 'mm_sim wheeled_sim' in lines and all(line.startswith('mm_sim ') for line in lines)
    assert 'mm_bringup ros2' in ros2('pkg', 'executables').stdout.splitlines()
    expect_error(ros2('pkg', 'executables', 'no_such_pkg'), 'Package not found')
    expect_error(ros2('run', 'mm_sim', 'no_such_exe'), 'No executable found')
    expect_error(ros2('run', 'no_such_pkg', 'x'), "Package 'no_such_pkg' not found")


def test_node_list_and_info():
    out = ros2('node', 'list')
    names = out.stdout.splitlines()
    assert SIM in names and all(re.fullmatch(r'(/[A-Za-z0-9_]+)+', n) for n in names), out.stdout
    assert not any(n.split('/')[-1].startswith('_') for n in names)        # the CLI's own hidden node
    info = ros2('node', 'info', SIM).stdout
    lines = info.splitlines()
    assert lines[0] == SIM
    headers = [line for line in lines if re.fullmatch(r'  [A-Z][A-Za-z ]+:', line)]
    assert headers == ['  Subscribers:', '  Publishers:', '  Service Servers:', '  Service Clients:',
                       '  Action Servers:', '  Action Clients:']
    publishers = info.split('  Publishers:\n')[1].split('  Service Servers:')[0]
    assert '    /wheeled/range/front_left: sensor_msgs/msg/Range\n' in publishers
    assert '    /wheeled/wheel_velocity_controller/commands: std_msgs/msg/Float64MultiArray' in \
        info.split('  Subscribers:\n')[1].split('  Publishers:')[0]
    assert '    /wheeled/reset: mm_msgs/srv/ResetPose' in info.split('  Service Servers:\n')[1]
    expect_error(ros2('node', 'info', '/no_such_node', '--timeout', '1'), "Unable to find node '/no_such_node'")


def test_param_list_get_set_describe_dump():
    listed = ros2('param', 'list', SIM).stdout.splitlines()
    assert '  dt' in listed and '  marker_period' in listed and listed == sorted(listed)
    everything = ros2('param', 'list').stdout
    assert f'{SIM}:\n' in everything
    assert ros2('param', 'get', SIM, 'dt').stdout == 'Double value is: 0.05\n'
    assert ros2('param', 'get', SIM, 'lockstep').stdout == 'Boolean value is: False\n'
    assert ros2('param', 'set', SIM, 'marker_period', '7').stdout == 'Set parameter successful\n'
    assert ros2('param', 'get', SIM, 'marker_period').stdout == 'Integer value is: 7\n'
    expect_error(ros2('param', 'set', SIM, 'marker_period', '-3'), r'Set parameter failed: .*out of range')
    expect_error(ros2('param', 'set', SIM, 'dt', '0.1'), 'Set parameter failed')      # read-only
    described = ros2('param', 'describe', SIM, 'dt').stdout
    assert described.startswith('Parameter name: dt\n  Type: double\n  Description: ')
    assert '    Read only: true' in described and '    Min value: 0.0001' in described
    dumped = yaml.safe_load(ros2('param', 'dump', SIM).stdout)
    assert list(dumped) == [SIM] and dumped[SIM]['ros__parameters']['dt'] == 0.05
    assert dumped[SIM]['ros__parameters']['marker_period'] == 7
    expect_error(ros2('param', 'get', SIM, 'no_such_param'), 'Parameter not set')
    expect_error(ros2('param', 'get', '/no_such_node', 'dt', '--timeout', '1'), 'Unable to find node')


def test_topic_list_info_echo_hz():
    listed = ros2('topic', 'list', '-t').stdout.splitlines()
    assert '/wheeled/range/front_left [sensor_msgs/msg/Range]' in listed
    assert '/clock [rosgraph_msgs/msg/Clock]' in listed
    info = ros2('topic', 'info', '/wheeled/range/front_left')
    assert info.stdout == \
        'Type: sensor_msgs/msg/Range\nPublisher count: 1\nSubscription count: 0\n', info
    verbose = ros2('topic', 'info', '-v', '/wheeled/range/front_left').stdout
    assert verbose.startswith('Type: sensor_msgs/msg/Range\n\nPublisher count: 1\n\nNode name: wheeled_sim\n')
    assert 'Endpoint type: PUBLISHER\n' in verbose and '  Reliability: RELIABLE\n' in verbose
    assert ros2('topic', 'type', '/clock').stdout == 'rosgraph_msgs/msg/Clock\n'
    echoed = ros2('topic', 'echo', '/wheeled/range/front_left', '--once').stdout
    body, rest = echoed.split('---\n')
    assert rest == ''
    msg = yaml.safe_load(body)
    assert list(msg) == ['header', 'radiation_type', 'field_of_view', 'min_range', 'max_range', 'range', 'variance']
    assert msg['header']['frame_id'] == 'front_left_link' and isinstance(msg['range'], float)
    assert re.fullmatch(r'(-?\d+\.\d+(e-?\d+)?\n---\n){2}',
                        ros2('topic', 'echo', '/wheeled/range/front_left', '--field', 'range', '-n', '2').stdout)
    hz = ros2('topic', 'hz', '/clock', '--reports', '1').stdout
    assert re.fullmatch(r'average rate: \d+\.\d{3}\n\tmin: \d+\.\d{3}s max: \d+\.\d{3}s std dev: \d+\.\d{5}s '
                        r'window: \d+\n', hz), hz
    for verb in ('info', 'echo', 'hz', 'type'):
        expect_error(ros2('topic', verb, '/no_such_topic', '--timeout', '1'), "Unknown topic '/no_such_topic'")


def test_topic_pub_reaches_echo():
    echo = start('topic', 'echo', '/cli_test/chatter', 'std_msgs/msg/String', '--once')
    try:
        pub = ros2('topic', 'pub', '-r', '20', '-t', '40', '/cli_test/chatter', 'std_msgs/msg/String',
                   '{data: hello}', '--timeout', '20')
        assert pub.returncode == 0, pub.stderr
        assert pub.stdout.startswith("publisher: beginning loop\npublishing #1: std_msgs.msg.String(data='hello')\n\n")
        out, err = echo.communicate(timeout=20)
    finally:
        stop(echo)
    assert out == 'data: hello\n---\n', err
    expect_error(ros2('topic', 'pub', '--once', '/cli_test/chatter', 'std_msgs/msg/String', '{dat: x}'),
                 "has no field named 'dat'")
    expect_error(ros2('topic', 'pub', '--once', '/cli_test/chatter', 'no_pkg/msg/X'), "Unknown package 'no_pkg'")


def test_service_list_and_call():
    assert '/wheeled/reset [mm_msgs/srv/ResetPose]' in ros2('service', 'list', '-t').stdout.splitlines()
    call = ros2('service', 'call', '/wheeled/reset', 'mm_msgs/srv/ResetPose', '{x: 0.0, y: 0.5, theta: 0.0}')
    assert call.returncode == 0, call.stderr
    lines = call.stdout.splitlines()
    assert 'requester: making request: mm_msgs.srv.ResetPose_Request(x=0.0, y=0.5, theta=0.0)' in lines
    assert lines[lines.index('response:') + 1].startswith('mm_msgs.srv.ResetPose_Response(success=True')
    refused = ros2('service', 'call', '/wheeled/reset', 'mm_msgs/srv/ResetPose', '{x: 0.0, y: 0.0, theta: 0.0}')
    assert 'success=False' in refused.stdout                  # the simulator's own validation answers
    expect_error(ros2('service', 'call', '/wheeled/reset', 'mm_msgs/srv/ResetPose', '{z: 1.0}'),
                 "has no field named 'z'")
    expect_error(ros2('service', 'call', '/no_such_service', 'mm_msgs/srv/ResetPose', '--timeout', '1'),
                 "Service '/no_such_service' is not available")


def test_interface_show():
    shown = ros2('interface', 'show', 'sensor_msgs/msg/Range').stdout
    share = Path(os.environ['VIRTUAL_ENV']) / 'share' / 'sensor_msgs' / 'msg' / 'Range.msg'
    assert shown.startswith(share.read_text().splitlines()[0] + '\n')
    assert 'std_msgs/Header header' in shown and '\tbuiltin_interfaces/Time stamp\n\t\tint32 sec\n' in shown
    srv = ros2('interface', 'show', 'mm_msgs/srv/ResetPose', '--no-comments').stdout.splitlines()
    assert srv[:4] == ['float64 x', 'float64 y', 'float64 theta', '---']
    assert 'builtin_interfaces/Time stamp' in srv and '\tint32 sec' in srv
    expect_error(ros2('interface', 'show', 'no_pkg/msg/X'), "Unknown package 'no_pkg'")
    expect_error(ros2('interface', 'show', 'std_msgs/msg/NoSuchType'), "Unknown interface 'std_msgs/msg/NoSuchType'")


def test_bag_record_info_play_reindex(tmp_path):
    bag = tmp_path / 'bag'
    recorder = start('bag', 'record', '-o', str(bag), '/cli_test/bagged')
    try:
        pub = ros2('topic', 'pub', '-r', '50', '-t', '25', '-p', '0', '/cli_test/bagged', 'std_msgs/msg/String',
                   '{data: recorded}', '--timeout', '20')
        assert pub.returncode == 0, pub.stderr
    finally:
        out, err = stop(recorder)
    assert recorder.returncode == 0, err
    info = ros2('bag', 'info', str(bag))
    assert 'Topic: /cli_test/bagged | Type: std_msgs/msg/String | Count: 25 | Serialization Format: cdr' in \
        info.stdout, info
    assert ros2('bag', 'reindex', str(bag)).returncode == 0
    echo = start('topic', 'echo', '/cli_test/bagged', 'std_msgs/msg/String', '--once')
    try:
        wait_for(lambda: '/cli_test/bagged' in ros2('topic', 'list').stdout, 30.0, message='echo subscribed')
        play = ros2('bag', 'play', str(bag), '-r', '0.2', '--topics', '/cli_test/bagged')   # 2.4 s: time to match
        assert play.returncode == 0, play.stderr
        out, err = echo.communicate(timeout=20)
    finally:
        stop(echo)
    assert out == 'data: recorded\n---\n', err
    expect_error(ros2('bag', 'info', str(tmp_path / 'missing')), 'ros2 bag')


if __name__ == '__main__':
    sys.exit(pytest.main([__file__, '-q']))
