"""The wheeled robot's behaviour in the wall task (paper Section 2), as one pure class driven step by step: by the
switching_controller node from ROS messages, and by the offline runner (mm_bringup.wall_experiment) from the
simulator model, so both run the same code.

Phases (mm_msgs/ControllerStatus): EXPLORING (RandomExplorer: random motion with a reflex on the readings and the
bumper) -> LEARNING (no commands: the lockstep loop pauses while the learner fits; a model that has not seen sensor 2
during its excursions cannot map any goal, or whose held-out predictions miss their bound, is not ready, so
`exploration_steps // 4` more exploration steps follow, until the learner's refit is) -> REHEARSING -> WAITING_FOR_GOAL
-> REACHING_SENSOR1 / REACHING_VIRTUAL_SENSOR1 / REACHING_SENSOR2 (SwitchingController, with its retries) ->
GOAL_REACHED or FAILED (then waiting again).

Rehearsing: a model the learner found ready is announced only after `rehearsals` practice reaches with it succeeded,
each from a practised sensor-1 state to a sensor-2 reading the robot saw during its own excursions (both drawn with
`random_state`; see _rehearse). Success is judged as for any goal, on the robot's own readings. One failed rehearsal
rejects the model: `verdict` says so (the node publishes it, and the learner refits after more samples), and
`exploration_steps // 4` more exploration steps follow, within the same cap. The held-out check alone let through
models that failed many tasks: on the paper layout's tuning seeds (results/tune_wall_rehearsals.json), 3 of 20
announced models reached 40-65 % of random tasks; with 5 rehearsals none below 80 %, mean success 0.91 -> 0.97, for a
median 4 400 samples instead of 3 000 (the rehearsals are samples too). A learner that holds fewer
samples than were explored (it restarted) gets as many more exploration steps before LEARNING. Nothing here sees world
coordinates: an observation holds the learner's state of one step, the raw readings and the bumper, and the events
(a new model, a new goal) that arrived since the last step.
"""
from __future__ import annotations

import inspect
import math
from dataclasses import dataclass, field
from typing import Any, List, Optional, Tuple, Union

import numpy as np
from mm_common.wheeled_sensors import SENSOR1
from mm_msgs.msg import ControllerStatus, ManifoldState

from mm_planner.exploration import RandomExplorer
from mm_planner.switching_controller import SwitchingController
from mm_planner.wall_model import WallModel

PHASE_NAMES = {getattr(ControllerStatus, n): n[len('PHASE_'):] for n in dir(ControllerStatus) if n.startswith('PHASE_')}
REACHING = {ManifoldState.SPACE_SENSOR1: ControllerStatus.PHASE_REACHING_SENSOR1,
            ManifoldState.SPACE_VIRTUAL_SENSOR1: ControllerStatus.PHASE_REACHING_VIRTUAL_SENSOR1,
            ManifoldState.SPACE_SENSOR2: ControllerStatus.PHASE_REACHING_SENSOR2}
COMMANDING = (ControllerStatus.PHASE_EXPLORING, ControllerStatus.PHASE_REHEARSING)   # besides REACHING


@dataclass
class Goal:
    """A sensor-2 reading to reach; `stamp` is opaque (the goal message's header stamp), reported back as is."""
    reading: np.ndarray
    tolerance: float = 0.0
    stamp: Any = None


@dataclass
class Observation:
    """One step's learner state (absent when the observation only carries events) and the events since the last."""
    state: bool = False
    stamp: Any = None                              # the state's stamp (opaque), reported back with its answer
    space: int = ManifoldState.SPACE_NONE
    coordinates: Optional[np.ndarray] = None
    sensor2_estimate: Optional[np.ndarray] = None
    readings: Optional[np.ndarray] = None          # (5,) raw: sensor 1 then sensor 2; +-inf out of range, NaN lost
    sensor1_range: Optional[np.ndarray] = None     # (2,) [min, max] the front sensors read [m] (with the readings)
    learner_samples: Optional[int] = None          # samples the learner holds (None: unknown)
    bumped: bool = False
    model: Optional[WallModel] = None
    fit_failure: Optional['FitFailure'] = None      # the learner could not fit a model on what was explored
    goal: Optional[Goal] = None


