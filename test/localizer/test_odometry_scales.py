"""The odometry scale calibration recovers the systematic error of synthetic odometry."""

from types import SimpleNamespace

from landmark_ros.localizer import motion
from landmark_ros.mrclam.localize_data import odometry_scales, window_samples
import numpy as np
import pytest


def _robot_and_odometry(number, scales, seed):
    """Return a robot whose true motion is its odometry through ``motion.scale_twists``."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 120.0, 0.015)
    v = 0.15 + 0.1 * np.sin(0.05 * t + seed) + 0.02 * rng.standard_normal(len(t))
    w = 0.4 * np.sin(0.13 * t + 2.0 * seed)
    odometry = np.stack([v, w], 1)
    truth, _ = motion.integrate_twists(t, motion.scale_twists(odometry, scales))
    robot = SimpleNamespace(number=number, gt_times=t, gt_poses=truth)
    return robot, SimpleNamespace(odom_times=t, odom_twist=odometry)


@pytest.mark.parametrize('scales', [(0.93, 0.9, 0.0, 0.0), (1.0, 1.0, 0.0, 0.0),
                                    (1.08, 0.95, 0.0, 0.0), (1.04, 0.9, -1.1, -0.04),
                                    (0.97, 1.05, 0.3, 0.03)])
def test_odometry_scales_recover_the_true_scales(scales):
    robots, extras = [], {}
    for number in (1, 2, 3):
        robot, odom = _robot_and_odometry(number, scales, number)
        robots.append(robot)
        extras[number] = odom
    dataset = SimpleNamespace(robots=robots)
    speed, yaw, per_yaw_rate, veer = odometry_scales(dataset, extras, [1, 2, 3], 0.0)
    assert speed == pytest.approx(scales[0], rel=2e-3)
    assert yaw == pytest.approx(scales[1], rel=2e-3)
    assert veer == pytest.approx(scales[3], abs=1e-3)
    # the true distance of a window is its chord: shorter than the arc in turns (about
    # 0.2 % at 0.4 rad/s over 0.5 s), which leans a little on the speed loss in turns
    assert per_yaw_rate == pytest.approx(scales[2], abs=1e-2)
    # with the scales applied the windows of integrated odometry match the truth
    errors = window_samples(dataset, extras, [1, 2, 3], 2.0, 0.0,
                            (speed, yaw, per_yaw_rate, veer)).errors
    raw = window_samples(dataset, extras, [1, 2, 3], 2.0, 0.0).errors
    assert np.sqrt(np.mean(errors ** 2)) < max(0.05 * np.sqrt(np.mean(raw ** 2)), 1e-3)


def test_scale_twists_is_scale_motion_of_each_twist():
    rng = np.random.default_rng(3)
    twists = np.column_stack([rng.uniform(-0.2, 0.3, 50), rng.uniform(-1.0, 1.0, 50)])
    scales = (1.04, 0.9, -1.1, -0.04)
    batch = motion.scale_twists(twists, scales)
    for (v, w), (v_true, w_true) in zip(twists, batch):
        delta = motion.delta_from_twist(v, w, 0.02)
        # the scaled arc is the arc of the scaled twist up to the chord's direction:
        # (1 - yaw scale) dtheta / 2 of the step, here below 2e-5 m
        scaled = motion.scale_motion(delta, 0.02, *scales)
        np.testing.assert_allclose(scaled, motion.delta_from_twist(v_true, w_true, 0.02),
                                   atol=2e-5)
    # the speed scale is held at zero: a fast turn does not drive backwards
    assert motion.scale_twists(np.array([[0.1, 2.0]]), scales)[0, 0] == 0.0
    assert motion.scale_motion(motion.delta_from_twist(0.1, 2.0, 0.1), 0.1, *scales)[0] == 0.0
