"""Dynamic programming on a discretised joint space (paper Section 3.3). No rclpy here.

The arm's two joint angles are cut into a rows x cols grid (8 x 12 in the paper; rows = joint 0, cols = joint 1).
Actions move to one of the four adjacent cells. Rewards, as in the paper: 0 for reaching the goal cell, -100 for
entering a cell where collision with the object is predicted, -1 for every other step. Collision cells are
penalised, not forbidden: with -100 against at most rows*cols - 1 steps, the optimal path avoids them whenever a
collision-free path exists, and when none exists (the goal is walled off) the values still say how to get there with
the fewest collisions; `plan_path(..., allow_collision=False)` then returns None.

Clearance (not in the paper): the predicted map is a per-cell yes/no, and the cells it misses are the ones the object
only partly covers, at the edge of the predicted region, where a move between cell centres can still graze the
object. So free cells can carry an extra reward <= 0 (`free_reward`) that the planner pays for entering them;
DPPlanner sets it from the learned closeness of each cell (clearance_rewards: `clearance_reward` at the contact
region's surface, rising linearly to 0 at closeness -`clearance`), so paths keep clear of the region when a detour
is cheap and still pass close to it when that is the only way. To keep the paper's guarantee that predicted
collision cells are avoided whenever a collision-free path exists, the collision reward is lowered by the most a
path can collect from `free_reward` ((rows*cols - 1) times its most negative entry); without it nothing changes.

Blocked moves (not in the paper): a per-cell map must mark a cell as soon as any move out of it would touch the
object, which cuts narrow passages that a path could cross along a free move. A map may instead say which moves
collide (`blocked_moves` (4, rows, cols) in MOVES order: the straight motion from the cell's centre to that
neighbour's centre is predicted to touch the object); the collision reward is then paid for a blocked move (the goal
included) rather than for entering a collision cell, and the per-cell map is not used for planning.
"""
from __future__ import annotations

from typing import List, Optional, Sequence, Tuple

import numpy as np

Cell = Tuple[int, int]
# Action order (also the tie-break order of the greedy policy and of CollisionMap.blocked_moves): up (row - 1), down,
# left (col - 1), right.
MOVES = np.array([(-1, 0), (1, 0), (0, -1), (0, 1)])


class JointGrid:
    """Regular grid over the joint box [joint0_limits] x [joint1_limits]; rows index joint 0, cols joint 1."""

    def __init__(self, joint0_limits: Sequence[float], joint1_limits: Sequence[float], rows: int = 8, cols: int = 12):
        lim = np.array([joint0_limits, joint1_limits], dtype=float)
        if lim.shape != (2, 2) or not np.all(np.isfinite(lim)) or np.any(lim[:, 0] >= lim[:, 1]):
            raise ValueError('joint limits must be finite (lo, hi) pairs with lo < hi')
        if rows < 1 or cols < 1:
            raise ValueError('rows and cols must be >= 1')
        self.limits = lim
        self.rows, self.cols = int(rows), int(cols)
        self.step = (lim[:, 1] - lim[:, 0]) / np.array([self.rows, self.cols])

    @property
    def shape(self) -> Tuple[int, int]:
        return self.rows, self.cols

    def centre(self, cell: Cell) -> np.ndarray:
        """Joint vector at the centre of a cell."""
        r, c = self.check_cell(cell)
        return self.limits[:, 0] + (np.array([r, c]) + 0.5) * self.step

    def centres(self) -> np.ndarray:
        """(rows, cols, 2) joint vectors of all cell centres."""
        r, c = np.meshgrid(np.arange(self.rows), np.arange(self.cols), indexing='ij')
        return self.limits[:, 0] + (np.stack([r, c], -1) + 0.5) * self.step

    def cell_of(self, joints: Sequence[float]) -> Cell:
        """Cell containing a joint vector (joints outside the box go to the nearest border cell)."""
        q = np.asarray(joints, dtype=float).reshape(-1)
        if q.shape != (2,) or not np.all(np.isfinite(q)):
            raise ValueError('expected 2 finite joint values')
        idx = np.floor((q - self.limits[:, 0]) / self.step).astype(int)
        idx = np.clip(idx, 0, [self.rows - 1, self.cols - 1])
        return int(idx[0]), int(idx[1])

    def check_cell(self, cell: Cell) -> Cell:
        r, c = (int(v) for v in cell)
        if not (0 <= r < self.rows and 0 <= c < self.cols):
            raise ValueError(f'cell {cell} is outside the {self.rows}x{self.cols} grid')
        return r, c