@dataclass
class FitFailure:
    """The learner announced that it could not fit a model on `samples` samples, and why."""
    reason: str
    samples: int


@dataclass
class Decision:
    """The command to send (None: none this step) and what the status reports."""
    command: Optional[np.ndarray]
    phase: int
    detail: str
    step: int
    goal_stamp: Any
    stamp: Any = None                               # stamp of the state answered (None: no state this step)
    error: float = math.nan
    target: Tuple[float, ...] = ()
    goal_accepted: Optional[bool] = None
    goal_reason: str = ''
    log: List[str] = field(default_factory=list)     # phase transitions, for the driver's log
    verdict: Optional['Verdict'] = None              # made on a model in this step (the node publishes it)

    @property
    def phase_name(self) -> str:
        return PHASE_NAMES[self.phase]


@dataclass
class Verdict:
    """The agent's judgement of a model the learner found ready, after rehearsing with it."""
    model_samples: int
    accepted: bool
    reason: str
    learner_samples: int = 0          # the learner's sample count at the state the verdict answered (0: unknown)


@dataclass
class Rehearsal:
    """The rehearsals of one model: how many reached; for the one under way, the practised sensor-1 state it starts
    from (None: sensor 1 not in range yet) and the practised sensor-2 reading it reaches (None: not started)."""
    model: WallModel
    passed: int = 0
    start: Optional[np.ndarray] = None
    goal: Optional[np.ndarray] = None
    steps: int = 0                  # steps spent getting to the start
    best: float = math.inf          # closest to the start so far, and steps since it improved
    stalled: int = 0


