"""ArmStateLearner: collision map from the embedding, fast out-of-sample maps, saving/loading without pickle."""
import numpy as np
import pytest
from scipy.ndimage import distance_transform_cdt

from mm_manifold.arm_evaluation import sample_exploration_joints
from mm_manifold.arm_learning import ArmStateLearner, ModelFileError, cell_map
from mm_manifold.embedding import ContactQuadric, ContactSphere
from mm_manifold.keypoints import KeypointExtractor
from mm_sim.arm_model import ArmModel


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
    learner = ArmStateLearner(random_state=0).fit(kps[:220], joints[:220], contact[:220], np.arange(220) * 10)
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
    X = learner.vectorizer_.fill_missing(learner.vectorizer_.transform(new_kps))
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
    # The planner keeps clear of the contact region by this map (mm_planner.value_iteration.clearance_rewards, which
    # charges closeness above -1 by default): free cells next to predicted collision cells must read as close, cells
    # farther away clearly less so.
    learner, _, _ = fitted
    close = learner.closeness_map_
    assert np.all(close[learner.collision_map_] >= -learner.map_margin)
    steps = distance_transform_cdt(~learner.collision_map_, metric='taxicab')    # grid moves to a collision cell
    assert np.median(close[steps == 1]) > -1.0
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
        ArmStateLearner().fit(kps, np.zeros((30, 2)) - 1.0, np.zeros(30, bool))
    with pytest.raises(ValueError):
        ArmStateLearner(joint_limits=((0, -1), (0, 1)))


@pytest.mark.parametrize('region', ['sphere', 'ellipsoid', 'quadric'])
def test_each_contact_region_predicts_and_survives_saving(frames, region, tmp_path):
    kps, joints, contact = frames
    learner = ArmStateLearner(region=region, random_state=0).fit(kps[:220], joints[:220], contact[:220])
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
        ArmStateLearner(region='cube')
