"""The localizer's fifth state: the change of the range scale error with the bearing."""

import math

from landmark_ros.core import sensors
from landmark_ros.localizer import motion
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.localizer.localizer import Localizer
from landmark_ros.localizer.update import observe
import numpy as np
import pytest

MS = 1_000_000
LANDMARKS = np.array([[4.0, 1.0], [-3.0, 5.0], [2.0, -4.0], [6.0, 6.0], [-5.0, -2.0],
                      [0.5, 6.0], [-6.0, 1.5]])


def test_observe_with_the_bearing_term_matches_central_differences():
    rng = np.random.default_rng(5)
    eps = 1e-6
    for _ in range(20):
        x = np.concatenate([rng.normal(size=3), rng.normal(0.0, 0.05, 2)])
        m = rng.normal(size=(4, 2)) * 3.0 + 5.0
        h, J_z_x, J_z_m = observe(x, m)
        true = sensors.observe(x[:3], m)
        np.testing.assert_allclose(h[:, 0], true[:, 0] * (1.0 + x[3] + x[4] * true[:, 1]),
                                   rtol=1e-12)
        np.testing.assert_allclose(h[:, 1], true[:, 1])
        for i in range(5):
            d = np.zeros(5)
            d[i] = eps
            num = (observe(x + d, m)[0] - observe(x - d, m)[0]) / (2 * eps)
            num[:, 1] = (num[:, 1] + math.pi / eps) % (2 * math.pi / eps) - math.pi / eps
            np.testing.assert_allclose(J_z_x[:, :, i], num, atol=1e-6)
        for i in range(2):
            d = np.zeros(2)
            d[i] = eps
            num = (observe(x, m + d)[0] - observe(x, m - d)[0]) / (2 * eps)
            np.testing.assert_allclose(J_z_m[:, :, i], num, atol=1e-6)
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


def _simulate(seed, lens, bearing_stddev, steps=2000):
    """
    Drive a robot whose ranges read ``1 + lens * bearing`` too long; return NEES, loc, RMSE.

    A scale state (prior 0.02) runs in both cases; ``bearing_stddev`` 0 leaves the
    bearing term out.
    """
    rng = np.random.default_rng(seed)
    cfg = LocalizerConfig(odometry_alphas=(0.5, 2.0, 0.5, 0.1), range_stddev=0.03,
                          range_stddev_per_m=0.0, bearing_stddev=0.02,
                          initial_stddev=(0.05, 0.05, 0.02), correlation='independent',
                          range_scale_state_stddev=0.02,
                          range_scale_bearing_state_stddev=bearing_stddev)
    loc = Localizer(cfg)
    loc.set_map(np.arange(len(LANDMARKS)), LANDMARKS,
                np.tile(np.eye(2) * 1e-10, (len(LANDMARKS), 1, 1)))
    x = np.zeros(3)
    loc.initialize(0, x + rng.normal(0, cfg.initial_stddev),
                   np.diag(np.square(cfg.initial_stddev)))
    loc.add_odometry(0, twist=np.array([0.3, 0.0]))
    nees, err, t = [], [], 0
    for k in range(steps):
        v, w = 0.3, 0.4 * math.sin(k / 200)
        d = motion.delta_from_twist(v, w, 0.02)
        Q = motion.odometry_noise(d, cfg.odometry_alphas) + np.eye(3) * 1e-14
        x = motion.compose(x, d + rng.multivariate_normal(np.zeros(3), Q))
        t += 20 * MS
        loc.add_odometry(t, twist=np.array([v, w]))
        if k % 10 == 3:
            z = sensors.observe(np.tile(x, (len(LANDMARKS), 1)), LANDMARKS)
            seen = np.flatnonzero(np.abs(z[:, 1]) < 1.0)[:3]  # a camera's field of view
            z = z[seen]
            z[:, 0] *= 1.0 + lens * z[:, 1]
            z += rng.normal(0, [0.03, 0.02], z.shape)
            loc.add_observations(t, seen, z)
        if k > 400 and k % 5 == 0:
            est = loc.estimate()
            e = est.x - x
            e[2] = motion.wrap(e[2])
            nees.append(e @ np.linalg.solve(est.P, e))
            err.append(math.hypot(e[0], e[1]))
    return np.array(nees), loc, math.sqrt(np.mean(np.square(err)))


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
