"""Wall benchmark (results/wall_task.json): paper Section 2 on the `paper` sensor layout, where no pose lets both
sensor groups see the wall, so every task crosses a blind stretch as in the paper (mm_sim/layouts/paper.yaml; the
simulator's default layout, `overlap`, is the easier problem and is measured in the matrix only).

Headline, through the ROS graph (wheeled_sim in lockstep + sensor_manifold + switching_controller as processes,
mm_bringup.wall_graph): the default robot on `paper`, 40 random tasks plus the paper's task per cell: issue 11's item 1
on all five exploration seeds with its sample-bound setting (wall_experiment.SAMPLE_BOUND_EXPLORATION steps and
SAMPLE_BOUND_REHEARSALS rehearsals), and 10 000 steps on one seed. Matrix, in process (mm_bringup.wall_experiment drives
the same WallAgent class as the switching_controller node, and the model reaches it through the same message; a node
test checks both command alike): layouts {paper, overlap} x robots {default, 1.5x scaled, dt 0.1} x exploration seeds x
budgets {3 000, 10 000}, and the same on `paper` with 1 % noise and 5 % dropout. Precision (issue 11, item 4;
`precision`): the headline's in-process cells (paper, default robot, 3 000 steps, the five seeds) with a 2 mm tolerance.

Each task: a start where sensor 1 sees the wall, a goal pose close to the wall where only sensor 2 does, shown to the
robot as its sensor-2 reading; tolerance 10 mm. Scoring uses ground truth (evaluation only):
- success: the controller reports GOAL_REACHED and the noise-free sensor-2 reading at the final pose is within the
  tolerance of the goal reading;
- final error: max |noise-free sensor-2 reading - goal reading| at the final pose [m] (inf when sensor 2 sees nothing);
- path ratio: travelled path over the oracle's (turn in place, drive straight to the goal distance, turn in place);
- longest blind stretch: the most consecutive steps with no sensor group in range, as the controller counts them
  (mm_planner.switching_controller.blind), and its ratio to the length the chosen route predicted;
- samples: samples the learner took in all, the extra exploration of a model that was not ready and the
  rehearsals of a model before it was announced included (`explored`: exploration steps among them).
Seeds: exploration seeds from 1000 and task seeds from 5000, disjoint from the tuning seeds (100-119,
mm_bringup.tune_wall) and from everything the code was developed on.
"""
from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np

from mm_bringup.bench import code_version, write_json
from mm_bringup.wall_experiment import (PAPER_GOAL_POSES, PAPER_START, SAMPLE_BOUND_EXPLORATION,
                                        SAMPLE_BOUND_REHEARSALS, layout_file, layout_robot, learn,
                                        oracle_path_length, random_task, run_episode, sensor2_goal_reading,
                                        simulator_params_file)
from mm_common.wheeled_sensors import SENSOR2
from mm_sim.wheeled_model import WheeledRobot

NAME = 'wall_task'
PAPER_TOLERANCE = 0.005
TOLERANCE = 0.01
PRECISION_TOLERANCE = 0.002   # issue 11, item 4: >= 0.95 success at 2 mm per reading on the paper layout
SAMPLE_TARGET = 3000          # issue 11, item 1: at most this many samples (rehearsals included) per seed
NOISE = {'std_fraction_of_max_range': 0.01, 'dropout': 0.05}
BUDGETS = (3000, 10000)
EXPLORATION_SEEDS = (1000, 1001, 1002, 1003, 1004)
TASK_SEED_BASE = 5000          # the task seed of exploration seed s is TASK_SEED_BASE + (s - 1000)
# Robots beside wheeled_sim.yaml's (dt None: the file's): 1.5x larger, a slower control loop, front sensors of half
# the range (no setting of the learner or the explorer was chosen on it: it checks that none is in metres; its
# exploration starts facing the wall at 0.6 m instead of 1 m, within its front range).
ROBOTS = {'default': {'scale': 1.0, 'dt': None}, 'scaled_1.5x': {'scale': 1.5, 'dt': None},
          'dt_0.1': {'scale': 1.0, 'dt': 0.1},
          'front_0.75m': {'scale': 1.0, 'dt': None, 'front_range': 0.75, 'start': (0.0, 0.6, -math.pi / 2)}}


