"""The localizer's range scale state: Jacobians, prediction, recovery and consistency."""

from dataclasses import replace
import math

from landmark_ros.core import sensors
from landmark_ros.localizer import motion
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.localizer.localizer import Localizer
from landmark_ros.localizer.update import observe
import numpy as np

MS = 1_000_000
LANDMARKS = np.array([[4.0, 1.0], [-3.0, 5.0], [2.0, -4.0], [6.0, 6.0], [-5.0, -2.0]])


def assert_jacobians_match_central_differences(x, m, eps=1e-6):
    """Check ``observe``'s Jacobians at ``x`` (n,) against central differences."""
    _, J_z_x, J_z_m = observe(x, m)
    for i in range(len(x)):
        d = np.zeros(len(x))
        d[i] = eps
        num = (observe(x + d, m)[0] - observe(x - d, m)[0]) / (2 * eps)
        num[:, 1] = (num[:, 1] + math.pi / eps) % (2 * math.pi / eps) - math.pi / eps
        np.testing.assert_allclose(J_z_x[:, :, i], num, atol=1e-6)
    for i in range(2):
        d = np.zeros(2)
        d[i] = eps
        num = (observe(x, m + d)[0] - observe(x, m - d)[0]) / (2 * eps)
        np.testing.assert_allclose(J_z_m[:, :, i], num, atol=1e-6)


def test_observe_with_scale_matches_central_differences():
    rng = np.random.default_rng(3)
    for _ in range(20):
        x = np.append(rng.normal(size=3), rng.normal(0.0, 0.05))
        m = rng.normal(size=(4, 2)) * 3.0 + 5.0
        h, _, _ = observe(x, m)
        np.testing.assert_allclose(h[:, 0], sensors.observe(x[:3], m)[:, 0] * (1.0 + x[3]))
        assert_jacobians_match_central_differences(x, m)
    h3, J3, Jm3 = observe(x[:3], m)
    assert J3.shape == (4, 2, 3)
    np.testing.assert_allclose(h3, sensors.observe(x[:3], m))


def test_predict_with_keeps_the_scale_and_turns_its_cross_covariance():
    rng = np.random.default_rng(4)
    for _ in range(20):
        x = np.append(rng.normal(size=3), 0.02)
        A = rng.normal(size=(4, 4))
        P = A @ A.T + np.eye(4) * 1e-3
        B = rng.normal(size=(3, 3)) * 0.1
        Q = B @ B.T
        d = rng.normal(size=3) * 0.5
        x_n, P_n = motion.predict_with(x, P, d, Q)
        # Jacobian of (pose (+) d, s) by central differences
        J = np.zeros((4, 4))
        for i in range(4):
            e = np.zeros(4)
            e[i] = 1e-6
            plus, minus = motion.predict_with(x + e, P, d, Q)[0], motion.predict_with(
                x - e, P, d, Q)[0]
            J[:, i] = (plus - minus) / 2e-6
        J_d = np.zeros((4, 3))
        c, s = math.cos(x[2]), math.sin(x[2])
        J_d[:3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
        np.testing.assert_allclose(P_n, J @ P @ J.T + J_d @ Q @ J_d.T, atol=1e-8)
        assert x_n[3] == x[3]
        x3, P3 = motion.predict(x[:3], P[:3, :3], d, Q)
        np.testing.assert_allclose(P_n[:3, :3], P3)


def _random_two(rng, x, landmarks):
    """Return the indices of the landmarks seen: two at random (a camera sees a few)."""
    return rng.permutation(len(landmarks))[:2]


def simulate(seed, scale, config, steps=1500, landmarks=LANDMARKS, seen=_random_two,
             settle=300):
    """
    Drive a robot whose ranges read ``scale(z)`` (relative) too long.

    ``scale`` is a number or a function of the true readings (N, 2); ``seen(rng, x,
    landmarks)`` picks the landmarks of each sighting. Returns the pose NEES after
    ``settle`` steps, the filter, and the position RMSE over the same steps.
    """
    rng = np.random.default_rng(seed)
    cfg = replace(LocalizerConfig(odometry_alphas=(0.5, 2.0, 0.5, 0.1), range_stddev=0.03,
                                  range_stddev_per_m=0.0, bearing_stddev=0.02,
                                  initial_stddev=(0.05, 0.05, 0.02),
                                  correlation='independent'), **config)
    loc = Localizer(cfg)
    loc.set_map(np.arange(len(landmarks)), landmarks,
                np.tile(np.eye(2) * 1e-10, (len(landmarks), 1, 1)))
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
            ids = seen(rng, x, landmarks)
            z = sensors.observe(np.tile(x, (len(ids), 1)), landmarks[ids])
            z[:, 0] *= 1.0 + (scale(z) if callable(scale) else scale)
            z += rng.normal(0, [0.03, 0.02], z.shape)
            loc.add_observations(t, ids, z)
        if k > settle and k % 5 == 0:
            est = loc.estimate()
            e = est.x - x
            e[2] = motion.wrap(e[2])
            nees.append(e @ np.linalg.solve(est.P, e))
            err.append(math.hypot(e[0], e[1]))
    return np.array(nees), loc, math.sqrt(np.mean(np.square(err)))


def _simulate(seed, scale, state_stddev):
    """Drive a robot whose ranges read ``scale`` too long; return pose NEES and the filter."""
    nees, loc, _ = simulate(seed, scale, {'range_scale_state_stddev': state_stddev})
    return nees, loc


def test_a_constant_range_scale_is_recovered_and_the_pose_stays_consistent():
    rng = np.random.default_rng(7)
    means = []
    for seed in range(5):
        scale = rng.normal(0.0, 0.03)
        nees, loc = _simulate(seed, scale, 0.03)
        s, sd = loc.range_scale()
        assert abs(s - scale) < 3.0 * sd, (seed, scale, s, sd)
        assert sd < 0.01
        means.append(np.mean(nees))
    assert 2.0 < np.mean(means) < 4.2, means


def test_without_the_state_a_range_scale_makes_the_pose_over_confident():
    nees, loc = _simulate(0, 0.04, 0.0)
    assert loc.range_scale() is None
    assert np.mean(nees) > 6.0
    nees_state, _ = _simulate(0, 0.04, 0.03)
    assert np.mean(nees_state) < 4.2