def clearance_rewards(closeness: np.ndarray, clearance_reward: float = -5.0, clearance: float = 1.0) -> np.ndarray:
    """Extra reward of entering each cell from its closeness to the learned contact region (0 on the region's
    surface, negative outside): `clearance_reward` at closeness >= 0, linear to 0 at closeness <= -clearance.
    Cells without any closeness information (-inf) get 0."""
    close = np.asarray(closeness, dtype=float)
    if np.any(np.isnan(close)) or np.any(close == np.inf):
        raise ValueError('closeness must be finite or -inf')
    if clearance_reward > 0 or clearance <= 0:
        raise ValueError('clearance_reward must be <= 0 and clearance > 0')
    return clearance_reward * np.clip(1.0 + close / clearance, 0.0, 1.0)


def cell_rewards(collision: np.ndarray, goal: Cell, step_reward: float = -1.0, collision_reward: float = -100.0,
                 goal_reward: float = 0.0, free_reward: Optional[np.ndarray] = None) -> np.ndarray:
    """(rows, cols) reward of entering each cell (module docstring): goal_reward at the goal; at collision cells
    collision_reward lowered by (rows*cols - 1) times the most negative free_reward of a free cell; step_reward +
    free_reward elsewhere."""
    col = np.asarray(collision, dtype=bool)
    reward = np.full(col.shape, float(step_reward))
    collision_reward = float(collision_reward)
    if free_reward is not None:
        extra = np.asarray(free_reward, dtype=float)
        if extra.shape != col.shape or not np.all(np.isfinite(extra)) or np.any(extra > 0):
            raise ValueError('free_reward must be finite, <= 0 and of the collision map\'s shape')
        reward += extra
        collision_reward += (col.size - 1) * float(extra[~col].min(initial=0.0))
    reward[col] = collision_reward
    reward[goal[0], goal[1]] = goal_reward
    return reward


def neighbour_values(cells: np.ndarray, off_grid) -> np.ndarray:
    """(4, rows, cols): for each move in MOVES order and each cell, the value of `cells` at the neighbour the move
    reaches (`off_grid` where it leaves the grid)."""
    a = np.asarray(cells)
    rows, cols = a.shape
    pad = np.full((rows + 2, cols + 2), off_grid, dtype=np.result_type(a, np.asarray(off_grid)))
    pad[1:-1, 1:-1] = a
    return np.stack([pad[1 + dr:1 + dr + rows, 1 + dc:1 + dc + cols] for dr, dc in MOVES])


def check_blocked_moves(blocked_moves: Optional[np.ndarray], shape) -> Optional[np.ndarray]:
    """The (4, rows, cols) bool array of a map's blocked moves (None stays None); ValueError if the shape is off."""
    if blocked_moves is None:
        return None
    moves = np.asarray(blocked_moves, dtype=bool)
    if moves.shape != (len(MOVES),) + tuple(shape):
        raise ValueError(f'blocked_moves must have shape {(len(MOVES),) + tuple(shape)}, got {moves.shape}')
    return moves