def robot_variant(layout: str, name: str, **robot_kwargs) -> Tuple[WheeledRobot, float, tuple]:
    """(robot, dt, exploration start pose) of the named robot (ROBOTS) on a sensor layout."""
    spec = ROBOTS[name]
    robot, dt = layout_robot(layout, spec['scale'], spec.get('front_range'), **robot_kwargs)
    return robot, spec['dt'] or dt, spec.get('start', PAPER_START)
HEADLINE_SEEDS = {SAMPLE_BOUND_EXPLORATION: 1000, 10000: 1001}
GRAPH_BUDGETS = (SAMPLE_BOUND_EXPLORATION, 10000)
GRAPH_REHEARSALS = {SAMPLE_BOUND_EXPLORATION: SAMPLE_BOUND_REHEARSALS}     # other budgets: the agent's default


def blind_fraction(robot: WheeledRobot, poses) -> float:
    """Share of the path length travelled while neither sensor group could see the wall (noise-free sensor model at
    the ground-truth poses, so dropped readings do not count as blind)."""
    P = np.asarray(poses, dtype=float)
    if len(P) < 2:
        return 0.0
    seen = [np.all(np.isfinite(r[:3])) or np.all(np.isfinite(r[3:])) for r in (robot.read(p, noisy=False) for p in P)]
    seg = np.linalg.norm(np.diff(P[:, :2], axis=0), axis=1)
    blind = ~np.array(seen[:-1]) | ~np.array(seen[1:])
    return float(seg[blind].sum() / seg.sum()) if seg.sum() > 0 else 0.0


def score(robot: WheeledRobot, episode, start, goal_pose, goal_reading, tolerance: float) -> dict:
    final = robot.read(episode.poses[-1], noisy=False)[list(SENSOR2)]
    error = float(np.max(np.abs(final - goal_reading))) if np.all(np.isfinite(final)) else math.inf
    steps, predicted = episode.longest_blind
    return {'reached': episode.reached, 'success': bool(episode.reached and error < tolerance),
            'final_error': error, 'path_ratio': episode.path_length() / oracle_path_length(start, goal_pose),
            'blind_fraction': blind_fraction(robot, episode.poses), 'steps': len(episode.poses) - 1,
            'longest_blind_steps': steps, 'longest_blind_ratio': steps / predicted if predicted else None,
            'final_heading': float(episode.poses[-1][2]), 'detail': episode.detail}


def summarise(episodes: List[dict]) -> dict:
    ok = [e for e in episodes if e['success']]
    blind = [e['longest_blind_steps'] for e in episodes]
    ratios = [e['longest_blind_ratio'] for e in episodes if e['longest_blind_ratio'] is not None]
    return {
        'tasks': len(episodes),
        'success_rate': len(ok) / len(episodes) if episodes else None,
        'median_final_error': float(np.median([e['final_error'] for e in episodes])) if episodes else None,
        'median_path_ratio': float(np.median([e['path_ratio'] for e in ok])) if ok else None,
        'longest_blind_steps_median': float(np.median(blind)) if blind else None,
        'longest_blind_steps_max': int(max(blind)) if blind else None,
        'longest_blind_ratio_median': float(np.median(ratios)) if ratios else None,
        'longest_blind_ratio_max': float(max(ratios)) if ratios else None,
        'share_longest_blind_over_2x_predicted': float(np.mean([r > 2 for r in ratios])) if ratios else None,
        'failures': [{'task': i, 'detail': e['detail'], 'final_error': e['final_error']}
                     for i, e in enumerate(episodes) if not e['success']],
    }


def unlearned_episode(detail: str) -> dict:
    """The score of a task that could not start: no model was ever announced ready."""
    return {'success': False, 'reached': False, 'final_error': math.inf, 'path_ratio': math.nan,
            'blind_fraction': math.nan, 'steps': 0, 'wall_seconds': 0.0, 'final_heading': math.nan,
            'longest_blind_steps': 0, 'longest_blind_ratio': None, 'detail': detail}


def tasks_for(robot: WheeledRobot, task_seed: int, n_tasks: int):
    rng = np.random.default_rng(task_seed)
    return [random_task(rng, robot) for _ in range(n_tasks)]


