"""The arm experiment as separate processes: arm_sim (lockstep) + image_embedding + dp_planner + recorder.
Short exploration with the object moving, one fit that is kept, then re-placements the model never saw, each with the
object in the way: image_embedding builds a map of the new placement's frame and the planner plans on it before
moving (no more frames than that one), never takes a move between cells that map predicts to collide, and every
outcome names its goal and says why; no learning/control node subscribes to a ground-truth topic. Whether the learned
map is right (contact of any arm part along the executed motion, simulator ground truth) is the arm_reach benchmark's
figure: measured and reported there, not asserted here."""
import numpy as np
import pytest
from mm_bringup.arm_demo import run_arm_demo
from mm_bringup.process_graph import ProcessGraph
from mm_common.rosbag import iter_messages, read_metadata
from mm_msgs.msg import CollisionMap
from mm_planner.value_iteration import MOVES, JointGrid
from rclpy.serialization import deserialize_message

from mm_manifold.arm_learning import ArmStateLearner

EXPLORATION = 500


@pytest.fixture(scope='module')
def episode(tmp_path_factory):
    work = tmp_path_factory.mktemp('arm_graph')
    bag, model_path = work / 'bag', work / 'model.npz'
    with ProcessGraph(log_dir=work / 'logs') as graph:
        recorder = graph.start('mm_bringup', 'recorder', {
            'output': str(bag), 'discovery_period': 0.05,
            'topics': ['/arm/(camera/image_raw|joint_states|contact|ground_truth/.*|planner/status|'
                       'embedding/collision_map)']})
        summary = run_arm_demo(graph, log=print, timeout_s=150.0, object_seed=3, exploration_steps=EXPLORATION,
                               embedding_params={'model_path': str(model_path)})
        assert graph.stop(recorder) == 0, graph.log_tail(recorder)
    return summary, bag, model_path


def test_plans_before_moving_for_re_placed_objects(episode):
    summary, _, _ = episode
    assert summary['object_in_way'], 'the chosen goals must need a way around the object'
    assert summary['exploration_placements'] > 3             # the object moved while the robot explored
    assert summary['exploration_contact_frames'] > 0        # exploration did touch: that is how it learned
    placements = summary['placements']
    assert len(placements) == 2
    for p in placements:
        assert p['new_frames'] == 1, p                       # planned on the placement's own frame, before moving
        assert p['goal_stamp'] > 0
        assert p['outcome'] in ('GOAL_REACHED', 'FAILED') and p['detail'], p
        if p['outcome'] == 'FAILED':
            assert p['steps'] == 0 and 'no collision-free path' in p['detail'], p     # refused before moving
        else:
            assert p['steps'] == len(p['executed_joints']) >= 3, p


def test_no_learning_or_control_node_subscribes_to_ground_truth(episode):
    summary, _, _ = episode
    gt = summary['ground_truth_subscribers']
    assert '/arm/ground_truth/state' in gt
    for topic, names in gt.items():
        assert not {'image_embedding', 'dp_planner', 'arm_sim'} & set(names), (topic, names)
        assert set(names) <= {'recorder', 'arm_demo_driver'}, (topic, names)
    assert 'arm_demo_driver' in gt['/arm/ground_truth/state']       # the evaluator reads it, nobody else


def test_the_arm_never_takes_a_move_the_map_of_its_placement_predicts_to_collide(episode):
    summary, bag, _ = episode
    maps = {}
    for m in iter_messages(bag, topics=['/arm/embedding/collision_map']):
        msg = deserialize_message(m.data, CollisionMap)
        maps[msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec] = msg
    grid = JointGrid((-3.2, -0.8), (0.0, 2.2), 8, 12)
    for p in summary['placements']:
        m = maps[p['placement_stamp']]                       # built from the placement's own frame
        assert len(m.blocked_moves) == 8 * 12 * 4
        blocked = np.array(m.blocked_moves, bool).reshape(8, 12, 4)     # (row * cols + col) * 4 + move
        cells = [tuple(p['start_cell'])] + [grid.cell_of(q) for q in p['executed_joints']]
        moves = [(a, b) for a, b in zip(cells, cells[1:]) if a != b]
        for a, b in moves:
            k = int(np.flatnonzero((MOVES == np.subtract(b, a)).all(axis=1))[0])       # adjacent: one move
            assert not blocked[a[0], a[1], k], (p['seed'], a, b)


def test_the_episode_is_recorded_and_the_model_saved(episode):
    summary, bag, model_path = episode
    counts = {t['topic_metadata']['name']: t['message_count'] for t in read_metadata(bag)['topics_with_message_count']}
    # the recorder may join a few steps late (topic discovery), never more
    assert counts['/arm/camera/image_raw'] >= EXPLORATION + summary['execution_steps'] - 20
    assert counts['/arm/embedding/collision_map'] >= 1 + len(summary['placements'])   # after the fit + per goal
    assert abs(counts['/arm/joint_states'] - counts['/arm/contact']) <= 1
    model = ArmStateLearner.load(model_path)
    assert model.n_frames_ == EXPLORATION           # the first fit starts as soon as this many frames are in
    assert 0 < model.train_contact_.sum() < EXPLORATION
    assert np.all(model.train_stamps_ >= 0) and len(set(model.train_stamps_.tolist())) == EXPLORATION