def move_rewards(collision: np.ndarray, goal: Cell, step_reward: float = -1.0, collision_reward: float = -100.0,
                 goal_reward: float = 0.0, free_reward: Optional[np.ndarray] = None,
                 blocked_moves: Optional[np.ndarray] = None) -> np.ndarray:
    """(4, rows, cols) reward of each move from each cell (-inf off the grid): the reward of entering the cell it
    reaches (cell_rewards), or - with `blocked_moves` - the collision reward (lowered as in cell_rewards, by the
    most negative free_reward of any cell) for a blocked move and the reward of entering a free cell otherwise."""
    col = np.asarray(collision, dtype=bool)
    moves = check_blocked_moves(blocked_moves, col.shape)
    if moves is None:
        return neighbour_values(cell_rewards(col, goal, step_reward, collision_reward, goal_reward, free_reward),
                                -np.inf)
    reward = neighbour_values(cell_rewards(np.zeros(col.shape, bool), goal, step_reward, collision_reward,
                                           goal_reward, free_reward), -np.inf)
    lowest_extra = 0.0 if free_reward is None else min(float(np.min(free_reward)), 0.0)
    reward[moves & np.isfinite(reward)] = float(collision_reward) + (col.size - 1) * lowest_extra
    return reward


def value_iteration(collision: np.ndarray, goal: Cell, step_reward: float = -1.0, collision_reward: float = -100.0,
                    goal_reward: float = 0.0, gamma: float = 1.0, tol: float = 1e-9, max_iter: int = 100000,
                    free_reward: Optional[np.ndarray] = None,
                    blocked_moves: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray]:
    """Optimal values and greedy policy on a 4-connected grid.

    V(goal) = 0 (terminal). For every other cell s: V(s) = max over the in-grid neighbours s' of R(s') + gamma V(s'),
    with R(s') = goal_reward if s' is the goal, collision_reward if s' is a collision cell, step_reward otherwise
    (plus free_reward[s'] and the lowered collision reward when free_reward is given, see cell_rewards); with
    `blocked_moves` the collision reward goes with the move instead (move_rewards).
    Synchronous sweeps from V = 0 until the largest change is below tol (with gamma = 1 and negative rewards this
    is Bellman-Ford: exact after as many sweeps as the longest optimal path).
    Returns values (rows, cols) and policy (rows, cols) of indices into MOVES (-1 at the goal).
    """
    col = np.asarray(collision, dtype=bool)
    if col.ndim != 2 or col.size == 0:
        raise ValueError('collision must be a non-empty 2-D boolean array')
    rows, cols = col.shape
    gr, gc = (int(v) for v in goal)
    if not (0 <= gr < rows and 0 <= gc < cols):
        raise ValueError(f'goal {goal} is outside the {rows}x{cols} grid')
    if not 0.0 < gamma <= 1.0:
        raise ValueError('gamma must be in (0, 1]')
    if max(step_reward, collision_reward) > 0 and gamma == 1.0:
        raise ValueError('with gamma = 1 the step and collision rewards must be <= 0 (values would diverge)')
    reward = move_rewards(col, (gr, gc), step_reward, collision_reward, goal_reward, free_reward, blocked_moves)
    terminal = np.zeros_like(col)
    terminal[gr, gc] = True
    V = np.zeros((rows, cols))
    for _ in range(max_iter):
        q = _action_values(V, reward, terminal, gamma)
        new = q.max(axis=0)
        new[gr, gc] = 0.0
        delta = np.max(np.abs(new - V))
        V = new
        if delta < tol:
            break
    else:
        raise RuntimeError('value iteration did not converge; raise max_iter or tol')
    q = _action_values(V, reward, terminal, gamma)
    policy = np.argmax(q, axis=0)            # first maximum = tie-break order of MOVES
    policy[gr, gc] = -1
    return V, policy


def _action_values(V: np.ndarray, reward: np.ndarray, terminal: np.ndarray, gamma: float) -> np.ndarray:
    """(4, rows, cols) value of each move: its reward (move_rewards, -inf off the grid) plus the discounted value of
    the cell it reaches (0 at the terminal goal)."""
    return reward + gamma * neighbour_values(np.where(terminal, 0.0, V), 0.0)


