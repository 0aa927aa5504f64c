"""ArmStateLearner(representation='contact_point'): a virtual contact point rigid with the last link, relative to the
learned object (mm_manifold.arm_learning module docstring)."""
import copy
import dataclasses

import numpy as np
import pytest

from mm_bringup.arm_evaluation import moving_object_exploration, render_keypoints
from mm_manifold.arm_learning import (MISPLACED_SOFTNESSES, OBJECT_SOURCES, ArmStateLearner, ModelFileError,
                                      fit_contact_disc, fit_template, label_modes)
from mm_manifold.keypoints import KeypointExtractor
from mm_sim.arm_model import ArmModel


@pytest.fixture(scope='module')
def scene():
    """Object re-placed every 10 frames; the learner sees keypoints, joint readings and the hand's touch sensor."""
    model = ArmModel(random_state=4)
    data = moving_object_exploration(model, 240, 10, rng=np.random.default_rng(4))
    ext = KeypointExtractor()
    kps = render_keypoints(model, data['joints'], data['object'], ext)
    data['keypoints'] = kps
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
    # the contact region learns from every frame but the touch frames the disc puts far outside it
    outside = np.linalg.norm(learner.train_vectors_, axis=1) > (
        learner.contact_radius_ + MISPLACED_SOFTNESSES * learner.contact_softness_)
    np.testing.assert_array_equal(learner.region_frames_, ~(data['contact'] & outside))
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


def test_the_object_track_follows_lone_labels_and_ignores_those_on_the_hand(scene):
    """object_labels=1: a lone object label within track_gate of the estimate confirms it; one farther away means
    the object was re-placed; a label where the joint regression puts one of the robot's labels is left out (SIFT
    there mostly matched the hand), unless the frame's joints are unknown."""
    _, data, learner, _ = scene
    labels = np.flatnonzero(learner.object_group_ == learner.contact_object_)
    assert len(labels) >= 2
    template = learner.object_modes_[:, 0]                   # each label's main offset
    centre = template.mean(axis=0)
    small = np.array([0.5, -0.5]) * learner.track_gate
    P = np.full((5, learner.vectorizer_.n_labels_, 2), np.nan)
    P[0, labels] = template + [30.0, 10.0]                   # all the object's labels: agreed
    P[1, labels[0]] = template[0] + [30.0, 10.0] + small     # one label, near the estimate: confirms it
    P[2, labels[1]] = template[1] + [90.0, -40.0]            # one label, far away: the object was re-placed
    P[3, labels[:2]] = template[:2] + [[88.0, -40.0], [92.0, -40.0]]   # two labels 4 px apart: within the gate
    centres, sources = learner._object_track(P)
    np.testing.assert_allclose(centres[:2], np.repeat(centre[None] + [30.0, 10.0], 2, axis=0))
    np.testing.assert_allclose(centres[2:], np.repeat(centre[None] + [90.0, -40.0], 3, axis=0))
    assert sources.tolist() == [0, 0, 0, 0, 1]
    # the far label of frame 2 placed on the hand: left out when the joints are known
    q = np.repeat(data['joints'][:1], 5, axis=0)
    hand = learner._robot_points(q[:1])[0, 0]
    P[2, labels[1]] = hand
    P[3] = np.nan
    moved = learner._object_track(P)[0]
    np.testing.assert_allclose(moved[2], hand - template[1] + centre)
    kept, kept_sources = learner._object_track(P, q)
    np.testing.assert_allclose(kept[2:], np.repeat(centre[None] + [30.0, 10.0], 3, axis=0))
    assert kept_sources.tolist() == [0, 0, 1, 1, 1]


def test_label_modes_finds_each_keypoint_a_label_stands_for():
    """A label that stands for two keypoints of the object (look-alikes in one track) gets both offsets, the
    frequent one first; labels of one keypoint get one."""
    rng = np.random.default_rng(5)
    n, offsets, other = 400, np.array([[0.0, 0.0], [20.0, 0.0], [0.0, 20.0], [20.0, 20.0]]), np.array([-25.0, 10.0])
    shift = rng.uniform(-100.0, 100.0, (n, 1, 2))
    P = shift + offsets[None] + rng.normal(0.0, 0.5, (n, 4, 2))
    second = rng.random(n) < 0.3
    P[second, 0] = shift[second, 0] + other
    P[rng.random((n, 4)) < 0.2] = np.nan
    modes = label_modes(P, fit_template(P), 3.0)
    np.testing.assert_allclose(modes[0, 1] - modes[0, 0], other - offsets[0], atol=1.0)
    np.testing.assert_allclose(modes[1:, 0] - modes[1, 0], offsets[1:] - offsets[1], atol=1.0)
    assert np.isnan(modes[1:, 1:]).all() and np.isnan(modes[0, 2]).all()


def test_the_object_track_places_the_object_from_either_keypoint_of_a_label(scene):
    """With object_modes 2 a frame whose label shows its second keypoint still agrees with another label; with one
    offset per label the two disagree and the frame is placed wrongly."""
    _, _, fitted, _ = scene
    learner = copy.deepcopy(fitted)
    labels = np.flatnonzero(learner.object_group_ == learner.contact_object_)
    learner.object_modes_ = np.full_like(learner.object_modes_, np.nan)
    learner.object_modes_[:, 0] = fitted.object_modes_[:, 0]
    learner.object_modes_[0, 1] = fitted.object_modes_[0, 0] + [-25.0, 10.0]
    main = learner.object_modes_[:, 0]
    P = np.full((1, learner.vectorizer_.n_labels_, 2), np.nan)
    P[0, labels[0]] = learner.object_modes_[0, 1] + [60.0, 40.0]
    P[0, labels[1]] = main[1] + [60.0, 40.0]
    learner.object_modes = 2
    centres, sources = learner._object_track(P)
    np.testing.assert_allclose(centres[0], main.mean(axis=0) + [60.0, 40.0])
    assert sources.tolist() == [0]
    learner.object_modes = 1
    assert np.linalg.norm(learner._object_track(P)[0][0] - main.mean(axis=0) - [60.0, 40.0]) > 10.0


