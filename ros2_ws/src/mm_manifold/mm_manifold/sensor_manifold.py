"""The wheeled robot's learned state representation (paper Section 2), from readings and its own commands only.

SensorManifoldModel.fit takes the exploration log: readings R[k] (5 proximity sensors, +-inf out of range, NaN lost),
the command U[k] applied after reading k, and continuous[k] (False where the next step does not follow, e.g. a
reset). It learns the intrinsic dimension of sensor group 1, the grid parameterisation of its 3-D readings, the
Jacobians of grid coordinates and of sensor-2 readings w.r.t. the wheel inputs, and the virtual sensor-1 space with
its overlap with sensor 2. StateTracker turns a live stream of readings into the current state (which space is active
and the coordinates in it). Persistence: np.savez + JSON, no pickle, written atomically.
"""
from __future__ import annotations

import json
import math
import os
import tempfile
import zipfile
import zlib
from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np
from mm_msgs.msg import ManifoldState

from mm_common.learned_fields import n_polynomial_features
from mm_common.wheeled_sensors import SENSOR1, SENSOR2

from mm_manifold.dimension import LocalPCADimension
from mm_manifold.grid import ElasticGrid
from mm_manifold.jacobian import PolynomialJacobianField, RegionJacobians
from mm_manifold.virtual_space import Excursion, ExtrapolatedField, VirtualSensorSpace

# The active spaces are the state message's constants (their one home).
SPACE_NONE, SPACE_SENSOR1 = ManifoldState.SPACE_NONE, ManifoldState.SPACE_SENSOR1
SPACE_VIRTUAL, SPACE_SENSOR2 = ManifoldState.SPACE_VIRTUAL_SENSOR1, ManifoldState.SPACE_SENSOR2
FORMAT_VERSION = 7              # 5: sensor1_gain; 6: mean_excursion_steps; 7: the routes' practised commands


def group_in_range(readings: np.ndarray, group) -> np.ndarray:
    """(n,) True where every sensor of the group reports a finite distance."""
    return np.all(np.isfinite(np.atleast_2d(readings)[:, list(group)]), axis=1)


def find_excursions(R: np.ndarray, U: np.ndarray, continuous: np.ndarray) -> List[Tuple[int, int, int]]:
    """(exit, reentry, last) step indices of each run out of sensor-1 range: R[exit] in range, R[exit+1..reentry-1]
    out, R[reentry] in range; reentry = -1 if the run ended without coming back (end of data or a break in the chain
    of consecutive samples), and `last` is the last sample the robot's own commands still connect to the exit."""
    inside = group_in_range(R, SENSOR1)
    lost = np.isnan(R[:, list(SENSOR1)]).any(axis=1) & ~np.isinf(R[:, list(SENSOR1)]).any(axis=1)
    runs = []
    k, n = 0, len(R)
    while k < n - 1:
        if inside[k] and continuous[k] and not inside[k + 1] and not lost[k + 1]:
            j = k + 1
            while j < n and not inside[j] and continuous[j - 1]:
                j += 1
            ok = j < n and continuous[j - 1] and inside[j]
            runs.append((k, j, j) if ok else (k, -1, j - 1))
            k = j
        else:
            k += 1
    return runs


NEGLIGIBLE_NOISE_GAIN = 0.99      # a gain this close to 1: the readings are used as they are
MAX_RATE_STEPS = 10               # longest span of a sensor-1 rate (a gain near 0: readings that hardly move)


