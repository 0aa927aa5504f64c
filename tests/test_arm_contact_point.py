"""ArmStateLearner(representation='contact_point'): a virtual contact point rigid with the last link, relative to the
learned object (mm_manifold.arm_learning module docstring)."""
import dataclasses

import numpy as np
import pytest

from mm_bringup.arm_evaluation import moving_object_exploration, render_keypoints
from mm_manifold.arm_learning import OBJECT_SOURCES, ArmStateLearner, ModelFileError
from mm_manifold.keypoints import KeypointExtractor
from mm_sim.arm_model import ArmModel


@pytest.fixture(scope='module')
def scene():
    """Object re-placed every 10 frames; the learner sees keypoints, joint readings and the hand's touch sensor."""
    model = ArmModel(random_state=4)
    data = moving_object_exploration(model, 240, 10, rng=np.random.default_rng(4))
    ext = KeypointExtractor()
    kps = render_keypoints(model, data['joints'], data['object'], ext)
    learner = ArmStateLearner(model.joint_limits, representation='contact_point', n_components=2, random_state=0,
                              n_folds=3, object_labels=1, lle_metric='local').fit(kps, data['joints'],
                                                                                  data['contact'])
    return model, data, learner, ext


def hidden_object(frame, model):
    """The frame with every keypoint on or next to the object removed."""
    keep = np.linalg.norm(frame.positions - model.object_position_, axis=1) > model.object_radius + 4
    return dataclasses.replace(frame, positions=frame.positions[keep], descriptors=frame.descriptors[keep])


def test_fitted_contact_point_lands_near_the_hand_centre(scene):
    model, data, learner, _ = scene
    assert len(learner.contact_labels_) == 2 and learner.train_vectors_.shape == (240, 2)
    A, M = learner._link_frame(data['joints'])
    p = A + np.einsum('nij,j->ni', M, learner.contact_coef_)
    hand = np.array([model.link_points(q)[2] for q in data['joints']])          # ground truth, for the test only
    error = np.linalg.norm(p - hand, axis=1)
    assert np.median(error) < 15.0, np.median(error)
    # the fitted circle sits near the true contact distance (up to the template centre's offset)
    assert abs(learner.contact_radius_ - model.contact_distance) < 15.0
    d = np.linalg.norm(learner.train_vectors_, axis=1)
    assert np.median(d[data['contact']]) < learner.contact_radius_ < np.median(d[~data['contact']])


def test_contact_is_inside_the_circle_on_a_new_placement(scene):
    model, _, learner, ext = scene
    rng = np.random.default_rng(77)
    test = moving_object_exploration(model, 120, 10, rng=rng)
    kps = render_keypoints(model, test['joints'], test['object'], ext)
    d = np.linalg.norm(learner.frame_vectors(kps, test['joints']), axis=1)
    predicted = d <= learner.contact_radius_
    c = test['contact']
    assert c.sum() >= 5
    assert predicted[c].mean() >= 0.8 and predicted[~c].mean() <= 0.15, (predicted[c].mean(), predicted[~c].mean())


def test_a_frame_that_hides_the_object_falls_back_to_earlier_estimates(scene):
    model, _, learner, ext = scene
    rng = np.random.default_rng(5)
    model.set_object_position(model.random_object_position(rng))
    q = max(model.sample_joints(50, rng), key=model.hand_object_distance)
    frame = ext(model.render(q))
    blind = hidden_object(frame, model)
    seen = learner.transform(frame, joints=q)
    assert seen['object_source'] == 'frame'
    from_recent = learner.transform(blind, recent=[frame], joints=q)
    assert from_recent['object_source'] == 'recent'
    np.testing.assert_allclose(from_recent['embedding'], seen['embedding'], atol=1e-9)
    alone = learner.transform(blind, joints=q)
    assert alone['object_source'] == 'mean' and np.all(np.isfinite(alone['embedding']))
    # a sequence: newest placing frame within recent_frames, then the last estimate ('stale')
    centres, sources = learner.object_track([frame] + [blind] * (learner.recent_frames + 2))
    assert sources.tolist() == ['frame'] + ['recent'] * learner.recent_frames + ['stale'] * 2
    np.testing.assert_allclose(centres, np.repeat(centres[:1], len(centres), axis=0))
    assert set(sources) <= set(OBJECT_SOURCES)
    # the map before moving uses the same estimate
    m1 = learner.predict_collision_map(frame, method='embedding')
    m2 = learner.predict_collision_map(blind, recent=[frame], method='embedding')
    np.testing.assert_array_equal(m1['collision'], m2['collision'])


