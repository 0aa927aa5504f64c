"""Sensor-switching Jacobian control (paper Section 2.4, Fig. 5): reach a goal given as a sensor-2 reading.

The goal reading maps to the closest point of the virtual sensor-1 space (learned overlap). While sensor 1 is in range
the robot is driven toward that point in grid coordinates, while it is blind the same happens in the virtual space,
and once sensor 2 is in range control switches to the sensor-2 readings themselves until they match the goal.

Beyond the paper, the blind stretch is crossed as it was crossed in practice: the route is one practised excursion
(where it left sensor-1 range and the commands it drove from there until sensor 2 first saw the wall). The robot drives
to that exit with sensor-1 control, to within `exit_tolerance` grid units by the mean of `exit_settle_steps` readings
it stands for there (or until it loses the wall near the exit, at the range's edge, as the excursion did), and replays
those commands; the virtual space tracks the state meanwhile and takes over if the replay ends with sensor 2 still out
of sight (after its last command went on for `replay_overrun_steps`: begun a little off the practised exit, a marginal
crossing misses by a step), or if the approach got stuck farther than `waypoint_tolerance` from the exit (from there
the commands would lead elsewhere). A pose relative to an infinite wall is fixed by its sensor-1 coordinates, and the
same commands from the same pose drive the same path, so the crossing no longer depends on how well the extrapolated
field predicts far from the range (on the tuning seeds the field's own plan missed sensor 2 on 15-40 % of the tasks of
some explorations, standing still where the field said the goal was). `replay_routes=False` gives the paper's method:
the virtual-space plan alone.

In every space the learned Jacobian field J(y) predicts how a command moves the state (y' = J(y) u); in sensor 2's,
the field is corrected online from what the readings did under the episode's own commands (`sensor2_adapt_steps`). Plain
one-step Jacobian control stalls at the nonholonomic singularity near "parallel to the wall" (no command moves the
distance-like reading there), so each step evaluates a set of constant commands over a short horizon with the learned
field and keeps the one that brings the state closest to the goal (plus the damped least-squares Jacobian step as one
candidate), with a small cost on wheel travel so rotating in place is preferred where it does the job.

Never wander blind: each blind stretch (no sensor group in range) gets a length the route predicts, in steps: during
a replay the route's practised blind length (the states between its exit and sensor 2's first reading in practice),
otherwise the controller's own plan rolled out in the learned virtual field from where the wall was lost to the route's
goal coordinates. A stretch that runs past `blind_factor` times that plus `blind_margin_steps` means the virtual space
is wrong there: the robot replays the commands it drove blind backwards (it knows its own commands; a differential
drive retraces its path exactly under reversed commands), back to where it last saw the wall (further back along the
path before the stretch if it is still blind there: a lost reading may have hidden one out of range; still blind at
its end, it stands still for `lost_wait_steps` fresh readings before it fails "lost"), and then takes the next
practised route, or fails with the reason once `max_retries` routes were tried. A crossing (a stretch begun
with sensor 1 last in sight) is held to a tighter budget while other routes remain: `blind_budget` times its
predicted length for the whole stretch, out and back, counted from where a replay ran out or from the wall's loss
when none is under way (see _turn_back_now). So is a stretch begun in sensor 2's range (a sensor-2 manoeuvre left it;
budget_sensor2_loss): the retrace undoes the blind commands and the one that left the range, and sensor-2 control
chooses afresh from there; the watchdog's limit for it is its margin alone (sensor2_loss_margin_only). Durations are in
steps and distances in readings or grid units: nothing here knows the robot's size.
"""
from __future__ import annotations

import math
from itertools import product
from typing import Optional

import numpy as np
from mm_common.learned_fields import PolynomialField, jacobian_design, polynomial_features, theta_from_solution
from mm_msgs.msg import ManifoldState

# The active spaces are the state message's constants (their one home).
SPACE_NONE, SPACE_SENSOR1 = ManifoldState.SPACE_NONE, ManifoldState.SPACE_SENSOR1
SPACE_VIRTUAL, SPACE_SENSOR2 = ManifoldState.SPACE_VIRTUAL_SENSOR1, ManifoldState.SPACE_SENSOR2


def blind(readings) -> bool:
    """Whether no sensor group sees the wall, from the raw readings (sensor 1's three, then sensor 2's two): a group
    sees it when none of its readings is out of range (+-inf) and at least one has a value; a lost reading (NaN)
    is not evidence of being out of range."""
    r = np.asarray(readings, dtype=float)

    def sees(group):
        return not np.any(np.isinf(group)) and bool(np.any(np.isfinite(group)))
    return not (sees(r[:3]) or sees(r[3:5]))


def _extend_runs(runs: list, u: np.ndarray, dt: float) -> None:
    """Append one step of command `u` to [command, seconds] runs, merged with the last run when equal."""
    if runs and np.array_equal(runs[-1][0], u):
        runs[-1][1] += dt
    else:
        runs.append([np.array(u, dtype=float), dt])


