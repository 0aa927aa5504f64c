"""The arm's learned state, all in one object: keypoint vectors -> LLE (and PCA) -> contact region -> collision map
on the joint grid, with saving and loading without pickle (paper Sections 3.2, 3.3, 3.5). No rclpy here.

Inputs per training frame are what the robot has: its SIFT keypoints, its own joint angles and its touch sensor.
The contact region in the LLE space is the paper's sphere (centre = mean of the contact frames), the Mahalanobis
ellipsoid or a quadric fitted by logistic regression (mm_manifold.embedding); `region='auto'` (default) lets 5-fold
cross-validation on the training frames choose among them, and the radius (threshold) is always chosen by that
cross-validation, with the validation frames embedded out of sample as new frames are.

The collision map is what the planner needs: for each cell of the rows x cols joint grid, whether entering it is
predicted to collide. The prediction comes from the embedding, not from the touch labels directly: every training
frame gets the closeness of the contact region in the LLE space (in-sample embedding; 0 on the region's surface, 1
at its centre / a typical contact frame, negative outside), counts as "collision for planning" when its closeness is
at least -`map_margin` (a margin inflates the region for planning only, because the planner's moves sweep whole
cells while the region is fitted for the best TPR - FPR on single frames), and a cell is marked as collision when at
least `cell_collision_fraction` of its frames count as collision. Frames are assigned to the cell
that contains their joint angles; a cell holding fewer than `cell_min_frames` frames takes the nearest frames (joint
distance in units of the cell size) up to that number, so sparsely explored cells still get a prediction. The cell's
closeness is the largest closeness of those frames (the most contact-like view seen there). The planner uses it to
keep clear of the region (mm_planner.value_iteration.clearance_rewards): a cell the object only partly covers often
has no contact frame and too few frames near the region to be marked, but its closeness is still high.
"""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Dict, Optional, Sequence

import numpy as np
from scipy.spatial import cKDTree
from sklearn.decomposition import PCA
from sklearn.manifold import LocallyLinearEmbedding
from sklearn.neighbors import NearestNeighbors
from threadpoolctl import threadpool_limits

from mm_manifold.embedding import (REGION_MODELS, ContactQuadric, ContactSphere, ImageEmbedding, fit_contact_model,
                                   quadratic_features, select_contact_model)
from mm_manifold.keypoints import FrameKeypoints, KeypointVectorizer, MeanImputer, NearestImputer

FORMAT_VERSION = 2
DEFAULT_JOINT_LIMITS = ((-3.2, -0.8), (0.0, 2.2))
_VECTORIZER_PARAMS = ('n_labels', 'max_features', 'scale', 'match_ratio', 'max_pixel_shift', 'n_frame_neighbors',
                      'min_frame_fraction', 'exemplar_spacing', 'imputation', 'n_impute_neighbors', 'max_fit_frames',
                      'random_state')


class ModelFileError(RuntimeError):
    """A saved model that cannot be read (missing, corrupt, or of another format)."""


def cell_indices(joints: np.ndarray, joint_limits: np.ndarray, shape) -> np.ndarray:
    """(n, 2) integer (row, col) of the joint-grid cell holding each joint vector (outside: nearest border cell)."""
    lim = np.asarray(joint_limits, dtype=float)
    step = (lim[:, 1] - lim[:, 0]) / np.asarray(shape, dtype=float)
    idx = np.floor((np.asarray(joints, dtype=float) - lim[:, 0]) / step).astype(int)
    return np.clip(idx, 0, np.asarray(shape) - 1)


def cell_map(joints: np.ndarray, predicted: np.ndarray, closeness: np.ndarray, joint_limits, shape=(8, 12),
             min_frames: int = 3, fraction: float = 0.1):
    """Per-cell collision (bool) and closeness (float) from per-frame predictions (see the module docstring)."""
    joints = np.asarray(joints, dtype=float)
    predicted = np.asarray(predicted, dtype=bool)
    closeness = np.asarray(closeness, dtype=float)
    lim = np.asarray(joint_limits, dtype=float)
    rows, cols = shape
    step = (lim[:, 1] - lim[:, 0]) / np.array([rows, cols], float)
    cells = cell_indices(joints, lim, shape)
    tree = cKDTree(joints / step)
    collision = np.zeros((rows, cols), bool)
    close = np.full((rows, cols), -np.inf)
    k_min = min(int(min_frames), len(joints))
    for r in range(rows):
        for c in range(cols):
            members = np.flatnonzero((cells[:, 0] == r) & (cells[:, 1] == c))
            if len(members) < k_min:
                centre = (lim[:, 0] + (np.array([r, c]) + 0.5) * step) / step
                _, nearest = tree.query(centre, k=k_min)
                members = np.unique(np.r_[members, np.atleast_1d(nearest)])[:max(k_min, len(members))]
            collision[r, c] = predicted[members].mean() >= fraction
            close[r, c] = closeness[members].max()
    return collision, close


