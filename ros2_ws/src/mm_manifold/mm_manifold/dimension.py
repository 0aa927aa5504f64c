"""Intrinsic dimension of a sensor group's samples by local PCA (paper Section 2.5: detect the dimension of the
robot's dynamics instead of assuming it)."""
from __future__ import annotations

from typing import Optional

import numpy as np
from scipy.spatial import cKDTree


class LocalPCADimension:
    """Estimate the intrinsic dimension as the number of local principal components needed to explain
    `variance_threshold` of the variance in neighbourhoods of `n_neighbors` samples, voted over `n_centres` random
    centres (local, so a curved 2-D surface in 3-D still counts as 2-D).

    Learned attributes: dimension_, votes_ (count per dimension), explained_variance_ratio_ (mean local spectrum).
    """

    def __init__(self, n_neighbors: int = 30, variance_threshold: float = 0.95, n_centres: int = 200,
                 random_state: Optional[int] = 0):
        if n_neighbors < 3 or not 0 < variance_threshold <= 1:
            raise ValueError('n_neighbors >= 3 and 0 < variance_threshold <= 1 are required')
        self.n_neighbors = n_neighbors
        self.variance_threshold = variance_threshold
        self.n_centres = n_centres
        self.random_state = random_state

    def fit(self, X: np.ndarray) -> 'LocalPCADimension':
        X = np.asarray(X, dtype=float)
        if X.ndim != 2 or len(X) <= self.n_neighbors or not np.all(np.isfinite(X)):
            raise ValueError(f'need more than n_neighbors={self.n_neighbors} finite samples, got shape {X.shape}')
        rng = np.random.default_rng(self.random_state)
        centres = rng.choice(len(X), min(self.n_centres, len(X)), replace=False)
        _, nn = cKDTree(X).query(X[centres], k=self.n_neighbors)
        spectra = []
        votes = np.zeros(X.shape[1] + 1, dtype=int)
        for idx in nn:
            local = X[idx] - X[idx].mean(axis=0)
            s = np.linalg.svd(local, compute_uv=False) ** 2
            if s.sum() <= 0:
                continue
            ratio = s / s.sum()
            spectra.append(ratio)
            votes[int(np.searchsorted(np.cumsum(ratio), self.variance_threshold - 1e-12) + 1)] += 1
        self.votes_ = votes
        self.dimension_ = int(np.argmax(votes))
        self.explained_variance_ratio_ = np.mean(spectra, axis=0)
        return self
