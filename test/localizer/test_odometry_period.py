"""Odometry alphas per period (``odometry_alphas_period_s``): noise white in time."""

from landmark_ros.localizer import motion
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.localizer.localizer import Localizer
import numpy as np
import pytest

ALPHAS = (0.5, 0.2, 0.1, 0.01)


def test_step_noise_scale_values():
    assert motion.step_noise_scale(0.02, 0.0) == 1.0
    assert motion.step_noise_scale(0.02, 0.01) == pytest.approx(0.5, rel=1e-15)
    np.testing.assert_array_equal(motion.step_noise_scale(np.array([0.005, 0.0, -1.0]), 0.01),
                                  [2.0, 0.0, 0.0])
    np.testing.assert_array_equal(motion.step_noise_scale(np.array([0.3, 0.01]), 0.0),
                                  [1.0, 1.0])


def _drive(period_s, step_s, duration_s=2.0, twist=(0.2, 0.3)):
    """Return the covariance after ``duration_s`` of a constant twist at ``step_s``."""
    loc = Localizer(LocalizerConfig(odometry_alphas=ALPHAS, odometry_alphas_period_s=period_s,
                                    min_step_variance=0.0, max_odometry_gap_s=1.0))
    loc.initialize(0, np.zeros(3), np.diag([1e-6, 1e-6, 1e-6]))
    n = int(round(duration_s / step_s))
    est = None
    for k in range(n + 1):
        est = loc.add_odometry(int(round(k * step_s * 1e9)), twist=np.array(twist))
    return est.P


def test_the_covariance_of_a_drive_does_not_depend_on_the_odometry_rate():
    fast, slow = _drive(0.01, 0.01), _drive(0.01, 0.04)
    # heading: the sum of the steps' variances, up to chord against arc (the turn per
    # step squared); position: to the order of a step
    assert slow[2, 2] == pytest.approx(fast[2, 2], rel=1e-4)
    np.testing.assert_allclose(slow, fast, rtol=0.05)
    # at the period, the model is Probabilistic Robotics' per step
    np.testing.assert_allclose(_drive(0.0, 0.01), fast, rtol=1e-12)
    # per step, steps four times as long give four times the variance in all
    per_step = _drive(0.0, 0.04)
    assert per_step[2, 2] == pytest.approx(4.0 * fast[2, 2], rel=1e-3)


def test_period_is_validated():
    with pytest.raises(ValueError):
        LocalizerConfig(odometry_alphas_period_s=-0.01)


def test_calibration_text_names_the_period():
    from landmark_ros.mrclam.localize_data import format_odometry_calibration
    result = {'alphas': [5.3, 2.4, 1.5, 0.3], 'period_s': 0.01, 'windows_s': [2.0, 5.0],
              'windows': 10, 'reference_stddev': [0.002, 0.002, 0.002], 'delay_s': 0.175,
              'scales': [1.04, 0.95, -1.1, -0.04], 'window_nees': {'2.0': 2.9},
              'cross_check': []}
    text = format_odometry_calibration(result)
    assert 'alphas per 0.01 s of odometry' in text
    assert '    odometry_alphas_period_s: 0.01\n' in text
    assert 'alphas per odometry step' in format_odometry_calibration(
        dict(result, period_s=0.0))
