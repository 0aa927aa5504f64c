import math

import numpy as np
import pytest

from mm_manifold.keypoints import FrameKeypoints, KeypointVectorizer, MeanImputer, NearestImputer, extract_keypoints
from mm_sim.arm_model import ArmModel


@pytest.fixture(scope='module')
def setup():
    model = ArmModel(random_state=3)
    rng = np.random.default_rng(0)
    train_q = model.sample_joints(260, rng)
    vec = KeypointVectorizer(random_state=0)
    train = [vec.extract(model.render(q)) for q in train_q]
    vec.fit(train)
    return model, vec, rng


def _forearm_coordinates(model, q, p):
    """Image point -> coordinates in the forearm frame (origin at the hand centre)."""
    a = q[0] + q[1]
    d = p - model.hand_position(q)
    return np.array([math.cos(a) * d[0] + math.sin(a) * d[1], -math.sin(a) * d[0] + math.cos(a) * d[1]])


def test_extract_keypoints_and_bad_images():
    model = ArmModel(random_state=3)
    kp = extract_keypoints(model.render([-2.0, 1.0]))
    assert isinstance(kp, FrameKeypoints) and len(kp) > 30
    assert kp.positions.shape == (len(kp), 2) and kp.descriptors.shape == (len(kp), 128)
    np.testing.assert_allclose(np.linalg.norm(kp.descriptors, axis=1), 1.0, rtol=1e-5)
    assert np.all((kp.positions >= 0) & (kp.positions < 400))
    with pytest.raises(ValueError):
        extract_keypoints(np.zeros((10, 10, 3), np.float32))
    with pytest.raises(ValueError):
        extract_keypoints(np.zeros((10, 10, 4), np.uint8))


def test_labels_stay_consistent_over_a_slow_motion(setup):
    model, vec, _ = setup
    assert 20 <= vec.n_labels_ <= vec.n_labels
    # A slow sweep: 40 frames, 0.02 rad per frame on both joints.
    q0 = np.array([-2.4, 0.5])
    seq = [q0 + k * np.array([0.02, 0.02]) for k in range(40)]
    X = vec.transform([model.render(q) for q in seq]).reshape(len(seq), vec.n_labels_, 2)
    observed = np.isfinite(X[:, :, 0])
    # Background keypoints: labels that are seen in most frames and never move.
    seen = observed.mean(axis=0) > 0.8
    Xs = X[:, seen]
    spread = np.nanmax(np.linalg.norm(Xs - np.nanmedian(Xs, axis=0), axis=2), axis=0)
    static = spread < 1.5
    assert static.sum() >= 10
    # Hand keypoints: labels found on the hand disc in the first frame keep the same place on the hand
    # (constant forearm coordinates) while the hand travels ~150 px.
    first = np.flatnonzero(observed[0])
    on_hand = [lab for lab in first
               if np.linalg.norm(X[0, lab] - model.hand_position(seq[0])) < model.hand_radius]
    assert len(on_hand) >= 2
    travel = np.linalg.norm(model.hand_position(seq[-1]) - model.hand_position(seq[0]))
    assert travel > 100
    assert observed[:, on_hand].any(axis=1).mean() > 0.8
    consistent = []
    for lab in on_hand:
        frames = np.flatnonzero(observed[:, lab])
        assert len(frames) >= 0.4 * len(seq)
        local = np.array([_forearm_coordinates(model, seq[k], X[k, lab]) for k in frames])
        ok = np.linalg.norm(local - np.median(local, axis=0), axis=1) < 3.0
        assert ok.mean() >= 0.8          # a look-alike point on the hand may take the label now and then
        consistent.extend(ok)
    assert np.mean(consistent) >= 0.9


