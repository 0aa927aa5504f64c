"""Random exploration of the wheeled robot from its readings only (paper Section 2.2: "collecting samples by random
motion", and Fig. 3: "repeats motion in and out of the sensing range").

Wander: piecewise-constant random wheel commands (rotations, straight runs, arcs) with a reflex that backs off when a
front reading is very small, drives away from a bumper contact (opposite to the last command's travel: a robot that
reversed into the wall must not keep reversing), and drives forward when the wall is at the edge of the front range.
A lost reading (NaN) is unknown, not out of range: the last valid value of that sensor stands in for it. Excursion: from
inside sensor-1 range, a random rotation / run / rotation leaves the range (often into sensor 2's), then the robot
undoes the segments in a different order, so it comes back near - not exactly at - where it left; if that does not
bring sensor 1 back, it retraces every command since it left (differential drive is exactly reversible), which
guarantees the return without any world model. A robot that starts where sensor 1 does not see the wall searches for
it first (straight rays out and back, each longer than the last). An excursion that brought sensor 2 into range is
remembered (its segments, in steps) and, with probability `repeat_probability`, a later excursion repeats one of those with each
segment's length jittered: sensor 2's range may be a small target that random excursions rarely hit, and what reached
it once reaches it again from a similar exit. Practice: while an excursion has sensor 2 in range, the robot now
and then inserts a few short random turns and drives followed by their exact reverse, so that sensor 2's Jacobians
are learned from many samples and the excursion resumes where it was.

Directed by default (issue 11): every new excursion first approaches the wall (`approach_probability` 1) and, beside
the random trigger, an excursion starts whenever excursions have had less than `excursion_share` of the steps so far.
Undirected, sensor 2 is rarely seen when its range never overlaps sensor 1's: on the paper layout with 3 000 steps
few models were ready (tuning figures in README). Once an excursion has seen sensor 2, most new ones
(`repeat_probability` 0.6) repeat a jittered one that did: the learner's held-out check needs several excursions that
saw sensor 2, and fresh random ones found the third only after 2 625-3 000 steps on four of 20 tuning seeds
(results/tune_wall_repeat.json). The price is fewer and less varied excursions, so the virtual space extrapolates
worse away from the practised routes. The paper's undirected exploration is UNDIRECTED.
"""
from __future__ import annotations

import math
from collections import deque
from typing import Deque, List, Optional

import numpy as np
from mm_common.wheeled_sensors import SENSOR1, SENSOR2

# The paper's exploration ("collecting samples by random motion"): RandomExplorer hyperparameters without direction.
UNDIRECTED = {'approach_probability': 0.0, 'excursion_share': 0.0, 'repeat_probability': 0.0}



