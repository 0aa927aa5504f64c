"""Sensor-manifold node: learns the wheeled robot's state representation online and publishes the state.

    ./mm run mm_manifold sensor_manifold --ros-args -p use_sim_time:=true -p model_path:=results/wall_model.npz

Inputs (what the robot senses and commands, nothing else): the five `wheeled/range/*` readings, grouped by stamp
into one sample per simulator step, and its own `wheeled/wheel_velocity_controller/commands`. The command that moved
the robot to a sample travels on another topic and may arrive after the sample's readings, so a sample with no command
yet waits for it up to `command_wait` wall seconds. A sample that does not follow exactly one command (a reset, a lost
command) breaks the chain of consecutive samples: it is not used as a Jacobian pair and the state tracker starts
afresh from it. A step the simulator re-publishes (it does so until the loop starts) is no new sample: its state is
sent again so a controller that joined late can start the loop.

After `learn_after` samples the SensorManifoldModel (dimension, elastic grid, Jacobians, virtual sensor space) is
fitted in a background thread, and refitted every `refit_every` further samples - and after `learn_after // 4`
more when sensor 2 was not seen during the excursions (such a model cannot map a sensor-2 goal, so the controller
explores on; it happened in a noisy graph run). The model is saved atomically to
`model_path` (np.savez + JSON) and announced on the latched `wheeled/manifold/model` topic; a saved model is loaded
at start, so a restart does not relearn. Every sample gives one `wheeled/manifold/state` (and a Jacobian estimate).
"""
from __future__ import annotations

import math
import threading
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
from mm_common.node_utils import declare, reject_non_finite, run_node
from mm_msgs.msg import JacobianEstimate, ManifoldState
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Range
from std_msgs.msg import Float64MultiArray, String

from mm_manifold.sensor_manifold import (SENSOR1, SENSOR2, SPACE_NONE, SPACE_SENSOR1, SPACE_SENSOR2,
                                         SPACE_VIRTUAL, SensorManifoldModel, StateTracker)

SENSOR_NAMES = ('front_left', 'front_center', 'front_right', 'side_front', 'side_rear')
# Lockstep loop topics are RELIABLE (no sample may be lost, the controller waits for each state).
LOOP_QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
# The model announcement is latched state: late joiners must get the last one.
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
SPACE_NAMES = {SPACE_SENSOR1: 'sensor1_grid', SPACE_VIRTUAL: 'virtual_sensor1', SPACE_SENSOR2: 'sensor2'}