def plan_path(values: np.ndarray, start: Cell, goal: Cell, collision: Optional[np.ndarray] = None,
              policy: Optional[np.ndarray] = None, allow_collision: bool = True, step_reward: float = -1.0,
              collision_reward: float = -100.0, goal_reward: float = 0.0, gamma: float = 1.0,
              free_reward: Optional[np.ndarray] = None,
              blocked_moves: Optional[np.ndarray] = None) -> Optional[List[Cell]]:
    """Cells from start to goal following the greedy policy (derived from `values` and the rewards of the
    `collision` map, `free_reward` and `blocked_moves` when `policy` is not given, exactly as value_iteration does).

    With allow_collision=False, returns None when the path would enter a collision cell - with `blocked_moves`: take
    a blocked move - (no collision-free path exists). Also returns None if the policy does not reach the goal."""
    values = np.asarray(values, dtype=float)
    rows, cols = values.shape
    for name, cell in (('start', start), ('goal', goal)):
        if not (0 <= cell[0] < rows and 0 <= cell[1] < cols):
            raise ValueError(f'{name} {cell} is outside the {rows}x{cols} grid')
    col = np.zeros((rows, cols), bool) if collision is None else np.asarray(collision, dtype=bool)
    if col.shape != (rows, cols):
        raise ValueError('collision and values must have the same shape')
    moves = check_blocked_moves(blocked_moves, col.shape)
    collides = neighbour_values(col, True) if moves is None else moves       # (4, rows, cols): the move collides
    if policy is None:
        reward = move_rewards(col, goal, step_reward, collision_reward, goal_reward, free_reward, moves)
        terminal = np.zeros((rows, cols), bool)
        terminal[goal[0], goal[1]] = True
        policy = np.argmax(_action_values(values, reward, terminal, gamma), axis=0)
    cell = (int(start[0]), int(start[1]))
    goal = (int(goal[0]), int(goal[1]))
    path = [cell]
    for _ in range(rows * cols):
        if cell == goal:
            return path
        a = int(policy[cell])
        if a < 0:
            return None
        if not allow_collision and collides[a][cell]:
            return None
        cell = (cell[0] + int(MOVES[a][0]), cell[1] + int(MOVES[a][1]))
        path.append(cell)
    return path if cell == goal else None


