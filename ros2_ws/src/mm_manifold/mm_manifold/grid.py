"""Grid-based parameterisation of a redundant sensor space (paper Section 2.3, Fig. 4 and 7).

A 2-D grid of nodes is fitted to samples lying on a 2-D surface in R^m (m = 3 for the front sensors) by minimising
    E = sum_samples |x - surface(x)|^2 / n  +  stretch * sum_edges |n_i - n_j|^2  +  bend * sum_ribs |n_i - 2 n_j + n_k|^2
in the style of an active contour. The nodes start around the centre of the samples and the border nodes are
extended, iteration by iteration, to the ends of the samples, so the grid spreads over the sample region while it
fits the surface. A reading maps to continuous grid coordinates (row, col) by projecting it on the bilinear surface
(Gauss-Newton from its lattice position), and back by bilinear interpolation; both extend linearly past the border.
"""
from __future__ import annotations

from typing import Optional, Tuple

import numpy as np

from mm_manifold.compiled import compiled


class ElasticGrid:
    """Fit a rows x cols grid of nodes to samples of a 2-D surface embedded in R^m.

    The nodes live on a regular lattice over the samples' principal plane plus a fitted offset along the remaining
    (normal) directions, so the grid cannot fold and every reading has one well-defined chart position. The lattice
    starts around the centre of the samples and its border is extended step by step to the ends of the samples
    (`border_quantile` of them lie beyond each border); at every step the node offsets minimise closeness to the
    samples (bilinear assignment) plus `stretch` (membrane) and `bend` (thin-plate) smoothness.

    Parameters: grid shape, `stretch`, `bend`, `n_iter` spreading steps, `border_quantile`, `max_samples`,
    `random_state` (subsampling).
    Learned attributes: nodes_ (rows, cols, m), mean_, axes_ (principal basis), extent_ (2, 2) lattice bounds in the
    principal plane, residual_ (RMS distance of the samples to the surface), n_samples_seen_.
    """

    def __init__(self, rows: int = 10, cols: int = 10, stretch: float = 1e-5, bend: float = 1e-4, n_iter: int = 10,
                 border_quantile: float = 0.005, max_samples: int = 4000, random_state: Optional[int] = 0):
        if rows < 2 or cols < 2:
            raise ValueError('the grid needs at least 2x2 nodes')
        if stretch < 0 or bend < 0 or n_iter < 1 or not 0.0 <= border_quantile < 0.5:
            raise ValueError('stretch, bend >= 0, n_iter >= 1 and 0 <= border_quantile < 0.5 are required')
        self.rows, self.cols = rows, cols
        self.stretch, self.bend = stretch, bend
        self.n_iter = n_iter
        self.border_quantile = border_quantile
        self.max_samples = max_samples
        self.random_state = random_state

    # --- fitting ----------------------------------------------------------------------------------------------
    def fit(self, X: np.ndarray) -> 'ElasticGrid':
        X = self._subsample(self._check(X))
        self.mean_ = X.mean(axis=0)
        _, _, vt = np.linalg.svd(X - self.mean_, full_matrices=False)
        self.axes_ = vt
        plane = (X - self.mean_) @ vt[:2].T
        centre = np.median(plane, axis=0)
        target = np.quantile(plane, [self.border_quantile, 1 - self.border_quantile], axis=0)
        # Spread from a small lattice around the centre to the ends of the samples (paper Fig. 7).
        for t in range(1, self.n_iter + 1):
            grow = min(1.0, 0.1 + 0.9 * t / self.n_iter)
            self.extent_ = centre + (target - centre) * grow
            self._fit_offsets(X)
        self.n_samples_seen_ = len(X)
        self._update_residual(X)
        return self

    def partial_fit(self, X: np.ndarray, n_iter: int = 1) -> 'ElasticGrid':
        """Online update with all samples seen so far (the caller keeps the buffer): re-extend the border to the
        ends of the samples and refit the offsets, keeping the principal basis."""
        if not hasattr(self, 'nodes_'):
            return self.fit(X)
        X = self._subsample(self._check(X))
        plane = (X - self.mean_) @ self.axes_[:2].T
        self.extent_ = np.quantile(plane, [self.border_quantile, 1 - self.border_quantile], axis=0)
        for _ in range(n_iter):
            self._fit_offsets(X)
        self.n_samples_seen_ = len(X)
        self._update_residual(X)
        return self

    def _check(self, X) -> np.ndarray:
        X = np.asarray(X, dtype=float)
        if X.ndim != 2 or X.shape[0] < 10 or X.shape[1] < 3:
            raise ValueError(f'need at least 10 samples of dimension >= 3, got shape {X.shape}')
        if not np.all(np.isfinite(X)):
            raise ValueError('samples must be finite (drop out-of-range readings first)')
        return X

    def _subsample(self, X: np.ndarray) -> np.ndarray:
        if len(X) <= self.max_samples:
            return X
        rng = np.random.default_rng(self.random_state)
        return X[rng.choice(len(X), self.max_samples, replace=False)]

    def _smoothness_matrix(self) -> np.ndarray:
        n = self.rows * self.cols
        idx = np.arange(n).reshape(self.rows, self.cols)
        L = np.zeros((n, n))
        for a, b in list(zip(idx[:, :-1].ravel(), idx[:, 1:].ravel())) + list(zip(idx[:-1].ravel(), idx[1:].ravel())):
            L[[a, b], [a, b]] += self.stretch
            L[a, b] -= self.stretch
            L[b, a] -= self.stretch
        ribs = list(zip(idx[:, :-2].ravel(), idx[:, 1:-1].ravel(), idx[:, 2:].ravel()))
        ribs += list(zip(idx[:-2].ravel(), idx[1:-1].ravel(), idx[2:].ravel()))
        for a, b, c in ribs:
            w = np.zeros(n)
            w[[a, b, c]] = [1.0, -2.0, 1.0]
            L += self.bend * np.outer(w, w)
        return L

    def _lattice_rc(self, plane: np.ndarray) -> np.ndarray:
        cell = (self.extent_[1] - self.extent_[0]) / np.array([self.rows - 1, self.cols - 1])
        return (plane - self.extent_[0]) / cell

    def _fit_offsets(self, X: np.ndarray) -> None:
        """Offsets of the nodes along the normal directions: bilinear least squares + smoothness (linear solve)."""
        plane = (X - self.mean_) @ self.axes_[:2].T
        normal = (X - self.mean_) @ self.axes_[2:].T
        rc = self._lattice_rc(plane)
        inside = np.all((rc >= -0.5) & (rc <= np.array([self.rows - 0.5, self.cols - 0.5])), axis=1)
        rc, normal = rc[inside], normal[inside]
        r0 = np.clip(np.floor(rc[:, 0]).astype(int), 0, self.rows - 2)
        c0 = np.clip(np.floor(rc[:, 1]).astype(int), 0, self.cols - 2)
        a, b = np.clip(rc[:, 0] - r0, 0, 1), np.clip(rc[:, 1] - c0, 0, 1)
        n_nodes = self.rows * self.cols
        W = np.zeros((len(rc), n_nodes))
        rows = np.arange(len(rc))
        for dr, dc, w in ((0, 0, (1 - a) * (1 - b)), (0, 1, (1 - a) * b), (1, 0, a * (1 - b)), (1, 1, a * b)):
            np.add.at(W, (rows, (r0 + dr) * self.cols + c0 + dc), w)
        A = W.T @ W / max(len(rc), 1) + self._smoothness_matrix() + 1e-9 * np.eye(n_nodes)
        offsets = np.linalg.solve(A, W.T @ normal / max(len(rc), 1))
        lattice = np.stack(np.meshgrid(np.linspace(self.extent_[0, 0], self.extent_[1, 0], self.rows),
                                       np.linspace(self.extent_[0, 1], self.extent_[1, 1], self.cols),
                                       indexing='ij'), axis=-1).reshape(-1, 2)
        self.nodes_ = (self.mean_ + lattice @ self.axes_[:2] + offsets @ self.axes_[2:]).reshape(
            self.rows, self.cols, -1)

    def _update_residual(self, X: np.ndarray) -> None:
        self.residual_ = float(np.sqrt(np.mean(self.distance_to_surface(X) ** 2)))

    # --- mapping ----------------------------------------------------------------------------------------------
    def transform(self, X: np.ndarray, clip: bool = False, n_newton: int = 6) -> np.ndarray:
        """Readings (n, m) -> continuous grid coordinates (n, 2) = (row, col), by Gauss-Newton projection on the
        bilinear patch of the nearest cell (extrapolated past the border, unless `clip`)."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        rc = _project(np.ascontiguousarray(X), np.ascontiguousarray(self.nodes_), self.mean_,
                      np.ascontiguousarray(self.axes_[:2]), self.extent_, n_newton)
        if clip:
            rc[:, 0] = np.clip(rc[:, 0], 0, self.rows - 1)
            rc[:, 1] = np.clip(rc[:, 1], 0, self.cols - 1)
        return rc

    def inverse_transform(self, rc: np.ndarray) -> np.ndarray:
        """Grid coordinates (n, 2) -> readings (n, m) by bilinear interpolation (linear extrapolation outside)."""
        return self._bilinear(np.atleast_2d(np.asarray(rc, dtype=float)))

    def _bilinear(self, rc: np.ndarray, derivatives: bool = False):
        r0 = np.clip(np.floor(rc[:, 0]).astype(int), 0, self.rows - 2)
        c0 = np.clip(np.floor(rc[:, 1]).astype(int), 0, self.cols - 2)
        a = (rc[:, 0] - r0)[:, None]
        b = (rc[:, 1] - c0)[:, None]
        n00, n01 = self.nodes_[r0, c0], self.nodes_[r0, c0 + 1]
        n10, n11 = self.nodes_[r0 + 1, c0], self.nodes_[r0 + 1, c0 + 1]
        p = (1 - a) * (1 - b) * n00 + (1 - a) * b * n01 + a * (1 - b) * n10 + a * b * n11
        if not derivatives:
            return p
        dr = (1 - b) * (n10 - n00) + b * (n11 - n01)
        dc = (1 - a) * (n01 - n00) + a * (n11 - n10)
        return p, dr, dc

    def distance_to_surface(self, X: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(np.asarray(X, dtype=float))
        return np.linalg.norm(X - self.inverse_transform(self.transform(X)), axis=1)


@compiled
def _project(X, nodes, mean, axes, extent, n_newton):
    """ElasticGrid.transform's Gauss-Newton projection, one reading at a time: the state trackers call it on every
    sample, where numpy's per-call overhead on (1, 3) arrays cost ~0.5 ms. numpy's error model: a division by zero
    gives inf or NaN, as the numpy code did, instead of raising."""
    rows, cols, m = nodes.shape
    out = np.empty((X.shape[0], 2))
    cell_r = (extent[1, 0] - extent[0, 0]) / (rows - 1)
    cell_c = (extent[1, 1] - extent[0, 1]) / (cols - 1)
    dr = np.empty(m)
    dc = np.empty(m)
    for n in range(X.shape[0]):
        pr = 0.0
        pc = 0.0
        for k in range(m):
            pr += (X[n, k] - mean[k]) * axes[0, k]
            pc += (X[n, k] - mean[k]) * axes[1, k]
        r = (pr - extent[0, 0]) / cell_r
        c = (pc - extent[0, 1]) / cell_c
        for _ in range(n_newton):
            r0 = min(max(int(np.floor(r)), 0), rows - 2)
            c0 = min(max(int(np.floor(c)), 0), cols - 2)
            a = r - r0
            b = c - c0
            jrr = 1e-12
            jrc = 0.0
            jcc = 1e-12
            gr = 0.0
            gc = 0.0
            for k in range(m):
                n00, n01 = nodes[r0, c0, k], nodes[r0, c0 + 1, k]
                n10, n11 = nodes[r0 + 1, c0, k], nodes[r0 + 1, c0 + 1, k]
                p = (1 - a) * (1 - b) * n00 + (1 - a) * b * n01 + a * (1 - b) * n10 + a * b * n11
                dr_k = (1 - b) * (n10 - n00) + b * (n11 - n01)
                dc_k = (1 - a) * (n01 - n00) + a * (n11 - n10)
                res = X[n, k] - p
                jrr += dr_k * dr_k
                jrc += dr_k * dc_k
                jcc += dc_k * dc_k
                gr += dr_k * res
                gc += dc_k * res
            det = jrr * jcc - jrc * jrc
            if not det > 0.0:            # a degenerate cell (or a non-finite reading): keep the estimate
                break
            r += min(max((jcc * gr - jrc * gc) / det, -1.0), 1.0)
            c += min(max((jrr * gc - jrc * gr) / det, -1.0), 1.0)
        out[n, 0] = r
        out[n, 1] = c
    return out
