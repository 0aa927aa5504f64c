"""Benchmarks behind `make bench`. Each part module exposes NAME (the JSON file stem) and
`run(output_dir: Path, quick: bool) -> dict`; `python -m mm_bringup.bench` runs them and writes results/<NAME>.json."""

import json
import os
import subprocess
from pathlib import Path
from typing import Optional

PARTS = ('graph_bench', 'wall_task', 'arm_task', 'arm_reach')


def write_json(path: Path, data: dict, sort_keys: bool = True) -> None:
    """Write a results file atomically (a killed run leaves the previous file, never half of one)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix('.json.tmp')
    tmp.write_text(json.dumps(data, indent=2, sort_keys=sort_keys) + '\n')
    os.replace(tmp, path)


def code_version(where: Optional[Path] = None) -> dict:
    """The commit the figures belong to (of the repository at `where`, this package's by default), and whether the
    tracked files differed from it ('' when not in git). The benchmarks' own output, `results/`, does not count: `make
    bench` rewrites it part by part, and a later part (or a re-run into a fresh results file) would otherwise call the
    committed code dirty."""
    here = Path(where) if where is not None else Path(__file__).resolve().parent
    try:
        commit = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], capture_output=True, text=True, cwd=here,
                                timeout=10).stdout.strip()
        dirty = subprocess.run(['git', 'status', '--porcelain', '--untracked-files=no', '--', ':(top)',
                                ':(top,exclude)results'], capture_output=True, text=True, cwd=here,
                               timeout=10).stdout.strip() != ''
    except (OSError, subprocess.SubprocessError):
        commit, dirty = '', False
    return {'git_commit': commit, 'git_dirty': dirty}