def _valid_rate_steps(value) -> bool:
    """A span of sensor-1 rates: an integer (not a bool) in [1, MAX_RATE_STEPS]."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool) and 1 <= value <= MAX_RATE_STEPS


def measurement_gain(S: np.ndarray, continuous: np.ndarray) -> float:
    """Steady-state Kalman gain of a reading that moves by random steps of variance q and is observed with noise of
    variance r, both estimated from the readings alone (robustly, by the median absolute deviation): consecutive
    second differences hold 6 r (white noise) and hardly any motion, first differences q + 2 r. Averaged over the
    group's sensors; a gain above NEGLIGIBLE_NOISE_GAIN counts as 1 (no noise to speak of: clean readings stay
    exactly as they are). Measured (tuning seeds, four robots, both layouts): 1.0 on every clean exploration, 0.40-0.61
    with the benchmark's 1 % noise - where a fixed gain of 0.5 had taken noisy success from 0.62 to 0.79 (and cost
    clean success 0.965 -> 0.935), README."""
    ok = np.all(np.isfinite(S), axis=1)
    step = ok[:-1] & ok[1:] & continuous[:-1]
    trip = step[:-1] & step[1:]
    if trip.sum() < 20:
        return 1.0
    d1 = S[1:][step] - S[:-1][step]                  # masked before subtracting: no inf - inf
    d2 = S[2:][trip] - 2 * S[1:-1][trip] + S[:-2][trip]

    def robust_variance(x):
        return (1.4826 * np.median(np.abs(x - np.median(x, axis=0)), axis=0)) ** 2
    r = robust_variance(d2) / 6.0
    q = np.maximum(robust_variance(d1) - 2.0 * r, 0.0)
    prior = (q + np.sqrt(q * q + 4.0 * q * r)) / 2.0
    with np.errstate(divide='ignore', invalid='ignore'):
        gain = np.where(prior + r > 0, prior / (prior + r), 1.0)
    gain = float(np.mean(gain))
    return 1.0 if gain > NEGLIGIBLE_NOISE_GAIN else gain


def excursions_without_sensor2(R: np.ndarray, U: np.ndarray, continuous: np.ndarray) -> bool:
    """The robot made excursions out of sensor-1 range (find_excursions) and sensor 2 saw the wall in none of them:
    a fit then has no practised route and no overlap, and its model cannot map a sensor-2 goal (readiness)."""
    in2 = group_in_range(R, SENSOR2)
    runs = find_excursions(R, U, continuous)
    return bool(runs) and not any(in2[exit_k + 1:last + 1].any() for exit_k, _, last in runs)


GRID_DIMENSION = 2        # the elastic grid's dimension (grid_rows x grid_cols)


class SensorManifoldModel:
    """Hyperparameters: dt, grid shape, polynomial degree of the Jacobian fields, virtual-space prior weight,
    route_travel_weight (VirtualSensorSpace.goal_route), validation_folds and heldout_bound (the model is ready only
    when the held-out sensor-2 error of VirtualSensorSpace.validate is at most heldout_bound x the span of the
    sensor-2 readings explored; chosen by mm_bringup.tune_wall), learn_measurement_gain (False: sensor1_gain_ = 1,
    the readings as they are), rate_steps (consecutive steps each sensor-1 rate spans in the Jacobian fit,
    _sensor1_rates; None: from the reading noise, 1 on clean readings), measure_outside_grid (the state tracker takes
    a sensor-1 reading whose grid coordinates fall outside the grid as it is, without blending in the learned
    prediction: StateTracker; False: blended like any other), measure_on_prediction_outside_grid (nor does it use a
    one-step prediction that lands outside the grid: the measurement is taken alone, a lost reading's last value
    included; False: used like any other). The last two are read by the tracker only (TRACKER_SETTINGS), not by fit.
    Learned: dimension_, grid_, field1_ (grid coords), regions1_, field2_ (sensor-2 readings), sensor1_gain_ (the
    state tracker's measurement gain for sensor 1: measurement_gain), rate_steps_ (the steps a sensor-1 rate spanned),
    sensor2_noise_ (std
    of the sensor-2 reading noise, estimated from consecutive samples), virtual_, n_samples_, n_excursions_,
    heldout_sensor2_error_ [m], heldout_reentry_error_ [grid units], heldout_count_, heldout_limit_ [m]."""

    # Hyperparameters only the StateTracker reads: they change how a fitted model is tracked, not the fit, so a
    # tuning run may set them on a model fitted without them (mm_bringup.tune_wall --learn-model).
    TRACKER_SETTINGS = ('measure_outside_grid', 'measure_on_prediction_outside_grid')

    def __init__(self, dt: float, grid_rows: int = 10, grid_cols: int = 10, jacobian_degree: int = 2,
                 virtual_prior_weight: float = 1.0, route_travel_weight: float = 5e-3, validation_folds: int = 3,
                 heldout_bound: float = 0.5, learn_measurement_gain: bool = True, rate_steps: Optional[int] = None,
                 measure_outside_grid: bool = True, measure_on_prediction_outside_grid: bool = True,
                 random_state: Optional[int] = 0):
        if validation_folds < 2 or not heldout_bound > 0:
            raise ValueError('validation_folds >= 2 and heldout_bound > 0 are required')
        if rate_steps is not None and not _valid_rate_steps(rate_steps):
            raise ValueError(f'rate_steps must be an integer in [1, {MAX_RATE_STEPS}] or None (from the reading '
                             f'noise), got {rate_steps!r}')
        self.rate_steps = rate_steps
        self.validation_folds = validation_folds
        self.heldout_bound = heldout_bound
        self.learn_measurement_gain = learn_measurement_gain
        self.measure_outside_grid = bool(measure_outside_grid)
        self.measure_on_prediction_outside_grid = bool(measure_on_prediction_outside_grid)
        self.dt = dt
        self.grid_rows, self.grid_cols = grid_rows, grid_cols
        self.jacobian_degree = jacobian_degree
        self.virtual_prior_weight = virtual_prior_weight
        self.route_travel_weight = route_travel_weight
        self.random_state = random_state

    def fit(self, R: np.ndarray, U: np.ndarray, continuous: np.ndarray,
            grid: Optional[ElasticGrid] = None) -> 'SensorManifoldModel':
        R, U = np.asarray(R, dtype=float), np.asarray(U, dtype=float)
        continuous = np.asarray(continuous, dtype=bool)
        if R.ndim != 2 or R.shape[1] != 5 or U.shape != (len(R), 2) or continuous.shape != (len(R),):
            raise ValueError('expected R (n, 5), U (n, 2), continuous (n,)')
        in1 = group_in_range(R, SENSOR1)
        if in1.sum() < 50:
            raise ValueError(f'only {int(in1.sum())} sensor-1 samples: explore more')
        S1 = R[in1][:, list(SENSOR1)]
        self.dimension_ = LocalPCADimension(random_state=self.random_state).fit(S1).dimension_
        # `grid` warm-starts an online refit; otherwise fit from scratch.
        self.grid_ = grid.partial_fit(S1) if grid is not None else ElasticGrid(
            self.grid_rows, self.grid_cols, random_state=self.random_state).fit(S1)

        step = continuous[:-1]
        gain = measurement_gain(R[:, list(SENSOR1)], continuous)
        self.sensor1_gain_ = gain if self.learn_measurement_gain else 1.0
        self.rate_steps_ = self.rate_steps or int(round(1.0 / max(gain, 1.0 / MAX_RATE_STEPS)))
        C0, U0, rates1 = self._sensor1_rates(R, U, continuous, in1)
        self.field1_ = PolynomialJacobianField(self.jacobian_degree).fit(C0, U0, rates1)
        node_coords = np.stack(np.meshgrid(np.arange(self.grid_rows), np.arange(self.grid_cols), indexing='ij'),
                               axis=-1).reshape(-1, 2).astype(float)
        self.regions1_ = RegionJacobians(bandwidth=0.8).fit(C0, U0, rates1, node_coords)

        in2 = group_in_range(R, SENSOR2)
        pair2 = step & in2[:-1] & in2[1:]
        self.sensor2_box_ = (np.array([R[in2][:, list(SENSOR2)].min(axis=0), R[in2][:, list(SENSOR2)].max(axis=0)])
                             if in2.any() else np.full((2, len(SENSOR2)), np.nan))
        if pair2.sum() >= 20:
            S20, S21 = R[:-1][pair2][:, list(SENSOR2)], R[1:][pair2][:, list(SENSOR2)]
            self.field2_ = PolynomialJacobianField(self.jacobian_degree).fit(S20, U[:-1][pair2],
                                                                             (S21 - S20) / self.dt)
        else:
            self.field2_ = None
        self.sensor2_noise_ = self._reading_noise(R[:, list(SENSOR2)], U, pair2)

        excursions = []
        for exit_k, reentry, last in find_excursions(R, U, continuous):
            start = self.grid_.transform(R[exit_k, list(SENSOR1)][None])[0]
            end_k = reentry if reentry >= 0 else None
            e = Excursion(start=start, commands=[U[k] for k in range(exit_k, last)],
                          end=self.grid_.transform(R[end_k, list(SENSOR1)][None])[0] if end_k is not None else None)
            for k in range(exit_k + 1, last + 1):
                if in2[k]:
                    e.sensor2.append((k - exit_k, R[k, list(SENSOR2)].copy()))
            excursions.append(e)
        self.excursions_ = excursions
        self.virtual_ = VirtualSensorSpace(self.dt, self.grid_box(), self.virtual_bounds(),
                                           prior_weight=self.virtual_prior_weight,
                                           route_travel_weight=self.route_travel_weight).fit(self.field1_, excursions)
        self.n_samples_ = int(len(R))
        self.n_excursions_ = int(self.virtual_.n_excursions_)
        held = self.virtual_.validate(self.field1_, excursions, self.validation_folds, self.random_state)
        self.heldout_sensor2_error_ = held['sensor2_error']
        self.heldout_reentry_error_ = held['reentry_error']
        self.heldout_count_ = int(held['held_out'])
        span = self.sensor2_box_[1] - self.sensor2_box_[0]
        self.heldout_limit_ = float(self.heldout_bound * np.max(span)) if np.all(np.isfinite(span)) else 0.0
        return self

    def _sensor1_rates(self, R: np.ndarray, U: np.ndarray, continuous: np.ndarray, in1: np.ndarray):
        """(grid coordinates, mean command, coordinate rate) over every chain of `rate_steps` consecutive steps that
        begins and ends in sensor-1 range, for the sensor-1 Jacobians. One step is the finest, but a reading's noise
        enters a one-step rate divided by one step's motion: far from the wall, where a step moves the readings
        least, the benchmark's 1 % noise outweighed the motion, the Jacobians there pointed the wrong way and tasks
        that started there drove away from the wall (a noisy tuning model reached 4 of 20 tasks, 20 of 20 with the
        same samples over two to four steps). With rate_steps None the span is 1 / the measurement gain, rounded:
        about the steps of motion it takes to move the readings as far as their noise (measurement_gain's q and r:
        the gain is near sqrt(q / r) when the noise dominates); 1 on clean readings (gain 1), whose one-step rates
        are exact where longer spans bend with the path (fast turns). On noisy tuning cells
        (results/tune_wall_rate_steps.json) mean success 0.92 with one step against 0.97 over two or four. At most
        MAX_RATE_STEPS."""
        h = self.rate_steps_
        k = np.arange(len(R) - h)
        linked = in1[k] & in1[k + h]
        for j in range(h):
            linked &= continuous[k + j]
        k = k[linked]
        C0 = self.grid_.transform(R[k][:, list(SENSOR1)])
        Ch = self.grid_.transform(R[k + h][:, list(SENSOR1)])
        mean_command = np.mean([U[k + j] for j in range(h)], axis=0).reshape(-1, U.shape[1])
        return C0, mean_command, (Ch - C0) / (h * self.dt)

    def _reading_noise(self, S: np.ndarray, U: np.ndarray, pair: np.ndarray) -> np.ndarray:
        """Std of the reading noise per sensor. The one-step prediction error e_k = s_{k+1} - s_k - J u_k dt holds
        the noise of both readings, so consecutive errors share one noise sample with opposite signs:
        cov(e_k, e_{k+1}) = -noise variance, while motion the field does not explain is not correlated that way."""
        if self.field2_ is None:
            return np.zeros(S.shape[1])
        e = np.full((len(S) - 1, S.shape[1]), np.nan)
        k = np.flatnonzero(pair)
        e[k] = S[k + 1] - S[k] - self.field2_.rates(S[k], U[k]) * self.dt
        both = np.isfinite(e[:-1]).all(axis=1) & np.isfinite(e[1:]).all(axis=1)
        if both.sum() < 20:
            return np.zeros(S.shape[1])
        return np.sqrt(np.maximum(-np.mean(e[:-1][both] * e[1:][both], axis=0), 0.0))

    def grid_box(self) -> np.ndarray:
        """Coordinates covered by the grid: where sensor 1 was observed."""
        return np.array([[0.0, 0.0], [self.grid_rows - 1.0, self.grid_cols - 1.0]])

    def virtual_bounds(self) -> np.ndarray:
        """The virtual space may extend one grid size beyond the grid on every side."""
        return np.array([[-(self.grid_rows - 1), -(self.grid_cols - 1)],
                         [2 * (self.grid_rows - 1), 2 * (self.grid_cols - 1)]], dtype=float)

    @property
    def ready(self) -> bool:
        return self.readiness() is None

    def unsupported_dimension(self) -> Optional[str]:
        """What to tell the user when the intrinsic dimension detected in the sensor-1 readings is not the grid's (2,
        the pose of a differential drive relative to an infinite wall): such a sensor manifold is unsupported, the 2-D
        grid is fitted anyway, and the held-out check and the rehearsals judge the result. None when they agree."""
        if self.dimension_ == GRID_DIMENSION:
            return None
        return (f'the sensor-1 readings look {self.dimension_}-D, the grid is {GRID_DIMENSION}-D: a '
                f'{self.dimension_}-D sensor manifold is unsupported (a 2-D grid is fitted anyway; the held-out check '
                'and the rehearsals judge it)')

    def readiness(self) -> Optional[str]:
        """Why a sensor-2 goal cannot be trusted to this model yet (None: ready)."""
        if not hasattr(self, 'virtual_') or self.field2_ is None or not len(self.virtual_.overlap_sensor2_):
            return 'the excursions have not seen sensor 2'
        if not self.heldout_sensor2_error_ <= self.heldout_limit_:
            return (f'held-out sensor-2 error {self.heldout_sensor2_error_:.4f} m above the bound '
                    f'{self.heldout_limit_:.4f} m ({self.heldout_count_} held-out readings)')
        return None

    # --- persistence (no pickle) --------------------------------------------------------------------------------
    def save(self, path: os.PathLike) -> None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {
            'grid_nodes': self.grid_.nodes_, 'grid_mean': self.grid_.mean_, 'grid_axes': self.grid_.axes_,
            'grid_extent': self.grid_.extent_, 'sensor2_box': self.sensor2_box_,
            'field1_theta': self.field1_.theta_, 'field1_center': self.field1_.center_,
            'field1_scale': self.field1_.scale_,
            'virtual_correction': self.virtual_.field_.correction,
            'overlap_coordinates': self.virtual_.overlap_coordinates_, 'overlap_sensor2': self.virtual_.overlap_sensor2_,
            'overlap_exits': self.virtual_.overlap_exits_, 'overlap_travel': self.virtual_.overlap_travel_,
            'overlap_route': self.virtual_.overlap_route_, 'route_commands': self.virtual_.route_commands_,
            'route_lengths': self.virtual_.route_lengths_,
            'regions1_anchors': self.regions1_.anchors_, 'regions1_jacobians': self.regions1_.jacobians_,
            'regions1_errors': self.regions1_.standard_errors_, 'regions1_support': self.regions1_.support_,
        }
        if self.field2_ is not None:
            arrays.update(field2_theta=self.field2_.theta_, field2_center=self.field2_.center_,
                          field2_scale=self.field2_.scale_)
        meta = {'format_version': FORMAT_VERSION, 'dt': self.dt, 'grid_rows': self.grid_rows,
                'grid_cols': self.grid_cols, 'jacobian_degree': self.jacobian_degree,
                'virtual_prior_weight': self.virtual_prior_weight,
                'route_travel_weight': self.route_travel_weight, 'dimension': int(self.dimension_),
                'sensor2_noise': [float(v) for v in self.sensor2_noise_], 'sensor1_gain': self.sensor1_gain_,
                'rate_steps': self.rate_steps_, 'measure_outside_grid': self.measure_outside_grid,
                'measure_on_prediction_outside_grid': self.measure_on_prediction_outside_grid,
                'grid_residual': self.grid_.residual_, 'n_samples': self.n_samples_,
                'n_excursions': self.n_excursions_,
                'reentry_rms_before': self.virtual_.reentry_rms_before_,
                'reentry_rms_after': self.virtual_.reentry_rms_after_,
                'mean_excursion_steps': self.virtual_.mean_excursion_steps_,
                'validation_folds': self.validation_folds, 'heldout_bound': self.heldout_bound,
                'heldout_sensor2_error': self.heldout_sensor2_error_,
                'heldout_reentry_error': self.heldout_reentry_error_, 'heldout_count': self.heldout_count_,
                'heldout_limit': self.heldout_limit_}
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix='.' + path.name, suffix='.npz')
        os.close(fd)
        try:
            np.savez(tmp, meta=np.array(json.dumps(meta)), **arrays)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)        # no half-written temp files left behind
            raise

    @classmethod
    def load(cls, path: os.PathLike) -> 'SensorManifoldModel':
        """Load a saved model; raises ValueError with the reason if the file is missing pieces or corrupt."""
        try:
            with np.load(path, allow_pickle=False) as data:
                meta = json.loads(str(data['meta']))
                arrays = {k: data[k] for k in data.files if k != 'meta'}
        except (OSError, ValueError, KeyError, json.JSONDecodeError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
            raise ValueError(f'cannot read model {path}: {exc}') from exc
        if not isinstance(meta, dict):
            raise ValueError(f'model {path}: meta is a {type(meta).__name__}, not a mapping')
        if meta.get('format_version') != FORMAT_VERSION:
            raise ValueError(f"model {path}: format {meta.get('format_version')} != {FORMAT_VERSION}")
        try:
            model = cls._from_parts(meta, arrays)
        except KeyError as exc:
            raise ValueError(f'model {path} lacks {exc}') from exc
        except (ValueError, TypeError, IndexError) as exc:
            raise ValueError(f'model {path}: {exc}') from exc
        return model

    @classmethod
    def _from_parts(cls, meta: dict, arrays: dict) -> 'SensorManifoldModel':
        """Rebuild a model from its saved parts, checking every field's type, shape and range."""
        for name in ('dt', 'virtual_prior_weight', 'route_travel_weight', 'grid_residual'):
            if not _number(meta[name]) or meta[name] < 0 or (name == 'dt' and meta[name] == 0):
                raise ValueError(f'{name} {meta[name]!r} must be a finite number (> 0 for dt, else >= 0)')
        for name, low in (('grid_rows', 2), ('grid_cols', 2), ('jacobian_degree', 0), ('dimension', 0),
                          ('n_samples', 0), ('n_excursions', 0), ('validation_folds', 0), ('heldout_count', 0)):
            if not isinstance(meta[name], int) or isinstance(meta[name], bool) or meta[name] < low:
                raise ValueError(f'{name} {meta[name]!r} must be an integer >= {low}')
        if meta['jacobian_degree'] > 4:
            raise ValueError(f"jacobian_degree {meta['jacobian_degree']} above 4")
        if meta['validation_folds'] < 2:
            raise ValueError(f"validation_folds {meta['validation_folds']!r} must be >= 2")
        for name in ('heldout_bound', 'heldout_limit'):
            if not _number(meta[name]) or meta[name] < 0 or (name == 'heldout_bound' and meta[name] == 0):
                raise ValueError(f'{name} {meta[name]!r} must be a finite number (> 0 for the bound, else >= 0)')
        if not (_number(meta['heldout_sensor2_error']) or meta['heldout_sensor2_error'] == float('inf')) \
                or meta['heldout_sensor2_error'] < 0:
            raise ValueError(f"heldout_sensor2_error {meta['heldout_sensor2_error']!r} must be >= 0 (inf: unknown)")
        for name in ('reentry_rms_before', 'reentry_rms_after', 'heldout_reentry_error'):
            value = meta[name]
            if not (isinstance(value, float) and (np.isnan(value) or (np.isfinite(value) and value >= 0))):
                raise ValueError(f'{name} {value!r} must be a number >= 0 (NaN: no excursion)')
        steps = meta['mean_excursion_steps']
        if not (isinstance(steps, float) and (np.isnan(steps) or (np.isfinite(steps) and steps >= 1))):
            raise ValueError(f'mean_excursion_steps {steps!r} must be a number >= 1 (NaN: no excursion)')
        rows, cols, degree = meta['grid_rows'], meta['grid_cols'], meta['jacobian_degree']
        f = n_polynomial_features(degree, 2)
        a = rows * cols
        o = len(np.atleast_1d(arrays['overlap_travel']))
        lengths = arrays['route_lengths']
        if lengths.dtype.kind != 'i' or lengths.ndim != 1 or np.any(lengths < 1):
            raise ValueError(f'route_lengths must be integers >= 1, got {lengths.dtype} of shape {lengths.shape}')
        shapes = {'grid_nodes': (rows, cols, 3), 'grid_mean': (3,), 'grid_axes': (3, 3), 'grid_extent': (2, 2),
                  'sensor2_box': (2, 2), 'field1_theta': (f, 2, 2), 'field1_center': (2,), 'field1_scale': (2,),
                  'virtual_correction': (f, 2, 2), 'overlap_coordinates': (o, 2), 'overlap_sensor2': (o, 2),
                  'overlap_exits': (o, 2), 'overlap_travel': (o,), 'route_commands': (int(lengths.sum()), 2),
                  'regions1_anchors': (a, 2), 'regions1_jacobians': (a, 2, 2), 'regions1_errors': (a, 2, 2),
                  'regions1_support': (a,)}
        if 'field2_theta' in arrays:
            shapes.update(field2_theta=(f, 2, 2), field2_center=(2,), field2_scale=(2,))
        may_be_nan = {'sensor2_box', 'regions1_jacobians', 'regions1_errors'}   # never seen / unknown region
        for name, shape in shapes.items():
            value = arrays[name]
            if value.dtype.kind not in 'fi' or value.shape != shape:
                raise ValueError(f'{name} has shape {value.shape} ({value.dtype}), expected {shape} of numbers')
            finite = np.isfinite(value) | (np.isnan(value) if name in may_be_nan else False)
            if not np.all(finite):
                raise ValueError(f'{name} is not finite')
            arrays[name] = value.astype(float)
        routes = arrays['overlap_route']
        if routes.dtype.kind != 'i' or routes.shape != (o,) or np.any((routes < 0) | (routes >= len(lengths))):
            raise ValueError(f'overlap_route must be {o} route indices below {len(lengths)}')
        for name in ('field1_scale', 'field2_scale'):
            if name in arrays and np.any(arrays[name] <= 0):
                raise ValueError(f'{name} must be > 0')
        if not np.any(np.isfinite(arrays['regions1_jacobians'][:, 0, 0])):
            raise ValueError('no sensor-1 region has a Jacobian')
        noise = np.asarray(meta['sensor2_noise'], dtype=float)
        if noise.shape != (2,) or not np.all(np.isfinite(noise)) or np.any(noise < 0):
            raise ValueError(f"sensor2_noise {meta['sensor2_noise']!r} must be two numbers >= 0")

        model = cls(meta['dt'], rows, cols, degree, meta['virtual_prior_weight'], meta['route_travel_weight'],
                    meta['validation_folds'], meta['heldout_bound'])
        model.dimension_ = meta['dimension']
        model.heldout_sensor2_error_ = float(meta['heldout_sensor2_error'])
        model.heldout_reentry_error_ = float(meta['heldout_reentry_error'])
        model.heldout_count_, model.heldout_limit_ = meta['heldout_count'], float(meta['heldout_limit'])
        model.sensor2_noise_ = noise
        if not (_number(meta['sensor1_gain']) and 0 < meta['sensor1_gain'] <= 1):
            raise ValueError(f"sensor1_gain {meta['sensor1_gain']!r} must be in (0, 1]")
        model.sensor1_gain_ = float(meta['sensor1_gain'])
        rate_steps = meta.get('rate_steps', 1)          # files saved before the span was learned used one step
        if not _valid_rate_steps(rate_steps):
            raise ValueError(f'rate_steps {rate_steps!r} must be an integer in [1, {MAX_RATE_STEPS}]')
        model.rate_steps_ = rate_steps
        for name in SensorManifoldModel.TRACKER_SETTINGS:
            measure = meta.get(name, False)     # files saved before the setting existed: blended everywhere
            if not isinstance(measure, bool):
                raise ValueError(f'{name} {measure!r} must be true or false')
            setattr(model, name, measure)
        model.n_samples_, model.n_excursions_ = meta['n_samples'], meta['n_excursions']
        model.sensor2_box_ = arrays['sensor2_box']
        grid = ElasticGrid(rows, cols)
        grid.nodes_, grid.mean_, grid.axes_ = arrays['grid_nodes'], arrays['grid_mean'], arrays['grid_axes']
        grid.extent_ = arrays['grid_extent']
        grid.residual_ = float(meta['grid_residual'])
        model.grid_ = grid
        model.field1_ = _field(degree, arrays['field1_theta'], arrays['field1_center'], arrays['field1_scale'])
        model.field2_ = (_field(degree, arrays['field2_theta'], arrays['field2_center'], arrays['field2_scale'])
                         if 'field2_theta' in arrays else None)
        model.regions1_ = RegionJacobians()
        model.regions1_.anchors_ = arrays['regions1_anchors']
        model.regions1_.jacobians_ = arrays['regions1_jacobians']
        model.regions1_.standard_errors_ = arrays['regions1_errors']
        model.regions1_.support_ = arrays['regions1_support']
        virtual = VirtualSensorSpace(meta['dt'], model.grid_box(), model.virtual_bounds(),
                                     meta['virtual_prior_weight'], route_travel_weight=meta['route_travel_weight'])
        virtual.field_ = ExtrapolatedField(model.field1_, correction=arrays['virtual_correction'])
        virtual.reentry_rms_before_, virtual.reentry_rms_after_ = meta['reentry_rms_before'], meta['reentry_rms_after']
        virtual.n_excursions_ = meta['n_excursions']
        virtual.mean_excursion_steps_ = steps
        virtual.overlap_coordinates_ = arrays['overlap_coordinates']
        virtual.overlap_sensor2_ = arrays['overlap_sensor2']
        virtual.overlap_exits_ = arrays['overlap_exits']
        virtual.overlap_travel_ = arrays['overlap_travel']
        virtual.overlap_route_, virtual.route_lengths_ = routes.astype(np.int64), lengths.astype(np.int64)
        virtual.route_commands_ = arrays['route_commands']
        model.virtual_ = virtual
        return model


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value)


