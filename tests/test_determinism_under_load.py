"""Same seeds, same answer, idle or busy: the wall exploration + learning through the graph (wheeled_sim +
sensor_manifold + switching_controller as processes) is run twice with the same seeds, the second time beside a
CPU-burning process. No wall-clock timeout may decide what is learned, so the first saved model must be identical
array for array, byte for byte, and so must every command of the exploration episode that produced its data."""
import subprocess
import sys

import numpy as np
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray

from mm_bringup.wall_graph import WallGraph

EXPLORATION = 600            # enough samples for a fit (learn_after), small enough for two runs in about a minute
SEED = 3
BURN_SECONDS = 150           # the burner ends by itself even if this test is killed
QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def run_once(work):
    """Explore and learn until the first model arrives; returns (saved model arrays, exploration commands)."""
    model_file = work / 'wall_model.npz'
    with WallGraph(work, exploration_steps=EXPLORATION, seed=SEED, model_path=model_file) as wall:
        commands = []
        wall.node.create_subscription(Float64MultiArray, 'wheeled/wheel_velocity_controller/commands',
                                      lambda m: commands.append(tuple(m.data)), QOS)
        # The learner saves before it publishes; the graph is stopped at the first model, before any refit.
        wall.spin_until(lambda: wall.model_msg is not None, 240.0, 'the first model')
        explored = commands[:EXPLORATION]
    with np.load(model_file) as data:
        arrays = {k: (data[k].dtype.str, data[k].shape, data[k].tobytes()) for k in data.files}
    return arrays, explored, wall.model_msg.samples


def test_same_seeds_give_the_same_model_and_commands_idle_and_under_load(tmp_path):
    arrays_idle, explored_idle, samples_idle = run_once(tmp_path / 'idle')
    burner = subprocess.Popen([sys.executable, '-c', 'import time\nend = time.monotonic() + %d\n'
                               'while time.monotonic() < end:\n    sum(i * i for i in range(10000))' % BURN_SECONDS])
    try:
        arrays_busy, explored_busy, samples_busy = run_once(tmp_path / 'busy')
        assert burner.poll() is None, 'the burner ended before the busy run did: it ran without load'
    finally:
        burner.kill()
        burner.wait()
    assert len(explored_idle) == EXPLORATION and samples_idle >= EXPLORATION
    assert explored_busy == explored_idle
    assert samples_busy == samples_idle
    assert sorted(arrays_busy) == sorted(arrays_idle)
    for key in arrays_idle:
        assert arrays_busy[key] == arrays_idle[key], f'model array {key} differs between the idle and busy run'
