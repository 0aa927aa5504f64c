"""The compiled kernels on a read-only install: numba refuses to cache without a writable directory, and the learner
must still import and run (compiled in the process) instead of failing at import."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import mm_manifold

PACKAGE = Path(mm_manifold.__file__).resolve().parent
CHECK = ('import numpy as np; from mm_manifold.grid import ElasticGrid; import mm_manifold.virtual_space; '
         'g = ElasticGrid(4, 4).fit(np.random.default_rng(0).normal(size=(200, 3)) * [1, 1, 0.01]); '
         'print("ran", np.isfinite(g.transform(np.zeros((1, 3)))).all())')


def can_mount_privately() -> bool:
    if os.geteuid() != 0 or shutil.which('unshare') is None:
        return False
    return subprocess.run(['unshare', '-m', 'true'], capture_output=True).returncode == 0


@pytest.mark.skipif(not can_mount_privately(), reason='needs root and mount namespaces to make the tree read-only')
def test_kernels_compile_without_a_writable_cache(tmp_path):
    home = tmp_path / 'home'
    home.mkdir()
    # the package's own directory and the home (numba's two cache places) read-only, in a private mount namespace
    script = (f'mount --bind -o ro "{PACKAGE}" "{PACKAGE}" && mount --bind -o ro "{home}" "{home}" && '
              f'! touch "{PACKAGE}/probe" 2>/dev/null && exec "{sys.executable}" -c \'{CHECK}\'')
    env = dict(os.environ, HOME=str(home), XDG_CACHE_HOME=str(home))
    env.pop('NUMBA_CACHE_DIR', None)
    done = subprocess.run(['unshare', '-m', 'bash', '-c', script], env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert 'ran True' in done.stdout