def test_look_alike_matches_vote_with_the_labels_but_never_place_the_object_alone(scene):
    """A frame whose object labels all lost the ratio test to a look-alike: their near-best keypoints, within
    object_match_distance, place the object where two agree; one alone, or beyond the distance, places nothing."""
    _, _, fitted, _ = scene
    learner = copy.deepcopy(fitted)
    labels = np.flatnonzero(learner.object_group_ == learner.contact_object_)
    main = learner.object_modes_[:, 0]
    shift = np.array([60.0, 40.0])
    P = np.full((2, learner.vectorizer_.n_labels_, 2), np.nan)
    positions = np.full((2, len(labels), 2, 2), np.nan)
    distances = np.full((2, len(labels), 2), np.inf)
    positions[:, 0, 0], positions[:, 1, 0] = main[0] + shift, main[1] + shift
    distances[:, :2, 0] = 0.05
    positions[1, 1, 0] = np.nan                          # the second frame shows one look-alike only
    learner.object_match_distance = 0.1
    centres, sources = learner._object_track(P, None, (positions, distances))
    np.testing.assert_allclose(centres[0], main.mean(axis=0) + shift)
    assert sources.tolist() == [0, 1]                    # the second frame keeps the first's estimate
    learner.object_match_distance = 0.04
    assert learner._object_track(P, None, (positions, distances))[1].tolist() == [3, 3]   # the training mean
    learner.object_match_distance = 0.0
    assert learner._object_track(P, None, (positions, distances))[1].tolist() == [3, 3]


def test_touch_frames_far_outside_the_disc_stay_out_of_the_contact_region(scene):
    """Four no-touch frames far from the object relabelled as touches (as a touch frame whose object estimate is
    wrong looks): the disc puts them far outside, so the contact region learns without them."""
    model, data, fitted, _ = scene
    far = np.flatnonzero(np.linalg.norm(fitted.train_vectors_, axis=1) > 3.0 * fitted.contact_radius_)[:4]
    contact = data['contact'].copy()
    contact[far] = True
    learner = ArmStateLearner(**fitted.get_params()).fit(data['keypoints'], data['joints'], contact)
    assert len(far) == 4 and not learner.region_frames_[far].any()
    assert learner.region_frames_.sum() >= len(contact) - 6


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
    for bad in (dict(hand_exclusion=-1.0), dict(track_gate=0.0), dict(hand_exclusion=float('nan')),
                dict(object_modes=0), dict(object_modes=4), dict(object_match_distance=-0.1),
                dict(object_match_distance=float('nan'))):
        with pytest.raises(ValueError):
            ArmStateLearner(model.joint_limits, **bad)


def test_save_load_round_trip(scene, tmp_path):
    model, data, learner, ext = scene
    path = tmp_path / 'model.npz'
    learner.save(path)
    loaded = ArmStateLearner.load(path)
    assert loaded.get_params() == learner.get_params()
    for name in ('contact_labels_', 'contact_coef_', 'contact_offset_', 'object_mean_', 'object_modes_',
                 'train_object_source_', 'region_frames_'):
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
                 dict(object_modes=arrays['object_modes'][:1]),
                 dict(object_modes=np.full_like(arrays['object_modes'], np.nan)),
                 dict(lle_metric_map=np.full((2, 2), np.nan)), dict(lle_metric_map=np.eye(3))):
        np.savez(tmp_path / 'bad.npz', **{**arrays, **case})
        with pytest.raises(ModelFileError):
            ArmStateLearner.load(tmp_path / 'bad.npz')


def test_contact_disc_fit_ignores_touch_frames_whose_object_estimate_is_wrong():
    """Touch frames whose object was placed 80-120 px off (a wrong estimate) would widen the disc; the fit refits
    without the touch frames far outside it and finds the true contact point and radius."""
    rng = np.random.default_rng(3)
    n, radius, c, e = 1500, 38.0, np.array([0.9, 0.1]), np.array([4.0, -6.0])
    angle, length = rng.uniform(-np.pi, np.pi, n), rng.uniform(40.0, 60.0, n)
    u = length[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    M = np.stack([u, np.stack([-u[:, 1], u[:, 0]], axis=1)], axis=2)           # the link frame [B - A, perp]
    d = rng.uniform(-90.0, 90.0, (n, 2))                                         # true p - o - e
    rel = d - np.einsum('nij,j->ni', M, c) + e
    contact = np.linalg.norm(d, axis=1) < radius
    wrong = rng.choice(np.flatnonzero(contact), 8, replace=False)
    shift = rng.uniform(80.0, 120.0, 8)[:, None] * np.stack([np.cos(angle[wrong]), np.sin(angle[wrong])], axis=1)
    rel[wrong] += shift
    theta = fit_contact_disc(rel, M, contact, np.ones(n, bool))
    assert abs(theta[4] - radius) < 1.5, theta
    np.testing.assert_allclose(theta[:2], c, atol=0.05)
    np.testing.assert_allclose(theta[2:4], e, atol=3.0)
