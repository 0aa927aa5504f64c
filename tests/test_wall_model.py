"""The learned wheeled model as a message: serialised and read back on the controller side it evaluates exactly as the
learner's model (Jacobian fields, local Jacobians, routes); every malformed field is refused with the reason. And the
WallAgent alone: never a non-finite command, phases as the node reports them."""
import copy
import math

import numpy as np
import pytest
from mm_msgs.msg import ControllerStatus, ManifoldState
from mm_msgs.msg import SensorManifoldModel as ModelMsg
from rclpy.serialization import deserialize_message, serialize_message

from mm_bringup.wall_experiment import explore, model_message, sensor2_goal_reading
from mm_manifold.sensor_manifold import SensorManifoldModel
from mm_planner.wall_agent import FitFailure, Goal, Observation, WallAgent
from mm_planner.wall_model import WallModel
from mm_sim.wheeled_model import WheeledRobot

DT = 0.05

FRONT = np.array([0.005, 1.5])      # the front sensors' [min, max] range these readings come from [m]


def exploring(readings, learner_samples):
    """A state while the agent explores: the readings, the front sensors' range, the learner's sample count."""
    return Observation(state=True, readings=readings, sensor1_range=FRONT, learner_samples=learner_samples)


@pytest.fixture(scope='module')
def model():
    log = explore(WheeledRobot(), 5000, random_state=0, dt=DT)
    return SensorManifoldModel(DT).fit(log.readings, log.commands, log.continuous)


def test_round_trip_through_the_wire_evaluates_as_the_learner(model):
    msg = deserialize_message(serialize_message(model_message(WheeledRobot(), model)), ModelMsg)
    view = WallModel.from_msg(msg)
    assert view.ready == model.ready and view.samples == model.n_samples_ and view.dt == model.dt
    rng = np.random.default_rng(0)
    Y = rng.uniform(-5, 15, (50, 2))
    U = rng.uniform(-6, 6, (50, 2))
    np.testing.assert_array_equal(view.virtual_field.jacobian(Y), model.virtual_.field_.jacobian(Y))
    np.testing.assert_array_equal(view.virtual_field.rates(Y, U), model.virtual_.field_.rates(Y, U))
    S = rng.uniform(0.05, 0.25, (50, 2))
    np.testing.assert_array_equal(view.sensor2_field.jacobian(S), model.field2_.jacobian(S))
    for y in Y[:10]:
        np.testing.assert_array_equal(view.sensor1_jacobian(y), model.regions1_.interpolate(y))
    goal = sensor2_goal_reading(WheeledRobot(), (0.0, 0.2, 0.0))
    for a, b in zip(view.goal_route(goal), model.virtual_.goal_route(goal)):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(view.ranked_routes(goal, 4), model.virtual_.ranked_routes(goal, 4), strict=True):
        for field_a, field_b in zip(a, b, strict=True):        # exit, goal coordinates, replayed commands
            np.testing.assert_array_equal(field_a, field_b)
        assert len(a.replay) >= 1
    np.testing.assert_array_equal(view.virtual_bounds, model.virtual_bounds())
    np.testing.assert_array_equal(view.sensor2_box, model.sensor2_box_)
    np.testing.assert_array_equal(view.sensor2_noise, model.sensor2_noise_)
    np.testing.assert_allclose(view.sensor2_range, [0.005, 0.25])
    assert view.unreadable_goal(np.array([50.0, 50.0])) and view.unreadable_goal(goal) is None


