"""Benchmarks behind `make bench`. Each part module exposes NAME (the JSON file stem) and
`run(output_dir: Path, quick: bool) -> dict`; `python -m mm_bringup.bench` runs them and writes results/<NAME>.json."""

PARTS = ('graph_bench', 'wall_task', 'arm_task', 'arm_reach')
