"""The arm experiment as separate processes: arm_sim (lockstep) + image_embedding + dp_planner + recorder.
Short exploration, online learning, then a goal with the object in the way: the planner must reach it without the
touch sensor ever firing, and no learning/control node may subscribe to a ground-truth topic."""
import numpy as np
import pytest
from mm_bringup.arm_demo import run_arm_demo
from mm_bringup.process_graph import ProcessGraph
from mm_common.rosbag import read_metadata

from mm_manifold.arm_learning import ArmStateLearner

EXPLORATION = 300


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


def test_plans_around_the_object_without_contact(episode):
    summary, _, _ = episode
    assert summary['object_in_way'], 'the chosen goal must need a way around the object'
    assert summary['reached'], summary
    assert summary['phase'] == 'GOAL_REACHED'
    assert summary['contact_count'] == 0
    # ground truth agrees: the hand never came within the contact distance (18 + 20 px) while executing
    assert summary['min_hand_object_distance_px'] > 38.0
    assert summary['exploration_contact_frames'] > 0        # exploration did touch: that is how it learned
    assert summary['execution_steps'] >= 3


def test_no_learning_or_control_node_subscribes_to_ground_truth(episode):
    summary, _, _ = episode
    gt = summary['ground_truth_subscribers']
    assert {'/arm/ground_truth/object_pose', '/arm/ground_truth/state'} <= set(gt)
    for topic, names in gt.items():
        assert not {'image_embedding', 'dp_planner', 'arm_sim'} & set(names), (topic, names)
        assert set(names) <= {'recorder', 'arm_demo_driver'}, (topic, names)


def test_the_episode_is_recorded_and_the_model_saved(episode):
    summary, bag, model_path = episode
    counts = {t['topic_metadata']['name']: t['message_count'] for t in read_metadata(bag)['topics_with_message_count']}
    # the recorder may join a few steps late (topic discovery), never more
    assert counts['/arm/camera/image_raw'] >= EXPLORATION + summary['execution_steps'] - 20
    assert abs(counts['/arm/joint_states'] - counts['/arm/contact']) <= 1
    assert counts['/arm/embedding/collision_map'] >= 1
    model = ArmStateLearner.load(model_path)
    assert model.n_frames_ == EXPLORATION           # the first fit starts as soon as this many frames are in
    assert 0 < model.train_contact_.sum() < EXPLORATION
    assert np.all(model.train_stamps_ >= 0) and len(set(model.train_stamps_.tolist())) == EXPLORATION
