import numpy as np
import pytest

from mm_planner.value_iteration import (DPPlanner, JointGrid, MOVES, clearance_rewards, plan_path,
                                        value_iteration)


def test_small_grid_matches_hand_computed_values():
    # 3x4 grid, goal top right, one collision cell at (1, 1).
    # V(s) = -(moves to the goal - 1) on the shortest collision-free path; the collision cell itself can leave at -1
    # per step: (1,1) -> (0,1) -> (0,2) -> goal = -1 + -1 + 0 = -2.
    collision = np.zeros((3, 4), bool)
    collision[1, 1] = True
    values, policy = value_iteration(collision, goal=(0, 3))
    expected = np.array([[-2, -1, 0, 0],
                         [-3, -2, -1, 0],
                         [-4, -3, -2, -1]], float)
    np.testing.assert_array_equal(values, expected)
    assert policy[0, 3] == -1
    # From (1, 0) going down-right through (1, 1) would cost -100: the policy goes up to (0, 0) instead.
    assert tuple(MOVES[policy[1, 0]]) == (-1, 0)


def test_path_avoids_collision_cells():
    collision = np.zeros((8, 12), bool)
    collision[1:8, 5] = True          # a wall with a gap in row 0
    values, policy = value_iteration(collision, goal=(7, 11))
    path = plan_path(values, (7, 0), (7, 11), collision=collision, policy=policy)
    assert path[0] == (7, 0) and path[-1] == (7, 11)
    assert not any(collision[c] for c in path)
    assert (0, 5) in path
    steps = np.abs(np.diff(np.array(path), axis=0)).sum(axis=1)
    assert np.all(steps == 1)
    # Shortest collision-free path: up 7, right 11, down 7.
    assert len(path) - 1 == 7 + 11 + 7
    # The same path when the policy is derived from the values and the collision map.
    assert plan_path(values, (7, 0), (7, 11), collision=collision) == path


def test_walled_off_goal_is_reported_unreachable_without_collision():
    collision = np.zeros((5, 5), bool)
    collision[1:4, 1:4] = True
    collision[2, 2] = False           # goal enclosed by a ring of collision cells
    values, policy = value_iteration(collision, goal=(2, 2))
    assert plan_path(values, (0, 0), (2, 2), collision=collision, policy=policy, allow_collision=False) is None
    path = plan_path(values, (0, 0), (2, 2), collision=collision, policy=policy)
    assert path[-1] == (2, 2)
    assert sum(collision[c] for c in path) == 1      # crosses the ring exactly once
    assert values[0, 0] < -100


def test_bad_inputs_raise():
    with pytest.raises(ValueError):
        value_iteration(np.zeros((3, 3), bool), goal=(3, 0))
    with pytest.raises(ValueError):
        value_iteration(np.zeros((3, 3), bool), goal=(0, 0), gamma=0.0)
    with pytest.raises(ValueError):
        JointGrid((1.0, 0.0), (0.0, 1.0))


def test_joint_grid_cells_and_centres():
    grid = JointGrid((-3.2, -0.8), (0.0, 2.2), rows=8, cols=12)
    centres = grid.centres()
    assert centres.shape == (8, 12, 2)
    for r in range(8):
        for c in range(12):
            assert grid.cell_of(centres[r, c]) == (r, c)
    np.testing.assert_allclose(grid.centre((0, 0)), [-3.2 + 0.15, 2.2 / 24])
    assert grid.cell_of([-10.0, 10.0]) == (0, 11)      # clipped to the border


def test_dp_planner_replans_when_the_collision_map_changes():
    grid = JointGrid((0.0, 1.0), (0.0, 1.0), rows=4, cols=4)
    planner = DPPlanner(grid)
    assert planner.next_cell((0, 0)) is None           # no goal yet
    planner.set_goal((0, 3))
    assert planner.plan((0, 0)) == [(0, 0), (0, 1), (0, 2), (0, 3)]
    mask = np.zeros((4, 4), bool)
    mask[0, 1] = True
    assert planner.update_collision(mask) is True
    assert planner.update_collision(mask.copy()) is False
    assert planner.n_plans_ == 2
    path = planner.plan((0, 0), allow_collision=False)
    assert (0, 1) not in path and path[-1] == (0, 3)
    assert planner.next_cell((0, 0)) == path[1]
    assert planner.next_cell((0, 3)) is None
    with pytest.raises(ValueError):
        planner.update_collision(np.zeros((3, 3), bool))