class SwitchingController:
    """Hyperparameters: dt, max_wheel_speed [rad/s], horizon [steps] of the virtual-space search, speed levels of
    its candidate set, travel_weight (cost of wheel travel relative to the squared goal error), manoeuvre_travel_weight
    (the same for the sensor-2 manoeuvres, relative to the squared error in tolerance units: 1e-2 makes a 28-step
    drive cost about one tolerance of error; on offline tasks disjoint from the benchmark's it shortened the median
    path by 1-6 % over 1e-3 at equal or better success), tolerance [m] on each sensor-2 reading, settle_steps /
    max_settle_steps (fewest / most steps standing still to decide whether the reading is within tolerance: noisy
    readings need more of them), damping of the least-squares step, waypoint_tolerance [grid units], turn_speed /
    drive_speed of the sensor-2 manoeuvres (fractions of max_wheel_speed, the robot's own limit: 1.5 and 4 rad/s
    on wheeled_sim's 6 rad/s), stall_steps (steps without progress toward the target before
    aiming at the next fallback), max_retries (times the route is restarted from the practised exit when every
    target was reached blind, or after the blind watchdog brought the robot back; 7 of 3 and 7, judged on the same
    models: noisy tuning cells 0.899 -> 0.925 mean success, clean 0.995 -> 0.997, results/tune_wall_retries.json),
    blind_factor and
    blind_margin_steps (the watchdog: a blind stretch may last blind_factor x its predicted length + the margin;
    set from the stall window and a 50 % allowance for the field's error, not tuned), blind_prediction_cap [steps]
    (longest rollout of the prediction), retrace_history_steps (how far before a blind stretch the watchdog's retrace
    may go on back when the robot is still blind where a sensor last saw the wall: a lost reading (NaN) can hide
    one out of range, and such a step is no sighting; 5 of 1 / 5 / 20 / 60 by `mm_bringup.tune_wall --noisy
    --controller` on tuning seeds, mean success 0.747 / 0.850 / 0.835 / 0.837 over 30 noisy cells,
    results/tune_wall_retrace.json; without lost readings it changes nothing), replay_routes (cross the blind stretch
    by replaying the route's practised commands from its exit, module docstring; False: the paper's virtual-space
    plan alone), exit_tolerance [grid units] (how close to the route's exit the replay starts, by the mean of the
    readings stood for: the approach stops where that first falls within it, on the side it came from, and under
    noise a pose a centimetre off the practised one can miss sensor 2; 0.02 of 0.05 / 0.03 / 0.02 by
    `mm_bringup.tune_wall --controller --rule blind` on the same models, 80 noisy `paper` tuning cells: share over 2x
    0.048 -> 0.044 / 0.041 at mean success 0.981 -> 0.974 / 0.977 (seeds 100-109 and 110-119 alike: 0.052 -> 0.045,
    0.044 -> 0.037), within a noisy run's spread; 40 clean cells' success 1.0 either way; item 1 18 of 20 tuning
    seeds either way; results/tune_wall_exit_tolerance.json, results/tune_wall_exit_tolerance_item1.json), exit_holds
    (times the exit's command is driven again while sensor 1 still sees the wall after it: the approach from inside
    the range stops short of the practised exit), replay_on_loss (the wall lost within waypoint_tolerance of the
    route's exit, on the way there, starts the replay on that first blind step: the exit is the excursion's last
    in-range state, at the range's edge, and noisy readings fall out of range before the approach gets within
    exit_tolerance; the virtual-space plan from there dithered blind until the watchdog's limit), blind_budget (a
    crossing, out and back, in multiples of its predicted length; issue 11's target is 2; 0: only the watchdog's
    limit). Both chosen together by `mm_bringup.tune_wall --controller` on tuning seeds 100-109
    (results/tune_wall_replay_on_loss.json; README, "Never wander blind"): over 40 noisy `paper` cells the share of
    episodes blind over 2x 0.381 -> 0.152 at mean success 0.986 -> 0.991, over 40 clean ones 0.093 -> 0.03 at 1.0;
    without noise replay_on_loss changes nothing; there the budget held only stretches past a replay that ran out),
    budget_every_crossing (the budget holds every crossing, not only one past a replay: one with no replay under way,
    the wall lost on the approach or a route without practised commands, is held to blind_budget times the plan's
    predicted length; on by `mm_bringup.tune_wall --controller` on tuning seeds 100-109, 40 noisy `paper` cells: share
    over 2x 0.143 -> 0.079 at mean success 0.991 -> 0.989, clean cells unchanged,
    results/tune_wall_budget_every_crossing.json; a stretch begun in sensor 2's range is not held by it: held that way
    then, it cost 1.5 points of noisy success; budget_sensor2_loss holds it now), virtual_on_carried_goal (sensor 2's
    readings out of range while the learner carries its state, and that state within tolerance of the goal: drive by
    the virtual-space plan instead of standing still for sensor 2 to confirm, which waited blind for the learner's
    20-step hold; 40 noisy tuning cells, the same models: share over 2x 0.077 -> 0.062 at mean success 0.988 -> 0.987,
    clean cells unchanged, results/tune_wall_virtual_on_carried_goal.json), sensor2_loss_margin_only (a stretch begun
    where sensor 2 last saw the wall is watched with blind_margin_steps alone instead of the limit from the plan's
    rollout, which reached 170 steps when the rollout hit its cap: on 400 noisy tuning tasks 201 of the 207 stretches
    begun after sensor 2 had seen the wall that found it again did so within 20 steps; 40 noisy tuning cells, the same
    models: share over 2x 0.058 -> 0.054 at mean success 0.987 -> 0.989, clean cells unchanged,
    results/tune_wall_sensor2_loss_margin.json),
    replay_overrun_steps (a replay that ran out with no sensor in sight drives its last moving command this many steps
    more before the virtual-space plan: a route practised as a turn in place that saw sensor 2 after one blind step,
    begun a little off its exit, ended one step short, and the plan's first command drove away; on the same tuning
    models, 40 clean `paper` cells: share over 2x 0.03 -> 0.001 at success 1.0 (2 and 4 alike); 80 noisy cells 0.057 ->
    0.042 at mean success 0.974 -> 0.972 (2: 0.044, 4: 0.046), results/tune_wall_replay_overrun.json), lost_wait_steps
    (steps the robot stands still for fresh readings where the watchdog's retrace ended still blind, before it fails
    'lost': back where a sensor last saw the wall, at the range's edge, a noisy reading falls out of range as often as
    not; on the same tuning models, 80 noisy `paper` cells: mean success 0.972 -> 0.976 (88 -> 78 failed episodes of
    3 200), share over 2x 0.046 either way; 10 steps on 40 cells as 5; clean cells unchanged,
    results/tune_wall_lost_wait.json), exit_settle_steps (readings the robot stands for once one estimate puts it within
    exit_tolerance of a route's exit; the replay starts if their mean is within it too, else the approach goes on from
    the mean; 0 or 1: the first estimate decides. Under noise one estimate is no pose, and the practised commands
    retrace the practised path only from the practised pose; 80 noisy `paper` tuning cells, the same models: share over
    2x 0.053 -> 0.040 at mean success 0.971 -> 0.970 (8: 0.043, 0.969), and with standing steps kept off the retrace's
    path (_remember) 0.051 -> 0.048 at 0.983 -> 0.981, both within a noisy run's spread; clean cells unchanged,
    results/tune_wall_exit_settle_length.json, results/tune_wall_exit_settle.json), hold_steps (sees_nothing: a lost
    reading stands for the sensor's last one for this many steps when judging whether a group sees the wall, the
    learner's StateTracker default), sensor2_adapt_steps and sensor2_adapt_ridge (sensor-2 control corrects the learned
    sensor-2 field from the episode's own steps: once this many steps with a moving command had sensor 2 measured on
    both ends, a correction of the field's own polynomial form is fitted by ridge regression, ridge relative to the mean
    diagonal of the normal equations, to what those steps' readings did and refitted on every such step after; 0: the
    field as learned. The field is learned from a few excursions' sensor-2 readings, and toward goals away from them
    its predictions of the manoeuvres are wrong: see _adapt_sensor2. On against off by `mm_bringup.tune_wall
    --controller --rule blind` on the same tuning models: 80 noisy `paper` cells mean success 0.978 -> 0.992, share over
    2x 0.043 -> 0.042, 40 clean cells 1.0 either way, results/tune_wall_sensor2_adapt.json; 20 steps and the ridge were
    set by hand on one traced tuning model, seed 113, not tuned), budget_sensor2_loss (a stretch begun where sensor 2
    last saw the wall is held to blind_budget times its predicted length, out and back, as a crossing is, and the
    manoeuvre under way is dropped when the robot turns back; off, such a stretch ran to the watchdog's margin, 20
    steps, and as far back. On against off by `mm_bringup.tune_wall --controller --rule blind` on the same tuning
    models: 80 noisy `paper` cells share over 2x 0.041 -> 0.017 at mean success 0.993 -> 0.992, 40 clean cells 0.004 ->
    0 at 1.0, results/tune_wall_budget_sensor2_loss.json; tried in the thirteenth session, before the sensor-2 field
    was corrected online, it cost 1.5 points of noisy success)."""

    def __init__(self, dt: float, max_wheel_speed: float = 6.0, horizon: int = 12,
                 speed_levels=(1.0, 0.4, 0.12, 0.0), travel_weight: float = 1e-3, tolerance: float = 0.01,
                 settle_steps: int = 4, damping: float = 1e-2, waypoint_tolerance: float = 0.3,
                 turn_speed: float = 0.25, drive_speed: float = 2 / 3, stall_steps: int = 20, max_retries: int = 7,
                 max_settle_steps: int = 30, manoeuvre_travel_weight: float = 1e-2, blind_factor: float = 1.5,
                 blind_margin_steps: int = 20, blind_prediction_cap: int = 100, retrace_history_steps: int = 5,
                 replay_routes: bool = True, exit_tolerance: float = 0.02, exit_holds: int = 5,
                 blind_budget: float = 2.0, hold_steps: int = 3, replay_on_loss: bool = True,
                 budget_every_crossing: bool = True, virtual_on_carried_goal: bool = True,
                 sensor2_loss_margin_only: bool = True, replay_overrun_steps: int = 1, lost_wait_steps: int = 5,
                 exit_settle_steps: int = 4, sensor2_adapt_steps: int = 20, sensor2_adapt_ridge: float = 1e-2,
                 budget_sensor2_loss: bool = True):
        if dt <= 0 or max_wheel_speed <= 0 or tolerance <= 0 or horizon < 1:
            raise ValueError('dt, max_wheel_speed, tolerance and horizon must be positive')
        if travel_weight < 0 or manoeuvre_travel_weight < 0:
            raise ValueError('travel weights must be >= 0')
        if not 2 <= settle_steps <= max_settle_steps:
            raise ValueError('need 2 <= settle_steps <= max_settle_steps')
        if not (0 < turn_speed <= 1 and 0 < drive_speed <= 1):
            raise ValueError('turn_speed and drive_speed are fractions of max_wheel_speed in (0, 1]')
        if blind_factor < 1 or blind_margin_steps < 0 or blind_prediction_cap < 1 or retrace_history_steps < 1:
            raise ValueError('need blind_factor >= 1, blind_margin_steps >= 0, blind_prediction_cap >= 1 and '
                             'retrace_history_steps >= 1')
        if not exit_tolerance > 0:
            raise ValueError('exit_tolerance must be positive')
        if (exit_holds < 0 or not (blind_budget == 0 or blind_budget >= 1) or hold_steps < 0 or replay_overrun_steps < 0
                or lost_wait_steps < 0 or exit_settle_steps < 0 or sensor2_adapt_steps < 0
                or not sensor2_adapt_ridge > 0):
            raise ValueError('need exit_holds >= 0, blind_budget 0 (off) or >= 1, hold_steps >= 0, '
                             'replay_overrun_steps >= 0, lost_wait_steps >= 0, exit_settle_steps >= 0, '
                             'sensor2_adapt_steps >= 0 and sensor2_adapt_ridge > 0')
        self.dt = dt
        self.max_wheel_speed = max_wheel_speed
        self.horizon = horizon
        self.tolerance = tolerance
        self.travel_weight = travel_weight
        self.manoeuvre_travel_weight = manoeuvre_travel_weight
        self.settle_steps = settle_steps
        self.max_settle_steps = max_settle_steps
        self.damping = damping
        self.waypoint_tolerance = waypoint_tolerance
        self.stall_steps = stall_steps
        self.max_retries = max_retries
        self.blind_factor = blind_factor
        self.blind_margin_steps = blind_margin_steps
        self.blind_prediction_cap = blind_prediction_cap
        self.retrace_history_steps = retrace_history_steps
        self.replay_routes = bool(replay_routes)
        self.exit_tolerance = exit_tolerance
        self.exit_holds = exit_holds
        self.blind_budget = blind_budget
        self.hold_steps = hold_steps
        self.replay_on_loss = bool(replay_on_loss)
        self.budget_every_crossing = bool(budget_every_crossing)
        self.virtual_on_carried_goal = bool(virtual_on_carried_goal)
        self.sensor2_loss_margin_only = bool(sensor2_loss_margin_only)
        self.replay_overrun_steps = int(replay_overrun_steps)
        self.lost_wait_steps = int(lost_wait_steps)
        self.exit_settle_steps = int(exit_settle_steps)
        self.sensor2_adapt_steps = int(sensor2_adapt_steps)
        self.sensor2_adapt_ridge = float(sensor2_adapt_ridge)
        self.budget_sensor2_loss = bool(budget_sensor2_loss)
        self._held: list = []               # each sensor's last reading and how many steps it has been lost since
        self._plan: Optional[np.ndarray] = None
        levels = sorted({s * max_wheel_speed * sign for s in speed_levels for sign in (-1, 1)})
        self.candidates = np.array(list(product(levels, levels)), dtype=float)
        self.manoeuvres, self.manoeuvre_travel = self._manoeuvres(turn_speed * max_wheel_speed,
                                                                  drive_speed * max_wheel_speed)
        self.goal_sensor2: Optional[np.ndarray] = None
        self.goal_coordinates: Optional[np.ndarray] = None
        self.waypoint: Optional[np.ndarray] = None
        self.settled, self._settle_readings = 0, []

    @staticmethod
    def _manoeuvres(turn_speed: float, drive_speed: float, turns=(0, 1, 3, 6, 12),
                    drives=(0, 1, 3, 8, 16, 28)):
        """Turn-drive-turn command sequences (zero-padded): the shortest manoeuvres of a differential drive that
        change a distance-like reading while keeping the heading-like one (parking manoeuvres)."""
        turn = [(n, sign) for n in turns for sign in ((1,) if n == 0 else (-1, 1))]
        drive = [(n, sign) for n in drives for sign in ((1,) if n == 0 else (-1, 1))]
        length = 2 * max(turns) + max(drives)
        seqs, travel = [], []
        for (n1, s1), (n2, s2), (n3, s3) in product(turn, drive, turn):
            seq = np.zeros((length, 2))
            seq[:n1] = (-s1 * turn_speed, s1 * turn_speed)
            seq[n1:n1 + n2] = (s2 * drive_speed, s2 * drive_speed)
            seq[n1 + n2:n1 + n2 + n3] = (-s3 * turn_speed, s3 * turn_speed)
            seqs.append(seq)
            travel.append(n2 * drive_speed + 0.1 * (n1 + n3) * turn_speed)
        return np.array(seqs), np.array(travel)

    def set_goal(self, sensor2_goal: np.ndarray, goal_coordinates: np.ndarray,
                 waypoint: Optional[np.ndarray] = None, fallbacks: Optional[np.ndarray] = None,
                 sensor2_noise: Optional[np.ndarray] = None, alternatives=(),
                 replay: Optional[np.ndarray] = None) -> None:
        """`waypoint`: where in sensor-1 range the practised excursions toward this goal left the range; the robot
        first goes there with sensor-1 control, then aims at the goal's virtual coordinates. `replay` (n, 2): the
        commands that excursion drove from the waypoint until sensor 2 saw the wall, replayed from there (with
        replay_routes). `fallbacks`: virtual coordinates to aim at next if the goal's are reached while sensor 2
        still does not see the wall (the virtual estimate has drifted). `alternatives`: further (waypoint, goal
        coordinates[, replay]) routes, taken in turn on each retry (the same route again when there are none).
        `sensor2_noise`: learned std of the sensor-2 reading noise; the stop decision never trusts a few readings
        to be less noisy than that."""
        sensor2_goal = np.asarray(sensor2_goal, dtype=float)
        goal_coordinates = np.asarray(goal_coordinates, dtype=float)
        if sensor2_goal.ndim != 1 or not len(sensor2_goal) or goal_coordinates.ndim != 1:
            raise ValueError(f'goal reading and coordinates must be vectors, got shapes {sensor2_goal.shape} and '
                             f'{goal_coordinates.shape}')
        if not (np.all(np.isfinite(sensor2_goal)) and np.all(np.isfinite(goal_coordinates))):
            raise ValueError('goal reading and coordinates must be finite')
        self.goal_sensor2 = sensor2_goal
        self.sensor2_noise = np.zeros_like(sensor2_goal) if sensor2_noise is None else np.asarray(sensor2_noise,
                                                                                                  dtype=float)
        self.goal_coordinates = goal_coordinates
        self.waypoint = None if waypoint is None else np.asarray(waypoint, dtype=float)
        self.fallbacks = [] if fallbacks is None else [np.asarray(f, dtype=float) for f in fallbacks]
        self._fallbacks = list(self.fallbacks)
        self._routes = [(self.waypoint, self.goal_coordinates, self._checked_replay(replay))] + [
            (np.asarray(route[0], dtype=float), np.asarray(route[1], dtype=float),
             self._checked_replay(route[2] if len(route) > 2 else None)) for route in alternatives]
        self._route_replay = self._routes[0][2]   # the current route's practised commands (None: none)
        self._replay: list = []                   # [command, seconds] runs of the replay under way
        self._replay_total = 0                    # its steps as driven here (_replay_steps when it started)
        self._exit_command, self._exit_holds = None, 0   # its first moving command, and how often driven again
        self._overrun_command, self._overrun_left = None, 0   # its last moving command, and how often it may go on
        self._exit_settle: Optional[list] = None   # coordinates measured standing at the exit (exit_settle_steps)
        self._seen_in_range = []           # grid coordinates measured in this episode with sensor 1 in range
        self.retries = 0
        self.best_error, self.stalled_steps = np.inf, 0
        self.settled, self._settle_readings = 0, []
        self._plan = None
        self._s2_best, self._s2_stalled, self._chosen, self._avoid = np.inf, 0, set(), set()
        # Blind watchdog: the current stretch, its prediction and limit, the commands driven in it (to retrace), the
        # longest stretch of the episode as (steps, predicted steps), and why the task cannot go on (None: it can).
        self.blind_steps, self.predicted_blind, self.blind_limit = 0, 0, 0
        self._practised_stretch = False     # the stretch began in a replay (blind_budget applies past it)
        self._sensor2_last = False          # on the last step a group saw the wall, control was in sensor 2's space
        self._from_sensor2 = False          # the stretch began there (lost in the sensor-2 phase, not a crossing)
        self._blind_runs: list = []         # [command, seconds] runs driven in this stretch (the way back)
        self._last_chance_taken = False     # the one step driven on after the way back stopped fitting (see there)
        self._path: list = []
        self.returning = False
        self._lost_waits = 0                # steps stood still at the retrace's end, still blind (lost_wait_steps)
        self.longest_blind = (0, 0)
        self.watchdog_trips = 0
        self.failure: Optional[str] = None
        # Online correction of the sensor-2 field (_adapt_sensor2): the last step's measured reading and command, the
        # normal equations of the steps so far, how many moved, and the corrected field (None: the field as learned).
        self._sensor2_step: Optional[tuple] = None
        self._adapt_normal, self._adapt_moves, self._adapted_field = None, 0, None

    def set_goal_from_routes(self, virtual_space, sensor2_goal: np.ndarray,
                             sensor2_noise: Optional[np.ndarray] = None) -> None:
        """set_goal with the learned model's route to the goal reading (`virtual_space` has goal_route and
        ranked_routes, e.g. mm_planner.wall_model.WallModel) and, for the retries, its next-best routes. Raises
        ValueError when the space cannot map the reading (no overlap with sensor 2 learned)."""
        _, _, fallbacks = virtual_space.goal_route(sensor2_goal)
        best, *alternatives = virtual_space.ranked_routes(sensor2_goal, 1 + self.max_retries)
        self.set_goal(sensor2_goal, best.goal, best.exit, fallbacks, sensor2_noise=sensor2_noise,
                      alternatives=alternatives, replay=best.replay)

    def _checked_replay(self, replay: Optional[np.ndarray]) -> Optional[np.ndarray]:
        """A route's practised commands as (n, 2) finite floats, or None (none, or replay_routes off)."""
        if replay is None or not self.replay_routes:
            return None
        replay = np.asarray(replay, dtype=float)
        if replay.ndim != 2 or replay.shape[1] != 2 or not np.all(np.isfinite(replay)):
            raise ValueError(f'a route replay must be finite (n, 2) wheel commands, got shape {replay.shape}')
        return replay if len(replay) else None

    @property
    def target(self) -> Optional[np.ndarray]:
        return self.waypoint if self.waypoint is not None else self.goal_coordinates

    def _best_constant_command(self, field, state: np.ndarray, goal: np.ndarray, scale: float,
                               bounds: Optional[np.ndarray]) -> np.ndarray:
        """Best constant command over the horizon (closest predicted approach to the goal, plus wheel travel),
        judged by the learned field; the damped least-squares Jacobian step is one of the candidates."""
        dls = self.jacobian_step(field.jacobian(state[None])[0], goal - state)
        U = np.vstack([self.candidates, dls])
        y = np.repeat(state[None], len(U), axis=0)
        best = np.full(len(U), np.inf)
        travel = np.zeros(len(U))
        for _ in range(self.horizon):
            y = y + field.rates(y, U) * self.dt
            if bounds is not None:
                y = np.clip(y, bounds[0], bounds[1])
            travel += np.abs(U.sum(axis=1))
            best = np.minimum(best, np.sum(((y - goal) / scale) ** 2, axis=1) + self.travel_weight * travel)
        return U[int(np.argmin(best))]

    def _best_manoeuvre(self, field, state: np.ndarray, goal: np.ndarray, box: Optional[np.ndarray]) -> np.ndarray:
        """Next command of the turn-drive-turn manoeuvre under way, or, when none is, the first command of the one
        whose predicted end reading is closest to the goal (in tolerance units). A chosen manoeuvre is carried out
        to its end: re-choosing every step from slightly wrong predictions makes the robot dither between turning
        left and right. Manoeuvres predicted to leave `box` (2, d), the readings sensor 2 was seen at, are
        discarded: there it would be lost and the field is extrapolating. The box is widened to hold the current
        reading and the goal, both seen in range (a goal nearer the wall than exploration went must stay reachable)."""
        if self._plan is not None and len(self._plan):
            u, self._plan = self._plan[0], self._plan[1:]
            return u
        seqs = self.manoeuvres
        if box is not None:
            box = np.array([np.minimum.reduce([box[0], state, goal]), np.maximum.reduce([box[1], state, goal])])
        y = np.repeat(state[None], len(seqs), axis=0)
        leaves = np.zeros(len(seqs), dtype=bool)
        for t in range(seqs.shape[1]):
            y = y + field.rates(y, seqs[:, t]) * self.dt
            if box is not None:
                leaves |= np.any((y < box[0]) | (y > box[1]), axis=1)
                y = np.clip(y, box[0], box[1])
        cost = (np.sum(((y - goal) / self.tolerance) ** 2, axis=1)
                + self.manoeuvre_travel_weight * self.manoeuvre_travel)
        cost[~np.isfinite(cost)] = np.inf
        cost[list(self._avoid)] = np.inf
        if np.isfinite(cost[~leaves]).any():
            cost[leaves] = np.inf
        elif self._s2_stalled <= self.stall_steps:
            # Every manoeuvre leaves: the one-step least-squares move, while it makes progress. Where the field is
            # wrong it can converge short of the goal (seen: 1 200 steps parked 8 mm off), so once it stalls the
            # best manoeuvre is taken even though its prediction leaves the box.
            return self.jacobian_step(field.jacobian(state[None])[0], goal - state)
        if not np.isfinite(cost).any():
            return self.jacobian_step(field.jacobian(state[None])[0], goal - state)
        chosen = int(np.argmin(cost))
        self._chosen.add(chosen)
        best = seqs[chosen]
        moving = np.flatnonzero(np.any(best != 0, axis=1))
        self._plan = best[1:moving[-1] + 1] if len(moving) else None
        return best[0]

    def _watch_progress(self, error: float) -> None:
        """Sensor-2 phase: when the manoeuvres chosen since the last progress have not brought the reading closer for
        3 * stall_steps, the learned field mispredicts them here (the robot cycles between them): rule them out until
        the error improves again."""
        if error < self._s2_best - 0.25 * self.tolerance:
            self._s2_best, self._s2_stalled, self._chosen, self._avoid = error, 0, set(), set()
            return
        self._s2_stalled += 1
        if self._s2_stalled > 3 * self.stall_steps and (self._plan is None or not len(self._plan)):
            self._avoid |= self._chosen
            if len(self._avoid) >= len(self.manoeuvres) - 1:
                self._avoid = set()
            self._chosen, self._s2_stalled = set(), 0

    def _refuted(self, target: np.ndarray) -> bool:
        """A target the robot has been at in this episode (by its measured grid coordinates) while sensor 1 saw the
        wall and sensor 2 did not cannot be where the goal reading is: its virtual coordinates (learned from noisy
        excursions) have drifted into sensor 1's range."""
        if not self._seen_in_range:
            return False
        seen = np.asarray(self._seen_in_range)
        return float(np.min(np.linalg.norm(seen - target, axis=1))) < self.waypoint_tolerance

    def _next_target(self) -> None:
        """Aim at the next fallback that this episode's sensor-1 readings have not refuted (the last one if all)."""
        while len(self.fallbacks) > 1 and self._refuted(self.fallbacks[0]):
            self.fallbacks.pop(0)
        self.goal_coordinates = self.fallbacks.pop(0)
        self.best_error, self.stalled_steps = np.inf, 0

    def _adapt_sensor2(self, field, reading: Optional[np.ndarray]) -> None:
        """Learn from the step just driven: when sensor 2 was measured before and after it, its reading rate under
        the command is one more equation J(y) u = dy/dt. The learned field mispredicts it away from the readings
        it was fitted on (tuning seed 113, front 0.75 m robot: a model announced after five rehearsals turned back and
        forth for 1 500 steps toward goals 1-2 cm of reading from any practised one); a correction of the field's own
        form, fitted to this episode's rates, moves its predictions toward what the readings did (sensor2_adapt_steps).
        The normal equations add up step by step, so each refit costs the same however long the episode."""
        last, self._sensor2_step = self._sensor2_step, None
        if not self.sensor2_adapt_steps or field is None or reading is None or last is None:
            return
        y, u = last
        if not np.any(u):
            return                                       # standing still says nothing about J
        p = polynomial_features(y[None], field.degree, field.center, field.scale)
        x = jacobian_design(p, u[None])[0]
        residual = (reading - y) / self.dt - field.rates(y[None], u[None])[0]
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(residual))):
            return                                       # a field that overflows here would poison every refit after
        if self._adapt_normal is None:
            self._adapt_normal = (np.zeros((len(x), len(x))), np.zeros((len(x), len(residual))))
        A, b = self._adapt_normal
        A += np.outer(x, x)
        b += np.outer(x, residual)
        self._adapt_moves += 1
        if self._adapt_moves < self.sensor2_adapt_steps:
            return
        ridge = self.sensor2_adapt_ridge * np.trace(A) / len(A)
        coef = np.linalg.solve(A + ridge * np.eye(len(A)), b)                  # (f * du, dy)
        correction = theta_from_solution(coef, p.shape[1], len(u))             # (f, dy, du), as the field's theta
        if field.correction is not None:
            correction = correction + field.correction
        self._adapted_field = PolynomialField(field.degree, field.theta, field.center, field.scale, correction)

    def jacobian_step(self, J: np.ndarray, error: np.ndarray) -> np.ndarray:
        """Damped least-squares Jacobian control: the wheel command that closes `error` in about `horizon` steps."""
        u = J.T @ np.linalg.solve(J @ J.T + self.damping * np.eye(len(error)), error / (self.horizon * self.dt))
        peak = np.max(np.abs(u))
        return u * (self.max_wheel_speed / peak) if peak > self.max_wheel_speed else u

    def sees_nothing(self, readings) -> bool:
        """blind() of the readings with each lost one (NaN) standing for the sensor's last reading for up to
        hold_steps steps, as the learner's StateTracker bridges them. A sensor out of range whose reading is lost stays
        out of range, so its group does not look in range on the strength of its other sensor alone: under 5 %
        dropout one such step ended a blind stretch, the watchdog's way back then began there, and the robot retraced
        only into the blind region ('lost'; README, "Never wander blind")."""
        values = [float(v) for v in readings]
        if len(self._held) != len(values):
            self._held = [[math.nan, 0] for _ in values]
        for i, v in enumerate(values):
            held = self._held[i]
            if math.isnan(v):
                held[1] += 1
                if held[1] <= self.hold_steps:
                    values[i] = held[0]
            else:
                held[0], held[1] = v, 0
        return blind(values)

    def command(self, space: int, coordinates: Optional[np.ndarray], sensor2: Optional[np.ndarray],
                virtual_field, sensor2_field, sensor1_jacobian: Optional[np.ndarray] = None,
                bounds: Optional[np.ndarray] = None, sensor2_box: Optional[np.ndarray] = None,
                sensor2_measured: bool = True, blind: Optional[bool] = None):
        """(wheel command, reached, error in the active space) for the current state. `virtual_field` and
        `sensor2_field` are the model's mm_common.learned_fields.PolynomialField (WallModel); `sensor1_jacobian` is
        the local Jacobian of the grid coordinates at the current reading (used while sensor 1 is in range);
        `sensor2_box` (2, 2) the range of sensor-2 readings seen during exploration; `sensor2_measured` False when
        the sensor-2 state is carried over a lost or out-of-range reading (it then never ends the task); `blind`
        whether no sensor group sees the wall (default: the active space is neither sensor's). When the task cannot
        go on, `failure` says why and the command is a stop."""
        if self.goal_sensor2 is None:
            raise ValueError('no goal set')
        reading = (np.asarray(sensor2, dtype=float) if space == SPACE_SENSOR2 and sensor2_measured
                   and sensor2 is not None else None)
        self._adapt_sensor2(sensor2_field, reading)
        u, reached, error = self._decide(space, coordinates, sensor2, virtual_field, sensor2_field, sensor1_jacobian,
                                         bounds, sensor2_box, sensor2_measured, blind)
        self._sensor2_step = None if reading is None else (reading, np.asarray(u, dtype=float))
        return u, reached, error

    def _decide(self, space, coordinates, sensor2, virtual_field, sensor2_field, sensor1_jacobian, bounds,
                sensor2_box, sensor2_measured, blind):
        """command() for this step, the sensor-2 field's correction up to date."""
        if blind is None:
            blind = space not in (SPACE_SENSOR1, SPACE_SENSOR2)
        if self.failure is not None:
            return np.zeros(2), False, float('nan')
        if not blind:
            self._sensor2_last = space == SPACE_SENSOR2
            self._end_blind_stretch(space)
            if self.failure is not None:
                return np.zeros(2), False, float('nan')
        else:
            if self.blind_steps == 0:
                self._start_blind_stretch(coordinates, virtual_field, bounds)
            self.blind_steps += 1
            if self.blind_steps > self.longest_blind[0]:
                self.longest_blind = (self.blind_steps, self.predicted_blind)
            if not self.returning and self.blind_steps > self.blind_limit:
                self._turn_back()
            if self.returning:
                return self._retrace()
        if (self.virtual_on_carried_goal and blind and space == SPACE_SENSOR2 and not sensor2_measured
                and sensor2 is not None
                and (self.settled or np.all(np.abs(np.asarray(sensor2) - self.goal_sensor2) < self.tolerance))):
            # Sensor 2's readings are out of range and the learner carries its state (a short virtual sensor 2),
            # which says the goal is reached: standing still until sensor 2 confirms waits for a reading that
            # cannot come while the robot stands where it is. The virtual-space plan drives on instead.
            space = SPACE_VIRTUAL
        replaying = bool(self._replay)
        u, reached, error = self._command(space, coordinates, sensor2, virtual_field, sensor2_field, sensor1_jacobian,
                                          bounds, sensor2_box, sensor2_measured)
        if (blind and self.blind_budget and not replaying and (
                self._practised_stretch
                or (self.budget_sensor2_loss if self._from_sensor2 else self.budget_every_crossing))
                and self.retries < self.max_retries and self._turn_back_now(u)):
            self._turn_back()
            return self._retrace()
        self._remember(u, blind)
        if blind:
            _extend_runs(self._blind_runs, u, self.dt)
        return u, reached, error

    # --- blind watchdog -----------------------------------------------------------------------------------------
    def _start_blind_stretch(self, coordinates: Optional[np.ndarray], virtual_field, bounds) -> None:
        """The wall was just lost: predict the stretch (while a replay is under way the route's practised blind
        length, else the plan's rollout to the route's goal) and set its limit."""
        self._blind_runs = []
        self._last_chance_taken = False
        self._practised_stretch = bool(self._replay)
        self._from_sensor2 = self._sensor2_last
        if self._practised_stretch:
            # The states between the exit and sensor 2's first reading in practice: the replay's steps (as driven
            # here, commands faster than max_wheel_speed slowed) but the last.
            self._predict_stretch(max(1, self._replay_total - 1))
        else:
            self._predict_stretch(self.blind_prediction_cap if coordinates is None
                                  else self.predict_blind_steps(virtual_field, np.asarray(coordinates, dtype=float),
                                                                bounds))
        if self._from_sensor2 and self.sensor2_loss_margin_only:
            # Lost where sensor 2 saw the wall: no crossing lies ahead, and the plan's rollout to the route's goal
            # (up to blind_prediction_cap) says nothing about the way back into sensor 2's range.
            self.blind_limit = min(self.blind_limit, self.blind_margin_steps)

    def _predict_stretch(self, steps: int) -> None:
        """The stretch's predicted length (at most blind_prediction_cap) and the watchdog's limit from it."""
        self.predicted_blind = min(self.blind_prediction_cap, steps)
        self.blind_limit = int(math.ceil(self.blind_factor * self.predicted_blind)) + self.blind_margin_steps

    def predict_blind_steps(self, virtual_field, coordinates: np.ndarray, bounds: Optional[np.ndarray]) -> int:
        """Steps the virtual-space plan needs from `coordinates` through the route's remaining exit to its goal
        coordinates, rolled out in the learned field (at most blind_prediction_cap)."""
        y = coordinates.copy()
        targets = [t for t in (self.waypoint, self.goal_coordinates) if t is not None]
        for n in range(self.blind_prediction_cap):
            while targets and np.linalg.norm(targets[0] - y) < self.waypoint_tolerance:
                targets.pop(0)
            if not targets:
                return max(n, 1)
            u = self._best_constant_command(virtual_field, y, targets[0], 1.0, bounds)
            y = y + virtual_field.rates(y[None], u[None])[0] * self.dt
            if bounds is not None:
                y = np.clip(y, bounds[0], bounds[1])
        return self.blind_prediction_cap

    def _turn_back(self) -> None:
        self.returning = True
        self._plan = None               # the retrace undoes the sensor-2 manoeuvre under way, if any
        self.watchdog_trips += 1
        self._lost_waits = 0

    def _turn_back_now(self, u: np.ndarray) -> bool:
        """A crossing with no replay under way (it ran out, or none began) and no sensor in sight: whether to go back
        instead of driving `u`. The budget is blind_budget times the stretch's predicted length (the route's practised
        blind length past a replay), counting the retrace at max_wheel_speed: drive on while a miss after `u` could
        still come back within it; else go back if that still fits now; else (the way back no longer fits: a route
        practised with one blind step that missed by one) drive one step more, which ends the stretch within the budget
        if sensor 2 sees the wall after it, then go back."""
        budget = self.blind_budget * self.predicted_blind
        runs = [[v.copy(), seconds] for v, seconds in self._blind_runs]
        back_now = self._retrace_steps(runs)
        _extend_runs(runs, u, self.dt)
        if self.blind_steps + 1 + self._retrace_steps(runs) <= budget:
            return False
        if self.blind_steps + back_now <= budget or self._last_chance_taken:
            return True
        self._last_chance_taken = self.blind_steps <= budget
        return not self._last_chance_taken

    def _retrace_steps(self, runs: list) -> int:
        """Steps _follow takes to drive [command, seconds] `runs` backward (each run sped up to max_wheel_speed, at
        least one step; standing still is skipped)."""
        return sum(math.ceil(seconds * float(np.max(np.abs(u))) / (self.max_wheel_speed * self.dt) - 1e-9) or 1
                   for u, seconds in runs if np.any(u))

    def _remember(self, u: np.ndarray, blind: bool) -> None:
        """Keep the path the retrace may take back: [command, seconds] runs, newest last. While blind every step is
        kept (equal consecutive commands merged into one run); while a group sees the wall, one run per step and
        only the last `retrace_history_steps` (older ones dropped): the last of them took the robot out of sight,
        and undone it puts the robot back where a sensor last saw the wall - where a lost reading hid one out of
        range, that was no sighting, and the retrace goes on back along the path before it. Standing still moves
        nothing and takes no place on the path (the exit's settle, exit_settle_steps, would fill the history)."""
        u = np.asarray(u, dtype=float)
        if not np.any(u):
            return
        path = self._path
        if blind and path and np.array_equal(path[-1][0], u):
            path[-1][1] += self.dt
        else:
            path.append([u.copy(), self.dt])
        if not blind:
            excess = sum(seconds for _, seconds in path) - self.retrace_history_steps * self.dt
            while excess > 1e-12 * self.dt:
                if path[0][1] <= excess + 1e-12 * self.dt:
                    excess -= path.pop(0)[1]
                else:
                    path[0][1] -= excess
                    excess = 0.0

    def _retrace(self):
        """Next command back along the path (see _remember): the last run reversed, sped up to max_wheel_speed (the
        same arc in less time). Nothing left to retrace and still blind: standing still for fresh readings
        (lost_wait_steps), then the wall cannot be found again."""
        u = self._follow(self._path, backward=True)
        if u is None and self._lost_waits < self.lost_wait_steps:
            # Back where a sensor last saw the wall, and still blind: there, at the range's edge, a noisy reading
            # falls out of range as often as not. Fresh readings standing still before giving up.
            self._lost_waits += 1
            return np.zeros(2), False, float('nan')
        if u is None:
            self.failure = (f'lost: blind for {self.blind_steps} steps and the retraced path did not find the wall '
                            'again')
            return np.zeros(2), False, float('nan')
        return u, False, float('nan')

    def _follow(self, runs: list, backward: bool) -> Optional[np.ndarray]:
        """Next command along [command, seconds] `runs`, consumed as it goes (None when none is left); runs that
        stand still are skipped (they move nothing). Backward: the last run reversed and sped up to
        max_wheel_speed; forward: the first run as driven, slowed to max_wheel_speed if it was faster. Either way a
        run keeps its arc (both wheels scaled alike) and takes its time at the new speed."""
        at = -1 if backward else 0
        while runs and not np.any(runs[at][0]):
            runs.pop(at)
        if not runs:
            return None
        run = runs[at]
        u, seconds = run
        speed = self.max_wheel_speed / float(np.max(np.abs(u)))
        covered = min(seconds, (speed if backward else min(1.0, speed)) * self.dt)
        run[1] -= covered
        if run[1] <= 1e-12:
            runs.pop(at)
        return (-u if backward else u) * (covered / self.dt)

    def _slowed(self, u: np.ndarray) -> np.ndarray:
        """One step of practised command `u` as the replay drives it: slowed to max_wheel_speed on the same arc."""
        return u * min(1.0, self.max_wheel_speed / float(np.max(np.abs(u))))

    def _start_replay(self) -> None:
        """At the route's exit: replay its practised commands (equal consecutive ones merged into runs)."""
        self._replay = []
        moving = [u for u in self._route_replay if np.any(u)]
        self._exit_command, self._exit_holds = (np.asarray(moving[0], dtype=float) if moving else None), 0
        self._overrun_command = np.asarray(moving[-1], dtype=float) if moving else None
        self._overrun_left = self.replay_overrun_steps if moving else 0
        for u in self._route_replay:
            if self._replay and np.array_equal(self._replay[-1][0], u):
                self._replay[-1][1] += self.dt
            else:
                self._replay.append([u.copy(), self.dt])
        self._replay_total = self._replay_steps()
        if self.replay_on_loss and self.blind_steps == 1 and not self.returning:
            # The wall was lost on the way to the exit (replay_on_loss): the stretch is this replay, begun one step
            # early - its steps as driven, the blind one it starts on included.
            self._practised_stretch = True
            self._predict_stretch(self._replay_total)
            if self.longest_blind[0] == self.blind_steps:
                self.longest_blind = (self.blind_steps, self.predicted_blind)

    def _replay_steps(self) -> int:
        """Steps the replay under way still takes (runs faster than max_wheel_speed take longer)."""
        return sum(int(math.ceil(seconds * max(1.0, float(np.max(np.abs(u))) / self.max_wheel_speed) / self.dt - 1e-9))
                   for u, seconds in self._replay if np.any(u))

    def _end_blind_stretch(self, space: int) -> None:
        """A sensor sees the wall again. After a retrace back to sensor 1, take the next practised route (or fail:
        every route was tried)."""
        returned, self.returning = self.returning, False
        self.blind_steps = 0
        if not returned or space == SPACE_SENSOR2:       # sensor 2 in sight: carry on toward the goal
            return
        if self.retries >= self.max_retries or self._routes[0][0] is None:
            self.failure = (f'blind longer than predicted on {self.retries + 1} routes (last stretch limit '
                            f'{self.blind_limit} steps, predicted {self.predicted_blind}); back at the wall')
            return
        self._restart_route()

    def _restart_route(self) -> None:
        """Start again from the next practised route's exit (sensor 1 re-localises on re-entry)."""
        self.retries += 1
        self.waypoint, self.goal_coordinates, self._route_replay = self._routes[self.retries % len(self._routes)]
        self._replay, self._overrun_left, self._exit_settle = [], 0, None
        self.fallbacks = list(self._fallbacks)
        self.best_error, self.stalled_steps = np.inf, 0
        if self.fallbacks and self._refuted(self.goal_coordinates):
            self._next_target()

    def _command(self, space: int, coordinates: Optional[np.ndarray], sensor2: Optional[np.ndarray],
                 virtual_field, sensor2_field, sensor1_jacobian: Optional[np.ndarray],
                 bounds: Optional[np.ndarray], sensor2_box: Optional[np.ndarray], sensor2_measured: bool):
        if space == SPACE_SENSOR2:
            # crossed: sensor-2 control from here, even if it loses the wall (readings stood for at the exit are old)
            if self._adapted_field is not None:
                sensor2_field = self._adapted_field
            self._replay, self._overrun_left, self._exit_settle = [], 0, None
            error = np.abs(sensor2 - self.goal_sensor2)
            if self.settled or np.all(error < self.tolerance):
                if not sensor2_measured:      # hold still until sensor 2 itself confirms
                    return np.zeros(2), False, float(error.max())
                # Within tolerance: stand still and decide on the mean reading (a sequential test). Done once the
                # mean is within tolerance by three standard errors; moving on once it is outside by as much, or
                # after max_settle_steps. Clean readings decide after settle_steps; noisy ones near the edge of
                # the tolerance take longer instead of ending the task outside it by chance.
                self.settled += 1
                self._settle_readings.append(np.asarray(sensor2, dtype=float))
                if self.settled >= self.settle_steps:
                    window = np.array(self._settle_readings)
                    centre = np.abs(window.mean(axis=0) - self.goal_sensor2)
                    spread = np.maximum(window.std(axis=0, ddof=1), self.sensor2_noise)
                    margin = 3.0 * spread / np.sqrt(len(window))
                    if np.all(centre + margin < self.tolerance):
                        return np.zeros(2), True, float((centre + margin).max())
                    if np.any(centre - margin >= self.tolerance) or self.settled >= self.max_settle_steps:
                        self.settled, self._settle_readings = 0, []
                        self._plan = None
                        u = self._best_manoeuvre(sensor2_field, window.mean(axis=0), self.goal_sensor2, sensor2_box)
                        return u, False, float(centre.max())
                return np.zeros(2), False, float(error.max())
            self.settled, self._settle_readings = 0, []
            self._watch_progress(float(error.max()))
            u = self._best_manoeuvre(sensor2_field, np.asarray(sensor2, dtype=float), self.goal_sensor2,
                                     sensor2_box)
            return u, False, float(error.max())
        self.settled, self._settle_readings = 0, []
        self._plan = None
        if (self._replay and space == SPACE_SENSOR1 and self._exit_command is not None
                and self._exit_holds < self.exit_holds and self._replay_total - self._replay_steps() == 1):
            # Still in range after the exit's command: the approach (from inside the range) stopped short of the
            # practised exit, the last in-range state. Its command again, until the wall is lost as in practice.
            self._exit_holds += 1
            return self._slowed(self._exit_command), False, float('nan')
        u = self._follow(self._replay, backward=False)
        if u is not None:                 # crossing as practised (module docstring)
            return u, False, float('nan')
        if self._overrun_left and not self.blind_steps:
            self._overrun_left = 0        # the replay ran out with a sensor in sight: nothing to carry on
        if self._overrun_left:
            # The replay ran out with no sensor in sight, where the practised excursion saw sensor 2: started a little
            # off the practised exit, a marginal crossing misses by a step or two. Its last command goes on, as the
            # excursion was moving, before the virtual-space plan takes over.
            self._overrun_left -= 1
            return self._slowed(self._overrun_command), False, float('nan')
        if coordinates is None:
            return np.zeros(2), False, float('nan')
        coordinates = np.asarray(coordinates, dtype=float)
        if space == SPACE_SENSOR1:
            self._seen_in_range.append(coordinates)
        replaying = self.waypoint is not None and self._route_replay is not None
        settled_at_exit = False
        if self._exit_settle is not None:
            if space != SPACE_SENSOR1:
                self._exit_settle = None          # lost the wall standing at the range's edge: as on the approach
            else:
                self._exit_settle.append(coordinates)
                if len(self._exit_settle) < self.exit_settle_steps:
                    return np.zeros(2), False, float(np.linalg.norm(self.target - coordinates))
                coordinates, self._exit_settle = np.mean(self._exit_settle, axis=0), None
                settled_at_exit = True
        error = float(np.linalg.norm(self.target - coordinates))
        if (replaying and self.exit_settle_steps > 1 and not settled_at_exit and space == SPACE_SENSOR1
                and error < self.exit_tolerance):
            # At the exit by one noisy estimate: the replay needs the practised pose, so the robot stands for
            # exit_settle_steps readings and judges their mean (above), going on with the approach from there if it
            # is not within exit_tolerance after all.
            self._exit_settle = [coordinates]
            return np.zeros(2), False, error
        # A replay needs the practised exit itself: approached more closely (progress counted in finer steps).
        if error < self.best_error - (min(0.05, self.exit_tolerance / 5) if replaying else 0.05):
            self.best_error, self.stalled_steps = error, 0
        else:
            self.stalled_steps += 1
        # The wall lost near the exit, on the way there: the practised excursion left the range about here too.
        lost_at_exit = (self.replay_on_loss and replaying and space != SPACE_SENSOR1 and self.blind_steps == 1
                        and error < self.waypoint_tolerance)
        if self.waypoint is not None and (
                error < (self.exit_tolerance if replaying else self.waypoint_tolerance) or lost_at_exit
                or self.stalled_steps > 3 * self.stall_steps):
            # At the practised exit (or unable to get closer, e.g. noisy readings at the range edge): go for the goal,
            # as practised from near the exit; from farther (stuck on the way) the practised commands would lead
            # elsewhere, and the virtual-space plan goes on instead.
            self.waypoint = None
            self.best_error, self.stalled_steps = np.inf, 0
            if replaying and error < self.waypoint_tolerance:
                self._start_replay()
                u = self._follow(self._replay, backward=False)
                if u is not None:
                    return u, False, float('nan')
        if space == SPACE_SENSOR1 and sensor1_jacobian is not None and self.waypoint is not None:
            step_error = self.waypoint - coordinates
            return self.jacobian_step(sensor1_jacobian, step_error), False, float(np.linalg.norm(step_error))
        error = float(np.linalg.norm(self.target - coordinates))
        if self.waypoint is None and self.fallbacks and (self.stalled_steps > self.stall_steps
                                                         or error < self.waypoint_tolerance):
            # Arrived (as far as the estimate knows) or stuck, and sensor 2 sees nothing: aim deeper.
            self._next_target()
        elif (self.waypoint is None and not self.fallbacks and self.stalled_steps > self.stall_steps
              and self.retries < self.max_retries and self._routes[0][0] is not None):
            # Every target reached blind and still no sensor 2: the virtual estimate has drifted too far. Go back
            # to a practised exit (sensor 1 re-localises on re-entry): the next alternative route, else this one.
            self._restart_route()
        elif (space == SPACE_SENSOR1 and self.waypoint is None and not self.fallbacks
              and self.stalled_steps > self.stall_steps):
            # Every route tried and no command brings the state closer: waiting for the step limit changes nothing.
            self.failure = (f'stuck in sensor-1 range {error:.3f} from the target after {self.retries + 1} routes '
                            f'({self.stalled_steps} steps without progress)')
            return np.zeros(2), False, error
        u = self._best_constant_command(virtual_field, coordinates, self.target, 1.0, bounds)
        return u, False, float(np.linalg.norm(self.target - coordinates))