@pytest.mark.parametrize('field, value, reason', [
    ('format_version', ModelMsg.FORMAT_VERSION + 1, 'format'),
    ('dt', -0.05, 'dt'),
    ('grid_rows', 1, 'grid'),
    ('grid_nodes', [0.0] * 7, 'grid_nodes'),
    ('grid_axes', [math.inf] * 9, 'grid_axes'),
    ('jacobian_degree', 7, 'jacobian_degree'),
    ('field1_theta', [0.0] * 3, 'field1_theta'),
    ('field1_scale', [1.0, -1.0], 'field1_scale'),
    ('virtual_correction', [math.nan] * 24, 'virtual_correction'),
    ('virtual_bounds', [10.0, 10.0, 0.0, 0.0], 'virtual_bounds'),
    ('reentry_rms_after', -1.0, 'reentry_rms_after'),
    ('field2_center', [0.1], 'field2_center'),
    ('region_anchors', [], 'region'),
    ('region_jacobians', [1.0], 'region_jacobians'),
    ('sensor2_box', [0.3, 0.3, 0.1, 0.1], 'sensor2_box'),
    ('sensor2_noise', [-0.1, 0.0], 'sensor2_noise'),
    ('sensor2_range', [0.0], 'sensor2_range'),
    ('route_travel_weight', math.nan, 'route_travel_weight'),
    ('goal_neighbors', 0, 'goal_neighbors'),
    ('overlap_sensor2', [0.1, 0.1], 'overlap_sensor2'),
    ('overlap_coordinates', [0.0], 'overlap_coordinates'),
    ('overlap_route', [0], 'overlap_route'),
    ('route_lengths', [0], 'route_lengths'),
    ('route_commands', [0.0], 'route_commands'),
])
def test_malformed_fields_are_refused_with_the_reason(model, field, value, reason):
    msg = model_message(WheeledRobot(), model)
    setattr(msg, field, value)
    with pytest.raises(ValueError, match=reason):
        WallModel.from_msg(msg)


def announced(model):
    """The model with a bound its held-out error meets (this short exploration has only a few sensor-2 excursions):
    for the checks that need a ready model, not about readiness itself."""
    ready = copy.copy(model)
    ready.heldout_limit_ = max(model.heldout_limit_, model.heldout_sensor2_error_)
    assert ready.ready
    return ready


def test_a_model_marked_ready_without_overlap_is_refused(model):
    msg = model_message(WheeledRobot(), announced(model))
    msg.overlap_coordinates = msg.overlap_sensor2 = msg.overlap_exits = msg.overlap_travel = []
    msg.overlap_route = msg.route_lengths = msg.route_commands = []
    with pytest.raises(ValueError, match='ready'):
        WallModel.from_msg(msg)
    msg.ready = False
    assert not WallModel.from_msg(msg).ready


def test_the_held_out_estimate_travels_with_the_model_and_gates_readiness(model):
    """The model carries its held-out sensor-2 error and the bound; one marked ready above its bound is refused, and
    a fit whose bound is tighter than its held-out error is not ready and says why."""
    msg = model_message(WheeledRobot(), model)
    view = WallModel.from_msg(msg)
    assert model.heldout_count_ > 0 and math.isfinite(model.heldout_sensor2_error_)
    assert view.heldout_sensor2_error == model.heldout_sensor2_error_ and view.heldout_limit == model.heldout_limit_
    assert view.ready == (model.heldout_sensor2_error_ <= model.heldout_limit_) and msg.readiness == (
        model.readiness() or '')
    msg.ready, msg.heldout_sensor2_error = True, msg.heldout_limit * 2 + 1e-3
    with pytest.raises(ValueError, match='held-out'):
        WallModel.from_msg(msg)
    msg.heldout_sensor2_error = -1.0
    with pytest.raises(ValueError, match='held-out'):
        WallModel.from_msg(msg)
    strict = copy.copy(model)
    strict.heldout_limit_ = model.heldout_sensor2_error_ / 2
    assert not strict.ready and 'held-out sensor-2 error' in strict.readiness()
    strict_view = WallModel.from_msg(model_message(WheeledRobot(), strict))
    assert not strict_view.ready and 'held-out' in strict_view.readiness


def test_agent_explores_on_while_the_model_is_not_ready_and_fails_at_the_cap(model):
    strict = copy.copy(model)
    strict.heldout_limit_ = model.heldout_sensor2_error_ / 2
    view = WallModel.from_msg(model_message(WheeledRobot(), strict))
    agent = WallAgent(DT, exploration_steps=8, random_state=0, max_exploration_steps=10)
    far = np.array([0.6, 0.5, 0.6, np.inf, np.inf])
    while agent.step(exploring(far, agent.explored + 1)).command is not None:
        pass
    assert agent.phase == ControllerStatus.PHASE_LEARNING and agent.explored == 8
    decision = agent.step(Observation(model=view))
    assert decision.phase_name == 'EXPLORING' and 'held-out sensor-2 error' in decision.detail
    while agent.step(exploring(far, agent.explored + 1)).command is not None:
        pass
    assert agent.explored == 10
    decision = agent.step(Observation(model=view))
    assert decision.phase_name == 'FAILED' and 'the cap' in decision.detail and 'held-out' in decision.detail
    decision = agent.step(Observation(goal=Goal(np.array([0.2, 0.2]), stamp=3)))
    assert decision.phase_name == 'FAILED' and 'not ready' in decision.detail