class SensorManifold(Node):
    def __init__(self, **node_kwargs):
        super().__init__('sensor_manifold', **node_kwargs)
        self.dt = declare(self, 'dt', 0.05, 'Simulator step [s] between consecutive samples', min_value=1e-4,
                          max_value=1.0)
        self.learn_after = declare(self, 'learn_after', 10000, 'Samples collected before the first fit',
                                   min_value=100, max_value=10_000_000)
        self.refit_every = declare(self, 'refit_every', 0, 'Refit after this many new samples (0: never)',
                                   min_value=0, max_value=10_000_000)
        self.grid_shape = declare(self, 'grid_shape', [10, 10], 'Elastic grid nodes [rows, cols]', read_only=True)
        self.jacobian_degree = declare(self, 'jacobian_degree', 2, 'Polynomial degree of the Jacobian fields',
                                       min_value=0, max_value=4, read_only=True)
        self.model_path = declare(self, 'model_path', '', 'Where the learned model is saved and loaded ("": not '
                                  'persisted)', read_only=True)
        self.hold_steps = declare(self, 'hold_steps', 3, 'Lost (NaN) readings bridged with the last value for '
                                  'this many steps', min_value=0, max_value=100)
        # Longer than the controller ever takes to answer (it may itself wait for a bumper reading), so that only a
        # reset or a lost command breaks the chain; a reset's first state comes this much later.
        self.command_wait = declare(self, 'command_wait', 1.0, 'Wall seconds a sample waits for the command that '
                                    'produced it before it counts as a break in the chain', min_value=0.0,
                                    max_value=5.0)
        if len(self.grid_shape) != 2 or min(self.grid_shape) < 3:
            raise ValueError('grid_shape must be [rows, cols], each >= 3')
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.readings: List[np.ndarray] = []
        self.commands: List[np.ndarray] = []
        self.continuous: List[bool] = []
        self.pending: Dict[int, List[float]] = {}
        self.commands_since_sample: List[np.ndarray] = []
        self.waiting: Optional[tuple] = None      # (reading, stamp, steady time) of a sample waiting for its command
        self.last_sample_ns: Optional[int] = None  # stamp of the newest sample taken
        self.last_state: Optional[ManifoldState] = None
        self.rejected = 0
        self.model: Optional[SensorManifoldModel] = None
        self.tracker: Optional[StateTracker] = None
        self.fitting: Optional[threading.Thread] = None
        self.fitted_samples = 0
        self.lock = threading.Lock()

        self.state_pub = self.create_publisher(ManifoldState, 'wheeled/manifold/state', LOOP_QOS)
        self.jacobian_pub = self.create_publisher(JacobianEstimate, 'wheeled/manifold/jacobian', LOOP_QOS)
        self.model_pub = self.create_publisher(String, 'wheeled/manifold/model', LATCHED_QOS)
        for index, name in enumerate(SENSOR_NAMES):
            self.create_subscription(Range, f'wheeled/range/{name}',
                                     lambda msg, i=index: self._on_range(i, msg), LOOP_QOS)
        self.create_subscription(Float64MultiArray, 'wheeled/wheel_velocity_controller/commands', self._on_command,
                                 LOOP_QOS)
        # Wall-clock timers: with use_sim_time the sim clock stands still while the loop waits (for the model, or
        # for the command of a waiting sample).
        self.steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(0.2, self._collect_fit, clock=self.steady)
        self.create_timer(0.02, self._expire_waiting, clock=self.steady)
        self._load()

    def _on_set_parameters(self, params) -> SetParametersResult:
        result = reject_non_finite(params)
        if result.successful:
            for p in params:
                if p.name == 'dt':
                    return SetParametersResult(successful=False, reason='dt can only be set at start-up')
                if p.name in ('learn_after', 'refit_every', 'hold_steps'):
                    setattr(self, p.name, int(p.value))
                if p.name == 'command_wait':
                    self.command_wait = float(p.value)
        return result

    # --- model lifecycle ----------------------------------------------------------------------------------------
    def _load(self) -> None:
        if not self.model_path or not Path(self.model_path).exists():
            return
        try:
            model = SensorManifoldModel.load(self.model_path)
            if not math.isclose(model.dt, self.dt):
                raise ValueError(f'model dt {model.dt} != node dt {self.dt}')
        except ValueError as exc:
            self.get_logger().error(f'{exc}; learning a new model')
            return
        self._install(model)
        self.get_logger().info(f'loaded model from {self.model_path} ({model.n_samples_} samples)')

    def _install(self, model: SensorManifoldModel) -> None:
        self.model = model
        self.tracker = StateTracker(model, hold_steps=self.hold_steps)
        self.model_pub.publish(String(data=str(Path(self.model_path).resolve()) if self.model_path else ''))

    def _start_fit(self) -> None:
        R = np.array(self.readings)
        U = np.array(self.commands + [np.zeros(2)])
        C = np.array(self.continuous + [False])
        warm = self.model.grid_ if self.model is not None else None
        self.fitted_samples = len(R)
        self.get_logger().info(f'fitting the sensor manifold on {len(R)} samples '
                               f'({int(np.sum(~C[:-1]))} breaks in the chain of consecutive samples)')

        def fit():
            try:
                model = SensorManifoldModel(self.dt, *self.grid_shape, jacobian_degree=self.jacobian_degree).fit(
                    R, U, C, grid=warm)
                if self.model_path:
                    model.save(self.model_path)
                self.fit_result = model
            except ValueError as exc:
                self.fit_result = exc

        self.fit_result = None
        self.fitting = threading.Thread(target=fit, name='manifold_fit', daemon=True)
        self.fitting.start()

    def _collect_fit(self) -> None:
        """Timer: install a finished fit (model swaps happen on the executor thread only)."""
        if self.fitting is None or self.fitting.is_alive():
            return
        self.fitting = None
        if isinstance(self.fit_result, Exception):
            self.get_logger().error(f'fit failed: {self.fit_result}; will retry with more samples')
            self.fitted_samples = len(self.readings) - self.learn_after // 2
            return
        m = self.fit_result
        self._install(m)
        self.get_logger().info(
            f'model {"ready" if m.ready else "fitted"}: dimension {m.dimension_}, grid residual '
            f'{m.grid_.residual_:.4f} m, {m.n_excursions_} excursions, re-entry RMS '
            f'{m.virtual_.reentry_rms_before_:.2f} -> {m.virtual_.reentry_rms_after_:.2f} grid units, '
            f'{len(m.virtual_.overlap_sensor2_)} overlap samples')
        if not m.ready:
            self.get_logger().warn(f'sensor 2 was not seen during the excursions: no sensor-2 goal can be mapped; '
                                   f'refitting after {max(self.learn_after // 4, 1)} more samples')

    # --- inputs -------------------------------------------------------------------------------------------------
    def _on_command(self, msg: Float64MultiArray) -> None:
        data = np.asarray(msg.data, dtype=float)
        if data.shape != (2,) or not np.all(np.isfinite(data)):
            # The simulator rejects it too: it did not move the robot, so it is no part of the chain either.
            self.rejected += 1
            self.get_logger().warn(f'ignored command {list(data)} ({self.rejected} so far): need two finite '
                                   'wheel speeds', throttle_duration_sec=1.0)
            return
        self.commands_since_sample.append(data)
        if self.waiting is not None:
            reading, stamp, _ = self.waiting
            self.waiting = None
            self._on_sample(reading, stamp)

    def _expire_waiting(self) -> None:
        """Timer: a sample whose command never came (a reset, a republished step) is taken as a chain break."""
        if self.waiting is not None and (self.steady.now().nanoseconds - self.waiting[2]) * 1e-9 >= self.command_wait:
            reading, stamp, _ = self.waiting
            self.waiting = None
            self._on_sample(reading, stamp)

    def _on_range(self, index: int, msg: Range) -> None:
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        values = self.pending.setdefault(stamp, [math.nan] * 5 + [0])
        values[index] = msg.range
        values[5] += 1
        if values[5] == 5:
            del self.pending[stamp]
            for old in [s for s in self.pending if s < stamp]:   # incomplete older steps never complete
                del self.pending[old]
            if self.last_sample_ns is not None and stamp <= self.last_sample_ns:
                # A re-published (or stale) step: already a sample. Re-send its state unless it still waits.
                if stamp == self.last_sample_ns and self.waiting is None and self.last_state is not None:
                    self.state_pub.publish(self.last_state)
                return
            self.last_sample_ns = stamp
            reading = np.asarray(values[:5], dtype=float)
            if self.waiting is not None:             # the earlier sample's command will not come any more
                waiting, self.waiting = self.waiting, None
                self._on_sample(*waiting[:2])
            if self.readings and not self.commands_since_sample and self.command_wait > 0:
                self.waiting = (reading, msg.header.stamp, self.steady.now().nanoseconds)
            else:
                self._on_sample(reading, msg.header.stamp)

    def _on_sample(self, reading: np.ndarray, stamp) -> None:
        # One command between two samples is the lockstep contract; anything else (reset, lost command) breaks
        # the chain of consecutive samples.
        follows = len(self.commands_since_sample) == 1
        if self.readings:
            step = self.commands_since_sample[-1] if self.commands_since_sample else np.zeros(2)
            self.commands.append(step)
            self.continuous.append(follows)
        if not follows and self.tracker is not None:
            self.tracker.reset()
        command = self.commands_since_sample[-1] if self.commands_since_sample else None
        self.commands_since_sample = []
        self.readings.append(reading)
        n = len(self.readings)
        more = n - self.fitted_samples
        if self.fitting is None and ((self.model is None and n >= self.learn_after and more > 0)
                                     or (self.model is not None and self.refit_every and more >= self.refit_every)
                                     or (self.model is not None and not self.model.ready
                                         and more >= max(self.learn_after // 4, 1))):
            self._start_fit()
        self._publish(reading, command, stamp)

    # --- output -------------------------------------------------------------------------------------------------
    def _publish(self, reading: np.ndarray, command: Optional[np.ndarray], stamp) -> None:
        msg = ManifoldState()
        msg.header.stamp = stamp
        msg.header.frame_id = 'base_link'
        msg.sensor1 = [float(v) for v in reading[list(SENSOR1)]]
        msg.sensor2 = [float(v) for v in reading[list(SENSOR2)]]
        msg.in_range = [bool(math.isfinite(v)) for v in reading]
        msg.samples = len(self.readings)
        msg.active_space = SPACE_NONE
        if self.model is not None:
            m = self.model
            space, coords, s2, _ = self.tracker.update(reading, command)
            msg.model_ready = bool(m.ready)
            msg.manifold_dimension = int(m.dimension_)
            msg.fit_residual = float(m.grid_.residual_)
            msg.active_space = space
            if coords is not None:
                msg.coordinates = [float(v) for v in coords]
            if s2 is not None:
                msg.sensor2_estimate = [float(v) for v in s2]
            if space == SPACE_VIRTUAL:
                # Re-entry error grows roughly with the time spent blind; scale by the practised excursions.
                msg.virtual_uncertainty = float(m.virtual_.reentry_rms_after_ * self.tracker.virtual_steps
                                                / max(self._mean_excursion_steps(), 1.0))
            self._publish_jacobian(space, coords, s2, stamp)
        self.state_pub.publish(msg)
        self.last_state = msg

    def _mean_excursion_steps(self) -> float:
        steps = [len(e.commands) for e in getattr(self.model, 'excursions_', []) if e.end is not None]
        return float(np.mean(steps)) if steps else 40.0

    def _publish_jacobian(self, space: int, coords, s2, stamp) -> None:
        m = self.model
        est = JacobianEstimate()
        est.header.stamp = stamp
        if space == SPACE_SENSOR1 and coords is not None:
            J, se, support = m.regions1_.at(coords)
            est.standard_error = [float(v) for v in se.ravel()]
            est.support = int(support)
        elif space == SPACE_VIRTUAL and coords is not None:
            J = m.virtual_.field_.jacobian(np.asarray(coords)[None])[0]
        elif space == SPACE_SENSOR2 and s2 is not None and m.field2_ is not None:
            J = m.field2_.jacobian(np.asarray(s2)[None])[0]
        else:
            return
        est.space = SPACE_NAMES[space]
        est.rows, est.cols = J.shape
        est.jacobian = [float(v) for v in J.ravel()]
        self.jacobian_pub.publish(est)


def main(args=None):
    run_node(SensorManifold, args)


if __name__ == '__main__':
    main()
