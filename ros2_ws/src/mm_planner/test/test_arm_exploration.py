"""The arm explorer: targets inside the limits, kept until reached, revisiting where contact was felt."""
import numpy as np
import pytest

from mm_planner.arm_exploration import ArmExplorer

LIMITS = ((-3.2, -0.8), (0.0, 2.2))


def test_targets_stay_inside_the_limits_and_are_kept_until_reached():
    ex = ArmExplorer(LIMITS, random_state=0)
    q = np.array([-2.0, 1.0])
    first = ex.next_command(q, False)
    assert np.all(first >= np.array(LIMITS)[:, 0]) and np.all(first <= np.array(LIMITS)[:, 1])
    assert np.array_equal(ex.next_command(q, False), first)          # not there yet: same target
    second = ex.next_command(first, False)                            # reached: a new one
    assert not np.array_equal(second, first)
    assert ex.n_targets_ == 2


def test_same_seed_same_targets_and_contact_revisits():
    a, b = ArmExplorer(LIMITS, random_state=3), ArmExplorer(LIMITS, random_state=3)
    touched = np.array([-1.5, 0.7])
    ta = [a.next_command(a.target_ if a.target_ is not None else touched, k == 0) for k in range(40)]
    tb = [b.next_command(b.target_ if b.target_ is not None else touched, k == 0) for k in range(40)]
    np.testing.assert_array_equal(ta, tb)
    ex = ArmExplorer(LIMITS, contact_share=1.0, spread=0.05, random_state=1)
    ex.next_command(touched, True)
    near = [ex.next_command(ex.target_, False) for _ in range(30)]
    assert np.max(np.abs(np.array(near) - touched)) < 0.3


def test_bad_input():
    with pytest.raises(ValueError):
        ArmExplorer(((0, 0), (0, 1)))
    with pytest.raises(ValueError):
        ArmExplorer(LIMITS).next_command([np.nan, 0.0], False)
