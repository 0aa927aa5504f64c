"""Choose image_embedding's `map_method` and `margin_quantile` for the arm_reach benchmark on scenes and placements
of its own.

    ./mm python -m mm_bringup.tune_arm_reach --output results/tune_arm_reach.json

Runs the arm_reach graph experiment (mm_bringup.bench.arm_reach.run: one exploration + fit, then held-out
placements with the object in the way, scored on the simulator's ground truth) on scene seeds TUNE_SCENES and
placement seeds from TUNE_PLACEMENT_SEED0 (the benchmark uses scene 7 and placements 70001...), once per value of the
setting, and writes every run's successes, contacts and plan failures. The benchmark's targets are 0 contacts and
success >= 0.98; a success already excludes contact, and a setting that refuses every goal has no contact either,
so the setting with the most successes (then the fewest placements with contact) is `best` (choose()).
Earlier runs of this script (before map_method existed, hand touch labels) kept dp_planner's
through_predicted_collision off (17 vs 25 placements with contact of 30) and found map_margin 0.1-0.6 identical (it
concerns the exploration-frame map only).
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

from mm_bringup.bench import arm_reach

TUNE_SCENES = (8, 9)
TUNE_PLACEMENT_SEED0 = 90_000
# image_embedding parameters under test: the paper's route, and the keypoint-distance route with the share of
# no-contact frames allowed inside a segment's contact distance (tune_arm_map chose 0.01 in-process, where DP may
# cross predicted collisions; through the graph a goal the map cuts off is refused, so a tighter map matters more)
SETTINGS = ({'map_method': 'embedding'},
            *({'map_method': 'keypoint_distance', 'margin_quantile': q} for q in (0.0, 0.005, 0.01, 0.02)))


def choose(rows) -> dict:
    """The setting with the most successes over all runs, then the fewest placements with contact."""
    def total(setting):
        runs = [r for r in rows if r['setting'] == setting]
        return sum(r['successes'] for r in runs), -sum(r['contacts'] for r in runs)

    return max(SETTINGS, key=total)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--output', default='results/tune_arm_reach.json')
    parser.add_argument('--placements', type=int, default=10)
    args = parser.parse_args(argv)
    rows = []
    for setting in SETTINGS:
        for scene in TUNE_SCENES:
            with tempfile.TemporaryDirectory(prefix='tune_arm_reach_') as tmp:
                out = arm_reach.run(Path(tmp), False, placements=args.placements, scene_seed=scene,
                                    placement_seed0=TUNE_PLACEMENT_SEED0 + 1000 * scene,
                                    embedding_params=dict(setting))
            row = dict(setting=setting, scene_seed=scene, placements=out['placements'],
                       successes=sum(r['success'] for r in out['per_placement']), contacts=out['contacts'],
                       plan_failures=len(out['plan_failures']), reached=out['reached'])
            rows.append(row)
            print(f'[tune_arm_reach] {row}', flush=True)
    best = choose(rows)
    path = Path(args.output)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix('.json.tmp')
    tmp.write_text(json.dumps(dict(best=best, rows=rows), indent=2) + '\n')
    os.replace(tmp, path)
    print(f'[tune_arm_reach] best {best}; wrote {path}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
