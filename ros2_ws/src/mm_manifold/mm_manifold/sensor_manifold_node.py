"""Sensor-manifold node: learns the wheeled robot's state representation online and publishes the state.

    ./mm run mm_manifold sensor_manifold --ros-args -p use_sim_time:=true -p model_path:=results/wall_model.npz

Inputs (what the robot senses and commands, nothing else): the five `wheeled/range/*` readings, grouped by stamp into
one sample per simulator step (`range_input: per_sensor`, the default), or the same five readings of a step in one
mm_msgs/RangeGroup on `wheeled/ranges` (`range_input: grouped`, what wheeled_sim also publishes: one delivery per step
instead of five, the lockstep loop's rate, README issue 14), and its own `wheeled/wheel_velocity_controller/commands`
(the rule below lives in
mm_manifold.sample_assembly, which a bag replay uses too). The command that moved the robot to a sample travels on
another topic and may arrive after the sample's readings, so a sample with no command yet waits for it - for as long
as it takes, never decided by a wall-clock timeout (the learned data must not depend on machine load). It stops
waiting when the simulator shows that no command will come: it re-publishes the sample's step (it does so only after a
period without a command, e.g. after a reset) or publishes a newer one. A wait longer than `stall_warning` wall
seconds is reported (throttled), not resolved. A sample that does not follow exactly one command (a reset, a lost
command) breaks the chain of consecutive samples: it is not used as a Jacobian pair and the state tracker starts
afresh from it. A step the simulator re-publishes (it does so until the loop starts) is no new sample: its state is
sent again so a controller that joined late can start the loop.

After `learn_after` samples the SensorManifoldModel (dimension, elastic grid, Jacobians, virtual sensor space) is
fitted in a background thread (on copies: the live model is never changed, a finished fit is swapped in on the
executor), and refitted every `refit_every` further samples - and after `learn_after // 4` more when the model is not
ready (sensor 2 not seen during the excursions, or held-out predictions above their bound: the controller explores
on), or when the controller rejected it (`wheeled/controller/model_verdict`: a rehearsal with it failed; the
controller explores on). Before the first model, samples whose excursions never had sensor 2 in range are not
fitted at all: that is announced as a fit failure, which the controller takes as such a model, and tried again after
`learn_after // 4` more. A refit that is worse than the live model (fewer samples, cannot map goals the live one can,
fewer practised routes, worse sensor-2 prediction of the newest samples) is logged and dropped, unless the live model
was rejected. The model is published as an mm_msgs/SensorManifoldModel message on the latched
`wheeled/manifold/model` topic (the controller needs no file and may run on another host); with
`model_path` set it is also saved atomically there (np.savez + JSON) and loaded at start (every field checked; a bad
file means learning anew), so a restart does not relearn. With `samples_path` set every sample is appended to that
file as it is taken (mm_manifold.sample_log) and the file is loaded at start, so a crashed learner restarts with all
it had explored (the first sample after the restart starts a new chain). Every sample gives one
`wheeled/manifold/state` (and a Jacobian estimate). Every input is validated (Range: REP 117, within its limits, sane
stamps; commands: two finite values) and a bad one is dropped with a throttled log line saying why.
"""
from __future__ import annotations

import copy
import math
import threading
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
from builtin_interfaces.msg import Time
from mm_common.node_utils import clock_went_back, declare, reject_non_finite, run_node
from mm_common.qos import LOOP_QOS  # RELIABLE, deep history: see mm_common/qos.py
from mm_common.wheeled_sensors import SENSOR1, SENSOR2, SENSOR_NAMES
from mm_msgs.msg import JacobianEstimate, ManifoldState, ModelVerdict, RangeGroup
from mm_msgs.msg import SensorManifoldModel as ModelMsg
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Range
from std_msgs.msg import Float64MultiArray

from mm_manifold.model_message import model_to_msg
from mm_manifold.sample_assembly import Resent, Sample, SampleAssembler
from mm_manifold.sample_log import SampleLog
from mm_manifold.sensor_manifold import (MAX_RATE_STEPS, SPACE_NONE, SPACE_SENSOR1, SPACE_SENSOR2, SPACE_VIRTUAL,
                                         SensorManifoldModel, StateTracker, excursions_without_sensor2,
                                         refit_problem)