# --- in process (the matrix) -------------------------------------------------------------------------------------
def run_cell(layout: str, robot_name: str, seed: int, budget: int, noisy: bool, n_tasks: int,
             tolerance: float = TOLERANCE) -> dict:
    """One matrix cell: explore and learn in process with the WallAgent, then n_tasks random tasks, each a success
    when it ends within `tolerance` of the goal reading (per reading)."""
    began = time.monotonic()
    noise = dict(noise_range_fraction=NOISE['std_fraction_of_max_range'], dropout=NOISE['dropout'],
                 random_state=seed) if noisy else {}
    robot, dt, start = robot_variant(layout, robot_name, **noise)
    clean_robot, _, _ = robot_variant(layout, robot_name)
    learned = learn(robot, budget, dt, random_state=seed, start=start)
    cell = {'layout': layout, 'robot': robot_name, 'exploration_seed': seed, 'exploration_budget': budget,
            'noisy': noisy, 'task_seed': TASK_SEED_BASE + seed - 1000, 'tolerance_m': tolerance,
            'samples': learned.samples,
            'explored': learned.explored, 'model_samples': learned.model.n_samples_ if learned.model else None,
            'learning_detail': learned.detail}
    tasks = tasks_for(clean_robot, cell['task_seed'], n_tasks)
    if learned.model is None:
        episodes = [unlearned_episode(f'no ready model after {learned.samples} samples: {learned.detail}')
                    for _ in tasks]
    else:
        episodes = []
        for start, goal_pose in tasks:
            reading = sensor2_goal_reading(clean_robot, goal_pose)
            episode = run_episode(robot, learned.model, start, reading, tolerance=tolerance, dt=dt)
            episodes.append(score(clean_robot, episode, start, goal_pose, reading, tolerance))
    cell.update(summarise(episodes))
    cell['wall_seconds'] = round(time.monotonic() - began, 1)
    return cell


def matrix_cells(seeds, budgets, robots=tuple(ROBOTS), layouts=('paper', 'overlap')) -> list:
    """Clean cells of every layout, then the noisy ones on `paper`; the headline's own cells (paper, default) first."""
    cells = [(layout, robot, seed, budget, False) for layout in layouts for robot in robots
             for budget in budgets for seed in seeds]
    cells += [('paper', robot, seed, budget, True) for robot in robots for budget in budgets for seed in seeds]
    return cells


def bench_cells(quick: bool) -> list:
    """The cells `make bench` runs: every exploration seed for the headline's layout and robot (paper, default) at
    both budgets, one seed (1000) for every other robot, layout and the noisy condition (the full matrix_cells()
    with five seeds each takes about 4 x longer: `python -m mm_bringup.bench.wall_task --matrix`)."""
    if quick:
        return [('paper', 'default', 1000, 3000, False), ('overlap', 'default', 1000, 3000, False)]
    cells = [('paper', 'default', seed, budget, False) for seed in EXPLORATION_SEEDS for budget in BUDGETS]
    return cells + [c for c in matrix_cells((EXPLORATION_SEEDS[0],), BUDGETS) if c not in cells]


def precision_cells(seeds=EXPLORATION_SEEDS) -> list:
    """Issue 11, item 4: the headline's cells (paper, default robot, 3 000 steps, clean) at PRECISION_TOLERANCE."""
    return [('paper', 'default', seed, 3000, False) for seed in seeds]


def cell_key(cell: dict) -> tuple:
    """A measured cell's place in matrix_cells()."""
    return (cell['layout'], cell['robot'], cell['exploration_seed'], cell['exploration_budget'], cell['noisy'])


def merged_cells(previous: Path, fresh: list) -> Tuple[list, int]:
    """`fresh` cells and those of the matrix in the `previous` results file that `fresh` did not measure again (each
    says when it was measured in `measured_at`, if it was recorded): `make bench` runs part of the matrix and must not
    throw away the rest (`--matrix` ran). Returns the cells and how many were kept."""
    old = json.loads(previous.read_text()) if previous.is_file() else {}
    ran = {cell_key(c) for c in fresh}
    kept = [c for c in old.get('matrix', {}).get('cells', []) if cell_key(c) not in ran]
    return fresh + kept, len(kept)


