"""The image embedding node in-process: bad images are rejected, frames are learned online, the collision map is
latched, the model is saved and reloaded, a corrupt model file means learning again."""
import numpy as np
from mm_common.testing import RosHarness
from mm_msgs.msg import CollisionMap, Contact, EmbeddingState
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image, JointState

from mm_manifold.arm_evaluation import sample_exploration_joints
from mm_manifold.image_embedding_node import ImageEmbeddingNode
from mm_sim.arm_model import ArmModel

QOS = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
N_FRAMES = 90


def image_msg(frame, k, encoding='rgb8'):
    img = Image(height=frame.shape[0], width=frame.shape[1], encoding=encoding, step=frame.shape[1] * 3)
    img.header.stamp.sec = k
    img.data = frame.tobytes()
    return img


def make_rig(ros, params):
    node = ros.add(ImageEmbeddingNode(context=ros.context, parameter_overrides=[
        Parameter(k, value=v) for k, v in params.items()]))
    client = ros.node('embedding_test_client')
    seen = {'state': [], 'map': []}
    client.create_subscription(EmbeddingState, 'arm/embedding/state', seen['state'].append, QOS)
    client.create_subscription(CollisionMap, 'arm/embedding/collision_map', seen['map'].append, LATCHED)
    pubs = dict(image=client.create_publisher(Image, 'arm/camera/image_raw', QOS),
                joints=client.create_publisher(JointState, 'arm/joint_states', QOS),
                contact=client.create_publisher(Contact, 'arm/contact', QOS))
    assert ros.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), timeout=10)
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
        node, pubs, seen = make_rig(ros, {'min_training_frames': N_FRAMES, 'refit_every': 0,
                                          'model_path': str(model_path)})
        for k, q in enumerate(joints):
            pubs['image'].publish(image_msg(model.render(q), k))
            js = JointState(name=['shoulder_roll', 'shoulder_pitch'], position=[float(v) for v in q])
            js.header.stamp.sec = k
            pubs['joints'].publish(js)
            touch = Contact(in_contact=model.in_contact(q))
            touch.header.stamp.sec = k
            pubs['contact'].publish(touch)
            assert ros.spin_until(lambda: len(seen['state']) == k + 1, timeout=10)
        assert ros.spin_until(lambda: seen['map'], timeout=60), 'no collision map after the fit'
        assert node.n_frames == N_FRAMES
        np.testing.assert_array_equal(np.array(node.model.train_contact_),
                                      [model.in_contact(q) for q in joints])       # labels paired correctly
        m = seen['map'][-1]
        assert (m.rows, m.cols) == (8, 12) and len(m.collision) == 96 and 0 < sum(m.collision) < 96
        assert model_path.is_file()
        # states after the fit carry the embedding
        q = joints[0]
        pubs['image'].publish(image_msg(model.render(q), 1000))
        assert ros.spin_until(lambda: seen['state'][-1].model_ready, timeout=10)
        assert len(seen['state'][-1].embedding) == 3 and seen['state'][-1].training_frames == N_FRAMES
    finally:
        ros.close()
    # a new node loads the saved model and latches its map at once
    ros = RosHarness()
    try:
        node, _, seen = make_rig(ros, {'model_path': str(model_path)})
        assert node.model is not None and ros.spin_until(lambda: seen['map'], timeout=10)
        assert list(seen['map'][-1].collision) == list(m.collision)
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
