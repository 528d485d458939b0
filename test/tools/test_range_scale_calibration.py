"""The range scale estimator (mrclam.range_calibration.fit_range_scale) and its use."""

from landmark_ros.core import range_scale
from landmark_ros.mrclam.calibrate import calibrate
from landmark_ros.mrclam.data import load_dataset, Part
from landmark_ros.mrclam.range_calibration import fit_range_scale
import numpy as np
import pytest
from test_mrclam import DATASET6

COEFFS = (0.047, -0.0044, -0.4675)
PER_M = -0.0034


def simulated(rng, n=5000, outliers=0.05, coeffs=COEFFS, per_m=PER_M, sd=0.015):
    """Return readings (r, b) and true ranges with the scale error, noise and outliers."""
    r_true = rng.uniform(1.0, 7.0, n)
    b = rng.uniform(-0.6, 0.6, n)
    p = 1.0 + coeffs[0] + coeffs[1] * b + coeffs[2] * b * b
    r = r_true * p / (1.0 - per_m * r_true) * (1.0 + sd * rng.standard_normal(n))
    bad = rng.random(n) < outliers          # heavy tail: far too short readings
    r[bad] *= rng.uniform(0.4, 0.9, bad.sum())
    return r, b, r_true


@pytest.mark.parametrize('seed', range(5))
def test_fit_recovers_the_coefficients_despite_outliers(seed):
    rng = np.random.default_rng(seed)
    r, b, r_true = simulated(rng)
    coeffs, per_m, sigma = fit_range_scale(r, b, r_true)
    assert np.all(np.abs(np.subtract(coeffs, COEFFS)) < [0.003, 0.003, 0.01])
    assert per_m == pytest.approx(PER_M, abs=0.0008)
    assert sigma == pytest.approx(0.015, rel=0.1)
    # The corrected readings of the inliers are unbiased.
    z_c, _ = range_scale.correct(np.stack([r, b], axis=1), coeffs, per_m)
    assert abs(np.median(z_c[:, 0] / r_true - 1.0)) < 0.002


def test_fit_of_a_sensor_without_scale_error_is_the_identity():
    rng = np.random.default_rng(9)
    r, b, r_true = simulated(rng, outliers=0.0, coeffs=(0.0, 0.0, 0.0), per_m=0.0)
    coeffs, per_m, _ = fit_range_scale(r, b, r_true)
    assert np.all(np.abs(coeffs) < [0.002, 0.002, 0.008])
    assert abs(per_m) < 0.0006


def test_plain_least_squares_would_be_pulled_by_the_tail():
    """Mutation check: without the Huber weights the outliers bias the fit."""
    rng = np.random.default_rng(4)
    r, b, r_true = simulated(rng, outliers=0.1)
    coeffs, _, _ = fit_range_scale(r, b, r_true)
    plain, _, _ = fit_range_scale(r, b, r_true, iterations=1)
    assert abs(coeffs[0] - COEFFS[0]) < 0.003
    assert abs(plain[0] - COEFFS[0]) > 0.01


def test_too_few_readings_is_an_error():
    with pytest.raises(ValueError, match='at least 4'):
        fit_range_scale([1.0, 2.0], [0.0, 0.1], [1.0, 2.0])


@pytest.mark.skipif(not DATASET6.is_dir(), reason=f'no MRCLAM dataset at {DATASET6}')
def test_dataset6_range_error_depends_on_the_bearing_and_carries_over():
    dataset = load_dataset(DATASET6)
    middle = dataset.duration / 2.0
    halves = [calibrate(dataset, part=Part(end_s=middle)),
              calibrate(dataset, part=Part(start_s=middle))]
    for cal in halves:
        assert cal.range_scale_coeffs[2] < -0.3   # shorter off the optical axis
        assert cal.scale['short_tail']['raw_beyond_3m'] > 0.05
        assert cal.scale['short_tail']['corrected_beyond_3m'] < 0.005
    difference = np.subtract(halves[0].range_scale_coeffs, halves[1].range_scale_coeffs)
    assert np.all(np.abs(difference) < [0.005, 0.005, 0.02])
    values = halves[0].localizer_values()
    assert values['range_scale_coeffs'] == halves[0].range_scale_coeffs
    assert values['range_stddev'] == halves[0].range_stddev
    # the localizer estimates each robot's own scale: its prior is the spread of the
    # robots' scales (the same in both halves), and the range bias (the same error) is 0
    assert values['range_bias_stddev'] == 0.0
    assert values['range_scale_state_stddev'] == halves[0].range_scale_state_stddev
    states = [cal.range_scale_state_stddev for cal in halves]
    assert 0.005 < min(states) and max(states) < 0.02 and abs(states[0] - states[1]) < 0.003


