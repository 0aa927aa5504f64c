"""node_utils: runtime parameter checks, throttled input rejection, and run_node's clean exit on SIGINT/SIGTERM."""
import array
import os
import signal
import subprocess
import sys
import time

import pytest
from rcl_interfaces.msg import Parameter as ParameterMsg, ParameterType, ParameterValue
from rclpy.duration import Duration
from rclpy.parameter import Parameter

from mm_common.node_utils import (InputRejections, array_problem, check_parameters, declare, ordered, ordered_pair,
                                  reject_input, reject_non_finite, rejected_inputs)
from mm_common.ros_harness import RosHarness


def _runtime_double_array(name, values):
    """A parameter exactly as rclpy's parameter service hands it to on-set callbacks (array.array, not list)."""
    msg = ParameterMsg(name=name, value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE_ARRAY,
                                                       double_array_value=values))
    return Parameter.from_parameter_msg(msg)


def test_reject_non_finite_checks_every_element_of_runtime_arrays():
    param = _runtime_double_array('pose', [0.0, float('nan'), 1.0])
    assert isinstance(param.value, array.array)
    result = reject_non_finite([param])
    assert not result.successful and 'pose[1]' in result.reason
    assert not reject_non_finite([Parameter('gain', value=float('inf'))]).successful
    assert reject_non_finite([_runtime_double_array('pose', [0.0, 1.0]), Parameter('name', value='nan')]).successful


@pytest.fixture
def harness():
    h = RosHarness()
    yield h
    h.close()


def test_cross_parameter_checks_see_current_and_proposed_values(harness):
    node = harness.node('checks')
    declare(node, 'low', 1.0, 'lower bound')
    declare(node, 'high', 2.0, 'upper bound')
    declare(node, 'span', [0.0, 1.0], 'a [low, high] pair')
    checks = [ordered('low', 'high'), ordered_pair('span')]
    node.add_on_set_parameters_callback(lambda params: check_parameters(node, params, checks))
    result = node.set_parameters([Parameter('low', value=3.0)])[0]
    assert not result.successful and 'low=3.0 must be <= high=2.0' in result.reason
    assert node.set_parameters_atomically([Parameter('low', value=3.0), Parameter('high', value=4.0)]).successful
    assert not node.set_parameters([Parameter('span', value=[1.0, 0.5])])[0].successful
    assert not node.set_parameters([Parameter('span', value=[0.0, float('nan')])])[0].successful
    assert node.get_parameter('span').value == [0.0, 1.0]


def test_reject_input_counts_per_source_and_throttles(harness):
    node = harness.node('rejects')
    for _ in range(5):
        reject_input(node, 'a', 'bad length')
    assert reject_input(node, 'b', 'nan') == 1
    assert rejected_inputs(node) == {'a': 5, 'b': 1}
    logged = []
    rejections = InputRejections(node, period=60.0)
    rejections.logger = type('L', (), {'warn': lambda self, text: logged.append(text)})()
    for _ in range(3):
        rejections('topic', 'wrong size')
    assert len(logged) == 1 and 'rejected input on topic: wrong size' in logged[0]
    assert rejections.total == 3


def test_array_problem_says_what_is_wrong():
    assert array_problem([1.0, 2.0], 'cmd', length=2, bounds=(-3, 3)) == ''
    assert 'expected 2 values, got 3' in array_problem([1.0, 2.0, 3.0], 'cmd', length=2)
    assert 'cmd[1] is nan' in array_problem([1.0, float('nan')], 'cmd')
    assert 'outside' in array_problem([1.0, 1e308], 'cmd', bounds=(-3, 3))


