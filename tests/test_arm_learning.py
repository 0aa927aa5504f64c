"""ArmStateLearner: label roles from the joints, collision maps (over exploration frames and predicted before moving for
an unseen object placement), fast out-of-sample maps, saving/loading without pickle."""
import copy
import dataclasses

import numpy as np
import pytest
from scipy.ndimage import distance_transform_cdt

from mm_bringup.arm_evaluation import moving_object_exploration, render_keypoints, sample_exploration_joints
from mm_manifold.arm_learning import (EXTERNAL, GRID_MOVES, SELF, STATIC, ArmStateLearner, ModelFileError, cell_map,
                                      cross_max, joint_features, label_roles, move_hits)
from mm_manifold.embedding import ContactQuadric, ContactSphere
from mm_manifold.keypoints import KeypointExtractor
from mm_sim.arm_model import ArmModel

# the robot's joint box (its description, as the nodes get it from their configuration)
LIMITS = ArmModel().joint_limits


@pytest.fixture(scope='module')
def frames():
    model = ArmModel(random_state=2)
    rng = np.random.default_rng(2)
    joints = sample_exploration_joints(model, 260, rng=rng)
    contact = np.array([model.in_contact(q) for q in joints])
    ext = KeypointExtractor()
    kps = [ext(model.render(q)) for q in joints]
    return kps, joints, contact


@pytest.fixture(scope='module')
def fitted(frames):
    kps, joints, contact = frames
    learner = ArmStateLearner(LIMITS, random_state=0).fit(kps[:220], joints[:220], contact[:220],
                                                          np.arange(220) * 10)
    return learner, kps[220:], contact[220:]


def test_cell_map_by_hand():
    limits = [[0.0, 2.0], [0.0, 3.0]]
    joints = np.array([[0.5, 0.5], [0.4, 0.6], [0.6, 0.4], [1.5, 2.5], [1.5, 2.4], [1.6, 2.6]])
    predicted = np.array([True, False, False, True, True, False])
    closeness = np.array([0.5, -1.0, -2.0, 0.1, 0.2, -0.5])
    col, close = cell_map(joints, predicted, closeness, limits, (2, 3), min_frames=3, fraction=0.5)
    # cell (0, 0): 1 of 3 -> free at fraction 0.5; cell (1, 2): 2 of 3 -> collision
    assert not col[0, 0] and col[1, 2]
    assert close[0, 0] == 0.5 and close[1, 2] == 0.2
    col, _ = cell_map(joints, predicted, closeness, limits, (2, 3), min_frames=3, fraction=0.3)
    assert col[0, 0]
    # empty cells borrow their 3 nearest frames: (0, 2) is nearest to the frames of cell (1, 2)
    assert col[0, 2] == (predicted[[3, 4, 5]].mean() >= 0.3)


def test_fast_out_of_sample_maps_equal_the_embedding_transforms(fitted):
    learner, new_kps, _ = fitted
    X = learner.frame_vectors(new_kps)
    np.testing.assert_allclose(learner.lle_transform(X), learner.lle_.transform(X), atol=1e-10)
    np.testing.assert_allclose(learner.pca_transform(X), learner.pca_.transform(X), atol=1e-8)
    # training vectors land near their own embedding
    Y = learner.lle_transform(learner.train_vectors_)
    spread = np.linalg.norm(learner.lle_.embedding_ - learner.lle_.embedding_.mean(0), axis=1).mean()
    assert np.median(np.linalg.norm(Y - learner.lle_.embedding_, axis=1)) < 0.05 * spread


