"""Collision prediction from rendered arm images, end to end (paper Section 3.5, Tables 1-2). No rclpy here.

Frames come from mm_sim.arm_model with the object re-placed every few frames (moving_object_exploration: the
paper varies the object's position independently of the arm); the touch-sensor label is the hand's contact.
Training and test frames come from disjoint placements (different random generators), so every test frame shows
the object where training never saw it. Pipeline: SIFT keypoints -> labelled keypoint vectors -> label roles from the
joint readings -> the vector to embed (mm_manifold.arm_learning) -> nearest-neighbour imputation -> LLE (or PCA)
embedding -> contact region. Everything is fitted on the training frames; the reported rates are on the test frames
embedded out of sample. Ground truth (contact of any part, distance) is used only for the scores.

Hyperparameters are chosen by 5-fold cross-validation on the training frames only
(mm_manifold.embedding.select_contact_model): LLE's n_neighbors, the radius (or threshold) of the contact region
and, for the 'best' rows, the region model itself among the paper's sphere (centre = mean of the contact frames),
the Mahalanobis ellipsoid and a quadric fitted by logistic regression. In each fold the frames are embedded out of
sample, as the test frames are, so the radius is set for out-of-sample frames. PCA goes through the same selection,
and two baselines work on the keypoint vector itself without an embedding (raw_vector_baselines).
"""
from __future__ import annotations

import time
from typing import Dict, Optional

import numpy as np

from mm_manifold.embedding import (REGION_MODELS, ContactSphere, best_of, confusion, fit_contact_model,
                                   select_contact_model)


def sample_exploration_joints(model, n: int, contact_share: float = 0.25, spread: float = 0.08,
                              rng: Optional[np.random.Generator] = None) -> np.ndarray:
    """n joint vectors: uniform inside the limits, plus about `contact_share` of them drawn around (Gaussian,
    `spread` rad) configurations that were in contact among the uniform ones (revisiting where contact was felt)."""
    rng = rng if rng is not None else np.random.default_rng()
    n_near = int(round(contact_share * n))
    uniform = model.sample_joints(n - n_near, rng)
    touched = uniform[[model.in_contact(q) for q in uniform]]
    while len(touched) == 0 and n_near > 0:       # keep exploring until contact was felt at least once
        extra = model.sample_joints(200, rng)
        touched = extra[[model.in_contact(q) for q in extra]]
    near = touched[rng.integers(0, len(touched), n_near)] + rng.normal(0.0, spread, (n_near, 2)) if n_near else \
        np.zeros((0, 2))
    q = np.vstack([uniform, near])
    q = np.clip(q, model.joint_limits[:, 0], model.joint_limits[:, 1])
    return q[rng.permutation(len(q))]


