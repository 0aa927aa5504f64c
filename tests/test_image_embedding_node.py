"""The image embedding node in-process: bad images, joint states, touch readings, map requests and parameter updates
are rejected with the node still working; frames are learned online; collision maps are built for the newest frame
after the fit and for a requested frame, stamped with it and latched; the model is saved and reloaded; a corrupt or
mismatched model file means learning again."""
import math

import numpy as np
from mm_common.ros_harness import RosHarness
from mm_msgs.msg import CollisionMap, Contact, EmbeddingState
from mm_common.node_utils import rejected_inputs
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import Header, String

from mm_bringup.arm_evaluation import sample_exploration_joints
from mm_manifold.arm_learning import ArmStateLearner
from mm_manifold.image_embedding_node import ImageEmbeddingNode, model_score
from mm_sim.arm_model import ArmModel

QOS = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
N_FRAMES = 90


def image_msg(frame, k, encoding='rgb8'):
    img = Image(height=frame.shape[0], width=frame.shape[1], encoding=encoding, step=frame.shape[1] * 3)
    img.header.stamp.sec = k
    img.data = frame.tobytes()
    return img


def make_rig(ros, params, box=None):
    """The node, publishers of its inputs and what it published; the arm_sim's robot description (over `box`, the
    simulated arm's joint box by default) is latched and taken before this returns."""
    node = ros.add(ImageEmbeddingNode(context=ros.context, parameter_overrides=[
        Parameter(k, value=v) for k, v in params.items()]))
    client = ros.node('embedding_test_client')
    seen = {'state': [], 'map': []}
    client.create_subscription(EmbeddingState, 'arm/embedding/state', seen['state'].append, QOS)
    client.create_subscription(CollisionMap, 'arm/embedding/collision_map', seen['map'].append, LATCHED)
    pubs = dict(image=client.create_publisher(Image, 'arm/camera/image_raw', QOS),
                joints=client.create_publisher(JointState, 'arm/joint_states', QOS),
                contact=client.create_publisher(Contact, 'arm/contact', QOS),
                request=client.create_publisher(Header, 'arm/embedding/map_request', QOS),
                description=client.create_publisher(String, 'arm/robot_description', LATCHED))
    assert ros.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), timeout=10)
    arm = ArmModel(random_state=0) if box is None else ArmModel(joint_limits=box, random_state=0)
    pubs['description'].publish(String(data=arm.robot_description(4.0)))
    assert ros.spin_until(lambda: node.learner_params['joint_limits'] is not None, timeout=10)
    assert np.allclose(node.learner_params['joint_limits'], arm.joint_limits)
    return node, pubs, seen


def test_bad_images_are_rejected_and_the_node_keeps_running():
    ros = RosHarness()
    try:
        node, pubs, seen = make_rig(ros, {})
        good = np.zeros((400, 400, 3), np.uint8)
        pubs['image'].publish(image_msg(good, 1, encoding='32FC1'))
        pubs['image'].publish(image_msg(np.zeros((300, 400, 3), np.uint8), 2))
        broken = image_msg(good, 3)
        broken.data = bytes(100)
        pubs['image'].publish(broken)
        assert ros.spin_until(lambda: node.images_rejected == 3)
        pubs['image'].publish(image_msg(ArmModel(random_state=0).render([-2.0, 1.0]), 4))
        assert ros.spin_until(lambda: len(seen['state']) == 1)
        assert not seen['state'][0].model_ready and seen['state'][0].keypoints_detected > 20
    finally:
        ros.close()