def test_collision_map_marks_the_cells_where_contact_frames_are(fitted):
    learner, new_kps, new_contact = fitted
    assert learner.collision_map_.shape == (8, 12)
    assert 0 < learner.collision_map_.sum() < 96
    cells = np.floor((learner.train_joints_ - learner.joint_limits[:, 0]) /
                     ((learner.joint_limits[:, 1] - learner.joint_limits[:, 0]) / [8, 12])).astype(int)
    contact_cells = {tuple(c) for c in cells[learner.train_contact_]}
    hit = np.mean([learner.collision_map_[c] for c in contact_cells])
    assert hit > 0.6, f'only {hit:.2f} of the cells with contact frames are marked'
    pred = np.array([learner.transform(k)['collision'] for k in new_kps])
    assert np.mean(pred == new_contact) > 0.75


def test_closeness_map_falls_off_with_the_distance_from_the_collision_cells(fitted):
    # The planner keeps clear of the contact region by this map (mm_planner.value_iteration.clearance_rewards): free
    # cells next to predicted collision cells must read as closer than cells farther away.
    learner, _, _ = fitted
    close = learner.closeness_map_
    assert np.all(close[learner.collision_map_] >= -learner.map_margin)
    steps = distance_transform_cdt(~learner.collision_map_, metric='taxicab')    # grid moves to a collision cell
    assert np.median(close[steps == 1]) > np.median(close[steps >= 3]) + 0.5


