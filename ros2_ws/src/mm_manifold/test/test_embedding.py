import numpy as np
import pytest
from scipy.stats import spearmanr

from mm_manifold.embedding import (ContactQuadric, ContactSphere, ImageEmbedding, best_of, best_threshold,
                                   confusion, fit_contact_model, format_confusion, quadratic_features,
                                   select_contact_model, synthetic_keypoint_frames)
from mm_manifold.keypoints import NearestImputer


def _swiss_roll(n, seed):
    rng = np.random.default_rng(seed)
    t = 1.5 * np.pi * (1 + 2 * rng.random(n))
    h = 20 * rng.random(n)
    return np.stack([t * np.cos(t), h, t * np.sin(t)], 1)


@pytest.mark.parametrize('method', ['lle', 'pca'])
def test_out_of_sample_transform_of_training_vectors_lands_near_their_embedding(method):
    X = _swiss_roll(600, 0)
    emb = ImageEmbedding(n_components=2, n_neighbors=12, method=method).fit(X)
    Y = emb.transform(X)
    spread = np.linalg.norm(emb.embedding_ - emb.embedding_.mean(0), axis=1).mean()
    err = np.linalg.norm(Y - emb.embedding_, axis=1)
    assert np.median(err) < 0.02 * spread
    assert np.percentile(err, 95) < 0.1 * spread
    # New points near training points land near them too.
    Xn = X + np.random.default_rng(1).normal(0, 0.05, X.shape)
    assert np.median(np.linalg.norm(emb.transform(Xn) - emb.embedding_, axis=1)) < 0.1 * spread


def test_local_lle_metric_keeps_a_disc_round_where_unit_coordinates_squeeze_it():
    """A 2-D input three times wider than high: LLE's unit-covariance coordinates squeeze the wide direction, so a
    disc of the input comes out as an ellipse; lle_metric='local' scales the coordinates back to the input's
    neighbour distances and the disc stays round; transform gives the scaled coordinates too."""
    rng = np.random.default_rng(0)
    X = rng.uniform([-3.0, -1.0], [3.0, 1.0], (1200, 2))
    disc = np.linalg.norm(X, axis=1) < 0.5

    def aspect(Y):
        w = np.linalg.eigvalsh(np.cov((Y[disc] - Y[disc].mean(0)).T))
        return float(np.sqrt(w[1] / w[0]))
    unit = ImageEmbedding(2, 10, 'lle', lle_method='standard').fit(X)
    local = ImageEmbedding(2, 10, 'lle', lle_method='standard', lle_metric='local').fit(X)
    assert aspect(unit.embedding_) > 2.0
    assert aspect(local.embedding_) < 1.3
    np.testing.assert_allclose(np.eye(2), unit.metric_map_)
    np.testing.assert_allclose(local.transform(X[:50]), local.embedding_[:50], atol=0.05 * local.embedding_.std())
    with pytest.raises(ValueError, match='lle_metric'):
        ImageEmbedding(2, 10, 'lle', lle_metric='whitened')


def test_embedding_rejects_nan_and_wrong_width():
    emb = ImageEmbedding(n_components=2, n_neighbors=8)
    with pytest.raises(ValueError):
        emb.fit(np.array([[np.nan, 0.0]] * 20))
    emb.fit(_swiss_roll(100, 2))
    with pytest.raises(ValueError):
        emb.transform(np.zeros((1, 4)))
    with pytest.raises(ValueError):
        ImageEmbedding(method='isomap')