def run_matrix(cells, n_tasks: int, workers: int, on_cell=None, tolerance: float = TOLERANCE) -> list:
    """run_cell on each cell, `workers` at a time; each result says which code measured it (`measured_at`: the
    commit, '-dirty' when tracked files outside results/ differed from it)."""
    version = code_version()
    measured_at = version['git_commit'] + ('-dirty' if version['git_dirty'] else '')
    results = []
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futures = [pool.submit(run_cell, *cell, n_tasks, tolerance) for cell in cells]
        for future in futures:
            results.append({**future.result(), 'measured_at': measured_at})
            if on_cell:
                on_cell(results)
    return results


def aggregate(cells: list) -> dict:
    """Per (layout, robot, budget, noisy): the cells' success rates over seeds (min / mean), median path ratio and
    the largest longest-blind ratio."""
    groups = {}
    for c in cells:
        key = f"{c['layout']}/{c['robot']}/{c['exploration_budget']}/{'noisy' if c['noisy'] else 'clean'}"
        groups.setdefault(key, []).append(c)
    out = {}
    for key, cs in sorted(groups.items()):
        rates = [c['success_rate'] for c in cs]
        paths = [c['median_path_ratio'] for c in cs if c['median_path_ratio'] is not None]
        out[key] = {'seeds': [c['exploration_seed'] for c in cs], 'success_rate_min': min(rates),
                    'success_rate_mean': float(np.mean(rates)), 'median_path_ratio_median':
                    float(np.median(paths)) if paths else None,
                    'samples': [c['samples'] for c in cs],
                    'longest_blind_steps_max': max(c['longest_blind_steps_max'] or 0 for c in cs)}
    return out


# --- through the graph (the headline) ------------------------------------------------------------------------------
def run_graph_cell(work_dir: Path, budget: int, seed: int, n_tasks: int, layout: str = 'paper') -> dict:
    from mm_bringup.wall_graph import LearningFailed, WallGraph
    robot, dt = layout_robot(layout)
    task_seed = TASK_SEED_BASE + seed - 1000
    tasks = tasks_for(robot, task_seed, n_tasks)
    rehearsals = GRAPH_REHEARSALS.get(budget)
    began = time.monotonic()
    with WallGraph(work_dir, exploration_steps=budget, seed=seed, dt=dt, rehearsals=rehearsals,
                   sim_params_files=[simulator_params_file(), layout_file(layout)]) as graph:
        try:
            graph.wait_learned(timeout=1800.0)
            failure = None
        except LearningFailed as exc:
            failure = str(exc)
        learning_seconds = time.monotonic() - began
        samples = graph.samples
        if failure is not None:          # every task fails with the reason, as in run_cell
            paper, *episodes = [unlearned_episode(failure) for _ in range(n_tasks + 1)]
        else:
            paper = run_graph_task(graph, robot, PAPER_START, PAPER_GOAL_POSES[layout], PAPER_TOLERANCE)
            episodes = [run_graph_task(graph, robot, start, goal_pose, TOLERANCE) for start, goal_pose in tasks]
    cell = {'layout': layout, 'robot': 'default', 'exploration_seed': seed, 'exploration_budget': budget,
            'rehearsals': rehearsals if rehearsals is not None else 'default', 'task_seed': task_seed,
            'samples': int(samples), 'learning_wall_seconds': round(learning_seconds, 1), 'learning_failure': failure,
            'stalled_episodes': sum(e['detail'].startswith('stalled') for e in episodes + [paper]),
            'seconds_per_episode': float(np.mean([e['wall_seconds'] for e in episodes])), 'paper_task': paper}
    cell.update(summarise(episodes))
    return cell


def run_graph_task(graph, robot: WheeledRobot, start, goal_pose, tolerance: float, timeout: float = 120.0) -> dict:
    """One scored episode; a stalled lockstep loop (no outcome within `timeout` wall seconds) counts as a failure
    and the next task's reset restarts the loop, so one stall does not end the benchmark."""
    reading = sensor2_goal_reading(robot, goal_pose)
    try:
        episode = graph.run_episode(start, reading, tolerance, timeout=timeout)
    except TimeoutError as exc:
        return {'success': False, 'reached': False, 'final_error': math.inf, 'path_ratio': math.nan,
                'blind_fraction': math.nan, 'steps': 0, 'wall_seconds': timeout, 'final_heading': math.nan,
                'longest_blind_steps': 0, 'longest_blind_ratio': None, 'detail': f'stalled: {exc}'}
    result = score(robot, episode, start, goal_pose, reading, tolerance)
    result['wall_seconds'] = episode.wall_seconds
    return result


