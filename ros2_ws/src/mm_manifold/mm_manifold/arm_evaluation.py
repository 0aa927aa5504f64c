"""Collision prediction from rendered arm images, end to end (paper Section 3.5, Tables 1-2). No rclpy here.

Frames come from mm_sim.arm_model: random joint configurations, a share of them drawn around configurations where
the contact sensor fired (the robot feels contact, so an explorer can revisit it; without this bias contact frames
are rare). Pipeline: SIFT keypoints -> labelled keypoint vectors -> nearest-neighbour imputation -> LLE (or PCA)
3-D embedding -> contact region. Everything is fitted on the training frames; the reported rates are on held-out
frames embedded out of sample. Ground truth (contact, distance) is used only for the labels and the scores.

Hyperparameters are chosen by 5-fold cross-validation on the training frames only
(mm_manifold.embedding.select_contact_model): LLE's n_neighbors, the radius (or threshold) of the contact region
and, for the reported method, the region model itself among the paper's sphere (centre = mean of the contact
frames), the Mahalanobis ellipsoid and a quadric fitted by logistic regression. In each fold the frames are
embedded out of sample, as the held-out frames are, so the radius is set for out-of-sample frames. The held-out
split is touched once, to score the chosen models. PCA goes through the same selection (the baseline is treated
exactly like LLE).
"""
from __future__ import annotations

import time
from typing import Dict, Optional

import numpy as np

from mm_manifold.embedding import REGION_MODELS, best_of, confusion, fit_contact_model, select_contact_model
from mm_manifold.keypoints import KeypointVectorizer


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


def evaluate_collision_prediction(n_frames: int = 1000, random_state: Optional[int] = 0, test_fraction: float = 0.3,
                                  contact_share: float = 0.25, n_neighbors_grid=(10, 20, 40), n_components: int = 3,
                                  vectorizer_params=None, model_params=None, embedding_params=None,
                                  n_folds: int = 5) -> Dict[str, object]:
    """Render `n_frames` frames, learn on (1 - test_fraction) of them, score collision prediction on the rest.

    Returns a dict with the contact share, and per method and region model the held-out confusion (tp, fn, fp, tn,
    tpr, fpr), the cross-validated choice (region, n_neighbors, C, radius, cv_tpr, cv_fpr) and the Spearman
    correlation of the region's closeness with the true hand-object distance on the held-out frames, under keys
    'lle' / 'pca' (region model chosen by cross-validation) and 'lle_sphere', 'lle_ellipsoid', 'lle_quadric',
    'pca_sphere', ... (each region model with its own cross-validated n_neighbors and radius); timings: render /
    extraction / vectorising ms per frame, vectoriser fit s, selection s, final fit s.
    """
    from scipy.stats import spearmanr
    from mm_sim.arm_model import ArmModel

    rng = np.random.default_rng(random_state)
    model = ArmModel(random_state=random_state, **(model_params or {}))
    joints = sample_exploration_joints(model, n_frames, contact_share=contact_share, rng=rng)
    contact = np.array([model.in_contact(q) for q in joints])
    distance = np.array([model.hand_object_distance(q) for q in joints])

    t0 = time.perf_counter()
    frames = [model.render(q) for q in joints]
    render_ms = 1e3 * (time.perf_counter() - t0) / n_frames

    vec = KeypointVectorizer(random_state=random_state, **(vectorizer_params or {}))
    t0 = time.perf_counter()
    kps = [vec.extract(f) for f in frames]
    extract_ms = 1e3 * (time.perf_counter() - t0) / n_frames

    n_test = int(round(test_fraction * n_frames))
    test = np.zeros(n_frames, bool)
    test[rng.choice(n_frames, n_test, replace=False)] = True
    train_idx, test_idx = np.flatnonzero(~test), np.flatnonzero(test)

    t0 = time.perf_counter()
    vec.fit([kps[i] for i in train_idx])
    vec_fit_s = time.perf_counter() - t0
    X_train = vec.fill_missing(vec.training_vectors_)
    t0 = time.perf_counter()
    X_test_raw = vec.transform([kps[i] for i in test_idx])
    X_test = vec.fill_missing(X_test_raw)
    vectorize_ms = 1e3 * (time.perf_counter() - t0) / max(len(test_idx), 1)

    result: Dict[str, object] = dict(
        n_frames=n_frames, n_train=len(train_idx), n_test=len(test_idx), contact_share=float(contact.mean()),
        n_labels=int(vec.n_labels_), observed_share=float(np.isfinite(X_test_raw).mean()),
        keypoints_per_frame=float(np.mean([len(k) for k in kps])), render_ms=render_ms, extract_ms=extract_ms,
        vectorize_ms=vectorize_ms, vectorizer_fit_s=vec_fit_s)
    for method in ('lle', 'pca'):
        t0 = time.perf_counter()
        sel = select_contact_model(X_train, contact[train_idx], method=method, n_components=n_components,
                                   n_neighbors_grid=n_neighbors_grid, n_folds=n_folds,
                                   embedding_params=embedding_params, random_state=random_state)
        select_s = time.perf_counter() - t0
        for key, cand in [(method, sel['best'])] + [(f'{method}_{m}', best_of(sel, m)) for m in REGION_MODELS]:
            t0 = time.perf_counter()
            emb, region = fit_contact_model(X_train, contact[train_idx], cand, method=method,
                                            n_components=n_components, embedding_params=embedding_params,
                                            random_state=random_state)
            fit_s = time.perf_counter() - t0
            Y_test = emb.transform(X_test)
            c = confusion(region.predict(Y_test), contact[test_idx])
            rho = spearmanr(region.closeness(Y_test), distance[test_idx])[0]
            result[key] = dict(c, region=cand['model'], n_neighbors=cand['n_neighbors'], C=cand['C'],
                               radius=float(region.radius_) if hasattr(region, 'radius_') else None,
                               relative_radius=-cand['threshold'] if cand['model'] != 'quadric' else None,
                               threshold=cand['threshold'], cv_tpr=cand['cv_tpr'], cv_fpr=cand['cv_fpr'],
                               fit_s=fit_s, select_s=select_s, closeness_distance_spearman=float(rho))
        result[f'{method}_cv_candidates'] = sel['candidates']
    return result


if __name__ == '__main__':      # python -m mm_manifold.arm_evaluation [n_frames] [seed]
    import json
    import sys
    args = [int(a) for a in sys.argv[1:3]]
    print(json.dumps(evaluate_collision_prediction(*args), indent=2))