def test_clearance_rewards_by_hand():
    close = np.array([[0.5, 0.0, -0.5], [-1.0, -3.0, -np.inf]])
    np.testing.assert_allclose(clearance_rewards(close, clearance_reward=-4.0, clearance=1.0),
                               [[-4.0, -4.0, -2.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(clearance_rewards(close, clearance_reward=-4.0, clearance=2.0)[0], [-4.0, -4.0, -3.0])
    with pytest.raises(ValueError):
        clearance_rewards(np.array([[np.nan]]))
    with pytest.raises(ValueError):
        clearance_rewards(close, clearance_reward=1.0)


def test_clearance_reward_makes_the_path_keep_clear_of_the_contact_region():
    # 3x6 grid, collision block at (2, 2..3). Closeness is high next to it (row 1, cols 1..4), low elsewhere: the
    # shortest path (1, 0) -> (1, 5) runs along the block; with the clearance reward it detours by row 0 (2 steps
    # more, but it passes no cell near the region).
    grid = JointGrid((0.0, 1.0), (0.0, 1.0), rows=3, cols=6)
    collision = np.zeros((3, 6), bool)
    collision[2, 2:4] = True
    closeness = np.full((3, 6), -3.0)
    closeness[2, 2:4] = 0.5
    closeness[1, 1:5] = -0.2
    paper = DPPlanner(grid, clearance_reward=0.0)
    paper.update_collision(collision, closeness)
    paper.set_goal((1, 5))
    assert paper.plan((1, 0)) == [(1, c) for c in range(6)]
    planner = DPPlanner(grid, clearance_reward=-5.0, clearance=1.0)
    planner.update_collision(collision, closeness)
    planner.set_goal((1, 5))
    path = planner.plan((1, 0), allow_collision=False)
    assert path == [(1, 0), (0, 0)] + [(0, c) for c in range(1, 6)] + [(1, 5)]
    np.testing.assert_allclose(planner.free_reward_[1, 1:5], -4.0)
    # without a closeness map the planner uses the paper's rewards
    assert planner.update_collision(collision) is True
    assert planner.plan((1, 0)) == paper.plan((1, 0))
    assert planner.update_collision(collision) is False


def test_clearance_reward_never_trades_a_collision_cell_for_clearance():
    # A wall of collision cells in row 1 with a gap at the far end; every cell is on the region's surface. The
    # collision-free detour (24 moves, 23 of them at -1 - 5 = -138) is worse than crossing the wall at the paper's -100,
    # so the collision reward must be lowered for the detour to stay the optimum.
    collision = np.zeros((3, 12), bool)
    collision[1, :11] = True
    free_reward = np.full((3, 12), -5.0)
    values, policy = value_iteration(collision, goal=(2, 0), free_reward=free_reward)
    path = plan_path(values, (0, 0), (2, 0), collision=collision, policy=policy, allow_collision=False)
    assert path is not None and len(path) - 1 == 11 + 2 + 11
    assert plan_path(values, (0, 0), (2, 0), collision=collision, free_reward=free_reward) == path
    np.testing.assert_allclose(values[0, 0], -6.0 * 23)


def _block(moves, a, b):
    """Block the move from cell a to the adjacent cell b and back."""
    for (r, c), (nr, nc) in ((a, b), (b, a)):
        k = int(np.flatnonzero((MOVES == (nr - r, nc - c)).all(axis=1))[0])
        moves[k, r, c] = True


def test_blocked_moves_replace_the_per_cell_map_and_the_goal_move_counts_too():
    # A corridor whose every cell is on the per-cell map (some move out of each touches the object) is still
    # crossed along its free moves; a blocked move is avoided by a detour, and a goal whose every way in is blocked
    # has no collision-free path.
    grid = JointGrid((0.0, 1.0), (0.0, 1.0), rows=2, cols=4)
    planner = DPPlanner(grid)
    planner.set_goal((0, 3))
    cells = np.ones((2, 4), bool)
    moves = np.zeros((4, 2, 4), bool)
    assert planner.update_collision(cells, None, moves) is True
    assert planner.plan((0, 0), allow_collision=False) == [(0, 0), (0, 1), (0, 2), (0, 3)]
    _block(moves, (0, 1), (0, 2))
    assert planner.update_collision(cells, None, moves) is True
    assert planner.move_collides((0, 1), (0, 2)) and planner.move_collides((0, 2), (0, 1))
    assert not planner.move_collides((0, 1), (1, 1))
    path = planner.plan((0, 0), allow_collision=False)
    assert path == [(0, 0), (0, 1), (1, 1), (1, 2), (0, 2), (0, 3)] or path == [(0, 0), (1, 0), (1, 1), (1, 2),
                                                                                (0, 2), (0, 3)]
    assert all(not planner.move_collides(a, b) for a, b in zip(path, path[1:]))
    _block(moves, (0, 2), (0, 3))
    _block(moves, (1, 3), (0, 3))
    planner.update_collision(cells, None, moves)
    assert planner.plan((0, 0), allow_collision=False) is None
    path = planner.plan((0, 0), allow_collision=True)
    assert path[-1] == (0, 3) and sum(planner.move_collides(a, b) for a, b in zip(path, path[1:])) == 1
    # the same map without the moves: the per-cell map, every cell blocked
    assert planner.update_collision(cells) is True and planner.plan((0, 0), allow_collision=False) is None
    with pytest.raises(ValueError):
        planner.update_collision(cells, None, np.zeros((4, 3, 4), bool))
    with pytest.raises(ValueError):
        planner.move_collides((0, 0), (1, 1))


def test_blocked_moves_keep_the_lowered_collision_reward_against_clearance_costs():
    # Every free move costs -1 - 5; the only collision-free way round is long, yet it beats one blocked move.
    collision = np.zeros((3, 12), bool)
    moves = np.zeros((4, 3, 12), bool)
    for c in range(11):
        _block(moves, (0, c), (1, c))
    free_reward = np.full((3, 12), -5.0)
    values, policy = value_iteration(collision, goal=(1, 0), free_reward=free_reward, blocked_moves=moves)
    path = plan_path(values, (0, 0), (1, 0), collision=collision, policy=policy, allow_collision=False,
                     blocked_moves=moves)
    assert path is not None and len(path) - 1 == 11 + 1 + 11
    assert plan_path(values, (0, 0), (1, 0), collision=collision, free_reward=free_reward, blocked_moves=moves) == path