def test_agent_explores_on_when_the_learner_could_not_fit_and_fails_at_the_cap():
    """The learner announces a fit that failed (no model: e.g. too few sensor-1 samples). Waiting in LEARNING for a
    model would wait for good (the learner refits only after more samples): the agent explores more, as for a model
    that is not ready, and ends FAILED with the reason at its cap; announced while it still explores (the learner
    fits one step before the agent's last), the failure is acted on when the exploration ends."""
    agent = WallAgent(DT, exploration_steps=8, random_state=0, max_exploration_steps=12)
    far = np.array([np.inf, np.inf, np.inf, np.inf, np.inf])
    while agent.step(exploring(far, agent.explored + 1)).command is not None:
        pass
    assert agent.phase == ControllerStatus.PHASE_LEARNING and agent.explored == 8
    decision = agent.step(Observation(fit_failure=FitFailure('fit failed: only 0 sensor-1 samples: explore more', 8)))
    assert decision.phase_name == 'EXPLORING' and 'only 0 sensor-1 samples' in decision.detail
    assert 'exploring 2 more' in decision.detail
    assert decision.command is not None                      # the state left unanswered gets its command
    while agent.step(exploring(far, agent.explored + 1)).command is not None:
        pass
    assert agent.phase == ControllerStatus.PHASE_LEARNING and agent.explored == 10
    decision = agent.step(Observation(fit_failure=FitFailure('fit failed: only 3 sensor-1 samples: explore more', 10)))
    assert decision.phase_name == 'EXPLORING' and agent.explored == 11      # 2 more: the state's answer was one
    # the learner holds one sample more than steps explored and fits before the agent's last step: set aside
    decision = agent.step(Observation(fit_failure=FitFailure('fit failed: only 5 sensor-1 samples: explore more', 12)))
    assert decision.phase_name == 'EXPLORING'
    assert agent.step(exploring(far, agent.explored + 1)).command is not None
    assert agent.explored == 12
    decision = agent.step(exploring(far, agent.explored + 1))
    assert decision.command is None
    assert decision.phase_name == 'FAILED' and 'the cap' in decision.detail and 'only 5 sensor-1' in decision.detail


def test_agent_never_commands_non_finite_and_reports_its_phases(model):
    view = WallModel.from_msg(model_message(WheeledRobot(), announced(model)))
    agent = WallAgent(DT, exploration_steps=0, rehearsals=0)       # rehearsals: tests/test_switching_controller.py
    assert agent.phase == ControllerStatus.PHASE_LEARNING
    decision = agent.step(Observation(model=view))
    assert decision.phase_name == 'WAITING_FOR_GOAL' and decision.command is None
    decision = agent.step(Observation(goal=Goal(np.array([0.2, 0.2]), stamp=7)))
    assert decision.goal_accepted and decision.phase_name == 'REACHING_SENSOR1' and decision.goal_stamp == 7
    # A blown-up state (not checked here: the node refuses it before) must still not give a non-finite command.
    view.virtual_field.correction = view.virtual_field.correction * 1e300
    decision = agent.step(Observation(state=True, space=ManifoldState.SPACE_VIRTUAL_SENSOR1,
                                      coordinates=np.array([1e200, -1e200]), readings=np.full(5, np.inf)))
    assert decision.command is not None and np.all(np.isfinite(decision.command))
    decision = agent.step(Observation(state=True, space=ManifoldState.SPACE_SENSOR2,
                                      sensor2_estimate=np.array([math.nan, 0.2]), readings=np.full(5, 0.2)))
    assert decision.command is not None and np.all(decision.command == 0.0)       # a stop, said in the log
    assert any('non-finite' in line for line in decision.log)