class RandomExplorer:
    """Hyperparameters: wheel speeds for turning and driving (fractions of max_wheel_speed, the robot's top wheel
    speed [rad/s] that the controller is given: 2 and 5 rad/s on wheeled_sim's 6 rad/s), hold range of a random command [steps],
    excursion probability per decision when the front-centre reading is below `excursion_below`, an excursion's
    first turn [steps, range], longest run and largest second turn [steps], repeat_probability and repeat_jitter
    (relative change of each segment's length) of a successful excursion, approach_probability (a new excursion
    first drives closer to the wall), the reflex reading `near` and the edge of the front range `far`, approach_bias
    (probability that a run with the front-centre reading between `back_off_below` and `far` goes toward the wall;
    below `back_off_below` runs mostly back off, between it and `mid_range_above` either way),
    practice_probability (per step with sensor 2 in range during an excursion) and practice_segments (random
    turn/drive segments per practice, each undone), excursion_share (excursions start, when in range, while they
    have had fewer than this share of all steps), search_growth (length ratio of successive search rays while
    sensor 1 has never seen the wall, see _search), random_state.

    Reading thresholds are fractions of the front sensors' max range, which `command` takes from their Range
    messages: no sensor's range is built in. The defaults are the metre values the explorer was tuned with on the
    1.5 m front sensors of wheeled_sim (0.08, 1.25, 0.6, 0.25 and 0.35 m), written as such fractions."""

    REFLEX_STEPS = 6        # steps of one reflex (back off, drive away from a contact, or turn when wedged)

    def __init__(self, turn_speed: float = 1 / 3, drive_speed: float = 5 / 6, max_wheel_speed: float = 6.0,
                 hold_steps=(4, 25),
                 excursion_probability: float = 0.3, excursion_below: float = 0.6 / 1.5, excursion_turn_steps=(7, 21),
                 excursion_run_steps: int = 40, excursion_turn2_steps: int = 5, repeat_probability: float = 0.6,
                 repeat_jitter: float = 0.2, approach_probability: float = 1.0, near: float = 0.08 / 1.5,
                 far: float = 1.25 / 1.5, back_off_below: float = 0.25 / 1.5, mid_range_above: float = 0.35 / 1.5,
                 approach_bias: float = 0.55, max_retrace: int = 400, practice_probability: float = 0.15,
                 practice_segments: int = 4, excursion_share: float = 0.3, search_growth: float = 2.0,
                 random_state: Optional[int] = None):
        if not (0 < turn_speed <= 1 and 0 < drive_speed <= 1 and max_wheel_speed > 0):
            raise ValueError('turn_speed and drive_speed are fractions of a positive max_wheel_speed, in (0, 1]')
        self.turn_speed = turn_speed
        self.drive_speed = drive_speed
        self.max_wheel_speed = max_wheel_speed
        self.turn_wheel_speed = turn_speed * max_wheel_speed       # [rad/s]
        self.drive_wheel_speed = drive_speed * max_wheel_speed     # [rad/s]
        self.hold_steps = hold_steps
        self.excursion_probability = excursion_probability
        self.excursion_below = excursion_below
        self.excursion_turn_steps = excursion_turn_steps
        self.excursion_run_steps = excursion_run_steps
        self.excursion_turn2_steps = excursion_turn2_steps
        self.repeat_probability = repeat_probability
        self.repeat_jitter = repeat_jitter
        self.approach_probability = approach_probability
        self.successes: List[list] = []          # segments of excursions that brought sensor 2 into range
        self.current: Optional[tuple] = None      # (exit front-centre reading, segments) of the excursion under way
        self.chosen: list = []                    # segments of the excursion being approached
        self.approach_target = 0.0
        self.current_saw_sensor2 = False
        self.near = near
        self.far = far
        self.back_off_below = back_off_below
        self.mid_range_above = mid_range_above
        self.front_range = math.nan               # the front sensors' max range [m] (command's argument)
        self.approach_bias = approach_bias
        self.max_retrace = max_retrace
        self.practice_probability = practice_probability
        self.practice_segments = practice_segments
        self.excursion_share = excursion_share
        self.search_growth = search_growth
        self.steps_in_excursions = 0
        self.practice_left = 0
        self.rng = np.random.default_rng(random_state)
        self.plan: Deque[np.ndarray] = deque()
        self.since_in_range: List[np.ndarray] = []
        self.mode = 'wander'
        self.excursions_started = 0
        self.last_valid = [math.inf] * (len(SENSOR1) + len(SENSOR2))    # the latest reading of each sensor
        self.last_command = np.zeros(2)
        self.steps = 0
        self.last_reflex_step = -10 ** 9
        self.seen_sensor1 = False                 # sensor 1 has had the wall in range at least once
        self.search_steps = 0                     # length of the last search ray [steps] (0: none yet)
        self.search_sighting = math.inf           # nearest front reading of the last step (inf: none)
        self.last_reflex_bumped = False
        self.wedge_turn = 0.0

    def _segment(self, command, steps) -> List[np.ndarray]:
        return [np.asarray(command, dtype=float)] * int(max(1, steps))

    def _random_wander(self, front: np.ndarray) -> None:
        centre = front[1]
        kind = self.rng.choice(['turn', 'drive', 'arc'])
        steps = self.rng.integers(*self.hold_steps)
        if kind == 'turn':
            s = self.rng.choice([-1, 1]) * self.turn_wheel_speed
            cmd = [-s, s]
            steps = max(1, steps // 3)          # short turns: stay mostly inside sensor-1 range
        else:
            direction = 1.0
            if np.isfinite(centre):
                if centre < self.back_off_below * self.front_range:
                    direction = -1.0 if self.rng.random() < 0.7 else 1.0
                elif centre > self.far * self.front_range:
                    direction = 1.0                        # at the edge of the front range: come closer
                elif centre > self.mid_range_above * self.front_range:
                    direction = 1.0 if self.rng.random() < self.approach_bias else -1.0
                else:
                    direction = self.rng.choice([-1.0, 1.0])
            v = direction * self.drive_wheel_speed * self.rng.uniform(0.4, 1.0)
            bend = self.rng.uniform(-0.4, 0.4) * self.drive_wheel_speed if kind == 'arc' else 0.0
            cmd = [v - bend, v + bend]
        self.plan.extend(self._segment(cmd, steps))

    def _search(self) -> None:
        """Before sensor 1 has ever seen the wall (a robot started beyond its range), wandering at random seldom
        finds it (0 of 10 seeds in 12 000 steps from 1 m with 0.75 m front sensors), and straight runs from random
        turns drift away. So: rays from where the search stands, each a random turn (none before the first), a
        straight run and the same run backwards, each `search_growth` times as long as the last; a ray heading
        toward the wall finds it once it is long enough, and no ray leaves the robot further away. Where part of
        sensor 1 sees the wall while the robot drives ahead and the sighting comes nearer, command() drives on, and
        the next rays start short again. (Driving on at any partial sighting failed twice: parallel to the wall with
        one sensor seeing it the robot drove along the wall for good, and a sighting during a ray's turn cut the turn
        short of facing the wall.)"""
        if self.search_steps:
            # a heading of its own, not a small step from the last one: up to four of an excursion's longest turns
            turn = self.rng.choice([-1.0, 1.0]) * self.turn_wheel_speed
            self.plan.extend(self._segment([-turn, turn], self.rng.integers(0, 4 * self.excursion_turn_steps[1])))
        self.search_steps = round(self.search_growth * self.search_steps) or self.hold_steps[1]
        self.plan.extend(self._segment([self.drive_wheel_speed] * 2, self.search_steps))
        self.plan.extend(self._segment([-self.drive_wheel_speed] * 2, self.search_steps))
        self.mode = 'search'

    def _start_approach(self, front: np.ndarray) -> None:
        """Choose the excursion: a repeat of one that reached sensor 2 (with probability repeat_probability) or a
        new random one. A repeat first drives toward the wall until the front-centre reading is the repeated one's
        exit reading (jittered); a new one does so with probability approach_probability, to an exit reading uniform
        between the reflex distance and the current reading (sensor 2 may only see the wall from close by)."""
        self._finish_excursion()
        self.mode = 'approach'
        self.approach_target = np.inf           # no approach: the excursion starts here
        if self.repeat_probability > 0 and self.successes and self.rng.random() < self.repeat_probability:
            exit_reading, base = self.successes[self.rng.integers(len(self.successes))]
            jitter = self.rng.uniform(1 - self.repeat_jitter, 1 + self.repeat_jitter, len(base) + 1)
            self.approach_target = exit_reading * jitter[0]
            self.chosen = [(cmd, max(0, round(steps * j))) for (cmd, steps), j in zip(base, jitter[1:])]
            return
        turn = self.rng.choice([-1, 1])
        turn_steps = self.rng.uniform(*self.excursion_turn_steps)
        run = self.rng.choice([-1.0, 1.0])
        run_steps = self.rng.uniform(0.0, self.excursion_run_steps)
        turn2_steps = self.rng.uniform(-self.excursion_turn2_steps, self.excursion_turn2_steps)
        turn2 = np.sign(turn2_steps)
        self.chosen = [(np.array([-turn, turn]) * self.turn_wheel_speed, round(turn_steps)),
                       (np.array([run, run]) * self.drive_wheel_speed, round(run_steps)),
                       (np.array([-turn2, turn2]) * self.turn_wheel_speed, round(abs(turn2_steps)))]
        if self.approach_probability > 0 and self.rng.random() < self.approach_probability:
            self.approach_target = self.rng.uniform(self.near * self.front_range, front[1])

    def _approach(self, front: np.ndarray, too_close: bool) -> None:
        if front[1] > self.approach_target and not too_close:
            self.plan.append(np.full(2, self.drive_wheel_speed * 0.5))
        else:
            self._excursion(front)

    def _finish_excursion(self) -> None:
        if self.current is not None and self.current_saw_sensor2:
            self.successes.append(self.current)
        self.current = None

    def _excursion(self, front: np.ndarray) -> None:
        """Rotate, run, rotate (the segments chosen by _start_approach); then undo the segments in the same (not
        reversed) order: a nearby return."""
        segments = self.chosen
        for cmd, steps in segments:
            self.plan.extend(self._segment(cmd, steps))
        for cmd, steps in segments:
            self.plan.extend(self._segment(-np.asarray(cmd), steps))
        self.mode = 'excursion'
        self.excursions_started += 1
        self.current, self.current_saw_sensor2 = (float(front[1]), segments), False

    def _reflex(self, bumped: bool) -> List[np.ndarray]:
        """Away from the contact: backwards, unless the robot got there reversing (bumper only). A reflex of the other
        kind (front reading too close / bumper) within a reflex's length means the robot is wedged: nearly parallel
        to the wall, a front sensor reads it too close and backing off bumps, so the two reflexes alternate for
        good. It then turns in place, which moves no part of it toward the wall, one way until no reflex follows."""
        recent = self.steps - self.last_reflex_step <= self.REFLEX_STEPS + 1
        wedged = recent and (bumped != self.last_reflex_bumped or self.wedge_turn != 0.0)
        self.last_reflex_step, self.last_reflex_bumped = self.steps, bumped
        if wedged:
            self.wedge_turn = self.wedge_turn or float(self.rng.choice([-1.0, 1.0]))
            return self._segment(np.array([-self.wedge_turn, self.wedge_turn]) * self.turn_wheel_speed, self.REFLEX_STEPS)
        self.wedge_turn = 0.0
        away = 1.0 if bumped and np.sum(self.last_command) < 0 else -1.0
        return self._segment([away * self.drive_wheel_speed] * 2, self.REFLEX_STEPS)

    def _practice(self) -> None:
        """Random short turns/drives, then the same in reverse order with negated commands (exact undo)."""
        moves = []
        for _ in range(self.practice_segments):
            steps = int(self.rng.integers(1, 8))
            sign = self.rng.choice([-1.0, 1.0])
            if self.rng.random() < 0.5:
                cmd = np.array([-sign, sign]) * self.turn_wheel_speed * self.rng.uniform(0.3, 1.0)
            else:
                cmd = np.array([sign, sign]) * self.drive_wheel_speed * self.rng.uniform(0.3, 1.0)
            moves += [cmd] * steps
        sequence = moves + [-c for c in reversed(moves)]
        self.plan.extendleft(reversed(sequence))
        self.practice_left = len(sequence)

    def follow(self, readings: np.ndarray, command: np.ndarray) -> None:
        """The robot drove `command` from `readings` on another's decision (the agent's rehearsals): remembered like
        its own commands, so that a later retrace toward sensor-1 range undoes it too; the plan under way is dropped
        (it was made for where the robot was)."""
        self.last_valid = [last if math.isnan(v) else v
                           for v, last in zip(np.asarray(readings, dtype=float).tolist(), self.last_valid)]
        cmd = np.asarray(command, dtype=float).copy()
        self.plan.clear()
        self.practice_left = 0
        self._finish_excursion()
        self.mode = 'wander'
        if all(math.isfinite(self.last_valid[i]) for i in SENSOR1):
            self.since_in_range = [cmd]
        else:
            self.since_in_range.append(cmd)
        self.last_command = cmd

    def command(self, readings: np.ndarray, front_range: float, bumped: bool = False) -> np.ndarray:
        """Next wheel command [left, right] from the current readings (NaN = lost, +-inf = out of range) and the
        front sensors' max range [m] (their Range messages' max_range), the unit of the reading thresholds."""
        if not (math.isfinite(front_range) and front_range > 0):
            raise ValueError(f'front_range {front_range!r} must be a positive max range [m]')
        self.front_range = float(front_range)
        # Plain Python on the five values: numpy's per-call cost on arrays this small was most of this step's work
        # (README, issue 14); the decisions are the same comparisons.
        values = readings.tolist() if isinstance(readings, np.ndarray) else [float(v) for v in readings]
        readings = [last if math.isnan(v) else v for v, last in zip(values, self.last_valid)]
        self.last_valid = readings
        front = [readings[i] for i in SENSOR1]
        finite = [math.isfinite(v) for v in front]
        in_range = all(finite)
        near = self.near * self.front_range
        too_close = bumped or any(ok and v < near for v, ok in zip(front, finite)) or -math.inf in front
        if in_range:
            if self.mode in ('retrace', 'search'):
                self.mode = 'wander'
                self.plan.clear()
            self.seen_sensor1 = True
        self.steps += 1
        if too_close and self.mode != 'retrace':
            self.plan.clear()
            self.practice_left = 0
            self.plan.extend(self._reflex(bumped))
            self.mode = 'wander'
        in_range2 = all(math.isfinite(readings[i]) for i in SENSOR2)
        if self.current is not None:
            self.current_saw_sensor2 |= in_range2 and not in_range
            if self.mode != 'excursion':          # it ended (back in range, reflex or retrace)
                self._finish_excursion()
        if self.practice_left > 0:
            self.practice_left -= 1
        elif (self.mode == 'excursion' and in_range2 and not too_close and self.plan
              and self.rng.random() < self.practice_probability):
            self._practice()
        sighted = [v for v, ok in zip(front, finite) if ok]
        if self.mode == 'search' and sighted:
            # Part of sensor 1 sees the wall. Driving ahead and coming nearer: drive on toward it until all of it
            # does or a reflex ends the ray (not during a turn, which must be completed to face the wall, nor along
            # the wall, where the sighting comes no nearer); the next rays start short again.
            ahead = bool((self.last_command == self.drive_wheel_speed).all())
            if ahead and not too_close and min(sighted) < self.search_sighting:
                self.plan.clear()
                self.plan.extend(self._segment([self.drive_wheel_speed] * 2, 1))
            self.search_steps = self.hold_steps[1]
        self.search_sighting = min(sighted) if sighted else math.inf
        if not self.plan:
            if not self.seen_sensor1:
                self._search()
            elif not in_range and self.since_in_range:
                # Still outside after the excursion: retrace exactly, newest command first.
                self.plan.extend(-c for c in reversed(self.since_in_range[-self.max_retrace:]))
                self.since_in_range = []
                self.mode = 'retrace'
            elif self.mode == 'approach' and in_range:
                self._approach(front, too_close)
            elif in_range and ((front[1] < self.excursion_below * self.front_range
                                and self.rng.random() < self.excursion_probability)
                               or self.steps_in_excursions < self.excursion_share * self.steps):
                self._start_approach(front)
                self._approach(front, too_close)
            else:
                self.mode = 'wander'
                self._random_wander(front)
        cmd = self.plan.popleft()
        if self.mode not in ('wander', 'search'):
            self.steps_in_excursions += 1
        if in_range:
            self.since_in_range = [cmd]       # the command that may take us out is the first one to undo
        elif self.mode != 'retrace':
            self.since_in_range.append(cmd)
        self.last_command = cmd
        return cmd.copy()