def headline(cells: dict) -> dict:
    """The benchmark's headline figures: the graph cells on `paper` (10 000-step budget first), and issue 11's item
    1 over the sample-bound cells of every seed (success and samples per seed)."""
    main = cells.get('10000') or next(iter(cells.values()))
    bound = {key: c for key, c in cells.items() if key.split('/')[0] == str(SAMPLE_BOUND_EXPLORATION)}
    return {'success_rate': main['success_rate'], 'median_final_error': main['median_final_error'],
            'median_path_ratio': main['median_path_ratio'], 'samples': main['samples'],
            'longest_blind_steps_max': main['longest_blind_steps_max'],
            'sample_bound': {'exploration_steps': SAMPLE_BOUND_EXPLORATION, 'rehearsals': SAMPLE_BOUND_REHEARSALS,
                             'success_rates': {k: c['success_rate'] for k, c in bound.items()},
                             'samples': {k: c['samples'] for k, c in bound.items()},
                             'met': bool(bound) and all(c['success_rate'] >= 0.95 and c['samples'] <= SAMPLE_TARGET
                                                        for c in bound.values())}}


def graph_seeds(budget: int, more=()) -> List[Tuple[str, int]]:
    """(key, exploration seed) of the graph cells at one budget: the headline seed under the budget's own key, the
    others as "budget/seed"."""
    head = HEADLINE_SEEDS.get(budget, EXPLORATION_SEEDS[0])
    return [(str(budget), head)] + [(f'{budget}/{seed}', seed) for seed in more if seed != head]


def run(output_dir: Path, quick: bool, workers: int = 2) -> dict:
    """`make bench`: the graph headline (40 tasks per cell: 10 000 steps on one seed, the sample-bound setting on
    all five, as issue 11's item 1 asks) and the in-process cells of bench_cells() (40 tasks each, two at a time);
    --quick: the sample-bound graph cell of one seed and two in-process cells, 10 tasks each."""
    n_tasks = 10 if quick else 40
    budgets = (SAMPLE_BOUND_EXPLORATION,) if quick else GRAPH_BUDGETS
    graph_cells = {}
    with tempfile.TemporaryDirectory(prefix='wall_task_') as tmp:
        for budget in budgets:
            more = EXPLORATION_SEEDS if budget == SAMPLE_BOUND_EXPLORATION and not quick else ()
            for key, seed in graph_seeds(budget, more):
                graph_cells[key] = run_graph_cell(Path(tmp) / key.replace('/', '_'), budget, seed, n_tasks)
    fresh = run_matrix(bench_cells(quick), n_tasks, workers)
    precision = run_matrix(precision_cells(EXPLORATION_SEEDS[:1] if quick else EXPLORATION_SEEDS), n_tasks, workers,
                           tolerance=PRECISION_TOLERANCE)
    if quick:                  # a smoke run of 10 tasks per cell is not mixed with the benchmark's 40-task cells
        return result_json(graph_cells, fresh, n_tasks, complete=False, precision=precision)
    matrix, kept = merged_cells(output_dir / f'{NAME}.json', fresh)
    complete = {cell_key(c) for c in matrix} >= set(matrix_cells(EXPLORATION_SEEDS, BUDGETS))
    return result_json(graph_cells, matrix, n_tasks, complete=complete, precision=precision,
                       note=f'make bench measured {len(fresh)} cells at {fresh[0]["measured_at"]} (5 seeds for '
                            f'paper/default, seed 1000 for the rest); {kept} cells kept from the earlier results file')


