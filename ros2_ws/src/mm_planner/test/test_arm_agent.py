"""ArmAgent (pure, no rclpy): explore -> learn-wait -> plan before moving on a map of the current frame -> execute ->
report, with every outcome naming its goal's stamp."""
import numpy as np
import pytest
from mm_msgs.msg import ControllerStatus

from mm_planner import arm_agent as A
from mm_planner.arm_agent import ArmAgent, ArmObservation

LIMITS = ((-3.2, -0.8), (0.0, 2.2))


def obs(stamp, q, contact=False):
    return ArmObservation(stamp, np.asarray(q, float), contact)


def test_phase_ids_are_the_message_constants():
    for value, name in A.PHASE_NAMES.items():
        assert getattr(ControllerStatus, f'PHASE_{name}') == value


def learned_agent(**kw):
    agent = ArmAgent(LIMITS, exploration_steps=0, **kw)
    assert agent.phase_ == A.PHASE_LEARNING
    agent.set_map(np.zeros((8, 12), bool), None, 0)
    assert agent.phase_ == A.PHASE_WAITING_FOR_GOAL
    return agent


def run_ideal(agent, q, stamp, max_frames=200):
    """Drive the agent from frame `stamp` with an arm that reaches every commanded target by the next frame; returns
    the visited joints."""
    visited = [np.array(q, float)]
    for _ in range(max_frames):
        cmd = agent.step(obs(stamp, q))
        if cmd is None:
            return visited, stamp
        q = cmd
        stamp += 1
        visited.append(np.array(q, float))
    raise AssertionError('agent never stopped')


def test_explores_the_configured_steps_then_waits_for_a_map():
    agent = ArmAgent(LIMITS, exploration_steps=20, exploration_seed=3)
    q = np.array([-2.0, 1.1])
    commands = []
    for k in range(25):
        cmd = agent.step(obs(k, q))
        if cmd is None:
            break
        commands.append(cmd)
        q = cmd
    assert len(commands) == 20 and agent.phase_ == A.PHASE_LEARNING
    assert all(np.all(c >= np.array(LIMITS)[:, 0]) and np.all(c <= np.array(LIMITS)[:, 1]) for c in commands)
    agent.explore_more('no map in time')
    assert agent.phase_ == A.PHASE_EXPLORING
    assert agent.step(obs(30, q)) is not None


def test_plans_only_on_a_map_of_the_current_frame_and_reaches_the_goal_around_the_object():
    agent = learned_agent()
    grid = agent.grid
    start, goal = (4, 1), (4, 10)
    blocked = np.zeros(grid.shape, bool)
    blocked[2:7, 5] = True                                   # a wall between start and goal with a way round
    q = grid.centre(start)
    agent.step(obs(10, q))
    assert agent.set_goal(grid.centre(goal), stamp=99) == ''
    assert agent.phase_ == A.PHASE_PLANNING
    assert agent.step(obs(10, q)) is None                    # no command before a map of frame 10 is in
    assert agent.take_map_request() == 10 and agent.take_map_request() is None
    assert agent.step(obs(11, q)) is None                    # a newer frame (e.g. the object was re-placed)
    assert agent.take_map_request() == 11
    agent.set_map(blocked, None, 10)                         # too old for frame 11
    assert agent.step(obs(11, q)) is None and agent.phase_ == A.PHASE_PLANNING
    agent.set_map(blocked, None, 11)
    visited, _ = run_ideal(agent, q, 11)
    assert agent.phase_ == A.PHASE_GOAL_REACHED, agent.detail_
    assert grid.cell_of(visited[-1]) == goal
    assert not any(blocked[grid.cell_of(v)] for v in visited)
    transitions = agent.pop_transitions()
    assert [t.phase for t in transitions][-3:] == [A.PHASE_PLANNING, A.PHASE_EXECUTING, A.PHASE_GOAL_REACHED]
    assert all(t.goal_stamp == 99 for t in transitions[-3:])
    assert agent.status()['goal_stamp'] == 99


def test_walled_off_goal_fails_with_the_reason_and_the_goal_stamp():
    agent = learned_agent()
    grid = agent.grid
    blocked = np.zeros(grid.shape, bool)
    blocked[:, 6] = True
    q = grid.centre((3, 2))
    agent.set_goal(grid.centre((3, 9)), stamp=5)
    agent.step(obs(1, q))
    agent.set_map(blocked, None, agent.take_map_request())
    assert agent.step(obs(1, q)) is None
    assert agent.phase_ == A.PHASE_FAILED and 'no collision-free path' in agent.detail_
    assert agent.pop_transitions()[-1].goal_stamp == 5


def test_bad_goals_and_maps_are_rejected():
    agent = learned_agent()
    for goal in ([1.0], [np.nan, 1.0], [-2.0, 9.0], [-5.0, 1.0]):
        assert agent.set_goal(goal, 1) != ''
    assert agent.goal_ is None and agent.phase_ == A.PHASE_WAITING_FOR_GOAL
    with pytest.raises(ValueError):
        agent.set_map(np.zeros((3, 3), bool), None, 1)
    with pytest.raises(ValueError):
        agent.set_map(np.zeros((8, 12), bool), np.full((8, 12), np.nan), 1)
    with pytest.raises(ValueError):
        agent.step(obs(1, [np.inf, 0.0]))


def test_execution_gives_up_after_max_steps():
    agent = learned_agent(max_execution_steps=3)
    grid = agent.grid
    q = grid.centre((0, 0))
    agent.set_goal(grid.centre((7, 11)), 1)
    agent.step(obs(1, q))
    agent.set_map(np.zeros(grid.shape, bool), None, 1)
    run_ideal(agent, q, 1)
    assert agent.phase_ == A.PHASE_FAILED and 'not reached in 3 steps' in agent.detail_


def test_goal_before_learning_is_pursued_once_the_map_is_in():
    agent = ArmAgent(LIMITS, exploration_steps=2)
    grid = agent.grid
    q = grid.centre((2, 2))
    assert agent.set_goal(grid.centre((2, 6)), 7) == ''
    assert agent.phase_ == A.PHASE_EXPLORING
    q = agent.step(obs(1, q))
    q = agent.step(obs(2, q))
    assert agent.step(obs(3, q)) is None and agent.phase_ == A.PHASE_LEARNING
    agent.set_map(np.zeros(grid.shape, bool), None, 3)
    assert agent.phase_ == A.PHASE_PLANNING
    assert agent.step(obs(3, q)) is not None and agent.phase_ == A.PHASE_EXECUTING


def test_through_predicted_collision_follows_the_fewest_collision_path_when_walled_off():
    agent = learned_agent(through_predicted_collision=True)
    grid = agent.grid
    blocked = np.zeros(grid.shape, bool)
    blocked[:, 6] = True
    q = grid.centre((3, 2))
    agent.set_goal(grid.centre((3, 9)), stamp=5)
    agent.step(obs(1, q))
    agent.set_map(blocked, None, agent.take_map_request())
    visited, _ = run_ideal(agent, q, 1)
    assert agent.phase_ == A.PHASE_GOAL_REACHED, agent.detail_
    assert 'with 1 moves predicted to collide' in agent.pop_transitions()[-2].detail
    assert sum(blocked[grid.cell_of(v)] for v in visited) >= 1
