"""Low-dimensional state from keypoint vectors: LLE (paper Section 3.2) with a PCA baseline, the contact sphere used to
predict collisions (Section 3.5, Tables 1-2) and the synthetic keypoint check of Section 3.4. No rclpy here.
"""
from __future__ import annotations

from typing import Dict, Optional, Sequence, Tuple

import numpy as np
from sklearn.decomposition import PCA
from sklearn.manifold import LocallyLinearEmbedding


class ImageEmbedding:
    """Embed imputed keypoint vectors in `n_components` dimensions with LLE (method='lle') or PCA (method='pca').

    Scaling: every coordinate is a pixel position, so by default ('global') all columns are divided by one common
    scale (the RMS column spread) - a hand keypoint that moves 150 px then weighs more than an elbow keypoint that
    moves 20 px, as it does in the image. 'standard' divides each column by its own spread (floored at `min_std` px
    so that keypoints which never move - background - do not turn their sub-pixel jitter into unit-variance
    noise); on rendered arm frames it inflates the small-motion keypoints near the shoulder together with their
    imputation errors, and predicts contact worse (see arm_evaluation).

    LLE suits the arm because the image changes smoothly with the joints only locally (the paper's argument).
    lle_method='modified' (MLLE: several weight vectors per neighbourhood) is the default because standard LLE on
    these vectors often collapses the 2-joint manifold onto a curve, depending on n_neighbors; 'standard' is the
    paper's plain LLE. `transform` embeds new vectors out of sample with LLE's barycentric weights on the
    `n_neighbors` nearest training vectors, so a new frame lands among the training frames that look like it.

    Parameters: n_components, n_neighbors, method, scaling ('global' or 'standard'), reg (LLE regulariser),
    lle_method (sklearn's 'standard', 'modified', 'hessian', 'ltsa'), min_std [px], random_state.
    Learned attributes: mean_, scale_, model_ (the sklearn estimator), embedding_ (training embedding),
    n_samples_seen_.
    """

    def __init__(self, n_components: int = 3, n_neighbors: int = 20, method: str = 'lle', scaling: str = 'global',
                 reg: float = 1e-3, lle_method: str = 'modified', min_std: float = 2.0,
                 random_state: Optional[int] = 0):
        if n_components < 1 or n_neighbors < 2:
            raise ValueError('n_components >= 1 and n_neighbors >= 2 are required')
        if method not in ('lle', 'pca'):
            raise ValueError("method must be 'lle' or 'pca'")
        if scaling not in ('global', 'standard'):
            raise ValueError("scaling must be 'global' or 'standard'")
        self.n_components = int(n_components)
        self.n_neighbors = int(n_neighbors)
        self.method = method
        self.scaling = scaling
        self.reg = float(reg)
        self.lle_method = lle_method
        self.min_std = float(min_std)
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
        self.n_samples_seen_ = len(X)
        return self

    def transform(self, X: np.ndarray) -> np.ndarray:
        if not hasattr(self, 'model_'):
            raise RuntimeError('ImageEmbedding is not fitted')
        X = self._check(X)
        return self.model_.transform((X - self.mean_) / self.scale_)

    def fit_transform(self, X: np.ndarray) -> np.ndarray:
        return self.fit(X).embedding_.copy()


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

    Parameters: radius (fixed; skips validation), radius_grid, criterion, metric ('euclidean' as in the paper or
    'mahalanobis'), validation_fraction, random_state.
    Learned attributes: centre_, radius_, whitening_ (identity for 'euclidean'), validation_ (confusion on the
    held-out split at radius_, or None).
    """

    def __init__(self, radius: Optional[float] = None, radius_grid: Optional[Sequence[float]] = None,
                 criterion: str = 'youden', metric: str = 'euclidean', validation_fraction: float = 0.3,
                 random_state: Optional[int] = 0):
        if radius is not None and not radius > 0:
            raise ValueError('radius must be positive')
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
