"""The benchmark runner's output: a smoke run never passes for the full benchmark's figures."""
from pathlib import Path

from mm_bringup.bench.__main__ import output_dir


def test_a_quick_run_never_writes_over_the_full_results():
    assert output_dir('results', False) == Path('results')
    assert output_dir('results', True) == Path('results/quick')
