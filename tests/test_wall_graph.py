"""Section 2 through the graph: wheeled_sim + sensor_manifold + switching_controller as processes, with a recorder.

One module-scoped run: the robot explores and learns in the graph, then the paper's task runs (start facing the wall
at 1 m, goal shown as the sensor-2 reading 0.25 m from the wall, parallel to it), with the learner keeping no file (as
in the shipped sensor_manifold.yaml): the controller gets the model as a message only. Checked: the task is reached
across a blind stretch and ends parallel to the wall; no learning or control node subscribes to ground truth; and the
grid relearnt offline from the recorded bag (replay) is the grid of the model message the manifold node published.
"""
import math

import numpy as np
import pytest
from mm_common.rosbag import iter_messages
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Range
from std_msgs.msg import Float64MultiArray

from mm_bringup.process_graph import ProcessGraph
from mm_bringup.wall_experiment import PAPER_GOAL_POSES, PAPER_START, explore, sensor2_goal_reading
from mm_bringup.wall_graph import WallGraph
from mm_manifold.sample_assembly import Sample, SampleAssembler
from mm_manifold.sensor_manifold import SensorManifoldModel
from mm_common.wheeled_sensors import SENSOR2, SENSOR_NAMES
from mm_sim.wheeled_model import WheeledRobot

EXPLORATION = 10000
GOAL_POSE = PAPER_GOAL_POSES['overlap']
TOLERANCE = 0.005
RECORDED = [f'/wheeled/range/{n}' for n in SENSOR_NAMES] + ['/wheeled/wheel_velocity_controller/commands']
ROBOT_NODES = {'wheeled_sim', 'sensor_manifold', 'switching_controller'}


@pytest.fixture(scope='module')
def run(tmp_path_factory):
    work = tmp_path_factory.mktemp('wall_graph')
    bag = work / 'bag'
    robot = WheeledRobot()
    with ProcessGraph(log_dir=work / 'logs') as graph:
        recorder = graph.start('mm_bringup', 'recorder', {
            'output': str(bag), 'discovery_period': 0.05,
            'topics': ['/wheeled/range/.*', '/wheeled/wheel_velocity_controller/commands']})
        with WallGraph(work, exploration_steps=EXPLORATION, graph=graph, recorder='recorder',
                       recorded_topics=RECORDED, model_path='') as wall:
            wall.wait_learned(timeout=900.0)
            wall.watch_ground_truth()
            topics = wall.node.get_topic_names_and_types()
            ground_truth = {name: sorted(i.node_name for i in wall.node.get_subscriptions_info_by_topic(name))
                            for name, _ in topics if 'ground_truth' in name}
            episode = wall.run_episode(PAPER_START, sensor2_goal_reading(robot, GOAL_POSE), TOLERANCE)
            model = wall.model_msg
        assert graph.stop(recorder) == 0, graph.log_tail(recorder)
    assert not list(work.glob('*.npz'))                          # nothing persisted: the model went as a message
    return dict(episode=episode, ground_truth=ground_truth, bag=bag, model=model, robot=robot)


def test_no_learning_or_control_node_subscribes_to_ground_truth(run):
    assert '/wheeled/ground_truth/odom' in run['ground_truth']
    for topic, subscribers in run['ground_truth'].items():
        assert not ROBOT_NODES & set(subscribers), f'{topic} is read by {subscribers}'
        assert 'wall_experimenter' in subscribers or topic != '/wheeled/ground_truth/odom'


def test_paper_task_crosses_the_blind_region_and_ends_parallel(run):
    ep, robot = run['episode'], run['robot']
    assert ep.reached, ep.detail
    goal = sensor2_goal_reading(robot, GOAL_POSE)
    final = robot.read(ep.poses[-1], noisy=False)[list(SENSOR2)]
    assert np.max(np.abs(final - goal)) < TOLERANCE
    # parallel as far as the goal says: within its tolerance both side readings allow |heading| up to
    # atan(2 x tolerance / the side sensors' spacing) (tests/test_switching_controller.py, the same task in process)
    side = [robot.sensors[i] for i in SENSOR2]
    heading = abs(math.atan2(math.sin(ep.poses[-1][2]), math.cos(ep.poses[-1][2])))
    assert heading < math.atan(2 * TOLERANCE / abs(side[0].x - side[1].x))
    assert any(ep.blind) and ep.longest_blind[0] >= 1    # steps with no group in range, as the controller counts them
    spaces = [s for i, s in enumerate(ep.spaces) if i == 0 or s != ep.spaces[i - 1]]
    assert spaces[0] == 1 and 2 in spaces and spaces[-1] == 3, spaces


def recorded_samples(bag):
    """The samples the learner took, rebuilt from the bag (see test_grid_relearnt_from_the_bag_is_the_online_grid)."""
    assembler, samples = SampleAssembler(len(SENSOR_NAMES)), []
    for record in sorted(iter_messages(bag), key=lambda r: r.publish_time_ns):
        topic, data = record.topic, record.data
        if topic.startswith('/wheeled/range/'):
            msg = deserialize_message(data, Range)
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            events = assembler.reading(SENSOR_NAMES.index(topic.rsplit('/', 1)[1]), stamp, msg.range)
        else:
            events = assembler.command(deserialize_message(data, Float64MultiArray).data)
        samples += [e for e in events if isinstance(e, Sample)]
    return samples


def test_grid_relearnt_from_the_bag_is_the_online_grid(run):
    """Replay: the recorded readings and commands, in the order they were published, go through the sample assembly
    the node uses (mm_manifold.sample_assembly: steps by stamp, each sample's command, chain breaks where a step did
    not follow exactly one command, re-sent steps and re-sent commands included), and the model is refitted with the
    node's hyperparameters. Publication order (the writers' source timestamps, one host clock) is the causal order
    of the loop; the bag's receive times come from the recorder's own readers, and under load one of its Range
    readers once ran hundreds of steps apart from the others (a fresh-clone run of 2 December), which in receive
    order split steps beyond the assembler's window although the node itself had taken every step."""
    samples = recorded_samples(run['bag'])
    online = run['model']
    n = online.samples
    assert len(samples) >= n
    R = np.array([s.reading for s in samples[:n]], dtype=float)
    U = np.array([s.command if s.command is not None else np.zeros(2) for s in samples[1:n]] + [np.zeros(2)])
    continuous = np.array([s.follows for s in samples[1:n]] + [False])
    replayed = SensorManifoldModel(online.dt, online.grid_rows, online.grid_cols,
                                   jacobian_degree=online.jacobian_degree).fit(R, U, continuous)
    np.testing.assert_allclose(replayed.grid_.nodes_.ravel(), online.grid_nodes, atol=1e-9)
    assert replayed.n_excursions_ == online.excursions
    np.testing.assert_allclose(replayed.virtual_.overlap_sensor2_.ravel(), online.overlap_sensor2, atol=1e-9)


def test_the_offline_runner_explores_exactly_as_the_graph(run):
    """The offline runner (mm_bringup.wall_experiment, which the benchmark's in-process cells and the tuning scripts
    use) rounds each reading to float32 as sensor_msgs/Range carries it, so on the graph's seed and start its
    WallAgent sends the graph's exploration commands one for one: offline figures are the graph's."""
    steps = 3000
    samples = recorded_samples(run['bag'])
    graph = np.array([s.command for s in samples[1:steps + 1]], dtype=float)
    offline = explore(run['robot'], steps, start=PAPER_START, random_state=0).commands
    np.testing.assert_array_equal(graph, offline)
