"""The arm's behaviour in paper Section 3.3, as one pure class (no rclpy): explore -> learn-wait -> plan with DP on
the joint grid -> execute -> report. The dp_planner node and the offline runners drive this same class.

Drivers call, per simulator frame, `step(ArmObservation) -> joint target or None` (None: send nothing; in lockstep
the simulator then waits), and forward events: `set_goal(joints, stamp)`, `set_map(collision, closeness, stamp,
blocked_moves)`
(a CollisionMap built from the frame with that stamp), `explore_more(reason)` (the driver's learning timeout).
They publish what `pop_transitions()` returns (each phase change, with its reason) and, after each command,
`status()`; they send a map request for `take_map_request()` (a frame stamp) when it is not None.

Phases: EXPLORING (random joint targets from mm_planner.arm_exploration, `exploration_steps` commands) -> LEARNING
(no commands until the first collision map) -> WAITING_FOR_GOAL -> PLANNING -> EXECUTING -> GOAL_REACHED or FAILED.

Plan before moving: a goal is planned on a map built from a frame at least as new as the frame the arm will start
moving from. The object may have been re-placed since the last map (the model is kept across placements; the map
comes from the current image plus what was learned), so on a goal the agent asks for a map of its current frame and
sends no command until one arrives; a newer frame arriving meanwhile (e.g. the frame showing the new placement)
renews the request. Once moving, the agent's own motion does not move the object: later maps (refits) replan at once.

Planning is value iteration on the rows x cols joint grid (mm_planner.value_iteration.DPPlanner) with the paper's
rewards (0 at the goal cell, -100 for entering a predicted collision cell - or, when the map says which moves
collide, for a blocked move - and -1 per step) plus the clearance reward
(`clearance_reward`, default -5: free cells near the learned contact region cost up to that much more, see
value_iteration; 0 gives the paper's rewards only). FAILED names the reason: no collision-free path on the map, the
next move predicted to collide, or `max_execution_steps` passed. With `through_predicted_collision` the agent
instead follows the DP policy as the paper's rewards alone would (collision cells penalised, not forbidden: the path
with the fewest predicted collisions) when no collision-free path exists; off by default. Execution commands the
centre of the next cell until the arm is within `arrival_tolerance` of it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

import numpy as np

from mm_planner.arm_exploration import ArmExplorer
from mm_planner.value_iteration import DPPlanner, JointGrid

# Phase ids are those of mm_msgs/ControllerStatus (one home: the message); repeated here as plain ints because
# this module has no ROS imports. test_arm_agent checks they agree.
PHASE_EXPLORING, PHASE_LEARNING, PHASE_WAITING_FOR_GOAL = 1, 2, 3
PHASE_PLANNING, PHASE_EXECUTING, PHASE_GOAL_REACHED, PHASE_FAILED = 7, 8, 9, 10
PHASE_NAMES = {PHASE_EXPLORING: 'EXPLORING', PHASE_LEARNING: 'LEARNING', PHASE_WAITING_FOR_GOAL: 'WAITING_FOR_GOAL',
               PHASE_PLANNING: 'PLANNING', PHASE_EXECUTING: 'EXECUTING', PHASE_GOAL_REACHED: 'GOAL_REACHED',
               PHASE_FAILED: 'FAILED'}


@dataclass
class ArmObservation:
    """What the robot senses in one frame: its stamp [ns], joint angles [rad] and the hand's touch reading."""
    stamp: int
    joints: np.ndarray
    contact: bool


# Frames explored before the first map (chosen through the graph by mm_bringup.tune_arm_reach: 600 -> 52/60 goals,
# 1000 -> 59/60, 1500 -> 58/60 on its own scenes).
EXPLORATION_STEPS = 1000


@dataclass
class Transition:
    """A phase change: the new phase, why, and the stamp of the goal it belongs to (None before any goal)."""
    phase: int
    detail: str
    goal_stamp: Optional[int]