def test_imputation_fills_nans_and_nearest_beats_mean(setup):
    model, vec, rng = setup
    test_q = model.sample_joints(60, rng)
    X = vec.transform([model.render(q) for q in test_q])
    assert np.isnan(X).any()
    filled = vec.fill_missing(X)
    assert np.all(np.isfinite(filled))
    np.testing.assert_array_equal(filled[np.isfinite(X)], X[np.isfinite(X)])
    # Held-out masking: hide 10% of the observed keypoints (x and y together) and compare the guesses.
    pairs = np.isfinite(X[:, 0::2])
    hide = pairs & (rng.random(pairs.shape) < 0.1)
    masked = X.copy().reshape(len(X), -1, 2)
    masked[hide] = np.nan
    masked = masked.reshape(len(X), -1)
    truth = X.reshape(len(X), -1, 2)[hide]
    nearest = NearestImputer(5).fit(vec.training_vectors_).transform(masked).reshape(len(X), -1, 2)[hide]
    mean = MeanImputer().fit(vec.training_vectors_).transform(masked).reshape(len(X), -1, 2)[hide]
    err_nearest = np.sqrt(np.mean(np.sum((nearest - truth) ** 2, axis=1)))
    err_mean = np.sqrt(np.mean(np.sum((mean - truth) ** 2, axis=1)))
    assert err_nearest < 0.5 * err_mean


def test_vectorizer_input_checks():
    with pytest.raises(ValueError):
        KeypointVectorizer(imputation='median')
    with pytest.raises(RuntimeError):
        KeypointVectorizer().transform([np.zeros((50, 50), np.uint8)])
    imp = NearestImputer(2).fit(np.array([[0.0, 0.0], [1.0, 1.0], [10.0, np.nan]]))
    np.testing.assert_allclose(imp.transform([[0.9, np.nan]]), [[0.9, 0.5]])
    with pytest.raises(ValueError):
        imp.transform([[1.0, 2.0, 3.0]])


def _unit(v):
    return (v / np.linalg.norm(v, axis=-1, keepdims=True)).astype(np.float32)


def test_near_best_matches_keep_what_the_ratio_test_cannot_tell_from_a_look_alike():
    """Two labels with near-identical descriptors 50 px apart (an object corner and a background corner that looks
    like it): a keypoint between them loses the ratio test, yet near_best_matches offers it for both, closest first,
    with its descriptor distance; a keypoint that looks like neither is offered too, far behind (the caller's bound
    on the distance leaves it out)."""
    rng = np.random.default_rng(5)
    corner = _unit(rng.normal(size=128))
    look_alike = _unit(corner + 0.1 * _unit(rng.normal(size=128)))
    others = _unit(rng.normal(size=(4, 128)))
    places = np.array([[100.0, 100.0], [150.0, 100.0], [300.0, 50.0], [50.0, 300.0], [250.0, 250.0],
                       [320.0, 320.0]])
    thumbnail = rng.random((32, 32)).astype(np.float32)
    frames = []
    for _ in range(30):
        desc = _unit(np.vstack([corner, look_alike, others]) + 0.002 * rng.normal(size=(6, 128)))
        frames.append(FrameKeypoints(places + rng.normal(0.0, 0.5, places.shape), desc, thumbnail))
    vec = KeypointVectorizer(random_state=0).fit(frames)
    label_of = vec.assign_labels(frames[0])
    assert sorted(label_of.tolist()) == list(range(6))
    between = _unit(corner + look_alike)
    stranger = _unit(rng.normal(size=128))
    frame = FrameKeypoints(np.array([[125.0, 100.0], [300.0, 50.0], [125.0, 96.0]]),
                           np.vstack([between, others[0], stranger]), thumbnail)
    assert vec.assign_labels(frame).tolist() == [-1, label_of[2], -1]
    wanted = [label_of[0], label_of[1], label_of[2], label_of[3]]
    positions, distances = vec.near_best_matches(frame, wanted, 2)
    assert positions.shape == (4, 2, 2) and distances.shape == (4, 2)
    for row in (0, 1):                                   # the ambiguous keypoint, for both look-alike labels
        np.testing.assert_allclose(positions[row, 0], [125.0, 100.0])
        np.testing.assert_allclose(positions[row, 1], [125.0, 96.0])
        assert distances[row, 0] < 0.01 and distances[row, 1] > 1.0
    np.testing.assert_allclose(positions[2, 0], [300.0, 50.0])                  # a clear match is near-best too
    assert np.isnan(positions[3]).all()                                          # not in the frame