_BUSY_NODE = r'''
import faulthandler
import signal
import sys
import numpy     # starts BLAS threads before run_node: a signal may be delivered to one of them
faulthandler.register(signal.SIGUSR1, all_threads=True)     # the test asks for every thread's stack if it hangs
from std_msgs.msg import Float64MultiArray
from rclpy.node import Node
from mm_common.node_utils import run_node

class Busy(Node):
    """Publishes and receives as fast as the executor allows, so a signal lands mid-spin and mid-publish."""
    def __init__(self):
        super().__init__('busy_signal_target')
        self.pub = self.create_publisher(Float64MultiArray, 'busy', 10)
        self.create_subscription(Float64MultiArray, 'busy', lambda m: None, 10)
        self.create_timer(0.0005, self.tick)
        self.ticks = 0
    def tick(self):
        self.ticks += 1
        if self.ticks == 20:
            print('spinning', flush=True)
        self.pub.publish(Float64MultiArray(data=[float(self.ticks)] * 64))

run_node(Busy, sys.argv)
'''


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM, signal.SIGHUP], ids=['SIGINT', 'SIGTERM', 'SIGHUP'])
def test_run_node_exits_cleanly_on_signals_mid_spin(sig, tmp_path):
    """Many signals at varying points of a busy spin: every run exits 0 without a traceback."""
    script = tmp_path / 'busy.py'
    script.write_text(_BUSY_NODE)
    failures = []
    for attempt in range(6):
        proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True, start_new_session=True)
        assert proc.stdout.readline().strip() == 'spinning', proc.stderr.read()
        time.sleep(0.003 * attempt)         # vary where in the spin loop the signal lands
        proc.send_signal(sig)
        if attempt % 2:
            proc.send_signal(sig)           # a second signal during clean-up must not matter
        try:
            out, err = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            # Where it hangs (seen once in about 500 runs, 6 December, a fresh-clone run under load): every thread's
            # Python stack, which faulthandler writes even while the main thread is blocked in C.
            proc.send_signal(signal.SIGUSR1)
            time.sleep(1.0)
            os.killpg(proc.pid, signal.SIGKILL)
            out, err = proc.communicate()
            failures.append((attempt, 'hung', err[-3000:]))
            continue
        if proc.returncode != 0 or 'Traceback' in err:
            failures.append((attempt, proc.returncode, err[-800:]))
    assert not failures, failures


_STRICT_NODE = r'''
import sys
from rclpy.node import Node
from mm_common.node_utils import declare, run_node

class Strict(Node):
    def __init__(self):
        super().__init__('strict_parameters')
        declare(self, 'rate', 1.0, 'a rate', min_value=0.0, max_value=10.0)

run_node(Strict, sys.argv)
'''


@pytest.mark.parametrize('value', ['nan', '-1.0', "'text'"])
def test_run_node_refuses_a_bad_start_up_parameter_in_one_line(value, tmp_path):
    script = tmp_path / 'strict.py'
    script.write_text(_STRICT_NODE)
    proc = subprocess.run([sys.executable, str(script), '--ros-args', '-p', f'rate:={value}'], capture_output=True,
                          text=True, timeout=30)
    assert proc.returncode == 2, proc.stderr
    assert 'Traceback' not in proc.stderr and 'cannot start' in proc.stderr and 'rate' in proc.stderr


_SLOW_SUBSCRIBER = r'''
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray
rclpy.init()
node = rclpy.create_node('slow_subscriber')
node.create_subscription(Float64MultiArray, 'acked', lambda m: None,
                         QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
print('subscribed', flush=True)
rclpy.spin(node)
'''


def test_stopping_nodes_wait_for_a_lagging_subscriber_to_acknowledge_within_the_cap(tmp_path):
    """run_nodes waits, before destroying the publishers, until reliable subscribers acknowledged what was published
    (a lagging recorder would otherwise lose the last messages), and never longer than the cap: here the subscriber
    is a process stopped with SIGSTOP, which acknowledges nothing until SIGCONT."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Float64MultiArray
    from mm_common.node_utils import wait_for_acknowledgements
    script = tmp_path / 'slow.py'
    script.write_text(_SLOW_SUBSCRIBER)
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    h = RosHarness()
    try:
        assert proc.stdout.readline().strip() == 'subscribed', proc.stderr.read()
        node = h.node('publisher')
        pub = node.create_publisher(Float64MultiArray, 'acked', QoSProfile(depth=1000,
                                                                           reliability=ReliabilityPolicy.RELIABLE))
        assert h.spin_until(lambda: pub.get_subscription_count() == 1, timeout=10)
        proc.send_signal(signal.SIGSTOP)
        for k in range(200):
            pub.publish(Float64MultiArray(data=[float(k)] * 100))
        began = time.monotonic()
        wait_for_acknowledgements([node], 0.5)
        assert 0.4 < time.monotonic() - began < 2.0             # waited, but not beyond the cap
        assert not pub.wait_for_all_acked(Duration(seconds=0))
        proc.send_signal(signal.SIGCONT)
        began = time.monotonic()
        wait_for_acknowledgements([node], 10.0)
        assert time.monotonic() - began < 5.0 and pub.wait_for_all_acked(Duration(seconds=0))
    finally:
        proc.send_signal(signal.SIGCONT)
        proc.kill()
        proc.communicate()
        h.close()