class DPPlanner:
    """Holds the joint grid, the predicted collision map (and the cells' closeness to the contact region) and the
    goal; replans whenever one of them changes.

    Parameters: grid (JointGrid), step_reward, collision_reward, goal_reward, gamma, clearance_reward and clearance
    (see clearance_rewards; clearance_reward = 0 plans with the paper's rewards only). The defaults -5 and 1 were
    chosen on 60 simulated placements disjoint from the benchmark's: the closest hand-object gap of the executed
    paths rose (tenth percentile 2 px -> 6 px, no contact left) for 1.3 more steps per path, and all goals reached.
    State: collision_ (rows, cols) bool, closeness_ (rows, cols) or None, blocked_moves_ ((4, rows, cols) bool or
    None: the map's per-cell collision is then not used for planning), free_reward_ (rows, cols) extra reward of
    entering each cell, goal_ (cell or None), values_ and policy_ (after a plan), n_plans_.
    """

    def __init__(self, grid: JointGrid, step_reward: float = -1.0, collision_reward: float = -100.0,
                 goal_reward: float = 0.0, gamma: float = 1.0, clearance_reward: float = -5.0,
                 clearance: float = 1.0):
        if clearance_reward > 0 or clearance <= 0:
            raise ValueError('clearance_reward must be <= 0 and clearance > 0')
        self.grid = grid
        self.step_reward = float(step_reward)
        self.collision_reward = float(collision_reward)
        self.goal_reward = float(goal_reward)
        self.gamma = float(gamma)
        self.clearance_reward = float(clearance_reward)
        self.clearance = float(clearance)
        self.collision_ = np.zeros(grid.shape, bool)
        self.closeness_: Optional[np.ndarray] = None
        self.blocked_moves_: Optional[np.ndarray] = None
        self.free_reward_ = np.zeros(grid.shape)
        self.goal_: Optional[Cell] = None
        self.values_: Optional[np.ndarray] = None
        self.policy_: Optional[np.ndarray] = None
        self.n_plans_ = 0

    def _replan(self) -> None:
        if self.goal_ is None:
            return
        self.values_, self.policy_ = value_iteration(self.collision_, self.goal_, self.step_reward,
                                                     self.collision_reward, self.goal_reward, self.gamma,
                                                     free_reward=self.free_reward_, blocked_moves=self.blocked_moves_)
        self.n_plans_ += 1

    def set_goal(self, goal: Cell) -> None:
        self.goal_ = self.grid.check_cell(goal)
        self._replan()

    def set_goal_joints(self, joints: Sequence[float]) -> Cell:
        cell = self.grid.cell_of(joints)
        self.set_goal(cell)
        return cell

    def update_collision(self, mask: np.ndarray, closeness: Optional[np.ndarray] = None,
                         blocked_moves: Optional[np.ndarray] = None) -> bool:
        """Replace the collision map, the cells' closeness (None: no clearance rewards) and the blocked moves (None:
        plan on the per-cell map); replan (if a goal is set) and return True only if any of them changed."""
        m = np.asarray(mask, dtype=bool)
        if m.shape != self.grid.shape:
            raise ValueError(f'collision map must have shape {self.grid.shape}, got {m.shape}')
        moves = check_blocked_moves(blocked_moves, self.grid.shape)
        close = None if closeness is None else np.asarray(closeness, dtype=float)
        if close is not None and close.shape != self.grid.shape:
            raise ValueError(f'closeness map must have shape {self.grid.shape}, got {close.shape}')
        same_close = (close is None if self.closeness_ is None
                      else close is not None and np.array_equal(close, self.closeness_))
        same_moves = (moves is None if self.blocked_moves_ is None
                      else moves is not None and np.array_equal(moves, self.blocked_moves_))
        if np.array_equal(m, self.collision_) and same_close and same_moves:
            return False
        self.free_reward_ = (np.zeros(self.grid.shape) if close is None
                             else clearance_rewards(close, self.clearance_reward, self.clearance))
        self.collision_ = m.copy()
        self.closeness_ = None if close is None else close.copy()
        self.blocked_moves_ = None if moves is None else moves.copy()
        self._replan()
        return True

    def move_collides(self, cell: Cell, neighbour: Cell) -> bool:
        """Whether the move from `cell` to the adjacent `neighbour` is predicted to collide (with the per-cell map:
        whether the neighbour is a collision cell)."""
        (r, c), (nr, nc) = self.grid.check_cell(cell), self.grid.check_cell(neighbour)
        match = np.flatnonzero((MOVES == (nr - r, nc - c)).all(axis=1))
        if not len(match):
            raise ValueError(f'cells {cell} and {neighbour} are not adjacent')
        if self.blocked_moves_ is None:
            return bool(self.collision_[nr, nc])
        return bool(self.blocked_moves_[match[0], r, c])

    def next_cell(self, current: Cell) -> Optional[Cell]:
        """The neighbour to move to from `current` (None at the goal or before a goal is set)."""
        if self.policy_ is None:
            return None
        r, c = self.grid.check_cell(current)
        a = int(self.policy_[r, c])
        if a < 0:
            return None
        return r + int(MOVES[a][0]), c + int(MOVES[a][1])

    def plan(self, start: Cell, allow_collision: bool = True) -> Optional[List[Cell]]:
        """Cells from start to the goal (see plan_path); None before a goal is set."""
        if self.values_ is None:
            return None
        return plan_path(self.values_, self.grid.check_cell(start), self.goal_, collision=self.collision_,
                         policy=self.policy_, allow_collision=allow_collision, blocked_moves=self.blocked_moves_)
