"""Benchmarks behind `make bench`. Each part module exposes NAME (the JSON file stem) and
`run(output_dir: Path, quick: bool) -> dict`; `python -m mm_bringup.bench` runs them and writes results/<NAME>.json."""

import json
import os
from pathlib import Path

PARTS = ('graph_bench', 'wall_task', 'arm_task', 'arm_reach')


def write_json(path: Path, data: dict, sort_keys: bool = True) -> None:
    """Write a results file atomically (a killed run leaves the previous file, never half of one)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix('.json.tmp')
    tmp.write_text(json.dumps(data, indent=2, sort_keys=sort_keys) + '\n')
    os.replace(tmp, path)