def result_json(graph_cells: dict, matrix: list, n_tasks: int, complete: bool, note: str = '',
                precision: Optional[list] = None) -> dict:
    out = {
        'layout': 'paper',
        'tolerance_m': TOLERANCE,
        'noise': NOISE,
        'seeds': {'exploration': list(EXPLORATION_SEEDS), 'headline_exploration': HEADLINE_SEEDS,
                  'task_seed': f'{TASK_SEED_BASE} + (exploration seed - 1000)',
                  'disjoint_from': 'tuning seeds 100-119 (mm_bringup.tune_wall)'},
        'graph': graph_cells,
        'matrix': {'in_process': 'mm_bringup.wall_experiment (the WallAgent class of the switching_controller node, '
                                 'model through the same message)',
                   'tasks_per_cell': n_tasks, 'complete': complete, 'note': note,
                   'summary': aggregate(matrix) if matrix else {}, 'cells': matrix},
        'targets': {'success_rate': 0.95, 'longest_blind_ratio_max': 2.0, 'samples_per_seed': SAMPLE_TARGET},
    }
    if precision:
        rates = [c['success_rate'] for c in precision]
        out['precision'] = {'tolerance_m': PRECISION_TOLERANCE, 'target_success_rate': 0.95,
                            'seeds': [c['exploration_seed'] for c in precision], 'success_rates': rates,
                            'success_rate_min': min(rates), 'cells': precision}
    if graph_cells:
        out.update(headline(graph_cells))
    return out


def main(argv=None) -> int:
    """Run parts of the benchmark and merge them into the JSON (for runs that do not fit in one sitting)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--output', default='results/wall_task.json',
                        help='merged into when it exists: its matrix cells are kept and only missing ones run (a '
                             'fresh matrix needs a new path); the graph and precision cells asked for run again')
    parser.add_argument('--graph', type=int, nargs='*', default=[],
                        help=f'graph headline budgets to run (of {GRAPH_BUDGETS}: their rehearsals as make bench '
                             'runs them)')
    parser.add_argument('--graph-seeds', type=int, nargs='*', default=[],
                        help='exploration seeds of more graph cells at each --graph budget (kept as "budget/seed")')
    parser.add_argument('--matrix', action='store_true', help='run matrix cells')
    parser.add_argument('--precision', action='store_true',
                        help=f'run the paper/default/3 000-step cells of --seeds at {PRECISION_TOLERANCE} m')
    parser.add_argument('--seeds', type=int, nargs='*', default=list(EXPLORATION_SEEDS))
    parser.add_argument('--budgets', type=int, nargs='*', default=list(BUDGETS))
    parser.add_argument('--robots', nargs='*', default=list(ROBOTS))
    parser.add_argument('--layouts', nargs='*', default=['paper', 'overlap'])
    parser.add_argument('--no-noisy', action='store_true')
    parser.add_argument('--tasks', type=int, default=40)
    parser.add_argument('--workers', type=int, default=2)
    parser.add_argument('--note', default='')
    args = parser.parse_args(argv)
    path = Path(args.output)
    old = json.loads(path.read_text()) if path.is_file() else {}
    graph_cells = dict(old.get('graph', {}))
    matrix = list(old.get('matrix', {}).get('cells', []))
    precision = list(old.get('precision', {}).get('cells', []))

    def write():
        complete = {cell_key(c) for c in matrix} >= set(matrix_cells(EXPLORATION_SEEDS, BUDGETS))
        write_json(path, result_json(graph_cells, matrix, args.tasks, complete, args.note, precision))
    with tempfile.TemporaryDirectory(prefix='wall_task_') as tmp:
        for budget in args.graph:
            for key, seed in graph_seeds(budget, args.graph_seeds):
                graph_cells[key] = run_graph_cell(Path(tmp) / key.replace('/', '_'), budget, seed, args.tasks)
                write()
    if args.matrix:
        cells = matrix_cells(args.seeds, args.budgets, args.robots, args.layouts)
        if args.no_noisy:
            cells = [c for c in cells if not c[4]]
        done = {cell_key(c) for c in matrix}
        todo = [c for c in cells if c not in done]
        kept = list(matrix)

        def on_cell(results):
            matrix[:] = kept + results
            write()
        run_matrix(todo, args.tasks, args.workers, on_cell)
    if args.precision:
        again = {c[2] for c in precision_cells(args.seeds)}
        kept_precision = [c for c in precision if c['exploration_seed'] not in again]

        def on_precision_cell(results):
            precision[:] = sorted(kept_precision + results, key=lambda c: c['exploration_seed'])
            write()
        run_matrix(precision_cells(args.seeds), args.tasks, args.workers, on_precision_cell, PRECISION_TOLERANCE)
    write()
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
