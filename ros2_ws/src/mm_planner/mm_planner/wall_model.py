"""The controller's view of the wheeled robot's learned model, read from an mm_msgs/SensorManifoldModel message.

Every field is checked (format version, types, shapes, finiteness, ranges) before anything is used: a model from
another host, another version or a hostile publisher is refused with the reason, never half-used. What the controller
evaluates (the virtual-space and sensor-2 Jacobian fields, the local sensor-1 Jacobians, the route to a sensor-2 goal)
goes through mm_common.learned_fields, the same code the learner fitted it with.
"""
from __future__ import annotations

import math
from typing import List, Optional, Tuple

import numpy as np
from mm_common.learned_fields import (PolynomialField, Route, blend_jacobians, deeper_fallbacks,
                                      n_polynomial_features, ranked_routes)
from mm_msgs.msg import SensorManifoldModel as ModelMsg

MAX_DEGREE = 4          # the learner's jacobian_degree parameter range


def _array(msg, name: str, shape: Tuple[int, ...], positive: bool = False) -> np.ndarray:
    values = np.asarray(getattr(msg, name), dtype=float)
    if values.size != int(np.prod(shape)):
        raise ValueError(f'{name} has {values.size} values, expected {int(np.prod(shape))} (shape {shape})')
    if not np.all(np.isfinite(values)):
        raise ValueError(f'{name} is not finite')
    if positive and np.any(values <= 0):
        raise ValueError(f'{name} must be > 0')
    return values.reshape(shape)


def _rows(msg, name: str, width: int) -> int:
    n = len(getattr(msg, name))
    if n % width:
        raise ValueError(f'{name} has {n} values, not a multiple of {width}')
    return n // width


def _ordered_box(box: np.ndarray, name: str) -> np.ndarray:
    if np.any(box[0] > box[1]):
        raise ValueError(f'{name} minimum exceeds its maximum')
    return box