def test_range_noise_fit_is_exact_on_model_spreads():
    from landmark_ros.mrclam.range_calibration import fit_range_noise
    r = np.linspace(0.5, 6.0, 10)
    a, k, c = 0.012, 0.008, 0.0015
    sigma = np.sqrt(a * a + (k * r) ** 2 + (c * r * r) ** 2)
    fitted = fit_range_noise(r, sigma, np.full(10, 1000))
    np.testing.assert_allclose(fitted, (a, k, c), rtol=1e-8)
    # Without a quadratic part in the data, none is fitted (non-negative least squares).
    fitted = fit_range_noise(r, np.sqrt(a * a + (k * r) ** 2), np.full(10, 1000))
    np.testing.assert_allclose(fitted, (a, k, 0.0), rtol=1e-8, atol=1e-9)
    # Two bins: only a and k.
    assert fit_range_noise(r[:2], sigma[:2], [10, 10])[2] == 0.0
    with pytest.raises(ValueError, match='no range bin'):
        fit_range_noise([], [], [])


@pytest.mark.parametrize('seed', range(3))
def test_range_noise_calibration_recovers_known_coefficients(seed):
    # Residuals drawn from the model, binned by range and fitted as calibrate does.
    from landmark_ros.mrclam.calibrate import central_sigma
    from landmark_ros.mrclam.range_calibration import fit_range_noise, range_noise_bins
    rng = np.random.default_rng(seed)
    a, k, c = 0.012, 0.008, 0.0015
    r = rng.uniform(0.5, 6.0, 40000)
    residuals = rng.normal(0.0, np.sqrt(a * a + (k * r) ** 2 + (c * r * r) ** 2))
    bins = range_noise_bins(r, residuals, central_sigma, bins=12)
    assert [b['n'] for b in bins] == [40000 // 12 + (i < 40000 % 12) for i in range(12)]
    assert all(b['low'] <= b['range'] <= b['high'] for b in bins)
    fa, fk, fc = fit_range_noise([b['range'] for b in bins], [b['robust_sd'] for b in bins],
                                 [b['n'] for b in bins])
    model = np.sqrt(fa ** 2 + (fk * r) ** 2 + (fc * r * r) ** 2)
    truth = np.sqrt(a * a + (k * r) ** 2 + (c * r * r) ** 2)
    assert np.max(np.abs(model / truth - 1.0)) < 0.06
    assert fc == pytest.approx(c, rel=0.3)
    assert fa == pytest.approx(a, rel=0.2)


def test_scale_spread_is_the_rms_of_the_robots_relative_errors():
    from landmark_ros.mrclam.calibrate import _scale_spread
    rng = np.random.default_rng(3)
    scales = np.array([-0.012, 0.013, -0.01, 0.002])
    robot = np.repeat(np.arange(4), 4000)
    true = rng.uniform(1.0, 6.0, len(robot))
    error = np.take(scales, robot) * true + 0.01 * rng.standard_normal(len(robot))
    e = {'robot': robot, 'range': true + error, 'range_error': error}
    spread = _scale_spread(e, np.full(len(robot), 0.01))
    assert spread == pytest.approx(np.sqrt(np.mean(scales ** 2)), rel=0.05)


def test_bearing_scale_spread_recovers_each_robots_lens():
    from landmark_ros.mrclam.range_calibration import bearing_scale_spread
    rng = np.random.default_rng(8)
    slopes = np.array([0.012, -0.038, 0.0, 0.015])
    robot = np.repeat(np.arange(4), 3000)
    true = rng.uniform(1.0, 6.0, len(robot))
    b = rng.uniform(-0.5, 0.5, len(robot))
    scale = 1.0 + 0.004 * (robot - 1.5) + np.take(slopes, robot) * b
    reading = true * scale * (1.0 + 0.012 * rng.standard_normal(len(robot)))
    e = {'robot': robot, 'range': reading, 'range_error': reading - true, 'bearing': b}
    spread, per_robot = bearing_scale_spread(e)
    np.testing.assert_allclose([per_robot[i] for i in range(4)], slopes, atol=0.003)
    assert spread == pytest.approx(np.sqrt(np.mean(slopes ** 2)), rel=0.05)
    # a robot with too few sightings is left out; no lens, no spread
    flat = dict(e, range=true * (1.0 + 0.012 * rng.standard_normal(len(robot))))
    flat['range_error'] = flat['range'] - true
    assert bearing_scale_spread(flat)[0] < 0.002
    assert bearing_scale_spread(e, min_sightings=3001) == (0.0, {})


def test_a_scale_error_model_in_the_params_file_is_kept_by_the_folds():
    from dataclasses import replace
    from landmark_ros.mrclam.calibrate import Calibration
    from landmark_ros.mrclam.config import load_config
    from landmark_ros.mrclam.crossval import calibrated_config
    cal = Calibration(100, {}, [], 1, [], 0.02, 0.001, 0.01, 0.03, 0.005, 0.04, 0.006, {},
                      range_scale_state_stddev=0.009)
    config = load_config()
    assert config.observer.range_scale_bias_stddev == 0.0
    offset = calibrated_config(config, cal).observer
    assert (offset.range_bias_stddev, offset.range_scale_bias_stddev) == (0.03, 0.0)
    scale_config = replace(config, observer=replace(config.observer,
                                                    range_scale_bias_stddev=0.01))
    scale = calibrated_config(scale_config, cal).observer
    assert (scale.range_bias_stddev, scale.range_scale_bias_stddev) == (0.0, 0.009)
    assert scale.bearing_bias_stddev == offset.bearing_bias_stddev == 0.005