class WallAgent:
    """Hyperparameters: dt [s] of a step, exploration_steps, max_wheel_speed [rad/s], tolerance [m] (when the goal
    gives none), max_reach_steps, random_state of the exploration, max_exploration_steps (the cap: a model still not
    ready after this many exploration steps ends FAILED with its reason; None: 4 x exploration_steps, at least 4),
    explorer_params (RandomExplorer hyperparameters that differ from its defaults; the paper's undirected exploration
    is exploration.UNDIRECTED), rehearsals (practice reaches a ready model must pass before it is announced; 0: the
    learner's readiness decides alone), controller_params (SwitchingController hyperparameters that differ from its
    defaults, for every reach and rehearsal)."""

    def __init__(self, dt: float, exploration_steps: int = 10000, max_wheel_speed: float = 6.0,
                 tolerance: float = 0.01, max_reach_steps: int = 1500, random_state: Optional[int] = 0,
                 max_exploration_steps: Optional[int] = None, explorer_params: Optional[dict] = None,
                 rehearsals: int = 5, controller_params: Optional[dict] = None):
        if rehearsals < 0:
            raise ValueError('rehearsals must be >= 0')
        self.dt = dt
        self.rehearsals = rehearsals
        self.rehearsal: Optional[Rehearsal] = None
        self.rehearsal_rng = np.random.default_rng(random_state)
        self.verdict: Optional[Verdict] = None
        self.exploration_steps = exploration_steps
        self.max_exploration_steps = (4 * max(exploration_steps, 1) if max_exploration_steps is None
                                      else max_exploration_steps)
        self.max_wheel_speed = max_wheel_speed
        self.tolerance = tolerance
        self.max_reach_steps = max_reach_steps
        self.explorer_params = _settable(RandomExplorer, explorer_params, ('max_wheel_speed', 'random_state'))
        self.controller_params = _settable(SwitchingController, controller_params,
                                           ('dt', 'max_wheel_speed', 'tolerance'))
        self._new_controller(tolerance)      # a bad hyperparameter fails here, not at the first goal (ValueError)
        self.explorer = RandomExplorer(**self.explorer_params, max_wheel_speed=max_wheel_speed,
                                       random_state=random_state)
        self.controller: Optional[SwitchingController] = None
        self.model: Optional[WallModel] = None
        self.goal: Optional[Goal] = None
        self.goal_stamp: Any = None
        self.phase = ControllerStatus.PHASE_EXPLORING if exploration_steps else ControllerStatus.PHASE_LEARNING
        self.phase_step = 0
        self.explored = 0
        self.exploration_budget = exploration_steps     # grows when the learned model is not ready
        self.learner_lost = 0                           # samples the learner lost (restarts) and were made up for
        self.pending: Optional[Observation] = None       # the newest state not answered with a command yet
        self.set_aside: Optional[Union[WallModel, FitFailure]] = None   # a not-ready model (or none) while exploring
        self.reach_steps = 0
        self.detail = 'started'
        self._log: List[str] = []

    @property
    def needs_bumper(self) -> bool:
        """Exploring (or rehearsing, which explores between reaches): the explorer's reflex reads the bumper, so a
        state should come with the step's bumper reading."""
        return self.phase in (ControllerStatus.PHASE_EXPLORING, ControllerStatus.PHASE_REHEARSING)

    def step(self, observation: Observation) -> Decision:
        """Take the events, then answer the observation's state (or, after an event, the state still waiting)."""
        self._log, self.verdict = [], None
        accepted, reason = None, ''
        if observation.model is not None:
            self._take_model(observation.model)
        if observation.fit_failure is not None:
            self._take_fit_failure(observation.fit_failure)
        if observation.goal is not None:
            accepted, reason = self._take_goal(observation.goal)
        state = observation if observation.state else self.pending
        command, error, target, stamp = None, math.nan, (), None
        commanding = self.phase in COMMANDING or self.phase in REACHING.values()
        if state is not None and (observation.state or commanding):
            self.pending, stamp = state, state.stamp
            command, error, target = self._answer(state)
        return Decision(command, self.phase, self.detail, self.phase_step, self.goal_stamp, stamp, error, target,
                        accepted, reason, self._log, self.verdict)

    # --- events -----------------------------------------------------------------------------------------------
    def _set_phase(self, phase: int, detail: str) -> None:
        """Enter `phase` (its step count restarts); a new detail in the same phase (another goal) is logged too."""
        if phase != self.phase or detail != self.detail:
            self._log.append(f'{PHASE_NAMES[self.phase]} -> {PHASE_NAMES[phase]}: {detail}')
        if phase != self.phase:
            self.phase, self.phase_step = phase, 0
        self.detail = detail

    def _explore_more(self, why: str, why_at_cap: str, what: str = 'not ready') -> None:
        """No usable model yet (not ready, none could be fitted, or `what` = 'rejected' by a rehearsal): explore
        `exploration_steps // 4` more, or end FAILED with the reason at the cap."""
        extra = min(max(self.exploration_steps // 4, 1), self.max_exploration_steps - self.explored)
        if extra <= 0:
            self._set_phase(ControllerStatus.PHASE_FAILED, f'model {what} after {self.explored} exploration steps '
                            f'(the cap): {why_at_cap}')
            return
        self.exploration_budget = self.explored + extra
        self._set_phase(ControllerStatus.PHASE_EXPLORING, f'model {what} ({why}): exploring {extra} more steps')

    def _take_fit_failure(self, failure: FitFailure) -> None:
        """As a model that is not ready: explore more (set aside while exploring, like such a model)."""
        if self.phase == ControllerStatus.PHASE_EXPLORING:
            self.set_aside = failure
        elif self.phase == ControllerStatus.PHASE_LEARNING:
            self._explore_more(failure.reason, failure.reason)

    def _take_model(self, model: WallModel) -> None:
        self.model = model
        if not model.ready:
            # Exploring, a model that is not ready changes nothing yet; kept, it is acted on when the exploration
            # ends if it was fitted on all of it (see _answer).
            self.set_aside = model if self.phase == ControllerStatus.PHASE_EXPLORING else None
            if self.phase == ControllerStatus.PHASE_LEARNING:
                self._explore_more(f'{model.readiness}; held-out sensor-2 error {model.heldout_sensor2_error:.4f} m, '
                                   f'bound {model.heldout_limit:.4f} m', model.readiness)
        elif self.phase in (ControllerStatus.PHASE_LEARNING, ControllerStatus.PHASE_EXPLORING,
                            ControllerStatus.PHASE_REHEARSING):
            skipped = self.phase == ControllerStatus.PHASE_EXPLORING and self.explored < self.exploration_budget
            ready = ('a learned model exists: exploration skipped' if skipped else
                     f'model ready (held-out sensor-2 error {model.heldout_sensor2_error:.4f} m within '
                     f'{model.heldout_limit:.4f} m)')
            if not self.rehearsals:
                self._set_phase(ControllerStatus.PHASE_WAITING_FOR_GOAL, ready)
                self._start_goal()
                return
            self.rehearsal = Rehearsal(model)
            self._set_phase(ControllerStatus.PHASE_REHEARSING, f'{ready}; rehearsal 1/{self.rehearsals}: getting '
                                                               'sensor 1 in range')

    def check_goal(self, goal: Goal) -> Optional[str]:
        """Why a goal cannot be taken (None if it can): a positive finite sensor-2 reading that the sensors can show."""
        reading = np.asarray(goal.reading, dtype=float)
        if reading.shape != (2,):
            return f'the goal must be a sensor-2 reading of two values, got {reading.size}'
        if not np.all(np.isfinite(reading)) or np.any(reading <= 0):
            return f'goal reading must be positive and finite, got {list(map(float, reading))}'
        if not (goal.tolerance == 0.0 or (math.isfinite(goal.tolerance) and goal.tolerance > 0)):
            return f'tolerance {goal.tolerance} must be positive and finite (0: the default)'
        if self.model is not None:
            return self.model.unreadable_goal(reading, goal.tolerance)
        return None

    def _take_goal(self, goal: Goal) -> Tuple[bool, str]:
        problem = self.check_goal(goal)
        if problem:
            return False, problem
        self.goal = goal
        problem = self._start_goal()
        return (False, problem) if problem else (True, 'accepted')

    def _start_goal(self) -> Optional[str]:
        """Begin reaching once there is both a goal and a model. A goal the model cannot map ends FAILED under that
        goal's stamp (so whoever sent it sees the outcome); returns why."""
        if self.goal is None or self.model is None or self.phase in (ControllerStatus.PHASE_EXPLORING,
                                                                     ControllerStatus.PHASE_LEARNING,
                                                                     ControllerStatus.PHASE_REHEARSING):
            return None
        goal, self.goal = self.goal, None
        self.goal_stamp = goal.stamp
        reading = np.asarray(goal.reading, dtype=float)
        problem = self.model.unreadable_goal(reading, goal.tolerance) or (None if self.model.ready else
                                                          f'the model is not ready: {self.model.readiness}')
        tolerance = goal.tolerance or self.tolerance
        self.controller = self._new_controller(tolerance)
        if problem is None:
            try:
                self.controller.set_goal_from_routes(self.model, reading, self.model.sensor2_noise)
            except ValueError as exc:
                problem = f'cannot map the goal: {exc}'
        if problem:
            self._set_phase(ControllerStatus.PHASE_FAILED, problem)
            return problem
        self.reach_steps = 0
        self._set_phase(ControllerStatus.PHASE_REACHING_SENSOR1,
                        f'goal {list(map(float, reading))} (tolerance {tolerance} m)')
        return None

    # --- control ------------------------------------------------------------------------------------------------
    def _answer(self, state: Observation):
        command, error, target = None, math.nan, ()
        if self.phase == ControllerStatus.PHASE_EXPLORING:
            command = self._explore(state)
        if self.phase == ControllerStatus.PHASE_REHEARSING:       # also when a ready model ended the exploration
            command, error, target = self._rehearse(state)
        elif self.phase in REACHING.values():
            command, error, target = self._reach(state)
        self.phase_step += 1
        if command is not None:
            if not all(map(math.isfinite, np.asarray(command, dtype=float).tolist())):    # plain Python: every step
                # Never send a non-finite wheel command; standing still keeps the lockstep loop going.
                self._log.append(f'non-finite command {list(command)} replaced by a stop')
                command = np.zeros(2)
            self.pending = None
        return command, error, target

    def _explore(self, state: Observation) -> Optional[np.ndarray]:
        """The explorer's command, or None once the exploration budget is spent (LEARNING)."""
        command = None
        if (self.explored >= self.exploration_budget and state.learner_samples is not None
                and state.learner_samples + self.learner_lost < self.explored):
            # The learner lost samples (it restarted): without them it would never learn and the loop would
            # wait for good. Explore as many more as it lost, once per loss (the lost ones never come back, so
            # comparing its count with all steps explored would chase them for ever).
            expected = self.explored - self.learner_lost
            missing = expected - state.learner_samples
            self.learner_lost += missing
            self.exploration_budget = self.explored + missing
            self._set_phase(ControllerStatus.PHASE_EXPLORING, f'the learner holds {state.learner_samples} of '
                                                              f'{expected} samples: exploring {missing} more')
        if self.explored >= self.exploration_budget:
            self._set_phase(ControllerStatus.PHASE_LEARNING, f'{self.explored} exploration steps done')
            early, self.set_aside = self.set_aside, None
            if early is not None and early.samples + self.learner_lost >= self.explored:
                # The learner's answer came before the last step did (the learner fits once it holds as many
                # samples as steps explored, the reading before the first command included, while the last
                # step can be held up, e.g. by a restarting simulator); it fits again only after more samples,
                # so waiting for another model would stall the loop for good.
                if isinstance(early, FitFailure):
                    self._take_fit_failure(early)
                else:
                    self._take_model(early)
        if self.phase == ControllerStatus.PHASE_EXPLORING:
            command = self._explorer_command(state)
            self.explored += 1
        return command

    def _explorer_command(self, state: Observation) -> np.ndarray:
        if state.sensor1_range is None or len(state.sensor1_range) != 2:
            raise ValueError('an exploring state needs sensor1_range, the front sensors\' [min, max] range: the '
                             'explorer\'s reading thresholds are fractions of it')
        return self.explorer.command(state.readings, state.sensor1_range[1], state.bumped)

    def _rehearse(self, state: Observation):
        """One step of the rehearsals (module docstring): explore until sensor 1 sees the wall, drive with the
        sensor-1 Jacobians to a practised sensor-1 state (a region anchor of the model, drawn at random: tasks start
        anywhere in sensor-1 range, and from near the sensor-2 side a reach can be trivial), then reach a practised
        sensor-2 reading as a goal. The explorer follows every command (RandomExplorer.follow), so getting back into
        sensor-1 range after a reach, or exploring on after a rejection, retraces the reach's commands."""
        r = self.rehearsal
        number = f'rehearsal {r.passed + 1}/{self.rehearsals}'
        if r.goal is None:
            r.steps += 1
            if r.steps > self.max_reach_steps:
                return self._reject(f'{number}: sensor 1 not in range after {self.max_reach_steps} steps', state)
            in_range = state.coordinates is not None and (state.space == ManifoldState.SPACE_SENSOR1 or (
                state.space == ManifoldState.SPACE_SENSOR2 and _sees(state.readings, SENSOR1)))
            if r.start is None and in_range:
                r.start = np.asarray(r.model.region_anchors[int(self.rehearsal_rng.integers(
                    len(r.model.region_anchors)))], dtype=float)
                self.controller = self._new_controller(self.tolerance)
                self._set_phase(ControllerStatus.PHASE_REHEARSING, f'{number}: going to the practised sensor-1 '
                                                                   f'state {_rounded(r.start)}')
            distance = float(np.linalg.norm(r.start - state.coordinates)) if in_range else math.inf
            if distance < r.best - 0.05:
                r.best, r.stalled = distance, 0
            elif r.start is not None:
                r.stalled += 1           # out of range too: no state there is reached for sure
            c = self.controller
            if not in_range:             # back into sensor-1 range as the explorer does (it approaches the wall)
                return self._explorer_command(state), math.nan, ()
            if distance >= c.waypoint_tolerance and r.stalled <= c.stall_steps:
                step = c.jacobian_step(r.model.sensor1_jacobian(np.asarray(state.coordinates, dtype=float)),
                                       r.start - state.coordinates)
                self.explorer.follow(state.readings, step)
                return step, distance, tuple(float(v) for v in r.start)
            # There, or as near as it gets: the rehearsal's reach starts here.
            goal = self._rehearsal_goal(r.model)
            self.controller = self._new_controller(self.tolerance)
            try:
                self.controller.set_goal_from_routes(r.model, goal, r.model.sensor2_noise)
            except ValueError as exc:
                return self._reject(f'{number}: cannot map the practised reading {_rounded(goal)}: {exc}', state)
            r.goal, self.reach_steps = goal, 0
            self._set_phase(ControllerStatus.PHASE_REHEARSING, f'{number}: reaching the practised sensor-2 reading '
                                                               f'{_rounded(goal)} (tolerance {self.tolerance} m)')
        u, error, target, outcome = self._control(state, r.model)
        if outcome is None:
            self.explorer.follow(state.readings, u)         # its retrace back to sensor 1 then undoes the reach
            return u, error, target
        reached, how = outcome
        if not reached:
            return self._reject(f'{number} to the practised sensor-2 reading {_rounded(r.goal)} failed: {how}', state)
        self.rehearsal = r = Rehearsal(r.model, passed=r.passed + 1)
        if r.passed < self.rehearsals:
            self._set_phase(ControllerStatus.PHASE_REHEARSING, f'rehearsal {r.passed}/{self.rehearsals} reached; '
                                                               f'rehearsal {r.passed + 1}: getting sensor 1 in range')
            return self._rehearse(state)
        self.rehearsal = None
        reason = f'{r.passed}/{self.rehearsals} rehearsals reached practised sensor-2 readings (last: {how})'
        self.verdict = Verdict(r.model.samples, True, reason, state.learner_samples or 0)
        self._set_phase(ControllerStatus.PHASE_WAITING_FOR_GOAL,
                        f'model ready (held-out sensor-2 error {r.model.heldout_sensor2_error:.4f} m within '
                        f'{r.model.heldout_limit:.4f} m; {reason})')
        self._start_goal()
        if self.phase in REACHING.values():          # a goal was waiting: this state is its first
            return self._reach(state)
        return None, error, target

    def _new_controller(self, tolerance: float) -> SwitchingController:
        return SwitchingController(self.dt, max_wheel_speed=self.max_wheel_speed, tolerance=tolerance,
                                   **self.controller_params)

    def _rehearsal_goal(self, model: WallModel) -> np.ndarray:
        """A sensor-2 reading seen during the excursions that the model can take as a goal."""
        readings = [r for r in model.overlap_sensor2 if model.unreadable_goal(r) is None]
        if not readings:
            readings = list(model.overlap_sensor2)
        return np.asarray(readings[int(self.rehearsal_rng.integers(len(readings)))], dtype=float)

    def _reject(self, reason: str, state: Observation):
        """A rehearsal failed: the model is not announced; explore more (within the cap) for the learner's refit."""
        model, self.rehearsal = self.rehearsal.model, None
        self.verdict = Verdict(model.samples, False, reason, state.learner_samples or 0)
        self._explore_more(reason, reason, what='rejected')
        command = self._explore(state) if self.phase == ControllerStatus.PHASE_EXPLORING else None
        return command, math.nan, ()

    def _control(self, state: Observation, model: WallModel):
        """(command, error, target, outcome) of the controller on this state with `model`; outcome None while under
        way, else (reached, how it ended)."""
        m, c = model, self.controller
        space, coords, s2 = state.space, state.coordinates, state.sensor2_estimate
        J1 = m.sensor1_jacobian(coords) if space == ManifoldState.SPACE_SENSOR1 and coords is not None else None
        measured = bool(np.all(np.isfinite(np.asarray(state.readings, dtype=float)[3:5])))
        u, done, error = c.command(space, coords, s2, m.virtual_field, m.sensor2_field, J1, m.virtual_bounds,
                                   m.sensor2_box, sensor2_measured=measured, blind=c.sees_nothing(state.readings))
        target = c.goal_sensor2 if space == ManifoldState.SPACE_SENSOR2 else (c.target if c.target is not None else ())
        target = tuple(float(v) for v in target)
        if done:
            return None, error, target, (True, f'sensor-2 error {error:.4f} m; {self.blind_report()}')
        if c.failure is not None:
            return None, error, target, (False, f'{c.failure}; {self.blind_report()}')
        self.reach_steps += 1
        if self.reach_steps > self.max_reach_steps:
            return None, error, target, (False, f'not reached within {self.max_reach_steps} steps; '
                                                f'{self.blind_report()}')
        return u, error, target, None

    def _reach(self, state: Observation):
        """A user's goal: the controller's step, with the phase of the active space and the outcome."""
        if state.space in REACHING:
            self._set_phase(REACHING[state.space], f'{PHASE_NAMES[REACHING[state.space]].lower()} active')
        u, error, target, outcome = self._control(state, self.model)
        if outcome is not None:
            reached, how = outcome
            self._set_phase(ControllerStatus.PHASE_GOAL_REACHED if reached else ControllerStatus.PHASE_FAILED, how)
        return u, error, target

    def blind_report(self) -> str:
        """The episode's longest blind stretch for the status detail (mm_bringup.wall_graph parses it)."""
        steps, predicted = self.controller.longest_blind
        ratio = steps / predicted if predicted else 0.0
        return (f'longest blind stretch {steps} steps, {ratio:.2f} x the route\'s predicted {predicted}, '
                f'{self.controller.watchdog_trips} watchdog returns')


def _settable(cls, params: Optional[dict], agents_own: Tuple[str, ...]) -> dict:
    """`params` as a dict, refused (ValueError) when it names what `cls` does not take or what the agent sets itself."""
    params = dict(params or {})
    refused = sorted(set(params) - (set(inspect.signature(cls).parameters) - set(agents_own)))
    if refused:
        raise ValueError(f'{cls.__name__} has no hyperparameter {", ".join(refused)} (or it cannot be set here: '
                         f'{", ".join(agents_own)} are the agent\'s own)')
    return params


def _sees(readings, group) -> bool:
    """Every sensor of `group` reads the wall in this step. Where both groups see it (layouts whose ranges overlap)
    the learner's state is sensor 2's, with sensor 1's coordinates measured all the same: a rehearsal that waited for
    the sensor-1 space there was left to the explorer, whose excursions into sensor 2's range kept it there (1 500
    steps, a rejected model, on the overlap layout's graph test once excursions were repeated). Stricter than the
    controller's group test in blind(), which lets a lost reading pass: with that one, a noisy tuning cell (seed 100,
    default robot) began rehearsals on lost readings and needed 20 499 samples instead of 4 343."""
    values = np.asarray(readings, dtype=float)[list(group)].tolist()
    return all(map(math.isfinite, values))


def _rounded(reading) -> list:
    return [round(float(v), 4) for v in reading]