class WallModel:
    """Attributes: dt, ready, readiness (why not ready), held-out errors and their limit, samples, virtual_field, sensor2_field (None until learned), virtual_bounds (2, 2),
    sensor2_box (2, 2, NaN when sensor 2 was never seen), sensor2_noise (2,), sensor2_range (2,), region_anchors,
    region_jacobians, the overlap arrays and the routes' practised commands."""

    @classmethod
    def from_msg(cls, msg: ModelMsg) -> 'WallModel':
        """Raises ValueError with the reason when any field is malformed."""
        if msg.format_version != ModelMsg.FORMAT_VERSION:
            raise ValueError(f'model format {msg.format_version}, this controller reads {ModelMsg.FORMAT_VERSION}')
        self = cls()
        if not (math.isfinite(msg.dt) and msg.dt > 0):
            raise ValueError(f'dt {msg.dt} must be finite and > 0')
        self.dt, self.samples = float(msg.dt), int(msg.samples)
        rows, cols = int(msg.grid_rows), int(msg.grid_cols)
        if rows < 2 or cols < 2:
            raise ValueError(f'grid {rows}x{cols} needs at least 2x2 nodes')
        self.grid_nodes = _array(msg, 'grid_nodes', (rows, cols, 3))
        for name, shape in (('grid_mean', (3,)), ('grid_axes', (3, 3)), ('grid_extent', (2, 2))):
            _array(msg, name, shape)
        if not (math.isfinite(msg.grid_residual) and msg.grid_residual >= 0):
            raise ValueError(f'grid_residual {msg.grid_residual} must be finite and >= 0')
        degree = int(msg.jacobian_degree)
        if degree > MAX_DEGREE:
            raise ValueError(f'jacobian_degree {degree} above {MAX_DEGREE}')
        f = n_polynomial_features(degree, 2)
        self.virtual_field = PolynomialField(degree, _array(msg, 'field1_theta', (f, 2, 2)),
                                             _array(msg, 'field1_center', (2,)),
                                             _array(msg, 'field1_scale', (2,), positive=True),
                                             correction=_array(msg, 'virtual_correction', (f, 2, 2)))
        self.virtual_bounds = _ordered_box(_array(msg, 'virtual_bounds', (2, 2)), 'virtual_bounds')
        for name in ('reentry_rms_before', 'reentry_rms_after'):
            value = getattr(msg, name)
            if not (math.isnan(value) or (math.isfinite(value) and value >= 0)):
                raise ValueError(f'{name} {value} must be >= 0 (NaN: no excursion)')
        self.sensor2_field = None
        if len(msg.field2_theta) or len(msg.field2_center) or len(msg.field2_scale):
            self.sensor2_field = PolynomialField(degree, _array(msg, 'field2_theta', (f, 2, 2)),
                                                 _array(msg, 'field2_center', (2,)),
                                                 _array(msg, 'field2_scale', (2,), positive=True))
        a = _rows(msg, 'region_anchors', 2)
        if a == 0:
            raise ValueError('no sensor-1 region Jacobian')
        self.region_anchors = _array(msg, 'region_anchors', (a, 2))
        self.region_jacobians = _array(msg, 'region_jacobians', (a, 2, 2))
        self.sensor2_box = (np.full((2, 2), np.nan) if not len(msg.sensor2_box)
                            else _ordered_box(_array(msg, 'sensor2_box', (2, 2)), 'sensor2_box'))
        self.sensor2_noise = _array(msg, 'sensor2_noise', (2,))
        if np.any(self.sensor2_noise < 0):
            raise ValueError('sensor2_noise must be >= 0')
        self.sensor2_range = _array(msg, 'sensor2_range', (2,))
        if not 0 <= self.sensor2_range[0] < self.sensor2_range[1]:
            raise ValueError(f'sensor2_range {list(self.sensor2_range)} must satisfy 0 <= min < max')
        if not (math.isfinite(msg.route_travel_weight) and msg.route_travel_weight >= 0):
            raise ValueError(f'route_travel_weight {msg.route_travel_weight} must be finite and >= 0')
        if msg.goal_neighbors < 1:
            raise ValueError('goal_neighbors must be >= 1')
        self.route_travel_weight, self.goal_neighbors = float(msg.route_travel_weight), int(msg.goal_neighbors)
        o = _rows(msg, 'overlap_coordinates', 2)
        self.overlap_coordinates = _array(msg, 'overlap_coordinates', (o, 2))
        self.overlap_sensor2 = _array(msg, 'overlap_sensor2', (o, 2))
        self.overlap_exits = _array(msg, 'overlap_exits', (o, 2))
        self.overlap_travel = _array(msg, 'overlap_travel', (o,))
        self.route_lengths = np.asarray(msg.route_lengths, dtype=np.int64)
        if np.any(self.route_lengths < 1):
            raise ValueError('route_lengths must be >= 1')
        self.overlap_route = np.asarray(msg.overlap_route, dtype=np.int64)
        if self.overlap_route.shape != (o,) or np.any(self.overlap_route >= len(self.route_lengths)):
            raise ValueError(f'overlap_route must hold {o} route indices below {len(self.route_lengths)}, got '
                             f'{len(self.overlap_route)}')
        self.route_commands = _array(msg, 'route_commands', (int(self.route_lengths.sum()), 2))
        e, r, limit = msg.heldout_sensor2_error, msg.heldout_reentry_error, msg.heldout_limit
        if not (e >= 0 and not math.isnan(e)) or not (math.isnan(r) or (math.isfinite(r) and r >= 0)):
            raise ValueError(f'held-out errors {e}, {r} must be >= 0 (sensor 2: inf when unknown, re-entry: NaN)')
        if not (math.isfinite(limit) and limit >= 0):
            raise ValueError(f'heldout_limit {limit} must be finite and >= 0')
        self.heldout_sensor2_error, self.heldout_reentry_error = float(e), float(r)
        self.heldout_limit, self.heldout_count = float(limit), int(msg.heldout_count)
        self.ready = bool(msg.ready)
        if self.ready:
            self.readiness = ''
        elif self.sensor2_field is None or o == 0:
            self.readiness = 'the excursions have not seen sensor 2'
        else:
            self.readiness = msg.readiness[:300] or 'not ready (no reason given)'
        if self.ready and (self.sensor2_field is None or o == 0 or not len(msg.sensor2_box)):
            raise ValueError('marked ready without a sensor-2 field, box and overlap')
        if self.ready and not e <= limit:
            raise ValueError(f'marked ready with a held-out error {e} m above its bound {limit} m')
        return self

    def sensor1_jacobian(self, coordinates: np.ndarray) -> np.ndarray:
        """Local Jacobian of the grid coordinates at the current reading (blend of the nearest regions)."""
        return blend_jacobians(self.region_anchors, self.region_jacobians, coordinates)

    def ranked_routes(self, sensor2_goal: np.ndarray, n_routes: int) -> List[Route]:
        """Up to `n_routes` practised routes (exit, goal coordinates, replay) to a sensor-2 goal reading, best first."""
        return ranked_routes(self.overlap_sensor2, self.overlap_coordinates, self.overlap_exits, self.overlap_travel,
                             self.overlap_route, self.route_commands, self.route_lengths, sensor2_goal, n_routes,
                             self.route_travel_weight, self.goal_neighbors)

    def goal_route(self, sensor2_goal: np.ndarray, n_fallbacks: int = 5):
        """(exit point, goal coordinates, fallbacks) of the best practised route to a sensor-2 goal reading."""
        route, = self.ranked_routes(sensor2_goal, 1)
        return route.exit, route.goal, deeper_fallbacks(self.overlap_sensor2, self.overlap_coordinates, sensor2_goal,
                                                        n_fallbacks)

    def unreadable_goal(self, reading: np.ndarray, tolerance: float = 0.0) -> Optional[str]:
        """Why sensor 2 could never show this reading (outside the range its sensors read), or a tolerance as wide
        as that range would accept any reading; None if neither."""
        low, high = self.sensor2_range
        if np.any(reading < low) or np.any(reading > high):
            return f'goal reading {list(map(float, reading))} m is outside what sensor 2 reads ([{low}, {high}] m)'
        if tolerance >= high - low:
            return f'tolerance {tolerance} m is not below the span of what sensor 2 reads ({high - low:.4g} m)'
        return None
