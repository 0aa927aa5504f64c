"""Figures of the wheeled-robot experiment (paper Section 2.5) as PNGs under results/figures/.

    ./mm python -m mm_bringup.figures_wheeled [--output results/figures] [--steps 10000] [--seed 0] [--layout paper]

fig7_sensor1_grid.png        samples of the three front readings (sensor 1) and the elastic grid fitted to them
fig8_trajectory_spaces.png   one reaching episode in (a) the grid coordinates of sensor 1, (b) the virtual sensor-1
                             space (outside the grid) and (c) the reading space of sensor 2
fig9_world_trajectory.png    the same episode in the world frame, with the wall at y = 0 and the blind part (no sensor
                             group in range) drawn thick

main() computes everything in process with the plain modules (mm_bringup.wall_experiment: exploration, model fit,
one episode from the paper's start to a goal reading); the plotting functions take plain lists / arrays, so the same
figures can be drawn from data recorded on the ROS graph (ground-truth odometry, ManifoldState messages). Missing
coordinates (None or empty entries) and non-finite readings (+-inf out of range, NaN lost) are skipped, not plotted.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Optional, Sequence

import matplotlib
matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Polygon, Rectangle  # noqa: E402

from mm_common.wheeled_sensors import SENSOR1, SENSOR2, SENSOR_NAMES  # noqa: E402
from mm_manifold.sensor_manifold import SPACE_NONE, SPACE_SENSOR1, SPACE_SENSOR2, SPACE_VIRTUAL  # noqa: E402

SENSOR1_LABELS = tuple(SENSOR_NAMES[i] for i in SENSOR1)
SENSOR2_LABELS = tuple(SENSOR_NAMES[i] for i in SENSOR2)
SPACE_NAMES = {SPACE_NONE: 'none', SPACE_SENSOR1: 'sensor 1', SPACE_VIRTUAL: 'virtual sensor 1',
               SPACE_SENSOR2: 'sensor 2'}


# --- helpers: plain data in, tolerant of gaps ------------------------------------------------------------------
def _points(entries: Sequence, dim: int) -> np.ndarray:
    """Per-step entries (array-like of `dim` values, or None / empty) -> (n, dim) float array, NaN rows where the
    entry is missing, of the wrong size or not finite."""
    out = np.full((len(entries), dim), np.nan)
    for k, e in enumerate(entries):
        if e is None:
            continue
        v = np.asarray(e, dtype=float).ravel()
        if v.size == dim and np.all(np.isfinite(v)):
            out[k] = v
    return out


def _runs(labels: np.ndarray):
    """(start, stop, label) of the maximal runs of equal labels."""
    runs, k = [], 0
    while k < len(labels):
        j = k
        while j + 1 < len(labels) and labels[j + 1] == labels[k]:
            j += 1
        runs.append((k, j + 1, labels[k]))
        k = j + 1
    return runs


def _plot_styled(ax, P: np.ndarray, classes: np.ndarray, styles: dict, labelled: set) -> None:
    """Polyline through the finite rows of P, each segment styled by the class of the step it arrives at; NaN rows
    break the line. Each class is labelled in the legend once."""
    for start, stop, c in _runs(classes):
        if c not in styles:
            continue
        lo = start - 1 if start > 0 and np.all(np.isfinite(P[start - 1])) else start   # connect to the previous step
        seg = P[lo:stop]
        if not np.isfinite(seg).any():
            continue
        style = dict(styles[c])
        if c not in labelled and 'label' in style:
            labelled.add(c)
        else:
            style.pop('label', None)
        ax.plot(seg[:, 0], seg[:, 1], **style)


def _grid(model):
    """The ElasticGrid of a SensorManifoldModel (or the grid itself)."""
    return getattr(model, 'grid_', model)


def _grid_box(model) -> np.ndarray:
    if hasattr(model, 'grid_box'):
        return np.asarray(model.grid_box(), dtype=float)
    nodes = _grid(model).nodes_
    return np.array([[0.0, 0.0], [nodes.shape[0] - 1.0, nodes.shape[1] - 1.0]])


def _box_patch(box, **kw) -> Rectangle:
    box = np.asarray(box, dtype=float)
    return Rectangle(tuple(box[0]), *(box[1] - box[0]), fill=False, **kw)


def _first_finite(P: np.ndarray) -> Optional[int]:
    idx = np.flatnonzero(np.all(np.isfinite(P), axis=1))
    return int(idx[0]) if len(idx) else None


def _last_finite(P: np.ndarray) -> Optional[int]:
    idx = np.flatnonzero(np.all(np.isfinite(P), axis=1))
    return int(idx[-1]) if len(idx) else None


def _no_data(ax, text: str = 'no data') -> None:
    if hasattr(ax, 'text2D'):                   # 3-D axes
        ax.text2D(0.5, 0.5, text, transform=ax.transAxes, ha='center', va='center', color='grey')
    else:
        ax.text(0.5, 0.5, text, transform=ax.transAxes, ha='center', va='center', color='grey')


# --- Fig. 7 ------------------------------------------------------------------------------------------------------
def plot_samples_and_grid(model, sensor1_samples, path) -> None:
    """Fig. 7: (a) the sensor-1 samples (three front readings) and (b) the fitted grid as a wireframe with its nodes
    as crosses over the samples. `model` is a SensorManifoldModel (or an ElasticGrid); rows of `sensor1_samples`
    with a non-finite reading are skipped."""
    grid = _grid(model)
    S = np.asarray(sensor1_samples, dtype=float).reshape(-1, 3)
    S = S[np.all(np.isfinite(S), axis=1)]
    nodes = np.asarray(grid.nodes_, dtype=float)
    residual = getattr(grid, 'residual_', float('nan'))
    fig = plt.figure(figsize=(12, 5.4))
    views = []
    ax = fig.add_subplot(1, 2, 1, projection='3d')
    if len(S):
        ax.scatter(S[:, 0], S[:, 1], S[:, 2], s=2, c=S[:, 1], cmap='viridis', alpha=0.6, depthshade=False)
    else:
        _no_data(ax, 'no sensor-1 samples')
    ax.set_title(f'(a) {len(S)} samples of sensor 1 (front readings)')
    views.append(ax)
    ax = fig.add_subplot(1, 2, 2, projection='3d')
    if len(S):
        ax.scatter(S[:, 0], S[:, 1], S[:, 2], s=1, c='lightgrey', alpha=0.35, depthshade=False)
    ax.plot_wireframe(nodes[..., 0], nodes[..., 1], nodes[..., 2], color='tab:blue', linewidth=0.9)
    ax.scatter(nodes[..., 0].ravel(), nodes[..., 1].ravel(), nodes[..., 2].ravel(), marker='x', s=18,
               c='tab:red', depthshade=False, label='nodes')
    ax.set_title(f'(b) {nodes.shape[0]}x{nodes.shape[1]} grid, residual {residual * 1000:.2f} mm RMS')
    ax.legend(fontsize=8, loc='upper left')
    views.append(ax)
    lo = np.nanmin(np.vstack([S, nodes.reshape(-1, 3)]), axis=0)
    hi = np.nanmax(np.vstack([S, nodes.reshape(-1, 3)]), axis=0)
    for ax in views:
        ax.set_xlabel(f's1 {SENSOR1_LABELS[0]} [m]', fontsize=8)
        ax.set_ylabel(f's2 {SENSOR1_LABELS[1]} [m]', fontsize=8)
        ax.set_zlabel(f's3 {SENSOR1_LABELS[2]} [m]', fontsize=8)
        ax.set_xlim(lo[0], hi[0]), ax.set_ylim(lo[1], hi[1]), ax.set_zlim(lo[2], hi[2])
        ax.tick_params(labelsize=7)
        ax.view_init(elev=22, azim=-60)
    fig.suptitle(f'Fig. 7: sensor-1 samples and the fitted elastic grid (fit residual {residual * 1000:.2f} mm)')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --- Fig. 8 ------------------------------------------------------------------------------------------------------
def plot_trajectory_spaces(model, coordinates, spaces, sensor2, goal_coordinates, goal_reading, path) -> None:
    """Fig. 8: one trajectory (a) in the grid coordinates of sensor 1 (steps with sensor 1 in range), (b) in the
    virtual sensor-1 space (all steps with coordinates; virtual steps dashed, the practised overlap with sensor 2
    faint, the goal's virtual coordinates marked) and (c) in the reading space of sensor 2 with the goal reading.

    Per step: `coordinates` (2 values, or None / empty), `spaces` (SPACE_* codes of mm_manifold.sensor_manifold),
    `sensor2` (2 readings, non-finite or None when out of range). `goal_coordinates` may be None."""
    n = max(len(coordinates), len(spaces), len(sensor2))
    C = _points(list(coordinates) + [None] * (n - len(coordinates)), 2)
    S2 = _points(list(sensor2) + [None] * (n - len(sensor2)), 2)
    sp = np.full(n, SPACE_NONE, dtype=int)
    sp[:len(spaces)] = np.asarray(spaces, dtype=int).ravel()[:n]
    box = _grid_box(model)
    bounds = np.asarray(model.virtual_bounds(), dtype=float) if hasattr(model, 'virtual_bounds') else None
    virtual = getattr(model, 'virtual_', None)
    overlap = np.asarray(getattr(virtual, 'overlap_coordinates_', np.zeros((0, 2))), dtype=float).reshape(-1, 2)
    goal_c = None if goal_coordinates is None else np.asarray(goal_coordinates, dtype=float).ravel()
    if goal_c is not None and (goal_c.size != 2 or not np.all(np.isfinite(goal_c))):
        goal_c = None
    goal_r = None if goal_reading is None else np.asarray(goal_reading, dtype=float).ravel()
    if goal_r is not None and (goal_r.size != 2 or not np.all(np.isfinite(goal_r))):
        goal_r = None

    fig, axes = plt.subplots(1, 3, figsize=(16, 5.2))
    counts = ', '.join(f'{SPACE_NAMES.get(s, s)} {int(np.sum(sp == s))}' for s in sorted(SPACE_NAMES))

    # (a) sensor-1 space: the grid coordinates while sensor 1 sees the wall.
    ax = axes[0]
    rows, cols = int(round(box[1, 0] - box[0, 0])) + 1, int(round(box[1, 1] - box[0, 1])) + 1
    for r in range(rows):
        ax.plot([box[0, 0] + r] * 2, [box[0, 1], box[1, 1]], color='lightsteelblue', linewidth=0.6, zorder=0)
    for c in range(cols):
        ax.plot([box[0, 0], box[1, 0]], [box[0, 1] + c] * 2, color='lightsteelblue', linewidth=0.6, zorder=0)
    ax.add_patch(_box_patch(box, edgecolor='tab:blue', linewidth=1.5, label='grid (sensor-1 range)'))
    P1 = np.where((sp == SPACE_SENSOR1)[:, None], C, np.nan)
    labelled: set = set()
    _plot_styled(ax, P1, sp, {SPACE_SENSOR1: dict(color='tab:blue', linewidth=1.8, marker='.', markersize=3,
                                                  label='trajectory (sensor 1)')}, labelled)
    first = _first_finite(P1)
    if first is not None:
        ax.plot(*P1[first], 'o', mfc='none', mec='k', markersize=10, mew=1.5, label='start')
        last = _last_finite(P1)
        ax.plot(*P1[last], 's', mfc='none', mec='tab:orange', markersize=8, mew=1.5, label='sensor 1 lost')
    else:
        _no_data(ax, 'no step with sensor 1 in range')
    pad = 0.6
    ax.set_xlim(box[0, 0] - pad, box[1, 0] + pad), ax.set_ylim(box[0, 1] - pad, box[1, 1] + pad)
    ax.set_aspect('equal')
    ax.set_xlabel('grid coordinate 1 (row)'), ax.set_ylabel('grid coordinate 2 (col)')
    ax.set_title(f'(a) sensor-1 space (grid coordinates), {int(np.sum(np.isfinite(P1[:, 0])))} steps', fontsize=10)
    ax.legend(fontsize=7, loc='upper right', framealpha=0.9)

    # (b) virtual sensor-1 space: the coordinates continue outside the grid with the robot's own commands.
    ax = axes[1]
    if len(overlap):
        ax.scatter(overlap[:, 0], overlap[:, 1], s=3, c='silver', alpha=0.5, zorder=0,
                   label='practised overlap with sensor 2')
    ax.add_patch(_box_patch(box, edgecolor='tab:blue', linewidth=1.5, label='grid (sensor-1 range)'))
    if bounds is not None:
        ax.add_patch(_box_patch(bounds, edgecolor='grey', linewidth=0.8, linestyle=':', label='virtual-space bounds'))
    cls = np.where(sp == SPACE_SENSOR1, SPACE_SENSOR1, np.where(np.isfinite(C[:, 0]), SPACE_VIRTUAL, SPACE_NONE))
    labelled = set()
    _plot_styled(ax, C, cls, {SPACE_SENSOR1: dict(color='tab:blue', linewidth=1.8, label='sensor 1 in range'),
                              SPACE_VIRTUAL: dict(color='tab:red', linewidth=1.8, linestyle='--',
                                                  label='virtual (out of sensor-1 range)')}, labelled)
    first, last = _first_finite(C), _last_finite(C)
    if first is not None:
        ax.plot(*C[first], 'o', mfc='none', mec='k', markersize=10, mew=1.5, label='start')
        ax.plot(*C[last], 'D', mfc='none', mec='tab:red', markersize=7, mew=1.5, label='end')
    else:
        _no_data(ax, 'no coordinates')
    if goal_c is not None:
        ax.plot(*goal_c, '*', color='gold', mec='k', markersize=16, label='goal (virtual coordinates)')
    pts = np.vstack([box, C[np.isfinite(C[:, 0])]] + ([goal_c[None]] if goal_c is not None else []))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    span = np.maximum(hi - lo, 1.0)
    lo, hi = lo - 0.15 * span, hi + 0.15 * span
    if bounds is not None:
        lo, hi = np.maximum(lo, bounds[0] - 0.5), np.minimum(hi, bounds[1] + 0.5)
    ax.set_xlim(lo[0], hi[0]), ax.set_ylim(lo[1], hi[1])
    ax.set_aspect('equal', adjustable='box')
    ax.set_xlabel('grid coordinate 1 (row)'), ax.set_ylabel('grid coordinate 2 (col)')
    ax.set_title(f'(b) virtual sensor-1 space, {int(np.sum(cls == SPACE_VIRTUAL))} steps outside sensor-1 range',
                 fontsize=10)
    ax.legend(fontsize=7, loc='best')

    # (c) sensor-2 space: the last part of the trajectory, with the goal reading.
    ax = axes[2]
    box2 = np.asarray(getattr(model, 'sensor2_box_', np.full((2, 2), np.nan)), dtype=float)
    if box2.shape == (2, 2) and np.all(np.isfinite(box2)):
        ax.add_patch(_box_patch(box2, edgecolor='tab:green', linewidth=1.0, linestyle=':',
                                label='sensor-2 readings seen in exploration'))
    labelled = set()
    in2 = np.isfinite(S2[:, 0])
    _plot_styled(ax, S2, np.where(in2, SPACE_SENSOR2, SPACE_NONE),
                 {SPACE_SENSOR2: dict(color='tab:green', linewidth=1.8, marker='.', markersize=4,
                                      label='trajectory (sensor 2)')}, labelled)
    first, last = _first_finite(S2), _last_finite(S2)
    if first is not None:
        ax.plot(*S2[first], 'o', mfc='none', mec='k', markersize=10, mew=1.5, label='sensor 2 reached')
        ax.plot(*S2[last], 'D', mfc='none', mec='tab:green', markersize=7, mew=1.5, label='end')
    else:
        _no_data(ax, 'sensor 2 never in range')
    if goal_r is not None:
        ax.plot(*goal_r, '*', color='gold', mec='k', markersize=16, label='goal reading')
        if last is not None:
            ax.plot(*zip(S2[last], goal_r), ':', color='k', linewidth=0.8)
    # Zoom on the trajectory and the goal (the range seen in exploration is only partly visible then).
    pts = np.vstack([S2[in2]] + ([goal_r[None]] if goal_r is not None else []))
    if len(pts):
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        centre, half = (lo + hi) / 2, max(float(np.max(hi - lo)) * 0.65, 0.01)
        ax.set_xlim(centre[0] - half, centre[0] + half), ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_aspect('equal', adjustable='box')
    ax.set_xlabel(f's4 {SENSOR2_LABELS[0]} [m]'), ax.set_ylabel(f's5 {SENSOR2_LABELS[1]} [m]')
    title = f'(c) sensor-2 space, {int(in2.sum())} steps in range'
    if goal_r is not None and last is not None:
        title += f'\nfinal error {np.max(np.abs(S2[last] - goal_r)) * 1000:.1f} mm (max over sensors)'
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7, loc='best')
    fig.suptitle(f'Fig. 8: trajectory in the sensor spaces ({n} steps: {counts})')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --- Fig. 9 ------------------------------------------------------------------------------------------------------
def _robot_glyph(ax, pose, colour, label, size=0.06) -> None:
    """A triangle pointing along the heading, centred on the robot, plus the body outline."""
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    local = np.array([[size, 0.0], [-0.6 * size, 0.55 * size], [-0.6 * size, -0.55 * size]])
    world = local @ np.array([[c, s], [-s, c]]) + [x, y]
    ax.add_patch(Polygon(world, closed=True, facecolor=colour, edgecolor='k', alpha=0.85, zorder=5, label=label))
    ax.add_patch(plt.Circle((x, y), 0.03, fill=False, edgecolor=colour, linewidth=1.0, zorder=5))


def plot_world_trajectory(poses, blind, path, wall_y: float = 0.0, title: Optional[str] = None) -> None:
    """Fig. 9: the x-y path in the world frame with the wall (y = wall_y) as a thick line, the robot at the start and
    the end (triangle along its heading) and the blind steps (no sensor group in range) drawn thick.
    `poses`: per step (x, y, theta); `blind`: per step bool (or None); non-finite poses are skipped."""
    P = _points(list(poses), 3)
    n = len(P)
    b = np.zeros(n, dtype=bool)
    if blind is not None:
        bl = np.asarray(blind, dtype=bool).ravel()[:n]
        b[:len(bl)] = bl
    fig, ax = plt.subplots(figsize=(8, 6.5))
    ok = np.isfinite(P[:, 0])
    labelled: set = set()
    _plot_styled(ax, P[:, :2], b.astype(int), {0: dict(color='tab:blue', linewidth=1.2, label='sensor in range'),
                                              1: dict(color='tab:red', linewidth=4.0, solid_capstyle='round',
                                                      label='blind (no sensor group in range)')}, labelled)
    first, last = _first_finite(P), _last_finite(P)
    if first is not None:
        _robot_glyph(ax, P[first], 'tab:green', 'start')
        _robot_glyph(ax, P[last], 'tab:orange', 'end')
        xs = P[ok, 0]
        lo, hi = float(xs.min()), float(xs.max())
        ys = np.append(P[ok, 1], wall_y)
    else:
        _no_data(ax, 'no poses')
        lo, hi, ys = -0.5, 0.5, np.array([wall_y, wall_y + 1.0])
    span = max(hi - lo, float(ys.max() - ys.min()), 0.2)
    ax.set_xlim(lo - 0.2 * span, hi + 0.2 * span)
    ax.set_ylim(wall_y - 0.08 * span, float(ys.max()) + 0.15 * span)
    ax.axhline(wall_y, color='k', linewidth=5, label=f'wall (y = {wall_y:g} m)')
    ax.axhspan(wall_y - span, wall_y, color='lightgrey', zorder=0)
    ax.set_aspect('equal', adjustable='box')
    ax.set_xlabel('x [m]'), ax.set_ylabel('y [m]')
    if title is None:
        title = (f'Fig. 9: trajectory in the world frame ({int(ok.sum())} steps, '
                 f'{int((b & ok).sum())} blind)')
    ax.set_title(title)
    ax.grid(True, linewidth=0.3)
    ax.legend(fontsize=8, loc='upper right')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --- the in-process experiment -------------------------------------------------------------------------------------
def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--output', default='results/figures')
    parser.add_argument('--steps', type=int, default=10000, help='exploration steps')
    parser.add_argument('--seed', type=int, default=0, help='exploration seed')
    parser.add_argument('--layout', default='paper', help='sensor layout (mm_sim/layouts): paper (no pose where both '
                        'groups see the wall, as in the paper) or overlap (the simulator\'s default)')
    parser.add_argument('--goal', type=float, nargs=3, default=None, metavar=('X', 'Y', 'THETA'),
                        help='pose whose sensor-2 reading is the goal (default: the benchmark\'s paper task of the '
                        'layout)')
    parser.add_argument('--tolerance', type=float, default=0.005, help='controller tolerance on sensor 2 [m]')
    args = parser.parse_args(argv)

    from mm_bringup.bench.wall_task import PAPER_GOAL_POSES
    from mm_bringup.wall_experiment import (PAPER_START, explore, layout_robot, run_episode, sensor2_goal_reading,
                                            success)
    from mm_manifold.sensor_manifold import SensorManifoldModel, group_in_range

    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    robot, dt = layout_robot(args.layout)
    goal_pose = tuple(args.goal) if args.goal is not None else PAPER_GOAL_POSES[args.layout]
    log = explore(robot, args.steps, random_state=args.seed, dt=dt)
    model = SensorManifoldModel(dt).fit(log.readings, log.commands, log.continuous)
    print(f'[figures_wheeled] model: {model.n_samples_} samples, {model.n_excursions_} excursions, '
          f'grid residual {model.grid_.residual_ * 1000:.2f} mm', flush=True)
    S1 = log.readings[group_in_range(log.readings, SENSOR1)][:, list(SENSOR1)]
    plot_samples_and_grid(model, S1, out / 'fig7_sensor1_grid.png')
    print('[figures_wheeled] fig7 written', flush=True)

    goal_reading = sensor2_goal_reading(robot, goal_pose)
    _, goal_coordinates, _ = model.virtual_.goal_route(goal_reading)
    episode = run_episode(robot, model, PAPER_START, goal_reading, tolerance=args.tolerance, dt=dt)
    ok, error = success(robot, episode, goal_reading, args.tolerance)
    R = np.array(episode.readings)
    print(f'[figures_wheeled] episode: {len(episode.poses)} steps, reached={episode.reached}, success={ok}, '
          f'final error {error * 1000:.1f} mm, path {episode.path_length():.2f} m', flush=True)
    plot_trajectory_spaces(model, episode.coordinates, episode.spaces, R[:, list(SENSOR2)], goal_coordinates,
                           goal_reading, out / 'fig8_trajectory_spaces.png')
    print('[figures_wheeled] fig8 written', flush=True)
    blind = ~group_in_range(R, SENSOR1) & ~group_in_range(R, SENSOR2)
    plot_world_trajectory(episode.poses, blind, out / 'fig9_world_trajectory.png')
    print(f'[figures_wheeled] fig9 written to {out}', flush=True)
    return 0


__all__ = ['plot_samples_and_grid', 'plot_trajectory_spaces', 'plot_world_trajectory', 'main']

if __name__ == '__main__':
    raise SystemExit(main())
