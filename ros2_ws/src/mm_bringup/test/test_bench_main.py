"""The benchmark runner's output: a smoke run never passes for the full benchmark's figures, and each figure names
the code that measured it."""
import shutil
import subprocess
from pathlib import Path

import pytest

from mm_bringup.bench import code_version
from mm_bringup.bench.__main__ import output_dir


def test_a_quick_run_never_writes_over_the_full_results():
    assert output_dir('results', False) == Path('results')
    assert output_dir('results', True) == Path('results/quick')


@pytest.mark.skipif(shutil.which('git') is None, reason='needs git')
def test_the_code_version_ignores_the_benchmarks_own_results(tmp_path):
    """A results file rewritten by the run (or removed before it) leaves the code clean; any other tracked file that
    differs from the commit makes it dirty."""
    def git(*args):
        subprocess.run(['git', '-c', 'user.name=t', '-c', 'user.email=t@t', *args], cwd=tmp_path, check=True,
                       capture_output=True)
    (tmp_path / 'results').mkdir()
    (tmp_path / 'results' / 'wall_task.json').write_text('{}\n')
    (tmp_path / 'code.py').write_text('x = 1\n')
    git('init', '-q')
    git('add', '.')
    git('commit', '-q', '-m', 'c')
    clean = code_version(tmp_path)
    assert clean['git_commit'] and not clean['git_dirty']
    (tmp_path / 'results' / 'wall_task.json').unlink()
    assert code_version(tmp_path) == clean
    (tmp_path / 'code.py').write_text('x = 2\n')
    assert code_version(tmp_path)['git_dirty']