# The model is latched state (TRANSIENT_LOCAL, depth 1): a controller that starts or restarts after the fit still gets
# the newest model at once; RELIABLE because a lost model would leave the controller unable to control.
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
SPACE_NAMES = {SPACE_SENSOR1: 'sensor1_grid', SPACE_VIRTUAL: 'virtual_sensor1', SPACE_SENSOR2: 'sensor2'}
MAX_STAMP_AHEAD = 60.0       # [s] a reading stamped further ahead of this node's clock (or newest sample) is forged
RANGE_INPUTS = ('per_sensor', 'grouped')
SORTED_SENSOR_NAMES = sorted(SENSOR_NAMES)
SENSOR_INDEX = {name: index for index, name in enumerate(SENSOR_NAMES)}


def _ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def range_problem(msg: Range) -> Optional[str]:
    """Why a Range message is unusable, or None (reading_problem)."""
    return reading_problem(msg.header.frame_id, msg.radiation_type, msg.field_of_view, msg.min_range, msg.max_range,
                           msg.range)


def reading_problem(frame_id: str, radiation_type: int, field_of_view: float, min_range: float, max_range: float,
                    value: float) -> Optional[str]:
    """Why a reading (the fields of a Range message, alone or in a RangeGroup) is unusable, or None. REP 117: +inf
    beyond max_range, -inf below min_range; NaN is a lost reading (the simulator's dropout); a finite reading must lie
    within [min_range, max_range]."""
    if radiation_type not in (Range.ULTRASOUND, Range.INFRARED):
        return f'unknown radiation_type {radiation_type}'
    if not frame_id:
        return 'empty frame_id'
    if not (math.isfinite(field_of_view) and 0.0 <= field_of_view <= math.pi):
        return f'field_of_view {field_of_view} outside [0, pi] rad'
    if not (math.isfinite(min_range) and math.isfinite(max_range) and 0.0 <= min_range < max_range):
        return f'min_range {min_range} / max_range {max_range} need 0 <= min < max'
    if math.isfinite(value) and not min_range <= value <= max_range:
        return f'range {value} m outside [{min_range}, {max_range}] m (out of range is +-inf)'
    return None