class ArmAgent:
    """Parameters: joint_limits ((lo0, hi0), (lo1, hi1)) [rad], grid_shape (rows, cols), exploration_steps,
    exploration_seed, contact_share, contact_spread, max_execution_steps, arrival_tolerance, step_reward,
    collision_reward, goal_reward, clearance_reward, clearance, through_predicted_collision (module docstring).
    State: phase_, detail_, phase_step_, explored_, goal_ (joints), goal_cell_, goal_stamp_ (ns of the goal being or
    last pursued), target_, map_stamp_ (frame of the map in use), maps_received_, commands_sent_."""

    def __init__(self, joint_limits, grid_shape: Tuple[int, int] = (8, 12),
                 exploration_steps: int = EXPLORATION_STEPS,
                 exploration_seed: Optional[int] = 0, contact_share: float = 0.25, contact_spread: float = 0.08,
                 max_execution_steps: int = 300, arrival_tolerance: float = 1e-3, step_reward: float = -1.0,
                 collision_reward: float = -100.0, goal_reward: float = 0.0, clearance_reward: float = -5.0,
                 clearance: float = 1.0, through_predicted_collision: bool = False):
        if exploration_steps < 0 or max_execution_steps < 1 or not arrival_tolerance > 0:
            raise ValueError('exploration_steps >= 0, max_execution_steps >= 1 and arrival_tolerance > 0 required')
        lim = np.asarray(joint_limits, dtype=float)
        self.grid = JointGrid(lim[0], lim[1], *grid_shape)
        self.planner = DPPlanner(self.grid, step_reward, collision_reward, goal_reward,
                                 clearance_reward=clearance_reward, clearance=clearance)
        self.explorer = ArmExplorer(self.grid.limits, contact_share=contact_share, spread=contact_spread,
                                    random_state=exploration_seed)
        self.exploration_steps = int(exploration_steps)
        self.max_execution_steps = int(max_execution_steps)
        self.arrival_tolerance = float(arrival_tolerance)
        self.through_predicted_collision = bool(through_predicted_collision)
        self.phase_ = PHASE_EXPLORING if self.exploration_steps > 0 else PHASE_LEARNING
        self.detail_ = 'start'
        self.phase_step_ = 0
        self.explored_ = 0
        self._explore_budget = self.exploration_steps
        self.goal_: Optional[np.ndarray] = None
        self.goal_cell_ = None
        self.goal_stamp_: Optional[int] = None
        self.target_: Optional[np.ndarray] = None
        self.joints_: Optional[np.ndarray] = None
        self.map_stamp_: Optional[int] = None
        self.maps_received_ = 0
        self.commands_sent_ = 0
        self._need_fresh_map = False
        self._requested_stamp: Optional[int] = None
        self._pending_request: Optional[int] = None
        self._transitions: List[Transition] = [Transition(self.phase_, 'start', None)]

    # --- events -------------------------------------------------------------------------------------------------
    def validate_goal(self, joints: Sequence[float]) -> str:
        """'' if `joints` is a goal the agent can pursue, else why not."""
        values = list(joints)
        if len(values) != 2 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
            return f'goal must be 2 finite joint angles [rad], got {values}'
        lim = self.grid.limits
        if any(v < lo or v > hi for v, (lo, hi) in zip(values, lim)):
            return f'goal {values} is outside the joint limits {lim.tolist()}'
        return ''

    def set_goal(self, joints: Sequence[float], stamp: int) -> str:
        """A new goal (joint angles, stamped by whoever set it); '' if accepted, else the reason it was rejected.
        Before learning is done it is kept and pursued once the first map is in."""
        problem = self.validate_goal(joints)
        if problem:
            return problem
        self.goal_ = np.asarray(joints, dtype=float)
        self.goal_cell_ = self.grid.cell_of(self.goal_)
        self.goal_stamp_ = int(stamp)
        if self.phase_ not in (PHASE_EXPLORING, PHASE_LEARNING):
            self._await_map(f'new goal {np.round(self.goal_, 3).tolist()} (cell {self.goal_cell_})')
        return ''

    def set_map(self, collision: np.ndarray, closeness: Optional[np.ndarray], stamp: int,
                blocked_moves: Optional[np.ndarray] = None) -> bool:
        """A collision map (rows, cols) bool, closeness (or None) and blocked moves ((4, rows, cols) in
        value_iteration.MOVES order, or None: plan on the per-cell map) built from the frame `stamp`. ValueError if
        it does not fit the grid. Returns True if the map changed the plan inputs."""
        changed = self.planner.update_collision(collision, closeness, blocked_moves)
        self.map_stamp_ = int(stamp)
        self.maps_received_ += 1
        if self.phase_ == PHASE_LEARNING:
            self._set_phase(PHASE_WAITING_FOR_GOAL, 'collision map received')
            if self.goal_ is not None:
                self._await_map('goal given before learning finished')
        elif self.phase_ == PHASE_EXECUTING and changed:
            self._plan('map changed')
        return changed

    def explore_more(self, reason: str) -> None:
        """Leave LEARNING (e.g. no map arrived in time) for `exploration_steps // 4` (at least 50) more steps."""
        if self.phase_ == PHASE_LEARNING:
            self._explore_budget = self.explored_ + max(50, self.exploration_steps // 4)
            self._set_phase(PHASE_EXPLORING, reason)

    def fail(self, reason: str) -> None:
        """End the current goal as FAILED (e.g. the driver waited too long for a map)."""
        if self.phase_ in (PHASE_PLANNING, PHASE_EXECUTING):
            self._set_phase(PHASE_FAILED, reason)

    # --- outputs for the driver ---------------------------------------------------------------------------------
    def pop_transitions(self) -> List[Transition]:
        out, self._transitions = self._transitions, []
        return out

    def take_map_request(self) -> Optional[int]:
        """Stamp of the frame the agent needs a collision map of (once per request), or None."""
        out, self._pending_request = self._pending_request, None
        return out

    @property
    def phase_name(self) -> str:
        return PHASE_NAMES[self.phase_]

    def status(self) -> dict:
        error = None
        if self.goal_ is not None and self.joints_ is not None:
            error = float(np.linalg.norm(self.joints_ - self.goal_))
        return dict(phase=self.phase_, phase_name=self.phase_name, detail=self.detail_, step=self.phase_step_,
                    error=error, target=None if self.target_ is None else [float(v) for v in self.target_],
                    goal_stamp=self.goal_stamp_)

    # --- per frame ----------------------------------------------------------------------------------------------
    def step(self, obs: ArmObservation) -> Optional[np.ndarray]:
        """Joint target to command after this frame, or None (send nothing)."""
        q = np.asarray(obs.joints, dtype=float).reshape(-1)
        if q.shape != (2,) or not np.all(np.isfinite(q)):
            raise ValueError('an observation needs 2 finite joint angles')
        self.joints_ = q
        command = self._decide(q, bool(obs.contact), int(obs.stamp))
        if command is not None:
            self.phase_step_ += 1
            self.commands_sent_ += 1
        return command

    def _decide(self, q: np.ndarray, contact: bool, stamp: int) -> Optional[np.ndarray]:
        if self.phase_ == PHASE_EXPLORING:
            if self.explored_ >= self._explore_budget:
                if self.maps_received_:
                    self._set_phase(PHASE_WAITING_FOR_GOAL, f'explored {self.explored_} steps')
                    if self.goal_ is not None:
                        self._await_map('exploration finished')
                        return self._decide(q, contact, stamp)
                else:
                    self._set_phase(PHASE_LEARNING, f'explored {self.explored_} steps')
                return None
            self.explored_ += 1
            self.target_ = self.explorer.next_command(q, contact)
            return self.target_
        if self.phase_ == PHASE_PLANNING:
            if self._need_fresh_map and (self.map_stamp_ is None or self.map_stamp_ < stamp):
                if self._requested_stamp != stamp:
                    self._requested_stamp = self._pending_request = stamp
                return None
            self._need_fresh_map = False
            if not self._plan('planned'):
                return None
        if self.phase_ != PHASE_EXECUTING:
            return None
        if self.phase_step_ >= self.max_execution_steps:
            self._set_phase(PHASE_FAILED, f'goal not reached in {self.max_execution_steps} steps')
            return None
        cell = self.grid.cell_of(q)
        if self.target_ is None:
            self.target_ = self.grid.centre(cell)       # first settle in the centre of the current cell
        if np.max(np.abs(q - self.target_)) <= self.arrival_tolerance:
            if cell == self.goal_cell_:
                self._set_phase(PHASE_GOAL_REACHED, f'at the centre of goal cell {cell}')
                return None
            nxt = self.planner.next_cell(cell)
            if nxt is None:
                self._set_phase(PHASE_FAILED, f'no move from cell {cell}')
                return None
            if self.planner.move_collides(cell, nxt) and not self.through_predicted_collision:
                self._set_phase(PHASE_FAILED, f'the move from cell {cell} to cell {nxt} is predicted to collide')
                return None
            self.target_ = self.grid.centre(nxt)
        return self.target_

    # --- phases -------------------------------------------------------------------------------------------------
    def _set_phase(self, phase: int, detail: str) -> None:
        self.phase_, self.detail_, self.phase_step_ = phase, detail, 0
        self._transitions.append(Transition(phase, detail, self.goal_stamp_))

    def _await_map(self, why: str) -> None:
        self._need_fresh_map = True
        self._requested_stamp = None
        self.target_ = None
        # the request goes out with the next step(): its frame is the one to map
        self._set_phase(PHASE_PLANNING, f'{why}: waiting for a collision map of the current frame')

    def _plan(self, why: str) -> bool:
        """Plan to the goal from the current cell; EXECUTING if a collision-free path exists, else FAILED."""
        self.planner.set_goal(self.goal_cell_)
        if self.joints_ is None:
            self._set_phase(PHASE_FAILED, 'no joint state yet')
            return False
        start = self.grid.cell_of(self.joints_)
        path = self.planner.plan(start, allow_collision=False)
        crossing = ''
        if path is None and self.through_predicted_collision:
            path = self.planner.plan(start, allow_collision=True)
            if path is not None:
                crossed = sum(self.planner.move_collides(a, b) for a, b in zip(path, path[1:]))
                crossing = f', with {crossed} moves predicted to collide'
        if path is None:
            blocked = f'{int(self.planner.collision_.sum())} collision cells'
            if self.planner.blocked_moves_ is not None:
                blocked += f', {int(self.planner.blocked_moves_.sum())} blocked moves'
            self._set_phase(PHASE_FAILED, f'no collision-free path from cell {start} to cell {self.goal_cell_} on '
                                          f'the map of frame {self.map_stamp_} ({blocked}; {why})')
            return False
        self._set_phase(PHASE_EXECUTING, f'{why}: {len(path) - 1} moves from cell {start} to cell '
                                         f'{self.goal_cell_} on the map of frame {self.map_stamp_}{crossing}')
        return True
