"""How the wall tuning script ranks settings (pure logic; its runs are in results/tune_wall_*.json)."""
import pytest

from mm_bringup.tune_wall import main, summarize


def row(controller, noisy, success, over_2x):
    return dict(exploration_steps=3000, explorer={}, controller=controller, noisy=noisy, ready=True, samples=4000,
                success=success, share_blind_over_2x=over_2x)


def test_the_blind_rule_takes_the_fewest_long_stretches_among_settings_as_successful_per_noise_condition():
    rows = [row({}, False, 1.0, 0.03), row({'a': 1}, False, 1.0, 0.001), row({'a': 2}, False, 0.98, 0.0),
            row({}, True, 0.974, 0.057), row({'a': 1}, True, 0.972, 0.042), row({'a': 2}, True, 0.95, 0.01)]
    ranked = [(s['noisy'], s['controller']) for s in summarize(rows, 'blind')]
    # Clean first; a setting that gives up more than SUCCESS_SLACK of success ranks behind, however short its stretches.
    assert ranked == [(False, {'a': 1}), (False, {}), (False, {'a': 2}),
                      (True, {'a': 1}), (True, {}), (True, {'a': 2})]


def test_settings_that_ran_on_different_seeds_are_ranked_on_the_cells_they_share():
    """A setting run on one more seed, where it failed, is not ranked below one that never met that seed: the
    ranking compares the cells both ran (the summary keeps every cell's figures beside)."""
    shared = [dict(row({'a': 1}, True, 1.0, 0.0), layout='paper', robot='default', seed=s) for s in (100, 101)]
    extra = dict(row({'a': 1}, True, 0.0, 0.5), layout='paper', robot='default', seed=102)
    other = [dict(row({}, True, 0.99, 0.0), layout='paper', robot='default', seed=s) for s in (100, 101)]
    for rule in ('success', 'blind', 'item1'):
        ranked = summarize(shared + [extra] + other, rule)
        assert [s['controller'] for s in ranked] == [{'a': 1}, {}]
    first = summarize(shared + [extra] + other)[0]
    assert (first['cells'], first['mean_success'], first['compared_cells'], first['compared_mean_success']) == (
        3, 0.667, 2, 1.0)
    assert summarize(shared + other)[0]['compared_cells'] == 2


def test_settings_judged_on_one_model_may_only_be_the_trackers(capsys):
    """--learn-model sets each --model set on the model learned with it: a setting the fit reads would then be
    reported without having been learned with, so only tracker settings are accepted there."""
    with pytest.raises(SystemExit):
        main(['--seeds', '100', '--learn-model', '{}', '--model', '{"measure_outside_grid": false}',
              '{"heldout_bound": 1.0}'])
    assert "may name only tracker settings, not ['heldout_bound']" in capsys.readouterr().err
    # set on the model as they are, so they are checked: a JSON object of true/false values
    for model_sets, why in ((['{"measure_outside_grid": "yes"}'], 'must be true or false'),
                            (['[1]'], 'must be JSON objects')):
        with pytest.raises(SystemExit):
            main(['--seeds', '100', '--learn-model', '{}', '--model', *model_sets])
        assert why in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(['--seeds', '100', '--learn-model', '[]', '--model', '{}'])
    assert 'must be JSON objects' in capsys.readouterr().err