def refit_problem(live: Optional['SensorManifoldModel'], new: 'SensorManifoldModel', R: np.ndarray, U: np.ndarray,
                  continuous: np.ndarray) -> Optional[str]:
    """Why a refit must not replace the live model (None: it may). It must map sensor-2 goals if the live one can,
    have been fitted on at least as many samples (a restarted node's first refits see only its new samples), keep
    most of the practised routes (excursions with a sensor-2 overlap), and predict the sensor-2 readings of the
    samples the live model did not see (R, U, continuous) about as well (one-step error, 25 % slack)."""
    if live is None or not live.ready:
        return None
    if not new.ready:
        return 'the refit cannot map sensor-2 goals, the live model can'
    if new.n_samples_ < live.n_samples_:
        return f'the refit saw {new.n_samples_} samples, the live model {live.n_samples_}'
    routes = [len(m.virtual_.route_lengths_) for m in (live, new)]
    if routes[1] < routes[0] / 2:
        return f'the refit has {routes[1]} practised routes to sensor 2, the live model {routes[0]}'
    pair = np.asarray(continuous[:-1], dtype=bool) & group_in_range(R[:-1], SENSOR2) & group_in_range(R[1:], SENSOR2)
    if pair.sum() >= 20:
        S0, S1, U0 = R[:-1][pair][:, list(SENSOR2)], R[1:][pair][:, list(SENSOR2)], U[:-1][pair]
        errors = [float(np.sqrt(np.mean((S1 - S0 - m.field2_.rates(S0, U0) * m.dt) ** 2))) for m in (live, new)]
        if not np.isfinite(errors[1]) or errors[1] > 1.25 * errors[0]:
            return (f'the refit predicts the newest sensor-2 readings worse ({errors[1]:.2e} m vs '
                    f'{errors[0]:.2e} m RMS one-step error)')
    return None