class SensorManifold(Node):
    def __init__(self, **node_kwargs):
        super().__init__('sensor_manifold', **node_kwargs)
        self.dt = declare(self, 'dt', 0.05, 'Simulator step [s] between consecutive samples; fixed at start-up',
                          min_value=1e-4, max_value=1.0, read_only=True)
        self.learn_after = declare(self, 'learn_after', 10000, 'Samples collected before the first fit',
                                   min_value=100, max_value=10_000_000)
        self.refit_every = declare(self, 'refit_every', 0, 'Refit after this many new samples (0: never)',
                                   min_value=0, max_value=10_000_000)
        self.grid_shape = declare(self, 'grid_shape', [10, 10], 'Elastic grid nodes [rows, cols]', read_only=True)
        self.jacobian_degree = declare(self, 'jacobian_degree', 2, 'Polynomial degree of the Jacobian fields',
                                       min_value=0, max_value=4, read_only=True)
        self.rate_steps = declare(self, 'rate_steps', 0, 'Consecutive steps each sensor-1 rate spans when the '
                                  'Jacobians are fitted (more steps: less of the reading noise in the rates); 0: from '
                                  'the reading noise, 1 on clean readings', min_value=0, max_value=MAX_RATE_STEPS,
                                  read_only=True)
        self.model_path = declare(self, 'model_path', '', 'Where the learner keeps its model across restarts ("": '
                                  'not persisted); the model reaches the controller as a message', read_only=True)
        self.samples_path = declare(self, 'samples_path', '', 'File the samples are appended to as they come and '
                                    'loaded from at start, so a crash loses none ("": kept in memory only)',
                                    read_only=True)
        self.hold_steps = declare(self, 'hold_steps', 3, 'Lost (NaN) readings bridged with the last value for '
                                  'this many steps', min_value=0, max_value=100)
        # Reporting only: what is learned never depends on how long a message took (determinism under load).
        self.stall_warning = declare(self, 'stall_warning', 2.0, 'Wall seconds a sample may wait for its command '
                                     'before a (throttled) warning names what is missing; the wait goes on',
                                     min_value=0.1, max_value=3600.0)
        self.range_input = declare(self, 'range_input', 'per_sensor', "Where the readings come from: 'per_sensor' "
                                   "(the five wheeled/range/<name> topics) or 'grouped' (one mm_msgs/RangeGroup per "
                                   'step on wheeled/ranges)', read_only=True)
        if self.range_input not in RANGE_INPUTS:
            raise ValueError(f"range_input must be one of {', '.join(RANGE_INPUTS)}, got {self.range_input!r}")
        if len(self.grid_shape) != 2 or min(self.grid_shape) < 3:
            raise ValueError('grid_shape must be [rows, cols], each >= 3')
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.readings: List[np.ndarray] = []
        self.commands: List[np.ndarray] = []
        self.continuous: List[bool] = []
        self.assembler = SampleAssembler(len(SENSOR_NAMES))
        self.waiting_since = 0                    # steady time [ns] the assembler's waiting sample began to wait
        self.last_state: Optional[ManifoldState] = None
        self.sensor_limits: Dict[int, tuple] = {}  # sensor index -> (min_range, max_range) of its latest reading
        self.rejected = 0
        self.model: Optional[SensorManifoldModel] = None
        self.model_published = False
        self.live_fitted_on = 0                   # samples of this run the live model was fitted on
        self.tracker: Optional[StateTracker] = None
        self.fitting: Optional[threading.Thread] = None
        self.fit_result: List = []                # written once by the fitting thread, read after it ended
        self.fitted_samples = 0
        self.live_rejected = False                # the controller's rehearsals with the live model failed
        self.fit_failed = False                   # the last fit without a live model raised (announced as such)

        self.state_pub = self.create_publisher(ManifoldState, 'wheeled/manifold/state', LOOP_QOS)
        self.state_msg = ManifoldState()
        self.state_msg.header.frame_id = 'base_link'
        self.jacobian_pub = self.create_publisher(JacobianEstimate, 'wheeled/manifold/jacobian', LOOP_QOS)
        self.model_pub = self.create_publisher(ModelMsg, 'wheeled/manifold/model', LATCHED_QOS)
        if self.range_input == 'grouped':
            self.create_subscription(RangeGroup, 'wheeled/ranges', self._on_range_group, LOOP_QOS)
        else:
            for index, name in enumerate(SENSOR_NAMES):
                self.create_subscription(Range, f'wheeled/range/{name}',
                                         lambda msg, i=index: self._on_range(i, msg), LOOP_QOS)
        self.create_subscription(Float64MultiArray, 'wheeled/wheel_velocity_controller/commands', self._on_command,
                                 LOOP_QOS)
        self.create_subscription(ModelVerdict, 'wheeled/controller/model_verdict', self._on_verdict, LATCHED_QOS)
        # Wall-clock timers: with use_sim_time the sim clock stands still while the loop waits (for the model, or
        # for the command of a waiting sample). Neither decides what is learned.
        self.steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(0.2, self._collect_fit, clock=self.steady)
        self.create_timer(0.5, self._report_stall, clock=self.steady)
        self.sample_log: Optional[SampleLog] = None
        self._load_samples()
        self._load()

    def _on_set_parameters(self, params) -> SetParametersResult:
        result = reject_non_finite(params)
        if result.successful:
            for p in params:
                if p.name in ('learn_after', 'refit_every', 'hold_steps'):
                    setattr(self, p.name, int(p.value))
                if p.name == 'hold_steps' and self.tracker is not None:
                    self.tracker.hold_steps = int(p.value)
                if p.name == 'stall_warning':
                    self.stall_warning = float(p.value)
        return result

    def _reject(self, what: str, reason: str) -> None:
        self.rejected += 1
        self.get_logger().warn(f'{what} rejected ({self.rejected} inputs so far): {reason}',
                               throttle_duration_sec=1.0)

    # --- model lifecycle ----------------------------------------------------------------------------------------
    def _load_samples(self) -> None:
        """The samples a previous run of this node kept; a file that is not this robot's is moved aside."""
        if not self.samples_path:
            return
        log = SampleLog(self.samples_path, self.dt)
        try:
            kept = log.load()
        except (ValueError, OSError, UnicodeDecodeError) as exc:
            aside = Path(f'{self.samples_path}.unreadable')
            self.get_logger().error(f'{exc}; moved to {aside}, collecting samples anew')
            try:
                Path(self.samples_path).replace(aside)
            except OSError as move_error:
                self.get_logger().error(f'could not move it ({move_error}); samples are kept in memory only')
                return
            kept = None
        if kept is not None and kept.readings:
            self.readings, self.commands, self.continuous = kept.readings, kept.commands, kept.continuous
            self.get_logger().info(f'loaded {len(self.readings)} samples from {self.samples_path}'
                                   + (f' ({len(kept.problems)} bad lines dropped, first: {kept.problems[0]})'
                                      if kept.problems else ''))
        try:
            log.open()
            self.sample_log = log
        except OSError as exc:
            self.get_logger().error(f'cannot append to {self.samples_path} ({exc}); samples are kept in memory only')

    def _keep_sample(self, stamp_ns: int, reading: np.ndarray, command: Optional[np.ndarray], follows: bool) -> None:
        if self.sample_log is None:
            return
        try:
            self.sample_log.append(stamp_ns, reading, command, follows)
        except OSError as exc:        # a full disk loses the file's copy, not the sample
            self.get_logger().error(f'could not append a sample to {self.samples_path} ({exc}); it is kept in '
                                    'memory only', throttle_duration_sec=5.0)

    def destroy_node(self):
        if self.sample_log is not None:
            self.sample_log.close()
        return super().destroy_node()

    def _load(self) -> None:
        if not self.model_path or not Path(self.model_path).exists():
            return
        try:
            model = SensorManifoldModel.load(self.model_path)
            if not math.isclose(model.dt, self.dt):
                raise ValueError(f'model dt {model.dt} != node dt {self.dt}')
            if tuple(self.grid_shape) != (model.grid_rows, model.grid_cols):
                raise ValueError(f'model grid {model.grid_rows}x{model.grid_cols} != grid_shape {self.grid_shape}')
        except ValueError as exc:
            self.get_logger().error(f'{exc}; learning a new model')
            return
        self._install(model)
        if model.n_samples_ <= len(self.readings):      # the kept samples include the ones it was fitted on
            self.fitted_samples = self.live_fitted_on = model.n_samples_
        self.get_logger().info(f'loaded model from {self.model_path} ({model.n_samples_} samples)')

    def _install(self, model: SensorManifoldModel) -> None:
        self.model = model
        self.tracker = StateTracker(model, hold_steps=self.hold_steps)
        self.model_published = False
        self._publish_model()

    def _publish_model(self) -> None:
        """The model goes out once the sensor-2 sensors' range is known (their first readings): a goal is checked
        against it."""
        if self.model is None or self.model_published or not all(i in self.sensor_limits for i in SENSOR2):
            return
        msg = model_to_msg(self.model, self._group_range(SENSOR2))
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = 'base_link'
        self.model_pub.publish(msg)
        self.model_published = True

    def _group_range(self, group) -> list:
        """[min, max] that every sensor of the group reads (their latest Range messages' limits)."""
        limits = [self.sensor_limits[i] for i in group]
        return [max(lo for lo, _ in limits), min(hi for _, hi in limits)]

    def _publish_fit_failure(self, reason: str) -> None:
        """A model message without a model (no grid, not ready; SensorManifoldModel.msg): what was explored could not
        be fitted, and why. Only while no model is live: the latched topic keeps the last usable model otherwise."""
        msg = ModelMsg(format_version=ModelMsg.FORMAT_VERSION, dt=self.dt, samples=self.fitted_samples, ready=False,
                       readiness=f'fit failed: {reason}'[:300], heldout_sensor2_error=math.inf,
                       heldout_reentry_error=math.nan, heldout_limit=0.0)
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = 'base_link'
        self.model_pub.publish(msg)

    def _start_fit(self) -> None:
        R = np.array(self.readings)
        U = np.array(self.commands + [np.zeros(2)])
        C = np.array(self.continuous + [False])
        if self.model is None and excursions_without_sensor2(R, U, C):
            # A fit could only say so (a model that is not ready), after a second or more beside the other nodes:
            # announced as a fit failure instead, which sends the controller exploring as such a model does.
            self.fitted_samples = len(R)
            self.fit_failed = True
            reason = 'no excursion has seen sensor 2 yet: not fitted'
            self.get_logger().info(f'{reason} ({len(R)} samples); trying again after '
                                   f'{max(self.learn_after // 4, 1)} more samples')
            self._publish_fit_failure(reason)
            return
        # The fitting thread gets copies only (the warm-start grid too: partial_fit changes it); the live model
        # is never changed after install, so the thread may read it for the comparison.
        warm = copy.deepcopy(self.model.grid_) if self.model is not None else None
        # a rejected live model is no standard a refit has to meet
        live, live_fitted_on = (None, 0) if self.live_rejected else (self.model, self.live_fitted_on)
        self.fitted_samples = len(R)
        self.get_logger().info(f'fitting the sensor manifold on {len(R)} samples '
                               f'({int(np.sum(~C[:-1]))} breaks in the chain of consecutive samples)')
        result: List = []

        def fit():
            try:
                model = SensorManifoldModel(self.dt, *self.grid_shape, jacobian_degree=self.jacobian_degree,
                                            rate_steps=self.rate_steps or None).fit(R, U, C, grid=warm)
                problem = refit_problem(live, model, R[live_fitted_on:], U[live_fitted_on:], C[live_fitted_on:])
            except ValueError as exc:
                result.append((None, str(exc), None))
                return
            unsaved = None
            if problem is None and self.model_path:
                try:
                    model.save(self.model_path)
                except OSError as exc:        # a full disk or a bad path loses the file, not the model
                    unsaved = str(exc)
            result.append((model, problem, unsaved))

        self.fit_result = result
        self.fitting = threading.Thread(target=fit, name='manifold_fit', daemon=True)
        self.fitting.start()

    def _collect_fit(self) -> None:
        """Timer: install a finished fit (model swaps happen on the executor thread only)."""
        if self.fitting is None or self.fitting.is_alive():
            return
        self.fitting = None
        m, problem, unsaved = (self.fit_result[0] if self.fit_result
                               else (None, 'the fitting thread ended without a result', None))
        if m is None:
            if self.model is None:
                # The controller waits for a model once it has explored: tell it that none could be fitted, so it
                # explores `learn_after // 4` more (as for a model that is not ready) instead of waiting for good.
                self.get_logger().error(f'fit failed on {self.fitted_samples} samples: {problem}; refitting after '
                                        f'{max(self.learn_after // 4, 1)} more samples')
                self.fit_failed = True
                self._publish_fit_failure(problem)
            else:
                self.get_logger().error(f'refit failed: {problem}; the live model is kept, retrying with more samples')
                self.fitted_samples = len(self.readings) - self.learn_after // 2
            return
        if problem is not None:
            self.get_logger().warn(f'refit on {m.n_samples_} samples not used, the live model is kept: {problem}')
            return
        if unsaved:
            self.get_logger().error(f'could not save the model to {self.model_path} ({unsaved}); it is used from '
                                    'memory and lost on a restart')
        self.live_fitted_on = m.n_samples_
        self.live_rejected = self.fit_failed = False
        self._install(m)
        self.get_logger().info(
            f'model {"ready" if m.ready else "fitted"}: dimension {m.dimension_}, grid residual '
            f'{m.grid_.residual_:.4f} m, {m.n_excursions_} excursions, re-entry RMS '
            f'{m.virtual_.reentry_rms_before_:.2f} -> {m.virtual_.reentry_rms_after_:.2f} grid units, '
            f'{len(m.virtual_.overlap_sensor2_)} overlap samples')
        unsupported = m.unsupported_dimension()
        if unsupported:
            self.get_logger().warn(unsupported)
        if not m.ready:
            self.get_logger().warn(f'model not ready ({m.readiness()}): refitting after '
                                   f'{max(self.learn_after // 4, 1)} more samples')

    # --- inputs -------------------------------------------------------------------------------------------------
    def _on_verdict(self, msg: ModelVerdict) -> None:
        """The controller rehearsed with a model: a rejection of the live one makes it refit after `learn_after // 4`
        more samples, counted from the state the verdict answered (the controller explores that many more from
        there, however late the verdict arrives), whatever the refit's comparison with the live model says."""
        if msg.learner_samples > len(self.readings):
            # it answered a state of this learner, so it cannot count more samples than the learner holds
            self._reject('model verdict', f'learner_samples {msg.learner_samples} above the {len(self.readings)} '
                                          'samples this node holds')
            return
        if msg.accepted or self.model is None or msg.model_samples != self.model.n_samples_ or self.live_rejected:
            return                          # accepted, or about a model this node no longer holds, or known
        self.live_rejected = True
        self.fitted_samples = msg.learner_samples or len(self.readings)
        self.get_logger().warn(f'the controller rejected the model fitted on {msg.model_samples} samples '
                               f'({msg.reason[:300]}); refitting after {max(self.learn_after // 4, 1)} more samples')
        self._fit_if_due()          # a verdict that came after those samples (no more come while the loop waits)

    def _on_command(self, msg: Float64MultiArray) -> None:
        data = msg.data
        if len(data) != 2 or not all(math.isfinite(v) for v in data):
            # The simulator rejects it too: it did not move the robot, so it is no part of the chain either.
            self._reject('command', f'{list(data)}: need two finite wheel speeds')
            return
        self._take(self.assembler.command(np.array(data, dtype=float)))

    def _report_stall(self) -> None:
        """Timer: say what a long-waiting sample misses; the wait itself goes on (only the simulator ends it)."""
        if self.assembler.waiting is None:
            return
        waited = (self.steady.now().nanoseconds - self.waiting_since) * 1e-9
        if waited >= self.stall_warning:
            self.get_logger().warn(
                f'sample {self.assembler.waiting[1] * 1e-9:.3f} s has waited {waited:.1f} s for the '
                'wheeled/wheel_velocity_controller/commands message that produced it (no state published meanwhile); '
                'it is taken as a chain break once the simulator re-sends that step or sends a newer one',
                throttle_duration_sec=5.0)

    def _stamp_problem(self, stamp: int) -> Optional[str]:
        now = self.get_clock().now().nanoseconds
        newest = self.assembler.last_sample_ns
        if clock_went_back(now, newest, stamp):
            self.get_logger().warn(f'the clock went back to {now * 1e-9:.3f} s, before the newest sample '
                                   f'{newest * 1e-9:.3f} s: following the new time, a new chain of samples')
            self._take(self.assembler.new_timeline())
            newest = None
        reference, what = (now, 'the clock') if now > 0 else (newest, 'the newest sample')
        if reference is not None and stamp > reference + MAX_STAMP_AHEAD * 1e9:
            return f'stamp {stamp * 1e-9:.3f} s is more than {MAX_STAMP_AHEAD} s ahead of {what}'
        if newest is not None and stamp < newest:
            return f'stamp {stamp * 1e-9:.3f} s goes backwards (newest sample {newest * 1e-9:.3f} s)'
        return None

    def _on_range(self, index: int, msg: Range) -> None:
        stamp = _ns(msg.header.stamp)
        problem = range_problem(msg) or self._stamp_problem(stamp)
        if problem:
            self._reject(f'{SENSOR_NAMES[index]} reading', problem)
            return
        self._take_readings(stamp, [(index, msg.min_range, msg.max_range, msg.range)])

    def _on_range_group(self, msg: RangeGroup) -> None:
        """A step's five readings at once: all usable, or the step is dropped whole (the simulator sends it again
        while no command comes)."""
        names = list(msg.names)
        fields = (msg.frame_ids, msg.radiation_type, msg.field_of_view, msg.min_range, msg.max_range, msg.range)
        if sorted(names) != SORTED_SENSOR_NAMES or any(len(field) != len(names) for field in fields):
            self._reject('range group', f'names {names[:10]} with {[len(field) for field in fields]} frame_ids, '
                                        'radiation types, fields of view, min and max ranges and ranges: need one '
                                        f'reading of each of {", ".join(SENSOR_NAMES)}')
            return
        readings = list(zip(*fields))
        stamp = _ns(msg.header.stamp)
        problem = next((f'{name}: {p}' for name, reading in zip(names, readings)
                        for p in [reading_problem(*reading)] if p), None) or self._stamp_problem(stamp)
        if problem:
            self._reject('range group', problem)
            return
        self._take_readings(stamp, [(SENSOR_INDEX[name], low, high, value)
                                    for name, (_, _, _, low, high, value) in zip(names, readings)])

    def _take_readings(self, stamp: int, readings) -> None:
        """Valid (sensor index, min_range, max_range, range) readings of the step `stamp` into the sample assembly."""
        was_waiting = self.assembler.waiting
        for index, low, high, value in readings:
            self.sensor_limits[index] = (float(low), float(high))
            self._publish_model()
            self._take(self.assembler.reading(index, stamp, value))
        if self.assembler.waiting is not None and self.assembler.waiting is not was_waiting:
            self.waiting_since = self.steady.now().nanoseconds

    def _take(self, events) -> None:
        for event in events:
            if isinstance(event, Resent):
                if self.last_state is not None:      # a late joiner gets the step's state again
                    self.state_pub.publish(self.last_state)
            else:
                self._on_sample(event)

    def _on_sample(self, sample: Sample) -> None:
        # One command between two samples is the lockstep contract; anything else (reset, lost command) breaks
        # the chain of consecutive samples.
        step = sample.command if sample.command is not None else np.zeros(2)
        follows = sample.follows and bool(self.readings)
        if self.readings:
            self.commands.append(step)
            self.continuous.append(follows)
        stamp = Time(sec=sample.stamp_ns // 1_000_000_000, nanosec=sample.stamp_ns % 1_000_000_000)
        self._keep_sample(sample.stamp_ns, sample.reading, step, follows)
        if not sample.follows and self.tracker is not None:
            self.tracker.reset()
        self.readings.append(sample.reading)
        self._fit_if_due()
        self._publish(sample.reading, sample.command, stamp)

    def _fit_if_due(self) -> None:
        """Start a fit when one is due: the first after `learn_after` samples, then every `refit_every`, and after
        `learn_after // 4` more when the live model is not ready or was rejected, or when no model could be fitted."""
        n = len(self.readings)
        more = n - self.fitted_samples
        after_failure = max(self.learn_after // 4, 1) if self.fit_failed else 1
        if self.fitting is None and ((self.model is None and n >= self.learn_after and more >= after_failure)
                                     or (self.model is not None and self.refit_every and more >= self.refit_every)
                                     or (self.model is not None and (not self.model.ready or self.live_rejected)
                                         and more >= max(self.learn_after // 4, 1))):
            self._start_fit()

    # --- output -------------------------------------------------------------------------------------------------
    def _publish(self, reading: np.ndarray, command: Optional[np.ndarray], stamp) -> None:
        # One message, every field written each step (building a new one cost the lockstep loop about 5 us a step);
        # last_state is this message, as the latest step's state must be when it is sent again.
        msg = self.state_msg
        msg.header.stamp = stamp
        msg.coordinates, msg.sensor2_estimate, msg.virtual_uncertainty = [], [], 0.0
        msg.model_ready, msg.manifold_dimension, msg.fit_residual = False, 0, 0.0
        values = reading.tolist()
        msg.sensor1 = [values[i] for i in SENSOR1]
        msg.sensor2 = [values[i] for i in SENSOR2]
        msg.sensor1_range = self._group_range(SENSOR1)      # a step is complete only with every sensor's reading
        msg.in_range = [math.isfinite(v) for v in values]
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
                                                / m.virtual_.mean_excursion_steps_)
            if self.jacobian_pub.get_subscription_count():      # for monitoring only: not computed for no one
                self._publish_jacobian(space, coords, s2, stamp)
        self.state_pub.publish(msg)
        self.last_state = msg

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
