"""Same seeds, same answer, idle or busy: the wall exploration + learning through the graph (wheeled_sim +
sensor_manifold + switching_controller as processes) is run twice with the same seeds, the second time beside a
CPU-burning process. No wall-clock timeout may decide what is learned, so the model the run ends with (the first
ready one, after the extra exploration the models before it asked for) must be identical array for array, byte for
byte, and so must every command of the exploration that produced its data. The same holds for the three nodes
composed in one process (mm_bringup wheeled_container): composition changes the speed, not the data."""
import subprocess
import sys

import numpy as np
import pytest
from mm_common.ros_harness import RosHarness
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray

from mm_bringup.wall_graph import WallGraph

EXPLORATION = 600            # enough samples for a fit (learn_after); with the extra rounds, two runs take about a minute
SEED = 3
BURN_SECONDS = 150           # the burner ends by itself even if this test is killed
COMMANDS = '/wheeled/wheel_velocity_controller/commands'
QOS = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)     # holds every command until drained


def run_once(work, composed=False):
    """Explore and learn until the controller stops exploring; returns (saved model arrays, exploration commands,
    samples of the last model)."""
    model_file = work / 'wall_model.npz'
    ros = RosHarness()
    try:
        # Subscribed before the loop starts: WallGraph starts the learner (which closes the loop) only once this
        # node has subscribed to the controller's commands, so the first command is recorded too.
        commands = []
        listener = ros.node('determinism_listener')
        listener.create_subscription(Float64MultiArray, COMMANDS, lambda m: commands.append(tuple(m.data)), QOS)
        with WallGraph(work, exploration_steps=EXPLORATION, seed=SEED, model_path=model_file,
                       recorder='determinism_listener', recorded_topics=[COMMANDS], composed=composed) as wall:
            # A model that is not ready sends the controller exploring on and the learner refits after more
            # samples, so the first model is no place to stop (where the graph stops would depend on timing). The
            # run ends where the controller stops exploring, at the first ready model; the learner saved it before
            # publishing it, and no sample, so no refit, follows. It was fitted on one reading per command (the
            # first before any command; the last command's reading came after the fit began); status, model and
            # commands may arrive in any order.
            wall.wait_learned(240.0)
            wall.spin_until(lambda: wall.model_msg is not None and wall.model_msg.ready, 30.0, 'the ready model')
            samples = wall.model_msg.samples
            assert ros.spin_until(lambda: len(commands) >= samples, 30.0), f'{len(commands)} of {samples} commands'
            explored = list(commands)
    finally:
        ros.close()
    with np.load(model_file) as data:
        arrays = {k: (data[k].dtype.str, data[k].shape, data[k].tobytes()) for k in data.files}
    return arrays, explored, samples


@pytest.fixture(scope='module')
def idle_run(tmp_path_factory):
    return run_once(tmp_path_factory.mktemp('idle'))


def assert_same_run(run, reference):
    arrays, explored, samples = run
    arrays_ref, explored_ref, samples_ref = reference
    assert len(explored_ref) == samples_ref >= EXPLORATION
    # a listener whose endpoint matched late misses the first commands: that shows as a shift, anything else is
    # non-determinism (seen once, unreproduced: which one it was is what this message tells next time)
    shift = next((k for k in range(1, 50) if explored[k:] == explored_ref[:-k]
                  or explored_ref[k:] == explored[:-k]), None)
    assert explored == explored_ref, f'shifted by {shift}' if shift else 'not a shift'
    assert samples == samples_ref
    assert sorted(arrays) == sorted(arrays_ref)
    for key in arrays_ref:
        assert arrays[key] == arrays_ref[key], f'model array {key} differs'


def test_same_seeds_give_the_same_model_and_commands_idle_and_under_load(tmp_path, idle_run):
    burner = subprocess.Popen([sys.executable, '-c', 'import time\nend = time.monotonic() + %d\n'
                               'while time.monotonic() < end:\n    sum(i * i for i in range(10000))' % BURN_SECONDS])
    try:
        busy = run_once(tmp_path / 'busy')
        assert burner.poll() is None, 'the burner ended before the busy run did: it ran without load'
    finally:
        burner.kill()
        burner.wait()
    assert_same_run(busy, idle_run)


def test_the_composed_loop_learns_exactly_what_three_processes_learn(tmp_path, idle_run):
    assert_same_run(run_once(tmp_path / 'composed', composed=True), idle_run)
