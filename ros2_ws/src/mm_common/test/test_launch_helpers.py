"""Pure launch helpers: boolean launch arguments, parameter-file resolution, Node parameter lists.

Runs without `launch`/`launch_ros`: the helpers that need them are exercised only through monkeypatched seams.
"""
import pytest

from mm_common import launch_helpers
from mm_common.launch_helpers import node_parameters, parse_bool, resolve_params_file


def test_module_does_not_import_launch():
    source = open(launch_helpers.__file__).read()
    top_level = [line for line in source.splitlines() if line.startswith(('import ', 'from '))]
    assert top_level == ['import os']


@pytest.mark.parametrize('text', ['true', 'True', ' TRUE ', '1', 'yes', 'on'])
def test_parse_bool_true(text):
    assert parse_bool(text) is True


@pytest.mark.parametrize('text', ['false', 'False', '0', 'no', ' off\n'])
def test_parse_bool_false(text):
    assert parse_bool(text) is False


def test_parse_bool_empty_gives_default():
    assert parse_bool('') is None
    assert parse_bool('   ') is None
    assert parse_bool('', default=True) is True
    assert parse_bool('', default=False) is False


@pytest.mark.parametrize('text', ['2', 'maybe', 'tru', 'none'])
def test_parse_bool_rejects_anything_else(text):
    with pytest.raises(ValueError, match='expected true or false'):
        parse_bool(text, default=True)


def test_resolve_given_file(tmp_path):
    given = tmp_path / 'my.yaml'
    given.write_text('x: {ros__parameters: {}}\n')
    default = tmp_path / 'default.yaml'
    default.write_text('')
    assert resolve_params_file(f' {given} ', 'sim_params', default=str(default)) == str(given)


def test_resolve_missing_given_file_is_an_error(tmp_path):
    with pytest.raises(FileNotFoundError, match='sim_params not found: .*nope.yaml'):
        resolve_params_file(str(tmp_path / 'nope.yaml'), 'sim_params', default=None)


def test_resolve_empty_falls_back_to_installed_default(tmp_path):
    default = tmp_path / 'arm_sim.yaml'
    assert resolve_params_file('', 'params_file', default=str(default)) is None   # not installed
    default.write_text('')
    assert resolve_params_file('  ', 'params_file', default=str(default)) == str(default)


def test_resolve_required(tmp_path):
    with pytest.raises(FileNotFoundError, match='^wheeled_sim params_file not found: $'):
        resolve_params_file('', 'wheeled_sim params_file', required=True)
    given = tmp_path / 'w.yaml'
    given.write_text('')
    assert resolve_params_file(str(given), 'wheeled_sim params_file', required=True) == str(given)


def test_node_parameters():
    assert node_parameters(None, {}) == []
    assert node_parameters('a.yaml', {}) == ['a.yaml']
    assert node_parameters(None, {'lockstep': True}) == [{'lockstep': True}]
    assert node_parameters('a.yaml', {'use_sim_time': False}) == ['a.yaml', {'use_sim_time': False}]


@pytest.fixture
def fake_launch(monkeypatch, tmp_path):
    """Launch arguments from a dict and package shares under tmp_path, instead of launch/ament_index."""
    args = {}
    monkeypatch.setattr(launch_helpers, 'launch_arg', lambda context, name: args[name])
    monkeypatch.setattr(launch_helpers, 'package_config',
                        lambda package, filename: str(tmp_path / package / 'config' / filename))
    return args


def test_params_file_from_context(fake_launch, tmp_path):
    fake_launch['sim_params'] = ''
    assert launch_helpers.params_file(None, 'sim_params', 'mm_sim', 'arm_sim.yaml') is None
    installed = tmp_path / 'mm_sim' / 'config' / 'arm_sim.yaml'
    installed.parent.mkdir(parents=True)
    installed.write_text('')
    assert launch_helpers.params_file(None, 'sim_params', 'mm_sim', 'arm_sim.yaml') == str(installed)
    fake_launch['sim_params'] = str(tmp_path / 'missing.yaml')
    with pytest.raises(FileNotFoundError, match='sim_params not found'):
        launch_helpers.params_file(None, 'sim_params', 'mm_sim', 'arm_sim.yaml')


def test_lockstep_overrides(fake_launch):
    fake_launch['lockstep'] = ''
    assert launch_helpers.lockstep_overrides(None) == {}
    fake_launch['lockstep'] = 'false'
    assert launch_helpers.lockstep_overrides(None) == {'lockstep': False}
    fake_launch['lockstep'] = 'on'
    assert launch_helpers.lockstep_overrides(None) == {'lockstep': True}


def test_recorder_off_needs_no_launch_ros(fake_launch):
    fake_launch['record'] = ''
    assert launch_helpers.recorder_actions(None) == []
    fake_launch['record'] = 'no'
    assert launch_helpers.recorder_actions(None) == []