def test_contact_sphere_on_separable_data():
    rng = np.random.default_rng(0)
    contact = rng.normal([3.0, 3.0, 3.0], 0.3, (150, 3))
    free = rng.normal(0.0, 1.0, (600, 3))
    Y = np.vstack([contact, free])
    c = np.r_[np.ones(150, bool), np.zeros(600, bool)]
    sphere = ContactSphere(random_state=0).fit(Y, c)
    np.testing.assert_allclose(sphere.centre_, contact.mean(0))
    assert 0.5 < sphere.radius_ < 2.5
    result = confusion(sphere.predict(Y), c)
    assert result['tpr'] > 0.97 and result['fpr'] < 0.02
    assert result['tp'] + result['fn'] == 150 and result['fp'] + result['tn'] == 600
    closeness = sphere.closeness(np.vstack([sphere.centre_, sphere.centre_ + [sphere.radius_, 0, 0], [-5, -5, -5]]))
    np.testing.assert_allclose(closeness[:2], [1.0, 0.0], atol=1e-12)
    assert closeness[2] < 0
    assert 'Recognized as collision' in format_confusion(result)
    # The ellipsoid variant follows an elongated contact region.
    stretched = np.vstack([contact * [4.0, 1.0, 1.0], free])
    ell = ContactSphere(metric='mahalanobis').fit(stretched, c)
    assert confusion(ell.predict(stretched), c)['fpr'] < 0.02
    with pytest.raises(ValueError):
        ContactSphere().fit(Y, np.zeros(len(Y), bool))


def test_confusion_counts():
    r = confusion([True, True, False, False, True], [True, False, False, True, True])
    assert (r['tp'], r['fp'], r['fn'], r['tn']) == (2, 1, 1, 1)
    assert r['tpr'] == pytest.approx(2 / 3) and r['fpr'] == pytest.approx(0.5)


def test_synthetic_keypoints_lle_coordinate_follows_hand_object_distance():
    X, d = synthetic_keypoint_frames(n_frames=1000, missing=0.1, random_state=0)
    assert X.shape == (1000, 50)
    assert 0.08 < np.isnan(X).mean() < 0.12
    filled = NearestImputer(5).fit(X).transform(X)
    Y = ImageEmbedding(n_components=3, n_neighbors=12, lle_method='standard', scaling='standard').fit_transform(filled)
    rho = max(abs(spearmanr(Y[:, i], d)[0]) for i in range(3))
    # Measured 0.93 with this seed (static object; one LLE axis runs away from the object).
    assert rho > 0.85


def test_relative_radius_is_a_multiple_of_the_contact_spread():
    rng = np.random.default_rng(3)
    Y = np.vstack([rng.normal([2.0, 0.0, 0.0], 0.5, (80, 3)), rng.normal(0.0, 2.0, (300, 3))])
    c = np.r_[np.ones(80, bool), np.zeros(300, bool)]
    for metric in ('euclidean', 'mahalanobis'):
        s = ContactSphere(relative_radius=1.5, metric=metric).fit(Y, c)
        d = s.distance(Y[c])
        assert s.spread_ == pytest.approx(np.sqrt(np.mean(d ** 2)))
        assert s.radius_ == pytest.approx(1.5 * s.spread_)
        assert s.validation_ is None
    # rotating and scaling the embedding (what a refit of LLE does) leaves the relative prediction unchanged
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    a = ContactSphere(relative_radius=1.2).fit(Y, c).predict(Y)
    b = ContactSphere(relative_radius=1.2).fit(7.0 * Y @ q, c).predict(7.0 * Y @ q)
    np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError):
        ContactSphere(radius=1.0, relative_radius=1.0)


def test_best_threshold_maximises_youden():
    score = np.array([0.1, 0.2, 0.3, 0.9, 0.8, 0.35])
    label = np.array([False, False, False, True, True, True])
    t, conf = best_threshold(score, label)
    assert 0.3 < t < 0.35
    assert conf['tpr'] == 1.0 and conf['fpr'] == 0.0