def test_an_agreed_recent_estimate_comes_before_a_frames_single_label(scene):
    """object_labels=1: a lone object label is often a hand keypoint taken for the object's, so the newest estimate
    on which two labels agreed (within recent_frames) comes first; after that the lone label places the object."""
    _, _, learner, _ = scene
    labels = np.flatnonzero(learner.object_group_ == learner.contact_object_)
    assert len(labels) >= 2
    template = learner.object_template_[labels]
    n = learner.recent_frames + 3
    P = np.full((n, learner.vectorizer_.n_labels_, 2), np.nan)
    P[0, labels] = template + [30.0, 10.0]                   # all the object's labels: agreed
    P[1:, labels[0]] = template[0] + [80.0, -40.0]           # afterwards one label only, somewhere else
    centres, sources = learner._object_track(P)
    agreed, lone = template.mean(axis=0) + [30.0, 10.0], template.mean(axis=0) + [80.0, -40.0]
    k = learner.recent_frames + 1
    np.testing.assert_allclose(centres[:k], np.repeat(agreed[None], k, axis=0))
    assert sources[:k].tolist() == [0] + [1] * learner.recent_frames
    np.testing.assert_allclose(centres[k:], np.repeat(lone[None], 2, axis=0))
    assert sources[k:].tolist() == [0, 0]


def test_contact_point_needs_the_joint_readings_and_two_dimensions(scene):
    model, data, learner, ext = scene
    frame = ext(model.render(data['joints'][0]))
    with pytest.raises(ValueError, match='joint'):
        learner.transform(frame)
    with pytest.raises(ValueError, match='joint'):
        learner.frame_vectors([frame])
    with pytest.raises(ValueError):
        ArmStateLearner(model.joint_limits, representation='contact_point', n_components=3)
    with pytest.raises(ValueError):
        ArmStateLearner(model.joint_limits, object_labels=3)


def test_save_load_round_trip(scene, tmp_path):
    model, data, learner, ext = scene
    path = tmp_path / 'model.npz'
    learner.save(path)
    loaded = ArmStateLearner.load(path)
    assert loaded.get_params() == learner.get_params()
    for name in ('contact_labels_', 'contact_coef_', 'contact_offset_', 'object_mean_', 'train_object_source_'):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(learner, name))
    assert loaded.contact_radius_ == learner.contact_radius_ and loaded.contact_object_ == learner.contact_object_
    for q in data['joints'][:4]:
        frame = ext(model.render(q))
        a, b = learner.transform(frame, joints=q), loaded.transform(frame, joints=q)
        np.testing.assert_allclose(a['embedding'], b['embedding'], atol=1e-12)
        assert a['collision'] == b['collision'] and a['object_source'] == b['object_source']
    np.testing.assert_array_equal(loaded.collision_map_, learner.collision_map_)
    # contact-point arrays that do not match the representation are refused
    with np.load(path, allow_pickle=False) as f:
        arrays = {k: f[k] for k in f.files}
    params = arrays['contact_params'].astype(float)
    bad_radius, nan_coef = params.copy(), params.copy()
    bad_radius[4], nan_coef[0] = -1.0, np.nan
    assert not np.allclose(loaded.lle_.metric_map_, np.eye(2))
    np.testing.assert_array_equal(loaded.lle_.metric_map_, learner.lle_.metric_map_)
    for case in (dict(contact_labels=np.zeros(0, int)), dict(contact_params=bad_radius),
                 dict(contact_params=nan_coef), dict(train_object_source=np.full(3, 7)),
                 dict(lle_metric_map=np.full((2, 2), np.nan)), dict(lle_metric_map=np.eye(3))):
        np.savez(tmp_path / 'bad.npz', **{**arrays, **case})
        with pytest.raises(ModelFileError):
            ArmStateLearner.load(tmp_path / 'bad.npz')
