"""Low-dimensional state from keypoint vectors: LLE (paper Section 3.2) with a PCA baseline, the contact sphere used to
predict collisions (Section 3.5, Tables 1-2) and the synthetic keypoint check of Section 3.4. No rclpy here.
"""
from __future__ import annotations

from typing import Dict, Optional, Sequence, Tuple

import numpy as np
from sklearn.decomposition import PCA
from sklearn.manifold import LocallyLinearEmbedding
from threadpoolctl import threadpool_limits

LLE_METRICS = ('unit', 'local')     # ImageEmbedding: unit-covariance LLE coordinates, or scaled to neighbour distances

class ImageEmbedding:
    """Embed imputed keypoint vectors in `n_components` dimensions with LLE (method='lle') or PCA (method='pca').

    Scaling: every coordinate is a pixel position, so by default ('global') all columns are divided by one common
    scale (the RMS column spread) - a hand keypoint that moves 150 px then weighs more than an elbow keypoint that
    moves 20 px, as it does in the image. 'standard' divides each column by its own spread (floored at `min_std` px
    so that keypoints which never move - background - do not turn their sub-pixel jitter into unit-variance
    noise); on rendered arm frames it inflates the small-motion keypoints near the shoulder together with their
    imputation errors, and predicts contact worse (see mm_bringup.arm_evaluation).

    LLE suits the arm because the image changes smoothly with the joints only locally (the paper's argument).
    lle_method='modified' (MLLE: several weight vectors per neighbourhood) is the default because standard LLE on
    these vectors often collapses the 2-joint manifold onto a curve, depending on n_neighbors; 'standard' is the
    paper's plain LLE. `transform` embeds new vectors out of sample with LLE's barycentric weights on the
    `n_neighbors` nearest training vectors, so a new frame lands among the training frames that look like it.

    LLE finds its coordinates only up to a linear map, and fixes it by making them unit-covariance: an input whose
    spread differs between directions comes out squeezed along the wider one, so a disc of the input (the hand
    within reach of the object) becomes an ellipse and the paper's sphere fits it badly. lle_metric='local' chooses
    the linear map instead so that squared distances between neighbours match those of the (scaled) input vectors
    (least squares over every training point's n_neighbors; the map is the square root of the fitted metric); it is
    applied to the stored embedding, so transform and a saved model carry it. 'unit' keeps sklearn's coordinates.

    Parameters: n_components, n_neighbors, method, scaling ('global' or 'standard'), reg (LLE regulariser),
    lle_method (sklearn's 'standard', 'modified', 'hessian', 'ltsa'), min_std [px], lle_metric ('unit' or
    'local'), random_state.
    Learned attributes: mean_, scale_, model_ (the sklearn estimator), embedding_ (training embedding),
    metric_map_ ((n_components, n_components) map applied to sklearn's LLE coordinates; identity for 'unit' and
    PCA), n_samples_seen_.
    """

    def __init__(self, n_components: int = 3, n_neighbors: int = 20, method: str = 'lle', scaling: str = 'global',
                 reg: float = 1e-3, lle_method: str = 'modified', min_std: float = 2.0, lle_metric: str = 'unit',
                 random_state: Optional[int] = 0):
        if n_components < 1 or n_neighbors < 2:
            raise ValueError('n_components >= 1 and n_neighbors >= 2 are required')
        if method not in ('lle', 'pca'):
            raise ValueError("method must be 'lle' or 'pca'")
        if scaling not in ('global', 'standard'):
            raise ValueError("scaling must be 'global' or 'standard'")
        if lle_metric not in LLE_METRICS:
            raise ValueError(f'lle_metric must be one of {LLE_METRICS}')
        self.n_components = int(n_components)
        self.n_neighbors = int(n_neighbors)
        self.method = method
        self.scaling = scaling
        self.reg = float(reg)
        self.lle_method = lle_method
        self.min_std = float(min_std)
        self.lle_metric = lle_metric
        self.random_state = random_state

    def _check(self, X: np.ndarray) -> np.ndarray:
        X = np.array(X, dtype=float, ndmin=2)
        if not np.all(np.isfinite(X)):
            raise ValueError('vectors contain NaN/inf; impute them first (KeypointVectorizer.fill_missing)')
        if hasattr(self, 'mean_') and X.shape[1] != self.mean_.shape[0]:
            raise ValueError(f'expected {self.mean_.shape[0]} columns, got {X.shape[1]}')
        return X

    def fit(self, X: np.ndarray) -> 'ImageEmbedding':
        X = self._check(X)
        if len(X) <= max(self.n_neighbors, self.n_components):
            raise ValueError('need more samples than n_neighbors and n_components')
        self.mean_ = X.mean(axis=0)
        std = X.std(axis=0)
        if self.scaling == 'standard':
            self.scale_ = np.maximum(std, self.min_std)
        else:
            self.scale_ = np.full_like(std, max(float(np.sqrt(np.mean(std ** 2))), 1e-9))
        Z = (X - self.mean_) / self.scale_
        if self.method == 'lle':
            self.model_ = LocallyLinearEmbedding(n_neighbors=self.n_neighbors, n_components=self.n_components,
                                                 reg=self.reg, method=self.lle_method, eigen_solver='dense',
                                                 random_state=self.random_state)
        else:
            self.model_ = PCA(n_components=self.n_components, random_state=self.random_state)
        self.embedding_ = self.model_.fit_transform(Z)
        self.metric_map_ = np.eye(self.n_components)
        if self.method == 'lle' and self.lle_metric == 'local':
            # LLE's own neighbour search, reused (this fit runs for every fold and n_neighbors of the selection)
            neighbours = self.model_.nbrs_.kneighbors(Z, self.n_neighbors + 1, return_distance=False)[:, 1:]
            self.metric_map_ = neighbour_metric_map(Z, self.embedding_, neighbours)
            self.embedding_ = self.embedding_ @ self.metric_map_
            self.model_.embedding_ = self.embedding_     # sklearn's out-of-sample transform combines these rows
        self.n_samples_seen_ = len(X)
        return self

    def transform(self, X: np.ndarray) -> np.ndarray:
        if not hasattr(self, 'model_'):
            raise RuntimeError('ImageEmbedding is not fitted')
        X = self._check(X)
        return self.model_.transform((X - self.mean_) / self.scale_)

    def fit_transform(self, X: np.ndarray) -> np.ndarray:
        return self.fit(X).embedding_.copy()


