import math

import cv2
import numpy as np
import pytest

from mm_sim.arm_model import ArmModel


@pytest.fixture(scope='module')
def model():
    return ArmModel(random_state=0)


def test_render_is_deterministic_per_seed(model):
    q = [-1.9, 1.0]
    a = model.render(q)
    assert a.shape == (400, 400, 3) and a.dtype == np.uint8
    np.testing.assert_array_equal(a, ArmModel(random_state=0).render(q))
    np.testing.assert_array_equal(a, model.render(q))
    assert np.mean(a != ArmModel(random_state=1).render(q)) > 0.2
    assert np.mean(a != model.render([-1.5, 0.5])) > 0.01      # the arm moved


def test_kinematics_and_contact_geometry(model):
    q = np.array([-math.pi / 2, 0.0])                          # straight up
    np.testing.assert_allclose(model.hand_position(q), model.shoulder + [0.0, -200.0], atol=1e-9)
    q_obj = model.inverse_kinematics(model.object_position_)
    assert q_obj is not None and model.within_limits(q_obj)
    np.testing.assert_allclose(model.hand_position(q_obj), model.object_position_, atol=1e-6)
    assert model.in_contact(q_obj) and model.hand_object_distance(q_obj) < 1e-6
    # Move the hand radially away from the object until the discs no longer overlap.
    direction = (model.object_position_ - model.shoulder) / np.linalg.norm(model.object_position_ - model.shoulder)
    near = model.inverse_kinematics(model.object_position_ - direction * (model.contact_distance - 2))
    far = model.inverse_kinematics(model.object_position_ - direction * (model.contact_distance + 2))
    assert model.in_contact(near) and not model.in_contact(far)
    # The whole contact circle around the object is reachable (object placement guarantee).
    for a in np.linspace(0, 2 * np.pi, 12, endpoint=False):
        p = model.object_position_ + (model.contact_distance + 3) * np.array([math.cos(a), math.sin(a)])
        assert model.inverse_kinematics(p) is not None
    qs = model.sample_joints(500, np.random.default_rng(0))
    d = np.array([model.hand_object_distance(q) for q in qs])
    assert np.array_equal([model.in_contact(q) for q in qs], d < model.contact_distance)


def test_link_collision_and_joint_validation(model):
    # An object just above the shoulder: the upper arm pointing up passes through it, the hand is far away.
    low = ArmModel(object_position=(200.0, 275.0), random_state=0)
    assert low.link_collides_object([-math.pi / 2, 0.0]) and not low.in_contact([-math.pi / 2, 0.0])
    assert not low.link_collides_object([-3.1, 0.0])
    with pytest.raises(ValueError):
        model.validate_joints([0.0])
    with pytest.raises(ValueError):
        model.validate_joints([np.nan, 0.0])
    np.testing.assert_allclose(model.clip_joints([-10.0, 10.0]), [-3.2, 2.2])
    with pytest.raises(ValueError):
        ArmModel(joint_limits=((0.0, -1.0), (0.0, 1.0)))


def test_sift_finds_keypoints_on_hand_object_and_background(model):
    q = np.array([-2.6, 0.8])
    assert not model.in_contact(q)
    frame = model.render(q)
    gray = cv2.resize(cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY), None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    pts = np.array([k.pt for k in cv2.SIFT_create().detect(gray, None)]) * 2.0
    hand = np.linalg.norm(pts - model.hand_position(q), axis=1) < model.hand_radius
    obj = np.linalg.norm(pts - model.object_position_, axis=1) < model.object_radius
    elbow, shoulder = model.link_points(q)[1], model.shoulder
    on_arm = np.array([_segment_distance(p, shoulder, elbow) < model.link_widths[0] / 2 for p in pts])
    far = np.array([_segment_distance(p, shoulder, elbow) > 40 and _segment_distance(p, elbow, model.hand_position(q))
                    > 40 for p in pts])
    background = far & ~obj
    assert hand.sum() >= 3
    assert obj.sum() >= 3
    assert on_arm.sum() >= 3
    assert background.sum() >= 10


def _segment_distance(p, a, b):
    t = np.clip(np.dot(p - a, b - a) / np.dot(b - a, b - a), 0.0, 1.0)
    return float(np.linalg.norm(p - (a + t * (b - a))))
