"""Jacobians from wheel input to sensor (or grid) coordinates, learned from consecutive samples (paper Section 2.2).

Two estimators over the same data (y_k, u_k, y_k+1), with dy/dt ~= J(y) u:
- RegionJacobians: local linear estimates per region (a kernel-weighted least-squares fit around each anchor point,
  e.g. the grid nodes), with standard errors and support: what the robot knows, and how well, region by region.
- PolynomialJacobianField: one smooth field J(y) = sum_f theta_f phi_f(y) (polynomial features of y), fitted to all
  samples by ridge regression. It evaluates vectorised (for predictive control) and extrapolates outside the sensing
  range, which is what the virtual sensor space starts from.
"""
from __future__ import annotations

from typing import Optional, Tuple

import numpy as np
from mm_common.learned_fields import blend_jacobians, jacobian_design, polynomial_features, theta_from_solution
from scipy.spatial import cKDTree


def finite_difference_rates(Y0: np.ndarray, Y1: np.ndarray, dt: float) -> np.ndarray:
    return (np.asarray(Y1, dtype=float) - np.asarray(Y0, dtype=float)) / dt


class RegionJacobians:
    """Local weighted least-squares Jacobians at anchor points.

    Parameters: `bandwidth` of the Gaussian kernel (in units of y), `n_neighbors` samples considered per anchor,
    `min_support` effective samples below which a region is marked unknown, `ridge`.
    Learned: anchors_ (a, dy), jacobians_ (a, dy, du), standard_errors_ (a, dy, du), support_ (a,) effective count.
    """

    def __init__(self, bandwidth: float = 0.8, n_neighbors: int = 80, min_support: float = 6.0, ridge: float = 1e-6):
        self.bandwidth = bandwidth
        self.n_neighbors = n_neighbors
        self.min_support = min_support
        self.ridge = ridge

    def fit(self, Y: np.ndarray, U: np.ndarray, Ydot: np.ndarray, anchors: np.ndarray) -> 'RegionJacobians':
        Y, U, Ydot = (np.asarray(a, dtype=float) for a in (Y, U, Ydot))
        anchors = np.atleast_2d(np.asarray(anchors, dtype=float))
        if not (len(Y) == len(U) == len(Ydot)) or len(Y) < 3:
            raise ValueError('Y, U and Ydot need the same number (>= 3) of samples')
        du, dy = U.shape[1], Ydot.shape[1]
        tree = cKDTree(Y)
        k = min(self.n_neighbors, len(Y))
        dist, idx = tree.query(anchors, k=k)
        self.anchors_ = anchors
        self.jacobians_ = np.full((len(anchors), dy, du), np.nan)
        self.standard_errors_ = np.full((len(anchors), dy, du), np.nan)
        self.support_ = np.zeros(len(anchors))
        for a in range(len(anchors)):
            w = np.exp(-0.5 * (dist[a] / self.bandwidth) ** 2)
            support = w.sum() ** 2 / max((w ** 2).sum(), 1e-300)   # Kish effective sample size
            self.support_[a] = support
            if support < self.min_support:
                continue
            X = U[idx[a]]
            T = Ydot[idx[a]]
            XtW = X.T * w
            A = XtW @ X + self.ridge * np.eye(du)
            J = np.linalg.solve(A, XtW @ T).T                      # (dy, du)
            resid = T - X @ J.T
            dof = max(support - du, 1.0)
            sigma2 = (w[:, None] * resid ** 2).sum(axis=0) / w.sum() * support / dof
            cov = np.linalg.inv(A) @ (XtW * w) @ X @ np.linalg.inv(A)   # sandwich for weighted LS
            self.jacobians_[a] = J
            self.standard_errors_[a] = np.sqrt(np.outer(sigma2, np.diag(cov)))
        return self

    def interpolate(self, y: np.ndarray, k: int = 4) -> np.ndarray:
        """Inverse-distance blend of the k nearest known regions' Jacobians at y (for control)."""
        known = self.known()
        return blend_jacobians(self.anchors_[known], self.jacobians_[known], y, k)

    def known(self) -> np.ndarray:
        """Indices of the regions with enough support for a Jacobian."""
        return np.flatnonzero(np.isfinite(self.jacobians_[:, 0, 0]))

    def at(self, y: np.ndarray) -> Tuple[np.ndarray, np.ndarray, float]:
        """Estimate of the nearest known region: (J, standard errors, support)."""
        known = np.isfinite(self.jacobians_[:, 0, 0])
        if not known.any():
            raise ValueError('no region has enough support yet')
        cand = np.nonzero(known)[0]
        i = cand[np.argmin(np.linalg.norm(self.anchors_[cand] - np.asarray(y, dtype=float), axis=1))]
        return self.jacobians_[i], self.standard_errors_[i], float(self.support_[i])


class PolynomialJacobianField:
    """J(y) with entries polynomial in y, fitted so that J(y_k) u_k matches the observed rates.

    Learned: theta_ (n_features, dy, du), center_, scale_, rms_ (residual of the rates).
    """

    def __init__(self, degree: int = 2, ridge: float = 1e-4):
        if degree < 0:
            raise ValueError('degree must be >= 0')
        self.degree = degree
        self.ridge = ridge

    def fit(self, Y: np.ndarray, U: np.ndarray, Ydot: np.ndarray,
            sample_weight: Optional[np.ndarray] = None) -> 'PolynomialJacobianField':
        Y, U, Ydot = (np.asarray(a, dtype=float) for a in (Y, U, Ydot))
        self.center_ = Y.mean(axis=0)
        self.scale_ = Y.std(axis=0) + 1e-9
        P = polynomial_features(Y, self.degree, self.center_, self.scale_)     # (n, f)
        X = jacobian_design(P, U)                                             # (n, f*du)
        w = np.ones(len(Y)) if sample_weight is None else np.asarray(sample_weight, dtype=float)
        XtW = X.T * w
        A = XtW @ X + self.ridge * len(Y) * np.eye(X.shape[1])
        coef = np.linalg.solve(A, XtW @ Ydot)                                  # (f*du, dy)
        self.theta_ = theta_from_solution(coef, P.shape[1], U.shape[1])       # (f, dy, du)
        self.rms_ = float(np.sqrt(np.mean((Ydot - self.rates(Y, U)) ** 2)))
        return self

    def jacobian(self, Y: np.ndarray) -> np.ndarray:
        """(n, dy, du) Jacobians at the rows of Y."""
        P = polynomial_features(Y, self.degree, self.center_, self.scale_)
        return np.einsum('nf,fij->nij', P, self.theta_)

    def rates(self, Y: np.ndarray, U: np.ndarray) -> np.ndarray:
        return np.einsum('nij,nj->ni', self.jacobian(Y), np.atleast_2d(U))

    def integrate(self, y0: np.ndarray, U_seq: np.ndarray, dt: float) -> np.ndarray:
        """Euler integration of y along a command sequence; returns the (T+1, dy) trajectory."""
        y = np.array(y0, dtype=float)
        out = [y.copy()]
        for u in np.atleast_2d(U_seq):
            y = y + self.rates(y[None], u[None])[0] * dt
            out.append(y.copy())
        return np.array(out)