class ArmStateLearner:
    """Learn the arm's image state from frames and predict collisions (module docstring).

    Parameters: n_components (LLE and PCA dimensions), n_neighbors (LLE), lle_method, region ('auto', or one of
    'sphere' (the paper's), 'ellipsoid', 'quadric'), grid_shape (rows, cols), joint_limits, cell_min_frames,
    cell_collision_fraction, map_margin, vectorizer_params (dict for KeypointVectorizer), random_state, n_folds
    (cross-validation of the region).
    Learned attributes: vectorizer_, lle_, pca_, region_ and pca_region_ (ContactSphere or ContactQuadric),
    selection_ and pca_selection_ (the cross-validated choice: model, C, threshold, cv_tpr, cv_fpr),
    train_vectors_ (imputed), train_joints_, train_contact_, train_stamps_ (int ns, or -1), train_predicted_ and
    train_closeness_ (LLE region, in-sample), collision_map_ (rows, cols) bool, closeness_map_ (rows, cols).
    """

    def __init__(self, n_components: int = 3, n_neighbors: int = 20, lle_method: str = 'modified',
                 region: str = 'auto', grid_shape=(8, 12), joint_limits=DEFAULT_JOINT_LIMITS,
                 cell_min_frames: int = 3, cell_collision_fraction: float = 0.1, map_margin: float = 0.1,
                 vectorizer_params: Optional[Dict] = None, random_state: Optional[int] = 0, n_folds: int = 5):
        lim = np.asarray(joint_limits, dtype=float)
        if lim.shape != (2, 2) or not np.all(np.isfinite(lim)) or np.any(lim[:, 0] >= lim[:, 1]):
            raise ValueError('joint_limits must be ((lo0, hi0), (lo1, hi1)) with finite lo < hi')
        if len(grid_shape) != 2 or min(grid_shape) < 1:
            raise ValueError('grid_shape must be (rows >= 1, cols >= 1)')
        if cell_min_frames < 1 or not 0.0 < cell_collision_fraction <= 1.0:
            raise ValueError('cell_min_frames >= 1 and 0 < cell_collision_fraction <= 1 are required')
        if region != 'auto' and region not in REGION_MODELS:
            raise ValueError(f"region must be 'auto' or one of {REGION_MODELS}")
        if n_folds < 2:
            raise ValueError('n_folds must be >= 2')
        unknown = set(vectorizer_params or {}) - set(_VECTORIZER_PARAMS)
        if unknown:
            raise ValueError(f'unknown vectorizer parameters: {sorted(unknown)}')
        self.n_components = int(n_components)
        self.n_neighbors = int(n_neighbors)
        self.lle_method = lle_method
        self.region = region
        self.grid_shape = (int(grid_shape[0]), int(grid_shape[1]))
        self.joint_limits = lim
        self.cell_min_frames = int(cell_min_frames)
        self.cell_collision_fraction = float(cell_collision_fraction)
        if not 0.0 <= map_margin < 10.0:
            raise ValueError('map_margin must be in [0, 10)')
        self.map_margin = float(map_margin)
        self.vectorizer_params = dict(vectorizer_params or {})
        self.random_state = random_state
        self.n_folds = int(n_folds)

    # --- fitting ------------------------------------------------------------------------------------------
    def fit(self, keypoints: Sequence[FrameKeypoints], joints, contact, stamps=None) -> 'ArmStateLearner':
        joints = np.asarray(joints, dtype=float).reshape(-1, 2)
        contact = np.asarray(contact, dtype=bool).ravel()
        if not len(keypoints) == len(joints) == len(contact):
            raise ValueError('keypoints, joints and contact must have the same length')
        if not np.all(np.isfinite(joints)):
            raise ValueError('joints must be finite')
        if contact.sum() < 4 or (~contact).sum() < 4:
            raise ValueError(f'need at least 4 contact and 4 no-contact frames, got {int(contact.sum())} and '
                             f'{int((~contact).sum())}')
        # every fold needs two frames of each class: fewer folds while contact frames are scarce
        folds = max(2, min(self.n_folds, int(contact.sum()) // 2, int((~contact).sum()) // 2))
        with threadpool_limits(1, user_api='blas'):
            vec = KeypointVectorizer(**{'random_state': self.random_state, **self.vectorizer_params})
            vec.fit(list(keypoints))
            X = vec.fill_missing(vec.training_vectors_)
        models = REGION_MODELS if self.region == 'auto' else (self.region,)
        fitted = {}
        for method in ('lle', 'pca'):
            sel = select_contact_model(X, contact, method, self.n_components, (self.n_neighbors,), models,
                                       n_folds=folds, embedding_params=self._embedding_params(method),
                                       random_state=self.random_state)['best']
            emb, region = fit_contact_model(X, contact, sel, method, self.n_components,
                                            self._embedding_params(method), self.random_state)
            fitted[method] = (emb, region, sel)
        self.vectorizer_ = vec
        self.lle_, self.region_, self.selection_ = fitted['lle']
        self.pca_, self.pca_region_, self.pca_selection_ = fitted['pca']
        self.train_vectors_ = X
        self.train_joints_ = joints.copy()
        self.train_contact_ = contact.copy()
        self.train_stamps_ = (np.full(len(joints), -1, np.int64) if stamps is None
                              else np.asarray(stamps, dtype=np.int64).ravel())
        if len(self.train_stamps_) != len(joints):
            raise ValueError('stamps must have one entry per frame')
        self.__dict__.pop('_lle_tree', None)
        self._update_map()
        return self

    def _embedding_params(self, method: str) -> Dict:
        return dict(lle_method=self.lle_method) if method == 'lle' else {}

    def _update_map(self) -> None:
        self.train_predicted_ = self.region_.predict(self.lle_.embedding_)
        self.train_closeness_ = self.region_.closeness(self.lle_.embedding_)
        self.collision_map_, self.closeness_map_ = cell_map(
            self.train_joints_, self.train_closeness_ >= -self.map_margin, self.train_closeness_, self.joint_limits,
            self.grid_shape, self.cell_min_frames, self.cell_collision_fraction)

    @property
    def n_frames_(self) -> int:
        return len(self.train_joints_)

    # --- per-frame state ----------------------------------------------------------------------------------
    def transform(self, frame: FrameKeypoints) -> Dict[str, object]:
        """State of one new frame: raw vector (NaN where unmatched), labelled count, LLE and PCA coordinates
        (out of sample), collision prediction and closeness of the LLE contact region.

        The out-of-sample maps are those of ImageEmbedding.transform (LLE: barycentric weights of the n_neighbors
        nearest training vectors, regularised like scikit-learn's barycenter_weights; PCA: projection), computed
        here directly with a KD-tree: for one frame, scikit-learn's neighbour search costs tens of ms in thread
        start-up alone, which a per-frame node cannot afford."""
        if not hasattr(self, 'region_'):
            raise RuntimeError('ArmStateLearner is not fitted')
        raw = self.vectorizer_.vectorize(frame)
        x = self.vectorizer_.fill_missing(raw[None])[0]
        y = self.lle_transform(x[None])[0]
        p = self.pca_transform(x[None])[0]
        return dict(vector=raw, labelled=int(np.isfinite(raw).sum() // 2), embedding=y, pca_embedding=p,
                    collision=bool(self.region_.predict(y[None])[0]),
                    closeness=float(self.region_.closeness(y[None])[0]))

    def lle_transform(self, X: np.ndarray) -> np.ndarray:
        """LLE out-of-sample coordinates of imputed vectors (n, d)."""
        Z = (np.atleast_2d(X) - self.lle_.mean_) / self.lle_.scale_
        if not hasattr(self, '_lle_tree'):
            self._lle_Z = (self.train_vectors_ - self.lle_.mean_) / self.lle_.scale_
            self._lle_tree = cKDTree(self._lle_Z)
        k = min(self.n_neighbors, len(self._lle_Z))
        _, ind = self._lle_tree.query(Z, k=k)
        ind = np.atleast_2d(ind)
        out = np.empty((len(Z), self.lle_.embedding_.shape[1]))
        for i, (z, nb) in enumerate(zip(Z, ind)):
            D = self._lle_Z[nb] - z
            G = D @ D.T
            trace = float(np.trace(G))
            G.flat[::k + 1] += self.lle_.reg * trace if trace > 0 else self.lle_.reg
            w = np.linalg.solve(G, np.ones(k))
            out[i] = (w / w.sum()) @ self.lle_.embedding_[nb]
        return out

    def pca_transform(self, X: np.ndarray) -> np.ndarray:
        """PCA coordinates of imputed vectors (n, d)."""
        Z = (np.atleast_2d(X) - self.pca_.mean_) / self.pca_.scale_
        m = self.pca_.model_
        return (Z - m.mean_) @ m.components_.T

    # --- persistence (np.savez + JSON, no pickle) ---------------------------------------------------------
    def save(self, path: os.PathLike) -> None:
        """Write the fitted model to `path` (.npz) atomically: a temp file in the same directory + os.replace."""
        path = Path(path)
        vec = self.vectorizer_
        meta = dict(format_version=FORMAT_VERSION, n_components=self.n_components, n_neighbors=self.n_neighbors,
                    lle_method=self.lle_method, region=self.region, n_folds=self.n_folds,
                    grid_shape=list(self.grid_shape),
                    joint_limits=self.joint_limits.tolist(), cell_min_frames=self.cell_min_frames,
                    cell_collision_fraction=self.cell_collision_fraction, map_margin=self.map_margin,
                    vectorizer_params={k: getattr(vec, k) for k in _VECTORIZER_PARAMS},
                    random_state=self.random_state, n_labels=int(vec.n_labels_),
                    n_frames_seen=int(vec.n_frames_seen_),
                    selection=self.selection_, pca_selection=self.pca_selection_)
        region_arrays = {}
        for name in ('region', 'pca_region'):
            meta[name + '_state'], arrays = _region_state(getattr(self, name + '_'))
            region_arrays.update({f'{name}_{k}': v for k, v in arrays.items()})
        arrays = dict(
            meta=np.array(json.dumps(meta)),
            label_counts=vec.label_counts_, label_positions=vec.label_positions_,
            exemplar_positions=vec.exemplar_positions_, exemplar_descriptors=vec.exemplar_descriptors_,
            exemplar_labels=vec.exemplar_labels_, raw_training_vectors=vec.training_vectors_,
            lle_mean=self.lle_.mean_, lle_scale=self.lle_.scale_, lle_embedding=self.lle_.embedding_,
            pca_mean=self.pca_.mean_, pca_scale=self.pca_.scale_, pca_embedding=self.pca_.embedding_,
            pca_components=self.pca_.model_.components_, pca_model_mean=self.pca_.model_.mean_,
            pca_explained_variance=self.pca_.model_.explained_variance_,
            **region_arrays,
            train_vectors=self.train_vectors_, train_joints=self.train_joints_, train_contact=self.train_contact_,
            train_stamps=self.train_stamps_)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=path.name + '.', suffix='.tmp', dir=path.parent)
        try:
            with os.fdopen(fd, 'wb') as f:
                np.savez(f, **arrays)
            os.replace(tmp, path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise

    @classmethod
    def load(cls, path: os.PathLike) -> 'ArmStateLearner':
        """Read a model written by `save`; ModelFileError if it is missing, corrupt or of another format."""
        try:
            with np.load(Path(path), allow_pickle=False) as data:
                a = {k: data[k] for k in data.files}
            meta = json.loads(str(a['meta']))
            if meta.get('format_version') != FORMAT_VERSION:
                raise ModelFileError(f'{path}: format version {meta.get("format_version")}, expected {FORMAT_VERSION}')
            self = cls(meta['n_components'], meta['n_neighbors'], meta['lle_method'], meta['region'],
                       tuple(meta['grid_shape']), meta['joint_limits'], meta['cell_min_frames'],
                       meta['cell_collision_fraction'], meta['map_margin'], random_state=meta['random_state'],
                       n_folds=meta['n_folds'])
            self._restore(meta, a)
        except ModelFileError:
            raise
        except Exception as exc:  # zip/npy/JSON/key/shape errors all mean "this file is not a usable model"
            raise ModelFileError(f'{path}: cannot load model ({type(exc).__name__}: {exc})') from exc
        return self

    def _restore(self, meta: dict, a: Dict[str, np.ndarray]) -> None:
        vp = meta['vectorizer_params']
        vec = KeypointVectorizer(**vp)
        vec.n_labels_ = int(meta['n_labels'])
        vec.n_frames_seen_ = int(meta['n_frames_seen'])
        vec.label_counts_, vec.label_positions_ = a['label_counts'], a['label_positions']
        vec.exemplar_positions_ = a['exemplar_positions'].astype(np.float32)
        vec.exemplar_descriptors_ = a['exemplar_descriptors'].astype(np.float32)
        vec.exemplar_labels_ = a['exemplar_labels'].astype(int)
        if vec.exemplar_labels_.size and vec.exemplar_labels_.max() >= vec.n_labels_:
            raise ModelFileError('exemplar labels exceed the number of labels')
        vec._exemplar_tree = cKDTree(vec.exemplar_positions_)
        vec.training_vectors_ = a['raw_training_vectors']
        if vec.training_vectors_.shape[1] != 2 * vec.n_labels_:
            raise ModelFileError('training vectors do not match the number of labels')
        vec.imputer_ = (NearestImputer(vec.n_impute_neighbors) if vec.imputation == 'nearest'
                        else MeanImputer()).fit(vec.training_vectors_)
        self.vectorizer_ = vec
        X = a['train_vectors']
        for name in ('lle', 'pca'):
            emb = ImageEmbedding(self.n_components, self.n_neighbors, name, lle_method=self.lle_method,
                                 random_state=self.random_state)
            emb.mean_, emb.scale_, emb.embedding_ = a[f'{name}_mean'], a[f'{name}_scale'], a[f'{name}_embedding']
            emb.n_samples_seen_ = len(X)
            Z = (X - emb.mean_) / emb.scale_
            if name == 'lle':
                m = LocallyLinearEmbedding(n_neighbors=self.n_neighbors, n_components=self.n_components,
                                           method=self.lle_method, eigen_solver='dense',
                                           random_state=self.random_state)
                m.nbrs_ = NearestNeighbors(n_neighbors=self.n_neighbors).fit(Z)
                m.embedding_ = emb.embedding_
            else:
                m = PCA(n_components=self.n_components, random_state=self.random_state)
                m.components_, m.mean_ = a['pca_components'], a['pca_model_mean']
                m.explained_variance_ = a['pca_explained_variance']
                m.n_components_ = self.n_components
            m.n_features_in_ = Z.shape[1]
            emb.model_ = m
            if emb.embedding_.shape != (len(X), self.n_components):
                raise ModelFileError(f'{name} embedding has shape {emb.embedding_.shape}')
            setattr(self, f'{name}_', emb)
        for name in ('region', 'pca_region'):
            arrays = {k[len(name) + 1:]: v for k, v in a.items() if k.startswith(name + '_')}
            setattr(self, name + '_', _region_from_state(meta[name + '_state'], arrays, self.random_state))
        self.selection_, self.pca_selection_ = meta['selection'], meta['pca_selection']
        self.train_vectors_ = X
        self.train_joints_ = a['train_joints']
        self.train_contact_ = a['train_contact'].astype(bool)
        self.train_stamps_ = a['train_stamps'].astype(np.int64)
        if not len(self.train_joints_) == len(self.train_contact_) == len(X) == len(self.train_stamps_):
            raise ModelFileError('training arrays have different lengths')
        self._update_map()


def _region_state(region):
    """(JSON-able parameters, arrays) of a fitted ContactSphere or ContactQuadric, for saving without pickle."""
    if isinstance(region, ContactQuadric):
        return (dict(kind='quadric', C=region.C, threshold=region.threshold_, intercept=region.intercept_,
                     depth=region.depth_),
                dict(mean=region.mean_, std=region.std_, coef=region.coef_))
    return (dict(kind='sphere' if region.metric == 'euclidean' else 'ellipsoid', radius=float(region.radius_),
                 spread=float(region.spread_)),
            dict(centre=region.centre_, whitening=region.whitening_))


def _region_from_state(meta: dict, arrays: Dict[str, np.ndarray], random_state):
    if meta['kind'] == 'quadric':
        r = ContactQuadric(C=meta['C'], threshold=meta['threshold'], random_state=random_state)
        r.mean_, r.std_, r.coef_ = arrays['mean'], arrays['std'], arrays['coef']
        if not r.mean_.shape == r.std_.shape or r.coef_.shape != quadratic_features(r.mean_[None]).shape[1:]:
            raise ModelFileError('quadric arrays do not fit together')
        r.intercept_, r.threshold_, r.depth_ = float(meta['intercept']), float(meta['threshold']), float(meta['depth'])
        return r
    if meta['kind'] not in ('sphere', 'ellipsoid'):
        raise ModelFileError(f"unknown contact region {meta['kind']!r}")
    r = ContactSphere(radius=meta['radius'], metric='euclidean' if meta['kind'] == 'sphere' else 'mahalanobis',
                      random_state=random_state)
    r.centre_, r.whitening_ = arrays['centre'], arrays['whitening']
    r.radius_, r.spread_, r.validation_ = float(meta['radius']), float(meta['spread']), None
    if r.whitening_.shape != (len(r.centre_), len(r.centre_)):
        raise ModelFileError('sphere arrays do not fit together')
    return r
