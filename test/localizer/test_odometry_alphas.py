"""The odometry alphas: the fit recovers known alphas against a noisy reference."""

import math
from types import SimpleNamespace

from landmark_ros.localizer import motion
from landmark_ros.mrclam.localize_data import (fit_alphas, reference_floor, robot_halves,
                                               window_nees, window_samples)
import numpy as np
import pytest

WINDOWS_S = (2.0, 5.0, 10.0, 20.0)
ROBOTS = (1, 2, 3, 4, 5)


def test_reference_floor_by_hand():
    # start at (1, 2) facing +y, end 1 m ahead: the motion is (1, 0, 0) in the start's
    # frame. Start heading error e: the end appears at (cos e, -sin e), so d_y errs by
    # -e and the turn by -e; position errors of either end move (d_x, d_y) one for one.
    s, s_th = 0.002, 0.003
    F = reference_floor([[1.0, 2.0, math.pi / 2]], [[1.0, 3.0, math.pi / 2]], (s, s, s_th))
    expected = np.array([[2 * s ** 2, 0.0, 0.0],
                         [0.0, 2 * s ** 2 + s_th ** 2, s_th ** 2],
                         [0.0, s_th ** 2, 2 * s_th ** 2]])
    np.testing.assert_allclose(F[0], expected, rtol=1e-12, atol=1e-20)


def _numerical_jacobian(f, x, eps=1e-7):
    J = np.zeros((3, 3))
    for k in range(3):
        step = np.zeros(3)
        step[k] = eps
        J[:, k] = (f(x + step) - f(x - step)) / (2 * eps)
    return J


def test_reference_floor_is_the_first_order_covariance_of_between():
    rng = np.random.default_rng(0)
    stddev = (0.002, 0.005, 0.004)  # unequal axes: the start heading matters
    Sigma = np.diag(np.square(stddev))
    starts = np.column_stack([rng.uniform(-3, 3, (8, 2)), rng.uniform(-3, 3, 8)])
    ends = np.column_stack([rng.uniform(-3, 3, (8, 2)), rng.uniform(-3, 3, 8)])
    F = reference_floor(starts, ends, stddev)
    assert F.shape == (8, 3, 3)
    for a, b, F_w in zip(starts, ends, F):
        J_d_gs = _numerical_jacobian(lambda x: motion.between(x, b), a)
        J_d_ge = _numerical_jacobian(lambda x: motion.between(a, x), b)
        np.testing.assert_allclose(F_w, J_d_gs @ Sigma @ J_d_gs.T + J_d_ge @ Sigma @ J_d_ge.T,
                                   rtol=1e-6, atol=1e-14)


def _sample_robot(number, alphas, reference_stddev, seed, duration_s=900.0, steps_s=(0.015,),
                  period_s=0.0):
    """
    Return a robot and its odometry: the true motion is the odometry's plus model noise.

    Each step's true motion is the odometry's plus a draw of the odometry model with
    ``alphas`` (``motion.odometry_noise_terms``, scaled by ``motion.step_noise_scale``
    with ``period_s``); the steps last one of ``steps_s`` [s] each, drawn at random;
    the ground truth is the true path plus white noise of ``reference_stddev``.
    """
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.choice(steps_s, int(duration_s / min(steps_s))))
    t = np.concatenate([[0.0], t[t < duration_s]])
    # commanded twists held for 1 to 6 s: straight, turning in place, or an arc (the
    # three make a1 to a4 separable)
    kinds = np.array([[0.15, 0.0], [0.0, 0.5], [0.1, 0.3]])
    ends = np.cumsum(rng.uniform(1.0, 6.0, int(duration_s)))
    segment = kinds[rng.integers(0, 3, len(ends))] * rng.choice([1.0, -1.0], (len(ends), 2))
    segment[:, 0] = np.abs(segment[:, 0])
    twists = segment[np.searchsorted(ends, t)]
    _, deltas = motion.integrate_twists(t, twists)
    Q = np.einsum('i,kijl->kjl', np.asarray(alphas), motion.odometry_noise_terms(deltas))
    Q *= motion.step_noise_scale(np.diff(t), period_s)[:, None, None]
    vals, vecs = np.linalg.eigh(Q)
    noise = np.einsum('kij,kj->ki', vecs,
                      np.sqrt(np.clip(vals, 0.0, None)) * rng.standard_normal(deltas.shape))
    truth = np.zeros((len(t), 3))
    for k, delta in enumerate(deltas + noise):
        truth[k + 1] = motion.compose(truth[k], delta)
    measured = truth + rng.standard_normal(truth.shape) * np.asarray(reference_stddev)
    robot = SimpleNamespace(number=number, gt_times=t, gt_poses=measured)
    return robot, SimpleNamespace(odom_times=t, odom_twist=twists)