def moving_object_exploration(model, n_frames: int, replace_every: int = 10, revisit_share: float = 0.5,
                              spread: float = 0.08, rng: Optional[np.random.Generator] = None) -> Dict[str, np.ndarray]:
    """Exploration frames with the object re-placed every `replace_every` frames (paper 3.1: its position varies
    independently of the arm), as (joints, object position) per frame with the touch-sensor label and ground truth.

    The arm takes uniform random joint vectors; once the touch sensor has fired since the last re-placement, a
    share `revisit_share` of the next targets is drawn around (Gaussian, `spread` rad) where it fired - what the
    robot can do with its own readings to see contact more often. Returns dict(joints (n, 2), object (n, 2),
    contact (n,) hand touch, any_contact (n,) any arm part overlaps the object, distance (n,) hand-object centre
    distance [px], placement (n,) index of the placement). Ground truth beyond `contact` is for evaluation only."""
    rng = rng if rng is not None else np.random.default_rng()
    if n_frames < 1 or replace_every < 1 or not 0.0 <= revisit_share <= 1.0:
        raise ValueError('n_frames >= 1, replace_every >= 1 and 0 <= revisit_share <= 1 are required')
    out = {k: [] for k in ('joints', 'object', 'contact', 'any_contact', 'distance', 'placement')}
    touched = []
    for i in range(n_frames):
        if i % replace_every == 0:
            model.set_object_position(model.random_object_position(rng))
            touched = []
        if touched and rng.random() < revisit_share:
            q = model.clip_joints(touched[int(rng.integers(len(touched)))] + rng.normal(0.0, spread, 2))
        else:
            q = model.sample_joints(1, rng)[0]
        c = model.in_contact(q)
        if c:
            touched.append(q)
        out['joints'].append(q)
        out['object'].append(model.object_position_.copy())
        out['contact'].append(c)
        out['any_contact'].append(bool(np.any(model.part_clearances(q) < 0.0)))
        out['distance'].append(model.hand_object_distance(q))
        out['placement'].append(i // replace_every)
    return {k: np.asarray(v) for k, v in out.items()}


def render_keypoints(model, joints: np.ndarray, objects: np.ndarray, extractor) -> list:
    """SIFT keypoints of the frames with the arm at joints[i] and the object at objects[i]."""
    out = []
    for q, p in zip(joints, objects):
        if not np.array_equal(p, model.object_position_):
            model.set_object_position(p)
        out.append(extractor(model.render(q)))
    return out


def raw_vector_baselines(X_train: np.ndarray, c_train: np.ndarray, X_test: np.ndarray, c_test: np.ndarray,
                         n_neighbors_grid=(5, 15, 45), random_state: Optional[int] = 0) -> Dict[str, Dict]:
    """No embedding: the paper's sphere in the (globally scaled) keypoint vector space itself (centre = mean of the
    contact vectors, radius by validation on a split of the training frames), and a k-nearest-neighbour vote
    (k by 5-fold cross-validation on the training frames, balanced: the share of contact neighbours is compared
    with the training contact share)."""
    from sklearn.model_selection import StratifiedKFold
    from sklearn.neighbors import NearestNeighbors
    mean = X_train.mean(0)
    scale = max(float(np.sqrt(np.mean(X_train.std(0) ** 2))), 1e-9)
    Z, Zt = (X_train - mean) / scale, (X_test - mean) / scale
    sphere = ContactSphere(random_state=random_state).fit(Z, c_train)
    out = dict(raw_sphere=dict(confusion(sphere.predict(Zt), c_test), radius=float(sphere.radius_)))
    prior = float(np.mean(c_train))

    def vote(Zfit, cfit, Zq, k):
        nb = NearestNeighbors(n_neighbors=k).fit(Zfit).kneighbors(Zq, return_distance=False)
        return cfit[nb].mean(1) >= prior

    best_k, best_j = n_neighbors_grid[0], -np.inf
    folds = StratifiedKFold(5, shuffle=True, random_state=random_state)
    for k in n_neighbors_grid:
        pred = np.zeros(len(c_train), bool)
        for tr, va in folds.split(Z, c_train):
            pred[va] = vote(Z[tr], c_train[tr], Z[va], k)
        cv = confusion(pred, c_train)
        if cv['tpr'] - cv['fpr'] > best_j:
            best_k, best_j = k, cv['tpr'] - cv['fpr']
    out['raw_knn'] = dict(confusion(vote(Z, c_train, Zt, best_k), c_test), n_neighbors=int(best_k))
    return out


def _source_counts(sources) -> Dict[str, int]:
    from mm_manifold.arm_learning import OBJECT_SOURCES
    return {s: int(np.sum(np.asarray(sources) == s)) for s in OBJECT_SOURCES}


def embedding_rows(learner, X, c, X_test, c_test, d_test, n_neighbors_grid=(10, 20, 40),
                   keys: Optional[tuple] = None) -> Dict[str, object]:
    """Tables 1-2 rows of one keypoint vector: for LLE and PCA, n_neighbors, region model and radius by 5-fold
    cross-validation on the training vectors X (the regions on the learner's region_frames_), scored on X_test
    (embedded out of sample). `keys` (default all):
    which of '<method>_best' / '<method>_<region model>' to fit and score."""
    from scipy.stats import spearmanr
    result: Dict[str, object] = {}
    for method in ('lle', 'pca'):
        wanted = [(f'{method}_best', None)] + [(f'{method}_{m}', m) for m in REGION_MODELS]
        wanted = [(k, m) for k, m in wanted if keys is None or k in keys]
        if not wanted:
            continue
        t0 = time.perf_counter()
        sel = select_contact_model(X, c, method, learner.n_components, n_neighbors_grid,
                                   embedding_params=learner._embedding_params(method),
                                   random_state=learner.random_state, region_frames=learner.region_frames_)
        select_s = time.perf_counter() - t0
        for key, m in wanted:
            cand = sel['best'] if m is None else best_of(sel, m)
            emb, region = fit_contact_model(X, c, cand, method, learner.n_components,
                                            learner._embedding_params(method), learner.random_state,
                                            region_frames=learner.region_frames_)
            Y_test = emb.transform(X_test)
            conf = confusion(region.predict(Y_test), c_test)
            rho = spearmanr(region.closeness(Y_test), d_test)[0]
            result[key] = dict(conf, region=cand['model'], n_neighbors=cand['n_neighbors'], C=cand['C'],
                               radius=float(region.radius_) if hasattr(region, 'radius_') else None,
                               threshold=cand['threshold'], cv_tpr=cand['cv_tpr'], cv_fpr=cand['cv_fpr'],
                               select_s=select_s, closeness_distance_spearman=float(rho))
            if key == 'lle_sphere':
                result['_lle_sphere_model'] = (emb, region, Y_test)
        result[f'{method}_cv_candidates'] = sel['candidates']
    return result


def evaluate_collision_prediction(n_train: int = 1000, n_test: int = 300, scene_seed: int = 0,
                                  train_seed: int = 1, test_seed: int = 2, replace_every: int = 10,
                                  learner_params=None, n_neighbors_grid=(10, 20, 40),
                                  extractor=None, touch: str = 'hand',
                                  compare_params: Optional[Dict[str, Dict]] = None,
                                  geometry_from: Optional[str] = None) -> Dict[str, object]:
    """Learn from moving-object exploration frames (placements drawn with `train_seed`), score collision
    prediction on frames of other placements (`test_seed`): never seen in training. Same frames for every method.

    The keypoint vectors (labels, roles, representation) come from an ArmStateLearner fitted on the training frames
    (`learner_params`); then for LLE and PCA alike, n_neighbors (LLE), the region model and its radius / threshold
    are chosen by 5-fold cross-validation on the training frames (select_contact_model) and the held-out frames are
    embedded out of sample. Keys 'lle_sphere' / 'pca_sphere' (the paper's sphere), 'lle_best' / 'pca_best' (the
    region model with the best cross-validated TPR - FPR), one per region model ('lle_ellipsoid', ...), and the
    no-embedding baselines 'raw_sphere', 'raw_knn', 'disc' (contact_point only: ||d|| < the learner's own
    contact radius) and 'geometry' (the learner's keypoint-distance route on the
    frame alone); each a confusion dict (tp, fn, fp, tn, tpr, fpr) with the
    chosen hyperparameters and the Spearman of the region's closeness with the true distance. Also returns the
    learner and the test data (for the figures), class balance and timings. `touch`: the label the robot learns
    from and is scored against, 'hand' (the hand's touch sensor, the paper's label) or 'any_part' (a touch sensor
    covering the whole arm). `compare_params` {name: learner params}: a learner per entry fitted on the same
    training frames and scored on the same test frames, keys '<name>_lle_sphere', '<name>_lle_best' and
    '<name>_pca_sphere' (another keypoint vector beside the learner's own; the fitted learners are returned as
    '_compare_learners'). `geometry_from`: the compare_params entry
    whose learner scores the 'geometry' row (its embedding fallback and map_threshold belong to that vector; default
    the learner's own)."""
    from scipy.stats import spearmanr
    from mm_manifold.arm_learning import ArmStateLearner
    from mm_manifold.keypoints import KeypointExtractor
    from mm_sim.arm_model import ArmModel

    if touch not in ('hand', 'any_part'):
        raise ValueError("touch must be 'hand' or 'any_part'")
    if geometry_from is not None and geometry_from not in (compare_params or {}):
        raise ValueError(f'geometry_from {geometry_from!r} is not a compare_params entry')
    label = 'contact' if touch == 'hand' else 'any_contact'
    model = ArmModel(random_state=scene_seed)
    extractor = extractor or KeypointExtractor()
    train = moving_object_exploration(model, n_train, replace_every, rng=np.random.default_rng(train_seed))
    test = moving_object_exploration(model, n_test, replace_every, rng=np.random.default_rng(test_seed))
    t0 = time.perf_counter()
    kps_train = render_keypoints(model, train['joints'], train['object'], extractor)
    kps_test = render_keypoints(model, test['joints'], test['object'], extractor)
    frames_ms = 1e3 * (time.perf_counter() - t0) / (n_train + n_test)
    t0 = time.perf_counter()
    learner = ArmStateLearner(model.joint_limits, **(learner_params or {})).fit(kps_train, train['joints'], train[label])
    fit_s = time.perf_counter() - t0
    X, c = learner.train_vectors_, train[label]
    t0 = time.perf_counter()
    X_test = learner.frame_vectors(kps_test, test['joints'])
    vector_ms = 1e3 * (time.perf_counter() - t0) / n_test
    c_test, d_test = test[label], test['distance']
    gap = np.min(np.linalg.norm(test['object'][:, None] - np.unique(train['object'], axis=0)[None], axis=2), 1)
    roles = np.bincount(learner.label_roles_, minlength=4)
    result: Dict[str, object] = dict(
        n_train=n_train, n_test=n_test, replace_every=replace_every, touch=touch, scene_seed=scene_seed,
        train_seed=train_seed,
        test_seed=test_seed, train_placements=int(train['placement'].max() + 1),
        test_placements=int(test['placement'].max() + 1), train_contact=int(c.sum()), test_contact=int(c_test.sum()),
        train_contact_share=float(c.mean()), test_contact_share=float(c_test.mean()),
        test_object_to_nearest_training_placement_px=dict(min=float(gap.min()), median=float(np.median(gap))),
        n_labels=int(learner.vectorizer_.n_labels_), label_roles=dict(static=int(roles[0]), self=int(roles[1]),
                                                                      external=int(roles[2]), unclear=int(roles[3])),
        representation=learner.representation, lle_method=learner.lle_method, n_components=learner.n_components,
        vector_width=int(X.shape[1]), frames_ms=frames_ms, learner_fit_s=fit_s, vectorize_ms=vector_ms)
    if learner.representation == 'contact_point':
        result['object_sources_test'] = _source_counts(learner.object_track(kps_test)[1])
        # no embedding: the disc ||d|| < r the vector was fitted with, which tells the object estimate's errors
        # (both rows suffer them) from the embedded region's
        result['disc'] = dict(confusion(np.linalg.norm(X_test, axis=1) < learner.contact_radius_, c_test),
                              region='the contact-point vector\'s own disc', radius=float(learner.contact_radius_))
    result.update(embedding_rows(learner, X, c, X_test, c_test, d_test, n_neighbors_grid))
    compared = {}
    for name, params in (compare_params or {}).items():
        other = compared[name] = ArmStateLearner(model.joint_limits, **params).fit(kps_train, train['joints'],
                                                                                  train[label])
        rows = embedding_rows(other, other.train_vectors_, c, other.frame_vectors(kps_test, test['joints']), c_test,
                              d_test, n_neighbors_grid, keys=('lle_sphere', 'lle_best', 'pca_sphere'))
        result.update({f'{name}_{k}': v for k, v in rows.items() if not k.startswith('_') and 'cv_candidates' not in k})
        result[f'{name}_params'] = dict(params, vector_width=int(other.train_vectors_.shape[1]))
        if other.representation == 'contact_point':
            result[f'{name}_object_sources_test'] = _source_counts(other.object_track(kps_test)[1])
    use = learner.region_frames_           # every region, with or without an embedding, learns from the same frames
    result.update(raw_vector_baselines(X[use], c[use], X_test, c_test, random_state=learner.random_state))
    # no embedding, the image geometry: the learned object placed where the frame alone shows it, against the
    # robot's segments at the frame's joints (the keypoint-distance map route); frames that do not place the
    # object fall back to the LLE region
    geometry_learner = compared[geometry_from] if geometry_from is not None else learner
    t0 = time.perf_counter()
    preds = [geometry_learner.predict_frames(k, q[None], method='keypoint_distance') for k, q in zip(kps_test, test['joints'])]
    geometry_ms = 1e3 * (time.perf_counter() - t0) / n_test
    closeness = np.array([p['closeness'][0] for p in preds])
    result['geometry'] = dict(confusion(np.array([p['collision'][0] for p in preds]), c_test),
                              region='per-segment contact distances',
                              margin_quantile=geometry_learner.margin_quantile,
                              objects_learned=geometry_learner.n_objects_, vector=geometry_from or 'own',
                              fallback_frames=int(sum(p['method'] != 'keypoint_distance' for p in preds)),
                              closeness_distance_spearman=float(spearmanr(closeness, d_test)[0]),
                              predict_ms=geometry_ms)
    result['_learner'], result['_test'], result['_kps_test'], result['_model'] = learner, test, kps_test, model
    result['_train'], result['_kps_train'], result['_compare_learners'] = train, kps_train, compared
    return result


if __name__ == '__main__':      # python -m mm_bringup.arm_evaluation
    import json
    ev = evaluate_collision_prediction()
    print(json.dumps({k: v for k, v in ev.items() if not k.startswith('_') and not k.endswith('candidates')},
                     indent=1, default=str))
