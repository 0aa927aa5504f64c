"""Choose the arm_reach graph's exploration length, image_embedding's `map_method` / `margin_quantile` /
`move_clearance` and dp_planner's `use_blocked_moves` on scenes and placements of their own.

    ./mm python -m mm_bringup.tune_arm_reach --output results/tune_arm_reach.json [--stage exploration|map|both|moves]

Runs the arm_reach graph experiment (mm_bringup.bench.arm_reach.run: one exploration + fit, then held-out placements
with the object in the way, scored on the simulator's ground truth). Stage `exploration`: exploration frames
EXPLORATION_CANDIDATES on scenes EXPLORATION_SCENES (10 placements each, seeds 100000 + 1000 x scene + 1...) with the
map settings at image_embedding's defaults. Stage `map`: the map SETTINGS on scenes TUNE_SCENES (placement seeds from
TUNE_PLACEMENT_SEED0 + 1000 x scene) with the chosen exploration. The benchmark uses scene 7 and placements 70001...;
tune_arm / tune_arm_map use scene 10, arm_task scene 0. The benchmark's targets are 0 contacts and success >= 0.98; a
success already excludes contact, and a setting that refuses every goal has no contact either, so the setting with the
most successes (then the fewest placements with contact, then the shorter exploration) is `best` (choose()).
Stage `moves` (run alone, with the defaults the other stages chose): planning on the per-cell map against planning on
the map's blocked moves with each MOVES_SETTINGS move clearance, on scenes MOVES_SCENES (10 placements each, seeds
from MOVES_PLACEMENT_SEED0 + 1000 x scene); moves open passages a per-cell map cuts but keep no half-cell slack, so
here the fewest placements with contact come first, then the most successes (choose_safe(); `best_moves`).
Earlier runs of this script (before map_method existed, hand touch labels) kept dp_planner's
through_predicted_collision off (17 vs 25 placements with contact of 30) and found map_margin 0.1-0.6 identical (it
concerns the exploration-frame map only).
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path
from typing import Optional

from mm_bringup.bench import arm_reach, write_json
from mm_planner.arm_agent import EXPLORATION_STEPS

TUNE_SCENES = (8, 9)
TUNE_PLACEMENT_SEED0 = 90_000
EXPLORATION_SCENES = (11, 12, 13, 14, 15, 16)
EXPLORATION_PLACEMENT_SEED0 = 100_000
EXPLORATION_CANDIDATES = (600, 1000, 1500)
# image_embedding parameters under test: the paper's route, and the keypoint-distance route with the share of
# no-contact frames allowed inside a segment's contact distance (tune_arm_map chose 0.01 in-process, where DP may
# cross predicted collisions; through the graph a goal the map cuts off is refused, so a tighter map matters more)
SETTINGS = ({'map_method': 'embedding'},
            *({'map_method': 'keypoint_distance', 'margin_quantile': q} for q in (0.0, 0.005, 0.01, 0.02)))
# Stage `moves`: dp_planner on the per-cell map (the paper's) or on the map's blocked moves, with the predicted
# clearance [px] image_embedding requires along a move; most conservative first (the tie-break).
MOVES_SCENES = (8, 9, 25, 26, 27)
MOVES_PLACEMENT_SEED0 = 110_000
MOVES_SETTINGS = ({'planner': {'use_blocked_moves': False}, 'embedding': {}},
                  *({'planner': {'use_blocked_moves': True}, 'embedding': {'move_clearance': c}}
                    for c in (9.0, 6.0, 3.0, 0.0)))


def choose(rows, key: str, candidates):
    """The candidate (value of `key` in the rows) with the most successes over all its runs, then the fewest
    placements with contact, then the first in `candidates` (the cheaper exploration)."""
    def total(candidate):
        runs = [r for r in rows if r[key] == candidate]
        return sum(r['successes'] for r in runs), -sum(r['contacts'] for r in runs), -candidates.index(candidate)

    return max(candidates, key=total)


def choose_safe(rows, candidates):
    """The moves-stage candidate with the fewest placements with contact (the benchmark's hard target), then the
    most successes, then the first in `candidates` (the more conservative)."""
    def total(candidate):
        runs = [r for r in rows if r['setting'] == candidate]
        return -sum(r['contacts'] for r in runs), sum(r['successes'] for r in runs), -candidates.index(candidate)

    return max(candidates, key=total)


def run_one(scene: int, seed0: int, placements: int, exploration: int, setting: dict,
            planner: Optional[dict] = None) -> dict:
    with tempfile.TemporaryDirectory(prefix='tune_arm_reach_') as tmp:
        out = arm_reach.run(Path(tmp), False, placements=placements, scene_seed=scene,
                            placement_seed0=seed0 + 1000 * scene, exploration_steps=exploration,
                            embedding_params=dict(setting), planner_params=dict(planner or {}))
    row = dict(setting=setting if planner is None else dict(embedding=setting, planner=planner),
               exploration_steps=exploration, scene_seed=scene, placements=out['placements'],
               successes=sum(r['success'] for r in out['per_placement']), contacts=out['contacts'],
               plan_failures=len(out['plan_failures']), reached=out['reached'])
    print(f'[tune_arm_reach] {row}', flush=True)
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--output', default='results/tune_arm_reach.json')
    parser.add_argument('--placements', type=int, default=15, help='placements per scene in the map stage')
    parser.add_argument('--stage', choices=('exploration', 'map', 'both', 'moves'), default='both',
                        help="'both' = exploration then map; 'moves' runs alone, with the current defaults")
    args = parser.parse_args(argv)
    path = Path(args.output)
    result = json.loads(path.read_text()) if path.is_file() else {}     # a stage run keeps the others' rows
    exploration = EXPLORATION_STEPS
    if args.stage in ('exploration', 'both'):
        rows = [run_one(scene, EXPLORATION_PLACEMENT_SEED0, 10, n, {})
                for n in EXPLORATION_CANDIDATES for scene in EXPLORATION_SCENES]
        exploration = choose(rows, 'exploration_steps', list(EXPLORATION_CANDIDATES))
        result.update(exploration_rows=rows, best_exploration_steps=exploration)
    if args.stage in ('map', 'both'):
        rows = [run_one(scene, TUNE_PLACEMENT_SEED0, args.placements, exploration, setting)
                for setting in SETTINGS for scene in TUNE_SCENES]
        result.update(map_rows=rows, best=choose(rows, 'setting', list(SETTINGS)), map_exploration_steps=exploration)
    if args.stage == 'moves':
        rows = [run_one(scene, MOVES_PLACEMENT_SEED0, 10, exploration, setting['embedding'], setting['planner'])
                for setting in MOVES_SETTINGS for scene in MOVES_SCENES]
        result.update(moves_rows=rows, best_moves=choose_safe(rows, list(MOVES_SETTINGS)))
    write_json(path, result, sort_keys=False)
    print(f"[tune_arm_reach] best exploration {result.get('best_exploration_steps')}, map setting "
          f"{result.get('best')}, moves setting {result.get('best_moves')}; wrote {path}")
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
