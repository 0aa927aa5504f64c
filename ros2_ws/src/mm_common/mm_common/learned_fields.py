"""Evaluation of the wheeled robot's learned model, shared by the learner (mm_manifold) and the controller (mm_planner),
which meet through the mm_msgs/SensorManifoldModel message: the polynomial basis of the Jacobian fields, the layout
of their least-squares fit (fitted by the learner, corrected online by the controller), the blend of local region
Jacobians and the route choice toward a sensor-2 goal (with the route's practised commands). One implementation on
both sides, so what the controller evaluates from the message is what the learner fitted. Pure numpy, no ROS.
"""
from __future__ import annotations

from functools import lru_cache
from itertools import combinations_with_replacement
from math import comb
from typing import List, NamedTuple, Optional, Tuple

import numpy as np


def n_polynomial_features(degree: int, dim: int) -> int:
    """Number of monomials of `dim` variables up to `degree` (the rows of a field's theta)."""
    return comb(degree + dim, dim)


@lru_cache(maxsize=None)
def monomials(degree: int, dim: int) -> Tuple[Tuple[int, ...], ...]:
    """The variables multiplied in each feature of polynomial_features, in their order (the constant first)."""
    return tuple(combo for d in range(degree + 1) for combo in combinations_with_replacement(range(dim), d))


def _product(Z: np.ndarray, variables: Tuple[int, ...]) -> np.ndarray:
    """The product of the columns `variables` of Z, left to right (as np.prod multiplies them; ones if none)."""
    if not variables:
        return np.ones(len(Z))
    out = Z[:, variables[0]]
    for k in variables[1:]:
        out = out * Z[:, k]
    return out