def test_a_goal_tolerance_is_judged_against_what_sensor_2_reads(model):
    """No tolerance in metres is built in: one as wide as sensor 2's range (here 0.005-0.25 m) would accept any
    reading, so it is refused with the model at hand; a goal that came before the model fails under its stamp."""
    view = WallModel.from_msg(model_message(WheeledRobot(), announced(model)))
    agent = WallAgent(DT, exploration_steps=0, rehearsals=0)
    for tolerance in (-0.01, math.inf, math.nan):
        assert 'positive and finite' in agent.step(Observation(goal=Goal(np.array([0.2, 0.2]), tolerance))).goal_reason
    early = agent.step(Observation(goal=Goal(np.array([0.2, 0.2]), 0.3, stamp=3)))
    assert early.goal_accepted                                    # no model yet: it waits
    decision = agent.step(Observation(model=view))
    assert decision.phase_name == 'FAILED' and 'span of what sensor 2 reads' in decision.detail
    assert decision.goal_stamp == 3
    refused = agent.step(Observation(goal=Goal(np.array([0.2, 0.2]), 0.245)))
    assert not refused.goal_accepted and 'span' in refused.goal_reason
    assert agent.step(Observation(goal=Goal(np.array([0.2, 0.2]), 0.01))).goal_accepted


def test_agent_explores_on_while_the_learner_holds_fewer_samples_than_explored():
    """A learner that restarted lost its samples: the agent explores until the learner holds as many as were explored
    (otherwise the learner never reaches its fit and the lockstep loop waits for good)."""
    agent = WallAgent(DT, exploration_steps=5, random_state=0)
    far = np.array([0.6, 0.5, 0.6, np.inf, np.inf])
    for k in range(5):
        assert agent.step(exploring(far, k + 1)).command is not None
    decision = agent.step(exploring(far, 3))     # restarted at step 3
    assert decision.command is not None and decision.phase_name == 'EXPLORING'
    assert 'holds 3 of 5 samples: exploring 2 more' in decision.detail
    assert agent.step(exploring(far, 4)).command is not None
    decision = agent.step(exploring(far, 8))
    assert decision.command is None and decision.phase_name == 'LEARNING'


def test_agent_makes_up_for_a_learner_restart_once():
    """The samples a restarted learner lost never come back: once they are made up for, the learner's count stays
    behind the steps explored by that many, and the agent must go on to LEARNING instead of chasing them for ever
    (a kill-and-restart graph explored 17 000 steps that way)."""
    agent = WallAgent(DT, exploration_steps=5, random_state=0)
    far = np.array([0.6, 0.5, 0.6, np.inf, np.inf])
    for k in range(3):
        assert agent.step(exploring(far, k + 1)).command is not None
    held = 0                                               # restarted after step 3: the learner holds nothing
    for _ in range(20):
        decision = agent.step(exploring(far, held))
        if decision.command is None:
            break
        held += 1
    assert decision.phase_name == 'LEARNING', decision.detail
    assert held == 5 and agent.explored == 8               # 3 lost steps made up for once


def test_agent_takes_a_verdict_that_came_before_its_last_exploration_step(model):
    """The learner fits once it holds `exploration_steps` samples: the reading before the first command counts, so
    that is one step before the agent ends its exploration. Normally the fit takes longer than a step; when the last
    step is held up (a simulator killed and restarted), the not-ready model came while the agent was still exploring
    and was set aside, the agent then waited in LEARNING for another model and the learner for more samples: the
    kill-and-restart graph stalled for good. The agent now acts on that model when its exploration ends, as it would
    had it come after."""
    strict = copy.copy(model)
    strict.heldout_limit_ = model.heldout_sensor2_error_ / 2
    far = np.array([0.6, 0.5, 0.6, np.inf, np.inf])
    outcomes = []
    for early in (True, False):
        view = WallModel.from_msg(model_message(WheeledRobot(), strict))
        view.samples = 8                               # fitted on the 8 readings of 7 commands and the first one
        agent = WallAgent(DT, exploration_steps=8, random_state=0)
        commands = [agent.step(exploring(far, k + 1)).command
                    for k in range(7)]
        if early:
            assert agent.step(Observation(model=view)).phase_name == 'EXPLORING'
        commands.append(agent.step(exploring(far, 8)).command)
        decision = agent.step(exploring(far, 9))
        if not early:
            assert decision.command is None and decision.phase_name == 'LEARNING'
            decision = agent.step(Observation(model=view))
        assert decision.phase_name == 'EXPLORING' and 'exploring 2 more' in decision.detail, decision.detail
        commands.append(decision.command)
        outcomes.append((agent.exploration_budget, np.array(commands)))
    (budget_early, early_commands), (budget_late, late_commands) = outcomes
    assert budget_early == budget_late == 10
    np.testing.assert_array_equal(early_commands, late_commands)