def _field(degree, theta, center, scale) -> PolynomialJacobianField:
    f = PolynomialJacobianField(degree)
    f.theta_, f.center_, f.scale_ = theta, center, scale
    if theta.ndim != 3 or not np.all(np.isfinite(theta)):
        raise ValueError('Jacobian field coefficients are malformed')
    return f


class StateTracker:
    """Live state from the reading stream: which space is active and the coordinates in it.

    Lost readings (NaN) are bridged with the last valid value for up to `hold_steps` steps; sensor 1 in range ->
    grid coordinates of the reading; out of range -> virtual coordinates integrated from the last in-range ones with
    the commands actually sent; sensor 2 in range takes precedence for control (the paper's switch). When sensor 2
    drops out of range after having been in range, its reading is continued with the learned sensor-2 field for up
    to `sensor2_hold_steps` (a short virtual sensor 2), so a manoeuvre near its range edge does not flip the space;
    a continued reading far outside the explored ones (the field extrapolating) ends the hold early.

    Noisy readings: while a group stays in range, its state is a blend of the learned-Jacobian prediction from the
    previous state and the command, and the new measurement (`measurement_gain` of the latter; 1 = raw readings;
    a lost reading, bridged with its last value, contributes no measurement, only the prediction). Sensor 1 takes
    the gain the model learned from its readings (SensorManifoldModel.sensor1_gain_: 1 on clean readings, where
    blending cost precision, about 0.5 with the benchmark's noise), sensor 2 its readings as they are (1), unless
    `measurement_gain` is given for both. A sensor-1 reading whose coordinates fall outside the grid (where
    exploration never took the robot: random tasks start up to 1.1 m from the wall, and a directed exploration may
    not have gone back there since its start) is taken as it is when the model says so (measure_outside_grid): the
    prediction there comes from a field extrapolated past its data, and blended in, it pulled the estimate several
    grid units off within a few steps, so that the approach to the exit drove away from it (README, "Starts beyond
    the explored range"). For the same reason a prediction that lands outside the grid is not used when the model says
    so (measure_on_prediction_outside_grid): the measurement is taken alone, a lost reading's bridged value included
    (far from the wall at speed, such predictions landed several grid sizes out while the readings' coordinates
    stayed smooth; README, "Predictions beyond the grid").
    """

    def __init__(self, model: SensorManifoldModel, hold_steps: int = 3, sensor2_hold_steps: int = 20,
                 measurement_gain: Optional[float] = None):
        if measurement_gain is not None and not 0.0 < measurement_gain <= 1.0:
            raise ValueError(f'measurement_gain must be in (0, 1], got {measurement_gain}')
        self.model = model
        self.hold_steps = hold_steps
        self.sensor2_hold_steps = sensor2_hold_steps
        self.measurement_gain = measurement_gain
        self._grid_box = model.grid_box()       # fixed for the model's life; a new model gets a new tracker
        self.reset()

    def reset(self) -> None:
        self.last_valid = np.full(5, np.inf)
        self.age = np.zeros(5, dtype=int)
        self.coordinates: Optional[np.ndarray] = None
        self.virtual_steps = 0
        self.sensor2: Optional[np.ndarray] = None
        self.sensor2_virtual_steps = 0

    def filtered(self, readings: np.ndarray) -> np.ndarray:
        readings = np.asarray(readings, dtype=float)
        if readings.shape != (5,):
            raise ValueError(f'expected 5 readings, got shape {readings.shape}')
        lost = np.isnan(readings)
        self.age = np.where(lost, self.age + 1, 0)
        self.last_valid = np.where(lost, self.last_valid, readings)
        return np.where(lost & (self.age > self.hold_steps), np.inf, self.last_valid)

    def _outside_grid(self, coordinates: np.ndarray) -> bool:
        box = self._grid_box
        return bool(np.any((coordinates < box[0]) | (coordinates > box[1])))

    def _plausible_sensor2(self, reading: np.ndarray) -> bool:
        """A continued sensor-2 reading within the readings seen in exploration, widened by their span on each
        side. Farther out the polynomial field is extrapolating and can run away (to overflow) within the hold."""
        box = self.model.sensor2_box_
        span = box[1] - box[0]
        return bool(np.all(np.isfinite(reading)) and np.all(reading >= box[0] - span)
                    and np.all(reading <= box[1] + span))

    def update(self, readings: np.ndarray, last_command: Optional[np.ndarray]):
        """Returns (space, coordinates, sensor-2 reading (measured or continued) or None, filtered readings)."""
        lost = np.isnan(np.asarray(readings, dtype=float))
        r = self.filtered(readings)
        in1 = bool(group_in_range(r, SENSOR1)[0])
        in2 = bool(group_in_range(r, SENSOR2)[0])
        command = None if last_command is None else np.asarray(last_command, dtype=float)
        k1 = self.model.sensor1_gain_ if self.measurement_gain is None else self.measurement_gain
        k2 = 1.0 if self.measurement_gain is None else self.measurement_gain
        if in1:
            measured = self.model.grid_.transform(r[list(SENSOR1)][None])[0]
            if self.coordinates is not None and self.virtual_steps == 0 and command is not None:
                predicted = self.model.virtual_.step(self.coordinates, command)
                outside = self.model.measure_outside_grid and self._outside_grid(measured)
                unfounded = self.model.measure_on_prediction_outside_grid and self._outside_grid(predicted)
                gain = 1.0 if unfounded else 0.0 if lost[list(SENSOR1)].any() else 1.0 if outside else k1
                measured = predicted + gain * (measured - predicted)
            self.coordinates = measured
            self.virtual_steps = 0
        elif self.coordinates is not None and command is not None:
            self.coordinates = self.model.virtual_.step(self.coordinates, command)
            self.virtual_steps += 1
        if in2:
            measured = r[list(SENSOR2)].copy()
            if (self.sensor2 is not None and self.sensor2_virtual_steps == 0 and command is not None
                    and self.model.field2_ is not None):
                predicted = self.sensor2 + self.model.field2_.rates(self.sensor2[None], command[None])[0] * self.model.dt
                measured = predicted + np.where(lost[list(SENSOR2)], 0.0, k2) * (measured - predicted)
            self.sensor2 = measured
            self.sensor2_virtual_steps = 0
        elif (self.sensor2 is not None and command is not None and self.model.field2_ is not None
              and self.sensor2_virtual_steps < self.sensor2_hold_steps):
            self.sensor2 = self.sensor2 + self.model.field2_.rates(self.sensor2[None], command[None])[0] * self.model.dt
            self.sensor2_virtual_steps += 1
            if not self._plausible_sensor2(self.sensor2):
                self.sensor2 = None
        else:
            self.sensor2 = None
        if self.sensor2 is not None:
            space = SPACE_SENSOR2
        elif in1:
            space = SPACE_SENSOR1
        elif self.coordinates is not None:
            space = SPACE_VIRTUAL
        else:
            space = SPACE_NONE
        return space, self.coordinates, self.sensor2, r