def polynomial_features(Y: np.ndarray, degree: int, center: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """1, y_i, y_i y_j, ... of the standardised y, up to `degree` (per-column products: cheaper than np.prod over a
    gathered array for the few rows the trackers evaluate per step)."""
    Z = (np.atleast_2d(Y) - center) / scale
    combos = monomials(degree, Z.shape[1])
    P = np.empty((len(Z), len(combos)))
    for f, combo in enumerate(combos):
        P[:, f] = _product(Z, combo)
    return P


def jacobian_design(P: np.ndarray, U: np.ndarray) -> np.ndarray:
    """(n, f * du) rows of J(y) u = dy/dt as a linear least-squares problem in theta, from the features P (n, f) of y
    and the commands U (n, du); theta_from_solution reads its solution back in this order."""
    return (P[:, :, None] * U[:, None, :]).reshape(len(P), -1)


def theta_from_solution(coef: np.ndarray, n_features: int, n_inputs: int) -> np.ndarray:
    """A (f * du, dy) solution of the jacobian_design problem as a field's theta (f, dy, du)."""
    return coef.reshape(n_features, n_inputs, -1).transpose(0, 2, 1)


class PolynomialField:
    """J(y) = sum_f phi_f(y) (theta + correction)[f], evaluated as the learner does (the in-range fit plus the
    virtual-space correction, each applied separately so the sums round the same way)."""

    def __init__(self, degree: int, theta: np.ndarray, center: np.ndarray, scale: np.ndarray,
                 correction: Optional[np.ndarray] = None):
        self.degree, self.theta, self.center, self.scale = degree, theta, center, scale
        self.correction = correction

    def jacobian(self, Y: np.ndarray) -> np.ndarray:
        """(n, dy, du) Jacobians at the rows of Y."""
        P = polynomial_features(Y, self.degree, self.center, self.scale)
        J = np.einsum('nf,fij->nij', P, self.theta)
        if self.correction is not None:
            J = J + np.ones(len(P))[:, None, None] * np.einsum('nf,fij->nij', P, self.correction)
        return J

    def rates(self, Y: np.ndarray, U: np.ndarray) -> np.ndarray:
        return np.einsum('nij,nj->ni', self.jacobian(Y), np.atleast_2d(U))


def blend_jacobians(anchors: np.ndarray, jacobians: np.ndarray, y: np.ndarray, k: int = 4) -> np.ndarray:
    """Inverse-distance blend of the k nearest regions' Jacobians at y (regions with a known Jacobian only)."""
    if not len(anchors):
        raise ValueError('no region has enough support yet')
    d = np.linalg.norm(anchors - np.asarray(y, dtype=float), axis=1)
    order = np.argsort(d)[:k]
    w = 1.0 / (d[order] + 1e-3)
    return np.einsum('a,aij->ij', w, jacobians[order]) / w.sum()


class Route(NamedTuple):
    """One practised route to a sensor-2 goal: where its excursion left sensor-1 range (grid coordinates), the
    virtual coordinates of its readings nearest the goal, and the commands it drove from that exit until sensor 2
    first saw the wall (n, 2): what the robot replays to cross the blind stretch as it was crossed in practice."""
    exit: np.ndarray
    goal: np.ndarray
    replay: np.ndarray


def route_offsets(route_lengths: np.ndarray) -> np.ndarray:
    """Start of each route's commands in the concatenated route_commands, and the end of the last (r + 1,)."""
    return np.concatenate([[0], np.cumsum(np.asarray(route_lengths, dtype=np.int64))])


def ranked_routes(overlap_sensor2: np.ndarray, overlap_coordinates: np.ndarray, overlap_exits: np.ndarray,
                  overlap_travel: np.ndarray, overlap_route: np.ndarray, route_commands: np.ndarray,
                  route_lengths: np.ndarray, sensor2_goal: np.ndarray, n_routes: int, route_travel_weight: float,
                  goal_neighbors: int) -> List[Route]:
    """Up to `n_routes` different practised excursions (`overlap_route`: the route of each overlap sample), best
    first: each metre of sensor-2 reading mismatch may be traded for 1 / route_travel_weight rad of blind wheel
    rotation saved. A route's goal coordinates blend the `goal_neighbors` overlap samples of that excursion nearest
    the goal reading; its replay is its slice of `route_commands` (`route_lengths` commands per route)."""
    if not len(overlap_sensor2):
        raise ValueError('no overlap with sensor 2 has been observed yet')
    mismatch = np.linalg.norm(overlap_sensor2 - np.asarray(sensor2_goal, dtype=float), axis=1)
    cost = mismatch + route_travel_weight * overlap_travel
    route = np.asarray(overlap_route, dtype=np.int64)
    best_cost = np.full(len(route_lengths), np.inf)
    np.minimum.at(best_cost, route, cost)
    offsets = route_offsets(route_lengths)
    routes = []
    for r in np.argsort(best_cost)[:n_routes]:
        if not np.isfinite(best_cost[r]):
            break                                   # a route without overlap samples
        same = np.flatnonzero(route == r)
        idx = same[np.argsort(mismatch[same])[:goal_neighbors]]
        w = 1.0 / (mismatch[idx] + 1e-4)
        routes.append(Route(overlap_exits[same[0]], (overlap_coordinates[idx] * w[:, None]).sum(axis=0) / w.sum(),
                            route_commands[offsets[r]:offsets[r + 1]]))
    return routes


def deeper_fallbacks(overlap_sensor2: np.ndarray, overlap_coordinates: np.ndarray, sensor2_goal: np.ndarray,
                     n_fallbacks: int = 5) -> np.ndarray:
    """Virtual coordinates of practised readings nearer the wall than the goal (ordered by closeness to it, spread a
    little deeper each time): where to aim if the goal's coordinates are reached without sensor 2 in sight."""
    mismatch = np.linalg.norm(overlap_sensor2 - np.asarray(sensor2_goal, dtype=float), axis=1)
    deeper = np.flatnonzero(np.all(overlap_sensor2 < sensor2_goal, axis=1))
    order = deeper[np.argsort(mismatch[deeper])]
    step = max(1, len(order) // (4 * n_fallbacks))
    return overlap_coordinates[order[::step][:n_fallbacks]]
