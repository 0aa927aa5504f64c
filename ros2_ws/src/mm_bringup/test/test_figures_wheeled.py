"""The Section 2 figure functions draw readable PNGs from small synthetic data, including gaps: steps without
coordinates, out-of-range (inf) and lost (NaN) readings, no sensor-2 steps at all."""
import math
from types import SimpleNamespace

import matplotlib.image as mpimg
import numpy as np
import pytest

from mm_bringup.figures_wheeled import plot_samples_and_grid, plot_trajectory_spaces, plot_world_trajectory
from mm_manifold.grid import ElasticGrid
from mm_manifold.sensor_manifold import SPACE_NONE, SPACE_SENSOR1, SPACE_SENSOR2, SPACE_VIRTUAL


def _assert_png(path, min_bytes=15_000):
    assert path.is_file()
    assert path.stat().st_size > min_bytes
    img = mpimg.imread(str(path))[..., :3]
    not_white = np.any(img < 0.9, axis=-1).mean()
    assert 0.01 < not_white < 0.9, f'{path.name}: {not_white:.3f} of the pixels drawn'
    assert img.std() > 0.05


@pytest.fixture(scope='module')
def model_and_samples():
    rng = np.random.default_rng(0)
    uv = rng.uniform(0.1, 1.0, size=(300, 2))
    S = np.column_stack([uv[:, 0], uv[:, 1], 0.5 * uv[:, 0] + 0.3 * uv[:, 1] ** 2])
    grid = ElasticGrid(5, 5, n_iter=3).fit(S)
    model = SimpleNamespace(
        grid_=grid, sensor2_box_=np.array([[0.05, 0.05], [0.25, 0.25]]),
        virtual_=SimpleNamespace(overlap_coordinates_=rng.normal([1.0, -2.0], 0.5, size=(50, 2))),
        grid_box=lambda: np.array([[0.0, 0.0], [4.0, 4.0]]),
        virtual_bounds=lambda: np.array([[-4.0, -4.0], [8.0, 8.0]]))
    S_with_gaps = np.vstack([S, [[np.inf, 0.2, 0.3], [np.nan, np.nan, np.nan]]])
    return model, S_with_gaps


def _episode(n=40):
    t = np.linspace(0.0, 1.0, n)
    spaces = [SPACE_NONE] * 2 + [SPACE_SENSOR1] * 18 + [SPACE_VIRTUAL] * 10 + [SPACE_SENSOR2] * (n - 30)
    coordinates = [None, np.zeros(0)] + [np.array([2.0 - 3 * s, 2.0 - 4 * s]) for s in t[2:]]
    coordinates[25] = None                                     # a gap in the middle
    sensor2 = [np.array([math.inf, math.inf])] * 30 + [np.array([0.25 - 0.1 * s, 0.24 - 0.1 * s]) for s in t[30:]]
    sensor2[33] = np.array([np.nan, 0.2])                      # a lost reading
    return coordinates, spaces, sensor2


def test_fig7_samples_and_grid(tmp_path, model_and_samples):
    model, S = model_and_samples
    plot_samples_and_grid(model, S, tmp_path / 'fig7.png')
    _assert_png(tmp_path / 'fig7.png')
    plot_samples_and_grid(model.grid_, np.zeros((0, 3)), tmp_path / 'fig7_empty.png')   # grid only, no samples
    _assert_png(tmp_path / 'fig7_empty.png')


def test_fig8_trajectory_spaces(tmp_path, model_and_samples):
    model, _ = model_and_samples
    coordinates, spaces, sensor2 = _episode()
    plot_trajectory_spaces(model, coordinates, spaces, sensor2, np.array([0.5, -1.5]), np.array([0.16, 0.15]),
                           tmp_path / 'fig8.png')
    _assert_png(tmp_path / 'fig8.png')


def test_fig8_without_sensor2_or_goal(tmp_path, model_and_samples):
    model, _ = model_and_samples
    coordinates, spaces, _ = _episode()
    sensor2 = np.full((len(spaces), 2), np.inf)                # sensor 2 never in range
    plot_trajectory_spaces(model, coordinates, spaces, sensor2, None, None, tmp_path / 'fig8.png')
    _assert_png(tmp_path / 'fig8.png')
    plot_trajectory_spaces(model, [None] * 3, [SPACE_NONE] * 3, [None] * 3, None, None, tmp_path / 'fig8_none.png')
    assert (tmp_path / 'fig8_none.png').stat().st_size > 10_000


def test_fig9_world_trajectory(tmp_path):
    n = 60
    s = np.linspace(0.0, 1.0, n)
    poses = [(0.6 * v, 1.0 - 0.75 * v, -math.pi / 2 + math.pi / 2 * v) for v in s]
    poses[10] = (math.nan, math.nan, math.nan)
    blind = [35 <= k < 45 for k in range(n)]
    plot_world_trajectory(poses, blind, tmp_path / 'fig9.png')
    _assert_png(tmp_path / 'fig9.png')
    plot_world_trajectory(np.array(poses), None, tmp_path / 'fig9_no_blind.png', wall_y=0.1)
    _assert_png(tmp_path / 'fig9_no_blind.png')
    plot_world_trajectory([], [], tmp_path / 'fig9_empty.png')
    assert (tmp_path / 'fig9_empty.png').stat().st_size > 5_000
