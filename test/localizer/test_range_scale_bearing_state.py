"""The localizer's fifth state: the change of the range scale error with the bearing."""

import math

from landmark_ros.core import sensors
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.localizer.localizer import Localizer
from landmark_ros.localizer.update import observe
import numpy as np
import pytest
from test_range_scale_state import assert_jacobians_match_central_differences, simulate

LANDMARKS = np.array([[4.0, 1.0], [-3.0, 5.0], [2.0, -4.0], [6.0, 6.0], [-5.0, -2.0],
                      [0.5, 6.0], [-6.0, 1.5]])


def test_observe_with_the_bearing_term_matches_central_differences():
    rng = np.random.default_rng(5)
    for _ in range(20):
        x = np.concatenate([rng.normal(size=3), rng.normal(0.0, 0.05, 2)])
        m = rng.normal(size=(4, 2)) * 3.0 + 5.0
        h, J_z_x, J_z_m = observe(x, m)
        true = sensors.observe(x[:3], m)
        np.testing.assert_allclose(h[:, 0], true[:, 0] * (1.0 + x[3] + x[4] * true[:, 1]),
                                   rtol=1e-12)
        np.testing.assert_allclose(h[:, 1], true[:, 1])
        assert_jacobians_match_central_differences(x, m)
        # a batch is the rows one by one
        for k in range(len(m)):
            one = observe(x, m[k:k + 1])
            for a, b in zip(one, (h, J_z_x, J_z_m)):
                np.testing.assert_allclose(a[0], b[k], rtol=1e-13, atol=1e-15)
    # without a bearing term the fifth state changes nothing but adds a column
    x[4] = 0.0
    h5, J5, Jm5 = observe(x, m)
    h4, J4, Jm4 = observe(x[:4], m)
    np.testing.assert_array_equal(h5, h4)
    np.testing.assert_array_equal(J5[:, :, :4], J4)
    np.testing.assert_array_equal(Jm5, Jm4)


def test_the_bearing_state_needs_the_scale_state():
    with pytest.raises(ValueError, match='range_scale_state_stddev'):
        LocalizerConfig(range_scale_bearing_state_stddev=0.02)
    cfg = LocalizerConfig(range_scale_state_stddev=0.01, range_scale_bearing_state_stddev=0.02)
    loc = Localizer(cfg)
    loc.initialize(0, np.zeros(3), np.eye(3) * 0.01)
    step = loc._steps[-1]
    assert step.x.shape == (5,)
    np.testing.assert_allclose(np.diag(step.P)[3:], [1e-4, 4e-4])
    step.x[3:] = [0.01, -0.03]  # a restart keeps what was learnt
    loc.initialize(10, np.ones(3), np.eye(3) * 0.01)
    np.testing.assert_allclose(loc._steps[-1].x[3:], [0.01, -0.03])


def _in_view(rng, x, landmarks):
    """Return the first three landmarks within 1 rad of the heading (a field of view)."""
    b = sensors.observe(np.tile(x, (len(landmarks), 1)), landmarks)[:, 1]
    return np.flatnonzero(np.abs(b) < 1.0)[:3]


def _simulate(seed, lens, bearing_stddev):
    """
    Drive a robot whose ranges read ``1 + lens * bearing`` too long; return NEES, loc, RMSE.

    A scale state (prior 0.02) runs in both cases; ``bearing_stddev`` 0 leaves the
    bearing term out.
    """
    return simulate(seed, lambda z: lens * z[:, 1], {
        'range_scale_state_stddev': 0.02, 'range_scale_bearing_state_stddev': bearing_stddev},
        steps=2000, landmarks=LANDMARKS, seen=_in_view, settle=400)


def test_a_lens_that_reads_one_side_short_is_learnt_and_the_pose_stays_consistent():
    rng = np.random.default_rng(11)
    means = []
    for seed in range(5):
        lens = rng.normal(0.0, 0.06)
        nees, loc, _ = _simulate(seed, lens, 0.06)
        s_b, sd = loc._steps[-1].x[4], math.sqrt(loc._steps[-1].P[4, 4])
        assert abs(s_b - lens) < 3.0 * sd and sd < 0.03, (seed, lens, s_b, sd)
        means.append(np.mean(nees))
    assert 2.0 < np.mean(means) < 4.2, means


def test_without_the_bearing_state_such_a_lens_makes_the_pose_over_confident():
    nees, _, rmse = _simulate(1, 0.12, 0.0)
    nees_state, _, rmse_state = _simulate(1, 0.12, 0.06)
    assert np.mean(nees) > 6.0 and np.mean(nees_state) < 4.2, (nees.mean(), nees_state.mean())
    assert rmse_state < 0.8 * rmse