def neighbour_metric_map(Z: np.ndarray, Y: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """(m, m) symmetric map B such that |(y_i - y_j) B|^2 best matches |z_i - z_j|^2 (least squares) over each
    point i and its `neighbours` (n, k) indices j: the metric G = B B^T is linear in its m (m + 1) / 2 entries;
    negative eigenvalues (none on any fit seen) are floored."""
    i, j = np.repeat(np.arange(len(Z)), neighbours.shape[1]), neighbours.ravel()
    dY, dz2 = Y[i] - Y[j], ((Z[i] - Z[j]) ** 2).sum(axis=1)
    m = Y.shape[1]
    rows, cols = np.triu_indices(m)
    F = dY[:, rows] * dY[:, cols] * np.where(rows == cols, 1.0, 2.0)
    g = np.linalg.lstsq(F, dz2, rcond=None)[0]
    G = np.zeros((m, m))
    G[rows, cols] = g
    G[cols, rows] = g
    w, V = np.linalg.eigh(G)
    w = np.maximum(w, 1e-12 * max(float(w.max()), 1e-300))
    return (V * np.sqrt(w)) @ V.T


def confusion(predicted: Sequence[bool], actual: Sequence[bool]) -> Dict[str, float]:
    """Counts and rates in the layout of the paper's Tables 1-2: tp (collision recognised as collision), fn, fp
    (no collision recognised as collision), tn, tpr = tp / collisions, fpr = fp / no-collisions."""
    p = np.asarray(predicted, dtype=bool).ravel()
    a = np.asarray(actual, dtype=bool).ravel()
    if p.shape != a.shape:
        raise ValueError('predicted and actual must have the same length')
    tp, fn = int(np.sum(p & a)), int(np.sum(~p & a))
    fp, tn = int(np.sum(p & ~a)), int(np.sum(~p & ~a))
    return dict(tp=tp, fn=fn, fp=fp, tn=tn, tpr=tp / max(tp + fn, 1), fpr=fp / max(fp + tn, 1),
                balanced_accuracy=0.5 * (tp / max(tp + fn, 1) + tn / max(fp + tn, 1)))


def format_confusion(c: Dict[str, float], title: str = '') -> str:
    """Text table like the paper's Table 1."""
    pos, neg = c['tp'] + c['fn'], c['fp'] + c['tn']
    pct = lambda a, b: 100.0 * a / max(b, 1)  # noqa: E731
    lines = [title] if title else []
    lines += ['                            Collision (%)        No collision (%)',
              f"Recognized as collision     {c['tp']}/{pos} ({pct(c['tp'], pos):.1f})"
              f"        {c['fp']}/{neg} ({pct(c['fp'], neg):.1f})",
              f"Recognized as no collision  {c['fn']}/{pos} ({pct(c['fn'], pos):.1f})"
              f"        {c['tn']}/{neg} ({pct(c['tn'], neg):.1f})"]
    return '\n'.join(lines)


class ContactSphere:
    """Collision prediction in an embedding: inside a sphere centred on the mean of the contact samples.

    The paper sets the radius empirically for the best discrimination (r = 0.74). Here the radius is chosen by
    validation: the centre is the mean of the contact samples of a training split, and among `radius_grid`
    (default: quantiles of the distances) the radius that maximises `criterion` ('youden' = TPR - FPR, or
    'balanced_accuracy') on the held-out split wins; the centre (and shape) is then refitted on all contact samples.
    metric='mahalanobis' measures distance in the whitened frame of the contact samples (an ellipsoid): an
    embedding needs not keep the contact region round, and an ellipsoid follows its elongation with 6 more numbers.

    A radius can also be given relative to the spread of the contact samples (`relative_radius`: radius = that many
    times the RMS distance of the contact samples from the centre, in the metric's frame). The relative radius does
    not change when an embedding is refitted on other frames (LLE coordinates come out rotated and rescaled), so it
    is what cross-validation over refitted embeddings chooses (see select_contact_model).

    Parameters: radius (fixed; skips validation), relative_radius (fixed, in units of spread_; skips validation),
    radius_grid, criterion, metric ('euclidean' as in the paper or 'mahalanobis'), validation_fraction, random_state.
    Learned attributes: centre_, radius_, whitening_ (identity for 'euclidean'), spread_ (RMS distance of the
    contact samples from centre_), validation_ (confusion on the held-out split at radius_, or None).
    """

    def __init__(self, radius: Optional[float] = None, radius_grid: Optional[Sequence[float]] = None,
                 criterion: str = 'youden', metric: str = 'euclidean', validation_fraction: float = 0.3,
                 random_state: Optional[int] = 0, relative_radius: Optional[float] = None):
        if radius is not None and not radius > 0:
            raise ValueError('radius must be positive')
        if relative_radius is not None and not relative_radius > 0:
            raise ValueError('relative_radius must be positive')
        if radius is not None and relative_radius is not None:
            raise ValueError('give radius or relative_radius, not both')
        self.relative_radius = relative_radius
        if criterion not in ('youden', 'balanced_accuracy'):
            raise ValueError("criterion must be 'youden' or 'balanced_accuracy'")
        if metric not in ('euclidean', 'mahalanobis'):
            raise ValueError("metric must be 'euclidean' or 'mahalanobis'")
        if not 0.0 < validation_fraction < 1.0:
            raise ValueError('validation_fraction must be in (0, 1)')
        self.radius = radius
        self.radius_grid = radius_grid
        self.criterion = criterion
        self.metric = metric
        self.validation_fraction = validation_fraction
        self.random_state = random_state

    def _shape(self, Yc: np.ndarray):
        centre = Yc.mean(axis=0)
        if self.metric == 'euclidean' or len(Yc) <= Yc.shape[1]:
            return centre, np.eye(Yc.shape[1])
        cov = np.atleast_2d(np.cov(Yc.T))
        cov += np.eye(len(cov)) * 1e-9 * max(np.trace(cov), 1e-12)
        return centre, np.linalg.inv(np.linalg.cholesky(cov))

    def fit(self, Y: np.ndarray, contact: Sequence[bool]) -> 'ContactSphere':
        Y = np.array(Y, dtype=float, ndmin=2)
        c = np.asarray(contact, dtype=bool).ravel()
        if len(Y) != len(c):
            raise ValueError('Y and contact must have the same length')
        if not np.all(np.isfinite(Y)):
            raise ValueError('Y must be finite')
        if c.sum() < 2 or (~c).sum() < 2:
            raise ValueError('need at least two contact and two no-contact samples')
        self.validation_ = None
        if self.radius is not None:
            self.radius_ = float(self.radius)
        elif self.relative_radius is not None:
            self.radius_ = None        # set below from the spread of all contact samples
        else:
            rng = np.random.default_rng(self.random_state)
            val = np.zeros(len(c), bool)
            for cls in (True, False):      # stratified split: both classes in both parts
                idx = np.flatnonzero(c == cls)
                n_val = min(max(1, int(round(self.validation_fraction * len(idx)))), len(idx) - 1)
                val[rng.choice(idx, n_val, replace=False)] = True
            centre, white = self._shape(Y[~val & c])
            d_all = np.linalg.norm((Y - centre) @ white.T, axis=1)
            d_val = d_all[val]
            grid = (np.asarray(self.radius_grid, float) if self.radius_grid is not None else
                    np.unique(np.quantile(d_all, np.linspace(0.005, 0.995, 199))))
            best, best_r = -np.inf, float(grid[0])
            for r in grid:
                s = confusion(d_val <= r, c[val])
                score = s['tpr'] - s['fpr'] if self.criterion == 'youden' else s['balanced_accuracy']
                if score > best:
                    best, best_r = score, float(r)
            self.radius_ = best_r
            self.validation_ = confusion(d_val <= best_r, c[val])
        self.centre_, self.whitening_ = self._shape(Y[c])
        d_contact = np.linalg.norm((Y[c] - self.centre_) @ self.whitening_.T, axis=1)
        self.spread_ = max(float(np.sqrt(np.mean(d_contact ** 2))), 1e-12)
        if self.radius_ is None:
            self.radius_ = float(self.relative_radius) * self.spread_
        return self

    def distance(self, Y: np.ndarray) -> np.ndarray:
        """Distance to the centre (in the whitened frame for metric='mahalanobis')."""
        if not hasattr(self, 'centre_'):
            raise RuntimeError('ContactSphere is not fitted')
        Y = np.array(Y, dtype=float, ndmin=2)
        if Y.shape[1] != self.centre_.shape[0]:
            raise ValueError(f'expected {self.centre_.shape[0]} columns, got {Y.shape[1]}')
        return np.linalg.norm((Y - self.centre_) @ self.whitening_.T, axis=1)

    def predict(self, Y: np.ndarray) -> np.ndarray:
        """True where a state is inside the sphere (collision predicted)."""
        return self.distance(Y) <= self.radius_

    def closeness(self, Y: np.ndarray) -> np.ndarray:
        """1 - distance / radius: 1 at the contact centre, 0 on the sphere, negative outside."""
        return 1.0 - self.distance(Y) / self.radius_


def quadratic_features(Z: np.ndarray) -> np.ndarray:
    """[z_1 .. z_k, z_i z_j for i <= j] per row: the monomials of a quadric in k dimensions (without the constant)."""
    Z = np.array(Z, dtype=float, ndmin=2)
    iu = np.triu_indices(Z.shape[1])
    return np.hstack([Z, Z[:, iu[0]] * Z[:, iu[1]]])


class ContactQuadric:
    """Collision prediction in an embedding: on the contact side of a quadric surface, {y : f(y) >= threshold}.

    f(y) = b + w . z + z^T A z on the standardised coordinates z = (y - mean_) / std_ is fitted to separate the
    contact from the no-contact samples by L2-regularised logistic regression (strength 1/C, balanced class
    weights), so f is the log-odds of contact with both classes weighted equally. The paper's sphere (centre = mean
    of the contact samples, radius set for the best discrimination) and the Mahalanobis ellipsoid are quadrics
    too, with the same number of free coefficients as the ellipsoid (10 in 3-D), but their centre and shape are
    fixed by the contact samples' mean and covariance, not by where the contact / no-contact boundary lies. The
    fitted quadric need not be closed: in a 3-D embedding of the arm's 2-D image manifold the frames lie on a curved
    surface, and the contact patch on it is cut out best by whatever quadric meets the surface along the patch's
    edge (often a hyperboloid). Like any decision boundary it means nothing far outside the frames' range, and an
    out-of-sample LLE frame lands among training frames.

    Closeness (for planning margins and the closeness map) is (f - threshold) / depth_: 0 on the surface, negative
    outside, 1 at the median contact sample (depth_ = median f of the contact samples - threshold), the analogue of
    the sphere's 1 - distance / radius (0 on the sphere, 1 at its centre).

    Parameters: C (inverse regularisation), threshold (on f, 0 = equal odds), max_iter, random_state.
    Learned attributes: mean_, std_, coef_ (k + k(k+1)/2,), intercept_, threshold_, depth_.
    """

    def __init__(self, C: float = 100.0, threshold: float = 0.0, max_iter: int = 10000,
                 random_state: Optional[int] = 0):
        if not C > 0 or not np.isfinite(threshold):
            raise ValueError('C must be positive and threshold finite')
        self.C = float(C)
        self.threshold = float(threshold)
        self.max_iter = int(max_iter)
        self.random_state = random_state

    def fit(self, Y: np.ndarray, contact: Sequence[bool]) -> 'ContactQuadric':
        from sklearn.linear_model import LogisticRegression
        Y = np.array(Y, dtype=float, ndmin=2)
        c = np.asarray(contact, dtype=bool).ravel()
        if len(Y) != len(c):
            raise ValueError('Y and contact must have the same length')
        if not np.all(np.isfinite(Y)):
            raise ValueError('Y must be finite')
        if c.sum() < 2 or (~c).sum() < 2:
            raise ValueError('need at least two contact and two no-contact samples')
        self.mean_ = Y.mean(axis=0)
        self.std_ = np.maximum(Y.std(axis=0), 1e-12)
        lr = LogisticRegression(C=self.C, class_weight='balanced', max_iter=self.max_iter,
                                random_state=self.random_state)
        with threadpool_limits(1):      # 10 features: thread hand-off costs more than it saves
            lr.fit(quadratic_features((Y - self.mean_) / self.std_), c)
        self.coef_ = lr.coef_[0].copy()
        self.intercept_ = float(lr.intercept_[0])
        self.threshold_ = self.threshold
        f = self.decision(Y)
        self.depth_ = max(float(np.median(f[c])) - self.threshold_, 1e-3 * float(np.std(f)) + 1e-12)
        return self

    def decision(self, Y: np.ndarray) -> np.ndarray:
        """f(y): log-odds of contact (balanced classes)."""
        if not hasattr(self, 'coef_'):
            raise RuntimeError('ContactQuadric is not fitted')
        Y = np.array(Y, dtype=float, ndmin=2)
        if Y.shape[1] != self.mean_.shape[0]:
            raise ValueError(f'expected {self.mean_.shape[0]} columns, got {Y.shape[1]}')
        return quadratic_features((Y - self.mean_) / self.std_) @ self.coef_ + self.intercept_

    def predict(self, Y: np.ndarray) -> np.ndarray:
        """True on the contact side of the quadric (collision predicted)."""
        return self.decision(Y) >= self.threshold_

    def closeness(self, Y: np.ndarray) -> np.ndarray:
        """(f(y) - threshold) / depth_: 0 on the surface, 1 at the median contact sample, negative outside."""
        return (self.decision(Y) - self.threshold_) / self.depth_


REGION_MODELS = ('sphere', 'ellipsoid', 'quadric')


def best_threshold(score: np.ndarray, label: np.ndarray) -> Tuple[float, Dict[str, float]]:
    """Threshold t on `score` (predict score >= t) with the largest TPR - FPR; among equally good thresholds the
    middle one. Candidates lie half-way between consecutive distinct scores. Returns t and the confusion there."""
    score = np.asarray(score, dtype=float)
    label = np.asarray(label, dtype=bool)
    u = np.unique(score)
    cand = np.r_[u[0] - 1.0, 0.5 * (u[1:] + u[:-1]), u[-1] + 1.0] if len(u) > 1 else np.array([u[0]])
    pos, neg = np.sort(score[label]), np.sort(score[~label])
    tpr = 1.0 - np.searchsorted(pos, cand, side='left') / max(len(pos), 1)
    fpr = 1.0 - np.searchsorted(neg, cand, side='left') / max(len(neg), 1)
    j = tpr - fpr
    best = np.flatnonzero(j >= j.max() - 1e-12)
    t = float(cand[best[len(best) // 2]])
    return t, confusion(score >= t, label)


def _region_score(model: str, Y_fit: np.ndarray, c_fit: np.ndarray, Y_eval: np.ndarray, C: Optional[float],
                  random_state) -> np.ndarray:
    """Contact score of Y_eval under a region fitted on (Y_fit, c_fit); higher = more contact-like, comparable
    across refitted embeddings: minus the distance in units of the contact spread (sphere, ellipsoid) or the
    quadric's log-odds."""
    if model == 'quadric':
        return ContactQuadric(C=C, random_state=random_state).fit(Y_fit, c_fit).decision(Y_eval)
    metric = 'euclidean' if model == 'sphere' else 'mahalanobis'
    s = ContactSphere(relative_radius=1.0, metric=metric, random_state=random_state).fit(Y_fit, c_fit)
    return -s.distance(Y_eval) / s.spread_


def select_contact_model(X: np.ndarray, contact: Sequence[bool], method: str = 'lle', n_components: int = 3,
                         n_neighbors_grid: Sequence[int] = (10, 20, 40), models: Sequence[str] = REGION_MODELS,
                         C_grid: Sequence[float] = (1.0, 10.0, 100.0, 1000.0), n_folds: int = 5,
                         embedding_params: Optional[Dict] = None,
                         random_state: Optional[int] = 0,
                         region_frames: Optional[np.ndarray] = None) -> Dict[str, object]:
    """Choose n_neighbors, the contact region model ('sphere', 'ellipsoid', 'quadric'), its C (quadric) and its
    threshold (radius) by stratified k-fold cross-validation on training frames only.

    Per fold, the embedding is fitted on the other folds and the fold's frames are embedded out of sample - as
    held-out frames are later - and every region model is fitted on the other folds' embedding. The out-of-fold
    scores of all folds are pooled. For the sphere and the ellipsoid the score is the distance in units of the
    contact frames' spread, which does not change when LLE comes out rotated or rescaled in another fold, and the
    radius is the one with the largest pooled TPR - FPR (Youden's J). The quadric keeps its own boundary f = 0 (its
    logistic regression already weighs both classes equally): its log-odds scale is set by the regularisation and
    grows without bound when a fold's frames are separable, so a threshold fitted on pooled out-of-fold log-odds
    does not carry over to the final fit (measured: cross-validated TPR 1.0 and held-out 0.86). The candidate with
    the largest J wins (ties: the simpler model, listed first). For PCA n_neighbors plays no role and only the first
    value is tried. `region_frames` (bool per frame, default all): the frames whose label the regions are fitted to
    and scored on; every frame is embedded (a frame whose vector belies its label still shapes the manifold).
    Returns dict(best=<candidate>, candidates=[...]), a candidate being dict(n_neighbors, model, C, threshold,
    cv_tpr, cv_fpr, cv_youden); for spheres and ellipsoids the relative radius is -threshold, for the quadric the
    threshold is 0.
    """
    X = np.asarray(X, dtype=float)
    c = np.asarray(contact, dtype=bool).ravel()
    if len(X) != len(c):
        raise ValueError('X and contact must have the same length')
    use = np.ones(len(c), bool) if region_frames is None else np.asarray(region_frames, dtype=bool).ravel()
    if len(use) != len(c):
        raise ValueError('region_frames must have one entry per frame')
    if n_folds < 2 or min((c & use).sum(), (~c & use).sum()) < 2 * n_folds:
        raise ValueError(f'need n_folds >= 2 and at least {2 * n_folds} frames of each class')
    unknown = set(models) - set(REGION_MODELS)
    if unknown or not models:
        raise ValueError(f'models must be among {REGION_MODELS}')
    rng = np.random.default_rng(random_state)
    fold = np.empty(len(c), int)
    for cls in (True, False):
        idx = rng.permutation(np.flatnonzero(c == cls))
        fold[idx] = np.arange(len(idx)) % n_folds
    grid = list(n_neighbors_grid)[:1] if method == 'pca' else list(n_neighbors_grid)
    keys = [(m, None) if m != 'quadric' else (m, float(C)) for m in models for C in
            (C_grid if m == 'quadric' else [None])]
    keys = list(dict.fromkeys(keys))
    candidates = []
    for nn in grid:
        scores = {k: np.empty(len(c)) for k in keys}
        for f in range(n_folds):
            tr, va = fold != f, fold == f
            emb = ImageEmbedding(n_components, nn, method, random_state=random_state, **(embedding_params or {}))
            with threadpool_limits(1):
                emb.fit(X[tr])
                Y_va = emb.transform(X[va])
                for model, C in keys:
                    scores[(model, C)][va] = _region_score(model, emb.embedding_[use[tr]], c[tr][use[tr]], Y_va, C,
                                                           random_state)
        for model, C in keys:
            if model == 'quadric':      # its own boundary, f = 0 (see select_contact_model's docstring)
                t, conf = 0.0, confusion(scores[(model, C)][use] >= 0.0, c[use])
            else:
                t, conf = best_threshold(scores[(model, C)][use], c[use])
            candidates.append(dict(n_neighbors=int(nn), model=model, C=C, threshold=t, cv_tpr=conf['tpr'],
                                   cv_fpr=conf['fpr'], cv_youden=conf['tpr'] - conf['fpr']))
    best = max(candidates, key=lambda k: k['cv_youden'])       # first maximum: simpler model, fewer neighbours
    return dict(best=best, candidates=candidates)


def best_of(selection: Dict[str, object], model: str) -> Dict[str, object]:
    """The best cross-validated candidate of one region model in a select_contact_model result."""
    cands = [k for k in selection['candidates'] if k['model'] == model]
    if not cands:
        raise ValueError(f'no {model} candidate in the selection')
    return max(cands, key=lambda k: k['cv_youden'])


def fit_contact_model(X: np.ndarray, contact: Sequence[bool], candidate: Dict[str, object], method: str = 'lle',
                      n_components: int = 3, embedding_params: Optional[Dict] = None, random_state: Optional[int] = 0,
                      region_frames: Optional[np.ndarray] = None):
    """Fit the embedding on all training frames and the contact region of a cross-validated candidate on
    `region_frames` of them (default all; select_contact_model): returns (ImageEmbedding, ContactSphere or
    ContactQuadric)."""
    use = np.ones(len(X), bool) if region_frames is None else np.asarray(region_frames, dtype=bool).ravel()
    emb = ImageEmbedding(n_components, candidate['n_neighbors'], method, random_state=random_state,
                         **(embedding_params or {}))
    with threadpool_limits(1, user_api='blas'):
        emb.fit(X)
    if candidate['model'] == 'quadric':
        region = ContactQuadric(C=candidate['C'], threshold=candidate['threshold'], random_state=random_state)
    else:
        region = ContactSphere(relative_radius=max(-candidate['threshold'], 1e-6), random_state=random_state,
                               metric='euclidean' if candidate['model'] == 'sphere' else 'mahalanobis')
    return emb, region.fit(emb.embedding_[use], np.asarray(contact, dtype=bool)[use])


def synthetic_keypoint_frames(n_frames: int = 1000, n_object: int = 10, n_hand: int = 10, n_background: int = 5,
                              missing: float = 0.1, image_size: float = 400.0, part_radius: float = 20.0,
                              move_object: bool = False, random_state: Optional[int] = 0
                              ) -> Tuple[np.ndarray, np.ndarray]:
    """Virtual keypoints of the paper's Section 3.4: vectors (n_frames, 2 * (n_object + n_hand + n_background))
    [object, hand, background keypoints; x, y each] with `missing` of the keypoints removed (NaN) to simulate
    matching errors, and the hand-object distance [px] per frame.

    Hand and object are rigid sets of keypoints within `part_radius` of their centre; the hand centre is uniform in
    the image; the object is static at a random place (move_object=True also draws it uniformly per frame, as in
    the paper's description); background keypoints never move."""
    if n_frames < 1 or min(n_object, n_hand, n_background) < 0 or not 0.0 <= missing < 1.0:
        raise ValueError('n_frames >= 1, non-negative keypoint counts and 0 <= missing < 1 are required')
    rng = np.random.default_rng(random_state)
    margin = part_radius

    def offsets(n):
        a, r = rng.uniform(0, 2 * np.pi, n), part_radius * np.sqrt(rng.random(n))
        return np.stack([r * np.cos(a), r * np.sin(a)], 1)

    obj_off, hand_off = offsets(n_object), offsets(n_hand)
    background = rng.uniform(0, image_size, (n_background, 2))
    hand = rng.uniform(margin, image_size - margin, (n_frames, 2))
    if move_object:
        obj = rng.uniform(margin, image_size - margin, (n_frames, 2))
    else:
        obj = np.repeat(rng.uniform(margin, image_size - margin, (1, 2)), n_frames, axis=0)
    pts = np.concatenate([obj[:, None, :] + obj_off[None], hand[:, None, :] + hand_off[None],
                          np.repeat(background[None], n_frames, axis=0)], axis=1)
    drop = rng.random(pts.shape[:2]) < missing
    pts[drop] = np.nan
    return pts.reshape(n_frames, -1), np.linalg.norm(hand - obj, axis=1)