def test_learns_online_latches_the_map_saves_and_reloads(tmp_path):
    model_path = tmp_path / 'model.npz'
    model = ArmModel(random_state=1)
    joints = sample_exploration_joints(model, N_FRAMES, rng=np.random.default_rng(1))
    ros = RosHarness()
    try:
        # the object stays put here, so it is background to the keypoint-distance map: the paper's route maps it
        node, pubs, seen = make_rig(ros, {'min_training_frames': N_FRAMES, 'refit_every': 0,
                                          'model_path': str(model_path), 'map_method': 'embedding'})
        for k, q in enumerate(joints):
            pubs['image'].publish(image_msg(model.render(q), k))
            js = JointState(name=['shoulder_roll', 'shoulder_pitch'], position=[float(v) for v in q])
            js.header.stamp.sec = k
            pubs['joints'].publish(js)
            arm = bool(model.part_clearances(q).min() < 0.0)      # the whole-arm sense (the default label)
            touch = Contact(in_contact=model.in_contact(q), in_contact_at_frame=model.in_contact(q),
                            arm_in_contact=arm, arm_in_contact_at_frame=arm)
            touch.header.stamp.sec = k
            pubs['contact'].publish(touch)
            assert ros.spin_until(lambda: len(seen['state']) == k + 1, timeout=10)
        assert ros.spin_until(lambda: seen['map'], timeout=60), 'no collision map after the fit'
        assert seen['map'][-1].header.stamp.sec == N_FRAMES - 1          # a map of the newest frame
        assert node.n_frames == N_FRAMES
        np.testing.assert_array_equal(np.array(node.model.train_contact_),
                                      [model.part_clearances(q).min() < 0.0 for q in joints])   # paired correctly
        m = seen['map'][-1]
        assert (m.rows, m.cols) == (8, 12) and len(m.collision) == 96 and 0 < sum(m.collision) < 96
        assert model_path.is_file()
        # states after the fit carry the embedding
        q = joints[0]
        pubs['image'].publish(image_msg(model.render(q), 1000))
        assert ros.spin_until(lambda: seen['state'][-1].model_ready, timeout=10)
        assert len(seen['state'][-1].embedding) == node.model.n_components == 4 and seen['state'][-1].training_frames == N_FRAMES
        # a refit that scores worse in cross-validation (labels shuffled) does not replace the live model
        live = node.model
        n = 60
        labels = np.random.default_rng(0).permutation(node.frames['contact'][:n])
        worse = ArmStateLearner(random_state=0, **node.learner_params).fit(
            node.frames['kp'][:n], np.array(node.frames['joints'][:n]), labels)
        assert model_score(worse) < model_score(live)
        with node._lock:
            node._fit_result = (worse, '')
        node._install_fitted()
        assert node.model is live and node.fits_discarded == 1
        # a map request for a frame not yet seen is answered once that frame is in, with its stamp
        n_maps = len(seen['map'])
        request = Header()
        request.stamp.sec = 1001
        pubs['request'].publish(request)
        ros.spin_for(0.2)
        assert len(seen['map']) == n_maps
        pubs['image'].publish(image_msg(model.render(joints[-1]), 1001))
        assert ros.spin_until(lambda: len(seen['map']) > n_maps, timeout=20)
        assert seen['map'][-1].header.stamp.sec == 1001
        assert list(seen['map'][-1].collision) == list(m.collision)      # same view as frame N - 1: same map
    finally:
        ros.close()
    # a new node loads the saved model and latches a map of the first frame it gets
    ros = RosHarness()
    try:
        node, pubs, seen = make_rig(ros, {'model_path': str(model_path)})
        assert node.model is not None
        pubs['image'].publish(image_msg(model.render(joints[-1]), 5))
        assert ros.spin_until(lambda: seen['map'], timeout=20)
        assert seen['map'][-1].header.stamp.sec == 5 and list(seen['map'][-1].collision) == list(m.collision)
    finally:
        ros.close()
    # a model for another grid or another robot's joint box is not used
    for params, box in (({'grid_rows': 6}, None), ({}, ((-3.0, -0.8), (0.0, 2.2)))):
        ros = RosHarness()
        try:
            node, _, _ = make_rig(ros, {'model_path': str(model_path), **params}, box)
            assert node.model is None
        finally:
            ros.close()


def test_a_corrupt_model_file_means_learning_again(tmp_path):
    bad = tmp_path / 'model.npz'
    bad.write_bytes(b'corrupt')
    ros = RosHarness()
    try:
        node, _, seen = make_rig(ros, {'model_path': str(bad)})
        assert node.model is None
        ros.spin_for(0.2)
        assert not seen['map']
    finally:
        ros.close()


def test_malformed_inputs_and_parameters_are_rejected_and_the_node_keeps_running():
    ros = RosHarness()
    try:
        node, pubs, seen = make_rig(ros, {'image_size': 0})
        tiny = image_msg(np.zeros((1, 1, 3), np.uint8), 1)
        pubs['image'].publish(tiny)
        odd = image_msg(np.zeros((40, 40, 3), np.uint8), 2)
        odd.step = 10                                       # shorter than a row
        pubs['image'].publish(odd)
        assert ros.spin_until(lambda: node.images_rejected == 2)
        for position in ([math.nan, 0.0], [1.0], []):
            pubs['joints'].publish(JointState(position=position))
        assert ros.spin_until(lambda: rejected_inputs(node).get('arm/joint_states', 0) == 3)
        pubs['image'].publish(image_msg(ArmModel(random_state=0).render([-2.0, 1.0]), 4))
        assert ros.spin_until(lambda: len(seen['state']) == 1)
        old = Header()
        old.stamp.sec = 1
        pubs['request'].publish(old)                         # older than every frame kept
        assert ros.spin_until(lambda: rejected_inputs(node).get('arm/embedding/map_request', 0) == 1)
        # the joint box is taken once: a malformed description or another robot's box is refused
        reversed_limits = '<robot><joint type="revolute" name="a"><limit lower="1" upper="0"/></joint></robot>'
        other_robot = ArmModel(joint_limits=((-1.0, 0.0), (0.0, 1.0)), object_position=(200.0, 100.0))
        for i, text in enumerate((reversed_limits, other_robot.robot_description(1.0))):
            pubs['description'].publish(String(data=text))
            assert ros.spin_until(lambda: rejected_inputs(node).get('arm/robot_description', 0) == i + 1)
        assert np.allclose(node.learner_params['joint_limits'], ArmModel().joint_limits)
        for name, value in (('min_training_frames', 2000), ('max_training_frames', 100), ('random_seed', 3),
                            ('grid_rows', 4), ('model_path', '/tmp/x.npz'), ('cell_collision_fraction', 0.0)):
            assert not node.set_parameters([Parameter(name, value=value)])[0].successful, name
        assert node.set_parameters([Parameter('max_training_frames', value=1200)])[0].successful
        assert node.max_training_frames == 1200
    finally:
        ros.close()