def _curved_patch_data(n, seed):
    """Frames on a curved 2-D surface in 3-D (like a 3-D embedding of the arm's 2-D image manifold); contact = a
    disc of the surface's own coordinates, which no sphere around the contact mean cuts out cleanly."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, (n, 2))
    near = rng.random(n) < 0.3
    u[near] = rng.normal([0.3, 0.0], 0.15, (near.sum(), 2))
    Y = np.stack([u[:, 0], u[:, 1], 1.5 * u[:, 0] ** 2 - 0.8 * u[:, 1] ** 2], 1)
    return Y, np.linalg.norm((u - [0.3, 0.0]) * [1.0, 0.4], axis=1) < 0.15


def test_contact_quadric_cuts_a_patch_out_of_a_curved_surface():
    Y, c = _curved_patch_data(1500, 0)
    Yt, ct = _curved_patch_data(800, 1)
    quad = ContactQuadric(C=100.0).fit(Y, c)
    q = confusion(quad.predict(Yt), ct)
    sphere = ContactSphere().fit(Y, c)
    s = confusion(sphere.predict(Yt), ct)
    assert q['tpr'] - q['fpr'] > 0.9
    assert q['tpr'] - q['fpr'] > s['tpr'] - s['fpr']
    close = quad.closeness(Y)
    np.testing.assert_array_equal(close >= 0, quad.predict(Y))
    assert np.median(close[c]) == pytest.approx(1.0)
    assert quad.coef_.shape == (quadratic_features(Y[:1]).shape[1],) == (9,)
    with pytest.raises(ValueError):
        ContactQuadric().fit(Y, np.zeros(len(Y), bool))


@pytest.mark.parametrize('method', ['pca', 'lle'])
def test_select_contact_model_cross_validates_on_training_frames(method):
    Y, c = _curved_patch_data(500, 2)
    rng = np.random.default_rng(0)
    X = np.hstack([Y, Y @ rng.normal(size=(3, 5))]) + rng.normal(0, 0.01, (500, 8))   # 8-D vectors, 3-D content
    sel = select_contact_model(X, c, method=method, n_neighbors_grid=(10, 20), C_grid=(10.0, 100.0), n_folds=4)
    n_grid = 1 if method == 'pca' else 2
    assert len(sel['candidates']) == n_grid * (2 + 2)
    best = sel['best']
    assert best['cv_youden'] == max(k['cv_youden'] for k in sel['candidates'])
    assert best_of(sel, 'sphere')['model'] == 'sphere'
    emb, region = fit_contact_model(X, c, best, method=method)
    Yt, ct = _curved_patch_data(400, 3)
    Xt = np.hstack([Yt, Yt @ np.random.default_rng(0).normal(size=(3, 5))])
    conf = confusion(region.predict(emb.transform(Xt)), ct)
    assert conf['tpr'] - conf['fpr'] > 0.8
    sphere_emb, sphere = fit_contact_model(X, c, best_of(sel, 'sphere'), method=method)
    assert isinstance(sphere, ContactSphere) and sphere.radius_ == pytest.approx(
        -best_of(sel, 'sphere')['threshold'] * sphere.spread_)
    with pytest.raises(ValueError):
        select_contact_model(X, np.zeros(len(X), bool))


def test_region_frames_leave_mislabelled_contact_frames_out_of_the_region():
    """Contact inside a disc of radius 1; a few 'contact' frames far outside it (a wrong label) pull the sphere's
    centre and radius outward, so it takes in far more no-contact frames. Left out of the region fit (region_frames),
    they no longer do; every frame is still embedded."""
    rng = np.random.default_rng(4)
    X = rng.uniform(-3.0, 3.0, (900, 2))
    c = np.linalg.norm(X, axis=1) < 1.0
    wrong = rng.choice(np.flatnonzero(np.linalg.norm(X, axis=1) > 2.5), 12, replace=False)
    c[wrong] = True
    use = np.ones(len(c), bool)
    use[wrong] = False
    Xt = rng.uniform(-3.0, 3.0, (2000, 2))
    ct = np.linalg.norm(Xt, axis=1) < 1.0
    fpr = {}
    for name, frames in (('all', None), ('clean', use)):
        sel = select_contact_model(X, c, method='pca', n_components=2, models=('sphere',), n_folds=4,
                                   region_frames=frames)
        emb, region = fit_contact_model(X, c, sel['best'], method='pca', n_components=2, region_frames=frames)
        assert emb.embedding_.shape == (900, 2)
        fpr[name] = confusion(region.predict(emb.transform(Xt)), ct)['fpr']
        assert confusion(region.predict(emb.transform(Xt)), ct)['tpr'] > 0.95
    assert fpr['clean'] < 0.02 and fpr['clean'] < 0.5 * fpr['all'], fpr
    with pytest.raises(ValueError):
        select_contact_model(X, c, method='pca', n_components=2, region_frames=use[:10])