def test_save_load_round_trip_and_corrupt_files(fitted, tmp_path):
    learner, new_kps, _ = fitted
    path = tmp_path / 'model.npz'
    learner.save(path)
    assert [p.name for p in tmp_path.iterdir()] == ['model.npz']        # no temp file left behind
    loaded = ArmStateLearner.load(path)
    np.testing.assert_array_equal(loaded.collision_map_, learner.collision_map_)
    np.testing.assert_array_equal(loaded.closeness_map_, learner.closeness_map_)
    np.testing.assert_array_equal(loaded.train_stamps_, learner.train_stamps_)
    for k in new_kps[:5]:
        a, b = learner.transform(k), loaded.transform(k)
        np.testing.assert_allclose(a['embedding'], b['embedding'], atol=1e-12)
        np.testing.assert_allclose(a['pca_embedding'], b['pca_embedding'], atol=1e-12)
        assert a['collision'] == b['collision']
    for name in ('label_roles_', 'joint_coef_', 'label_mean_'):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(learner, name))
    assert loaded.get_params() == learner.get_params()
    for method in ('embedding', 'keypoint_distance'):
        m1, m2 = (m.predict_collision_map(new_kps[0], method=method) for m in (learner, loaded))
        # the object never moved here: no object is learned, so the keypoint route falls back to the embedding
        assert m1['method'] == m2['method'] == 'embedding'
        np.testing.assert_array_equal(m1['collision'], m2['collision'])
        np.testing.assert_allclose(m1['closeness'], m2['closeness'], atol=1e-9)
    data = path.read_bytes()
    (tmp_path / 'truncated.npz').write_bytes(data[:len(data) // 2])
    (tmp_path / 'garbage.npz').write_bytes(b'not a model')
    for name in ('truncated.npz', 'garbage.npz', 'missing.npz'):
        with pytest.raises(ModelFileError):
            ArmStateLearner.load(tmp_path / name)


def test_fit_needs_contact_and_no_contact_frames(fitted):
    learner, _, _ = fitted
    kps = [learner.vectorizer_.extract(np.zeros((400, 400, 3), np.uint8))] * 30
    with pytest.raises(ValueError, match='contact'):
        ArmStateLearner(LIMITS).fit(kps, np.zeros((30, 2)) - 1.0, np.zeros(30, bool))
    with pytest.raises(ValueError):
        ArmStateLearner(joint_limits=((0, -1), (0, 1)))


@pytest.mark.parametrize('region', ['sphere', 'ellipsoid', 'quadric'])
def test_each_contact_region_predicts_and_survives_saving(frames, region, tmp_path):
    kps, joints, contact = frames
    learner = ArmStateLearner(LIMITS, region=region, random_state=0).fit(kps[:220], joints[:220], contact[:220])
    assert learner.selection_['model'] == region == learner.pca_selection_['model']
    assert isinstance(learner.region_, ContactQuadric if region == 'quadric' else ContactSphere)
    # the cross-validated threshold puts the region's surface at closeness 0
    np.testing.assert_array_equal(learner.train_predicted_, learner.train_closeness_ >= -1e-12)
    pred = np.array([learner.transform(k)['collision'] for k in kps[220:]])
    assert np.mean(pred == contact[220:]) > 0.75
    learner.save(tmp_path / 'm.npz')
    loaded = ArmStateLearner.load(tmp_path / 'm.npz')
    assert loaded.region == region and loaded.selection_ == learner.selection_
    np.testing.assert_allclose(loaded.train_closeness_, learner.train_closeness_, atol=1e-12)
    np.testing.assert_array_equal(loaded.collision_map_, learner.collision_map_)
    np.testing.assert_array_equal(loaded.closeness_map_, learner.closeness_map_)
    for k in kps[220:225]:
        a, b = learner.transform(k), loaded.transform(k)
        assert a['collision'] == b['collision'] and a['closeness'] == pytest.approx(b['closeness'], abs=1e-12)
    with pytest.raises(ValueError):
        ArmStateLearner(LIMITS, region='cube')


def test_joint_features_make_a_two_link_arm_point_linear():
    rng = np.random.default_rng(0)
    q = rng.uniform(-3, 3, (50, 2))
    a0, a1 = q[:, 0], q[:, 0] + q[:, 1]
    point = np.stack([5 + 3 * np.cos(a0) + 2 * np.cos(a1), 1 + 3 * np.sin(a0) + 2 * np.sin(a1)], 1)
    phi = joint_features(q)
    assert phi.shape == (50, 9)
    coef = np.linalg.lstsq(phi, point, rcond=None)[0]
    np.testing.assert_allclose(phi @ coef, point, atol=1e-9)


def test_label_roles_by_hand():
    rng = np.random.default_rng(1)
    q = rng.uniform(-2, 0, (200, 2))
    arm = np.stack([100 + 50 * np.cos(q[:, 0]), 100 + 50 * np.sin(q[:, 0])], 1)
    obj = rng.uniform(50, 350, (200, 2))            # moves, but not with the joints
    wall = np.full((200, 2), 30.0) + rng.normal(0, 0.3, (200, 2))
    raw = np.hstack([arm, obj, wall])
    raw[rng.random(200) < 0.2, 2:4] = np.nan        # the object is sometimes hidden
    roles, coef, r2, motion = label_roles(raw, q)
    assert roles.tolist() == [SELF, EXTERNAL, STATIC]
    assert r2[0] > 0.999 and r2[1] < 0.1 and motion[2] < 1.0


def test_cross_max_covers_the_centre_and_the_halves_of_the_moves_to_the_neighbours():
    s = 4
    hit = np.zeros((2 * s + 1, 3 * s + 1), bool)
    hit[s + s // 2, 2 * s + 1] = True            # on (1, 2)'s half of the move from cell (1, 1)'s centre to (1, 2)'s
    value = np.where(hit, 1.0, -1.0)
    col, close = cross_max(hit, value, (2, 3), s)
    assert col.tolist() == [[False, False, False], [False, False, True]]
    assert close[1, 2] == 1.0 and close[1, 1] == -1.0 and close[0, 0] == -1.0
    hit[s + s // 2, 2 * s] = True                # on the border: both cells' halves of the move
    assert cross_max(hit, np.where(hit, 1.0, -1.0), (2, 3), s)[0].tolist() == [[False, False, False],
                                                                                 [False, True, True]]
    with pytest.raises(ValueError):
        cross_max(hit[:-1], value[:-1], (2, 3), s)


@pytest.fixture(scope='module')
def moving():
    """A learner kept across placements: exploration with the object re-placed every 10 frames."""
    model = ArmModel(random_state=4)
    data = moving_object_exploration(model, 240, 10, rng=np.random.default_rng(4))
    kps = render_keypoints(model, data['joints'], data['object'], KeypointExtractor())
    learner = ArmStateLearner(model.joint_limits, random_state=0, n_folds=3).fit(kps, data['joints'], data['contact'])
    return model, learner


def test_moving_object_exploration_replaces_the_object():
    model = ArmModel(random_state=5)
    d = moving_object_exploration(model, 40, 10, rng=np.random.default_rng(5))
    assert len(np.unique(d['object'], axis=0)) == 4 and d['placement'].tolist() == sorted(d['placement'])
    np.testing.assert_allclose(d['distance'], np.linalg.norm(
        np.array([model.link_points(q)[2] for q in d['joints']]) - d['object'], axis=1))
    assert np.all(d['any_contact'][d['contact']])


def test_predict_collision_map_for_an_unseen_placement(moving):
    model, learner = moving
    assert (learner.label_roles_ == SELF).sum() >= 10          # the arm's labels follow the joints
    ext = KeypointExtractor()
    rng = np.random.default_rng(99)
    accuracy = []
    for _ in range(3):
        model.set_object_position(model.random_object_position(rng))
        far = max(model.sample_joints(50, rng), key=model.hand_object_distance)
        out = learner.predict_collision_map(ext(model.render(far)), method='embedding')
        assert out['collision'].shape == out['closeness'].shape == (8, 12) and out['new_frames'] == 1
        assert np.all(np.isfinite(out['closeness']))
        lattice = out['lattice_joints']
        truth = np.array([[model.in_contact(q) for q in row] for row in lattice])
        pred = out['lattice_closeness'] >= learner.map_threshold
        accuracy.append(np.mean(pred == truth))
        # closeness is higher where the hand is near the object than where it is far from it
        dist = np.array([[model.hand_object_distance(q) for q in row] for row in lattice])
        assert np.median(out['lattice_closeness'][dist < 60]) > np.median(out['lattice_closeness'][dist > 150])
    assert np.mean(accuracy) > 0.8, accuracy
    # the same call with recent frames, and the per-frame state with them
    frame = ext(model.render(model.sample_joints(1, rng)[0]))
    assert learner.predict_collision_map(frame, recent=[frame], method='embedding')['new_frames'] == 2
    assert np.isfinite(learner.transform(frame, recent=[frame])['closeness'])


def test_keypoint_distance_map_places_the_learned_object_where_the_frame_shows_it(moving):
    """The keypoint-distance route: the labels that move rigidly together but not with the joints are one object;
    a frame that shows two of them places the whole object, and the robot's predicted segments come within their
    learned contact distances exactly where the arm is near it. A frame that does not show the object falls back to
    the embedding."""
    model, learner = moving
    assert learner.n_objects_ == 1 and (learner.object_group_ == 0).sum() >= 3
    assert np.all(learner.label_roles_[learner.object_group_ == 0] == EXTERNAL)
    assert len(learner.rigid_pairs_) > len(learner.self_labels_) and np.all(learner.segment_margins_ >= 0.0)
    ext = KeypointExtractor()
    rng = np.random.default_rng(98)
    recall, bias = [], []
    for _ in range(3):
        model.set_object_position(model.random_object_position(rng))
        far = max(model.sample_joints(50, rng), key=model.hand_object_distance)
        frame = ext(model.render(far))
        centre = learner.object_centres(frame)
        assert centre.shape == (1, 2) and np.all(np.isfinite(centre))
        bias.append(centre[0] - model.object_position_)
        out = learner.predict_collision_map(frame, method='keypoint_distance')
        assert out['method'] == 'keypoint_distance' and out['objects_placed'] == 1
        assert out['collision'].shape == (8, 12)
        lattice = out['lattice_joints'].reshape(-1, 2)
        hand_gap = np.array([model.hand_object_distance(q) for q in lattice]) - model.contact_distance
        gap = model.part_clearances(lattice).min(axis=1)
        close = out['lattice_closeness'].ravel()
        recall.append(np.mean(close[hand_gap < 0.0] >= 0.0))      # learned from the hand's touch sensor
        assert np.median(close[gap > 60]) < 0.0 < np.median(close[hand_gap < -10])
    # the template's centre sits at one place on the object wherever the object is
    assert np.ptp(np.array(bias), axis=0).max() < 2.0 and np.linalg.norm(bias[0]) < model.object_radius
    print('recall of hand-contact lattice points', recall)
    assert np.mean(recall) > 0.9, recall
    hidden = np.linalg.norm(frame.positions - model.object_position_, axis=1) > model.object_radius + 4
    blind = dataclasses.replace(frame, positions=frame.positions[hidden], descriptors=frame.descriptors[hidden])
    assert np.all(np.isnan(learner.object_centres(blind)))
    out = learner.predict_collision_map(blind, method='keypoint_distance')
    assert out['method'] == 'embedding' and out['objects_placed'] == -1
    # or, where a map that does not know the object's place must not be trusted, every cell is blocked
    careful = copy.copy(learner)
    careful.unplaced_object = 'block'
    out = careful.predict_collision_map(blind, method='keypoint_distance')
    assert out['method'] == 'keypoint_distance' and out['objects_placed'] == 0 and out['collision'].all()
    assert careful.predict_collision_map(frame, method='keypoint_distance')['objects_placed'] == 1
    with pytest.raises(ValueError):
        ArmStateLearner(LIMITS, unplaced_object='guess')
    # an earlier frame of the same scene places it
    out = learner.predict_collision_map(blind, recent=[frame], method='keypoint_distance')
    assert out['method'] == 'keypoint_distance' and out['new_frames'] == 2


def test_keypoint_distance_outlines_the_robot_with_precisely_placed_labels_only(moving):
    """A robot label the joints place only roughly (SIFT sometimes matches it elsewhere on the arm) takes no part in
    the segments: through it the map blocked cells whose true clearance was 20-100 px."""
    _, learner = moving
    raw = learner.vectorizer_.training_vectors_
    joints, contact = learner.train_joints_, learner.train_contact_
    P = raw.reshape(len(raw), -1, 2)
    residuals = learner._label_residuals(P, joints)
    used = np.unique(learner.rigid_pairs_)
    assert len(used) >= 10 and np.all(residuals[used] <= learner.rigid_tolerance)
    # the most connected label, moved 15 px off in every other frame where it is seen, drops out
    label = np.bincount(learner.rigid_pairs_.ravel()).argmax()
    corrupted = P.copy()
    corrupted[::2, learner.self_labels_[label]] += 15.0
    other = copy.copy(learner)                    # the fixture's learner stays as it was
    other._fit_object_geometry(corrupted.reshape(len(raw), -1), joints, contact)
    assert label not in np.unique(other.rigid_pairs_)
    assert label in used and len(np.unique(other.rigid_pairs_)) >= len(used) - 1


def test_move_hits_mark_the_moves_between_centres_that_cross_a_hit():
    # 2 x 3 grid, resolution 4: a hit on the lattice point halfway between the centres of cells (0, 0) and (0, 1)
    hit = np.zeros((2 * 4 + 1, 3 * 4 + 1), bool)
    hit[2, 4] = True
    moves = move_hits(hit, (2, 3), 4)
    right, left = GRID_MOVES.index((0, 1)), GRID_MOVES.index((0, -1))
    assert moves[right, 0, 0] and moves[left, 0, 1]
    assert not moves[right, 0, 1] and not moves[right, 1, 0]
    assert moves[GRID_MOVES.index((-1, 0)), 0, :].all() and moves[right, :, 2].all()      # off the grid
    assert moves.sum() == 2 + 3 + 3 + 2 + 2