ALPHAS = np.array([0.5, 0.2, 0.1, 0.01])
STDDEV = (0.005, 0.005, 0.005)


@pytest.fixture(scope='module')
def team():
    """Five robots of 15 min with ALPHAS, a reference with STDDEV of white noise."""
    robots, extras = [], {}
    for number in ROBOTS:
        robot, odom = _sample_robot(number, ALPHAS, STDDEV, 10 + number)
        robots.append(robot)
        extras[number] = odom
    return SimpleNamespace(robots=robots), extras


def test_fit_recovers_known_alphas_against_a_noisy_reference(team):
    alphas, stddev = ALPHAS, STDDEV
    dataset, extras = team
    samples = window_samples(dataset, extras, ROBOTS, WINDOWS_S, 0.0, (1.0, 1.0), stddev)
    assert samples.errors.shape[1:] == (3,) and samples.floors.shape[1:] == (3, 3)
    assert sorted(set(samples.lengths.tolist())) == list(WINDOWS_S)
    fitted = fit_alphas(samples)
    # five robots of 15 min, as MRCLAM: over seeds the fit spreads by about 15 %
    np.testing.assert_allclose(fitted, alphas, rtol=0.25)
    for length in WINDOWS_S:
        one = window_samples(dataset, extras, ROBOTS, length, 0.0, (1.0, 1.0), stddev)
        assert 2.4 < window_nees(fitted, one) < 3.6


def test_ignoring_the_reference_noise_inflates_the_alphas(team):
    alphas = ALPHAS
    dataset, extras = team
    samples = window_samples(dataset, extras, ROBOTS, 2.0, 0.0, (1.0, 1.0))
    assert np.all(samples.floors == 0.0)
    fitted = fit_alphas(samples)
    # the 2 s windows' reference noise is taken up by the odometry's alphas
    assert fitted[1] > 1.5 * alphas[1] or fitted[2] > 1.5 * alphas[2]


def test_robot_halves_prefers_the_own_model_of_a_robot_that_keeps_it():
    # robot 1's odometry is four times as noisy as the others' over the whole run: its
    # own model, fitted on one half, scores nearer 3 on the other than the pooled one.
    robots, extras = [], {}
    for number, alphas in ((1, 4.0 * ALPHAS), (2, ALPHAS), (3, ALPHAS)):
        robot, odom = _sample_robot(number, alphas, STDDEV, 30 + number, duration_s=600.0)
        robots.append(robot)
        extras[number] = odom
    entries = robot_halves(SimpleNamespace(robots=robots), extras, 0.0, (5.0, 20.0), STDDEV)
    assert [(e['fitted_on'], e['robot']) for e in entries] == [
        ('first', 1), ('first', 2), ('first', 3), ('second', 1), ('second', 2), ('second', 3)]
    for entry in entries:
        own = np.mean(list(entry['nees_own'].values()))
        pooled = np.mean(list(entry['nees_pooled'].values()))
        assert abs(own - 3.0) < abs(pooled - 3.0)
        if entry['robot'] == 1:  # the pooled model is too narrow for robot 1
            assert pooled > 4.0 and entry['alphas'][0] > 2.0 * ALPHAS[0]
        else:  # and too wide for the others
            assert pooled < 2.5


def test_alphas_per_period_carry_over_to_other_odometry_stamps():
    # The odometry error is white in time. Robot 1 logs every 10 ms, robot 2 every 10 or
    # 21 ms with some 0.3 s gaps (as MRCLAM's robots differ): with the alphas per period
    # (odometry_alphas_period_s), the fit on robot 1 holds on robot 2; per step, the
    # long steps of robot 2 get far too much variance.
    period = 0.01
    one, odom_one = _sample_robot(1, ALPHAS, STDDEV, 41, 600.0, (0.01,), period)
    two, odom_two = _sample_robot(2, ALPHAS, STDDEV, 42, 600.0,
                                  (0.01,) * 30 + (0.021,) * 12 + (0.3,), period)
    dataset = SimpleNamespace(robots=[one, two])
    extras = {1: odom_one, 2: odom_two}
    nees, fits = {}, {}
    for p in (period, 0.0):
        fitted = fits[p] = fit_alphas(window_samples(dataset, extras, [1], WINDOWS_S, 0.0,
                                                     (1.0, 1.0), STDDEV, period_s=p))
        nees[p] = [window_nees(fitted, window_samples(dataset, extras, [2], w, 0.0,
                                                      (1.0, 1.0), STDDEV, period_s=p))
                   for w in (5.0, 20.0)]
    # at the period the alphas describe, both models are one
    np.testing.assert_allclose(fits[period], fits[0.0], rtol=1e-6)
    assert all(2.3 < v < 3.8 for v in nees[period]), nees
    assert all(v < 1.5 for v in nees[0.0]), nees
