"""Replay: the embedding learned online by image_embedding is rebuilt offline from the recorded bag (images, joint
states and touch readings) and matches: same training frames, same keypoint vectors, same LLE embedding and
collision map, same out-of-sample states."""
import numpy as np
import pytest
from mm_bringup.arm_demo import run_arm_demo
from mm_bringup.process_graph import ProcessGraph
from mm_common.rosbag import iter_messages
from mm_msgs.msg import Contact
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Image, JointState

from mm_manifold.arm_learning import ArmStateLearner
from mm_manifold.image_embedding_node import image_to_array
from mm_manifold.keypoints import KeypointExtractor
from mm_sim.arm_model import ArmModel

EXPLORATION = 200
SEED = 4


def stamp_ns(msg):
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


@pytest.fixture(scope='module')
def recorded(tmp_path_factory):
    work = tmp_path_factory.mktemp('arm_replay')
    bag, model_path = work / 'bag', work / 'model.npz'
    with ProcessGraph(log_dir=work / 'logs') as graph:
        recorder = graph.start('mm_bringup', 'recorder', {
            'output': str(bag), 'discovery_period': 0.05,
            'topics': ['/arm/(camera/image_raw|joint_states|contact)']})
        summary = run_arm_demo(graph, log=print, timeout_s=120.0, object_seed=SEED, exploration_steps=EXPLORATION,
                               embedding_params={'model_path': str(model_path)})
        assert graph.stop(recorder) == 0, graph.log_tail(recorder)
    assert summary['phase'] in ('GOAL_REACHED', 'FAILED')
    return bag, ArmStateLearner.load(model_path)


def frames_from_bag(bag):
    """stamp -> (image, joints, contact), joined by the frame stamp every message carries, as the node does."""
    images, joints, contacts = {}, {}, {}
    for m in iter_messages(bag):
        if m.topic == '/arm/camera/image_raw':
            img = deserialize_message(m.data, Image)
            images[stamp_ns(img)] = image_to_array(img, 400)
        elif m.topic == '/arm/joint_states':
            js = deserialize_message(m.data, JointState)
            joints[stamp_ns(js)] = np.array(js.position)
        elif m.topic == '/arm/contact':
            touch = deserialize_message(m.data, Contact)
            contacts[stamp_ns(touch)] = touch.arm_in_contact_at_frame      # image_embedding's default label
    return {stamp: (images[stamp], joints[stamp], value) for stamp, value in contacts.items()
            if stamp in images and stamp in joints}


def test_rebuilt_embedding_matches_the_online_fit(recorded):
    bag, online = recorded
    frames = frames_from_bag(bag)
    stamps = online.train_stamps_.tolist()
    assert len(stamps) == EXPLORATION
    missing = [s for s in stamps if s not in frames]
    assert not missing, f'{len(missing)} training frames are not in the bag'
    # the same joint angles and touch labels as the node paired online
    np.testing.assert_array_equal(np.array([frames[s][1] for s in stamps]), online.train_joints_)
    np.testing.assert_array_equal(np.array([frames[s][2] for s in stamps]), online.train_contact_)

    extractor = KeypointExtractor()
    kps = [extractor(frames[s][0]) for s in stamps]
    params = online.get_params()
    params['grid_shape'] = tuple(params['grid_shape'])
    rebuilt = ArmStateLearner(**params).fit(kps, online.train_joints_, online.train_contact_, stamps)
    assert rebuilt.vectorizer_.n_labels_ == online.vectorizer_.n_labels_
    np.testing.assert_allclose(rebuilt.vectorizer_.training_vectors_, online.vectorizer_.training_vectors_,
                               atol=1e-4, equal_nan=True)
    np.testing.assert_allclose(rebuilt.train_vectors_, online.train_vectors_, atol=1e-4)
    spread = np.abs(online.lle_.embedding_).max()
    np.testing.assert_allclose(rebuilt.lle_.embedding_, online.lle_.embedding_, atol=1e-6 * max(spread, 1.0))
    np.testing.assert_allclose(rebuilt.pca_.embedding_, online.pca_.embedding_, atol=1e-6)
    assert rebuilt.selection_['model'] == online.selection_['model']
    assert rebuilt.selection_['threshold'] == pytest.approx(online.selection_['threshold'], rel=1e-6, abs=1e-9)
    np.testing.assert_allclose(rebuilt.train_closeness_, online.train_closeness_, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(rebuilt.collision_map_, online.collision_map_)

    # frames the fit never saw map out of sample to the same states with both models: the planner's moves when it
    # moved, else frames of the same scene rendered at random joint angles (the episode may end without a plan)
    later = [frames[s][0] for s in sorted(frames) if s > max(stamps)][:10]
    if len(later) < 10:
        scene = ArmModel(random_state=SEED)
        later += [scene.render(q) for q in scene.sample_joints(10 - len(later), np.random.default_rng(SEED))]
    for image in later:
        kp = extractor(image)
        a, b = online.transform(kp), rebuilt.transform(kp)
        np.testing.assert_allclose(a['embedding'], b['embedding'], atol=1e-6 * max(spread, 1.0))
        assert a['collision'] == b['collision']
