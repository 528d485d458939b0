"""Tests of observer.rows: observation noise, row checks, observation rows to landmarks."""

from collections import Counter

from conftest import random_observations, random_poses, random_spd
from landmark_ros.core.covariance import COVARIANCE_RANGE_PROBLEMS, covariance_range_status
from landmark_ros.core.landmarks import landmark_to_world_dependent
from landmark_ros.core.sensors import MIN_RANGE
from landmark_ros.observer.rows import (bias_covariance, landmarks_from_rows, observation_noise,
                                        row_problems)
from landmark_ros.pipeline.limits import MAX_COORDINATE
from landmark_ros.pipeline.rows import MAX_ID
import numpy as np
import pytest


# --- observation_noise ---------------------------------------------------------------------------

def test_noise_without_noise_columns_is_one_shared_matrix():
    R = observation_noise({'range': np.array([1.0, 2.0, 3.0]), 'bearing': np.zeros(3)},
                          0.01, 0.0004)
    assert R.shape == (2, 2)
    np.testing.assert_array_equal(R, [[0.01, 0.0], [0.0, 0.0004]])


def test_noise_per_row_with_nan_falling_back_to_defaults(no_warnings):
    nan = np.nan
    columns = {'range': np.ones(4), 'bearing': np.zeros(4),
               'range_variance': np.array([0.04, nan, 0.09, nan]),
               'bearing_variance': np.array([nan, 0.001, 0.002, nan]),
               'range_bearing_covariance': np.array([0.001, nan, -0.002, nan])}
    R = observation_noise(columns, 0.01, 0.0004)
    expected = np.array([[[0.04, 0.001], [0.001, 0.0004]],
                         [[0.01, 0.0], [0.0, 0.001]],
                         [[0.09, -0.002], [-0.002, 0.002]],
                         [[0.01, 0.0], [0.0, 0.0004]]])
    np.testing.assert_array_equal(R, expected)


@pytest.mark.parametrize('present', ['range_variance', 'bearing_variance',
                                     'range_bearing_covariance'])
def test_noise_with_one_column_uses_defaults_for_the_others(present):
    values = {'range_variance': 0.5, 'bearing_variance': 0.25, 'range_bearing_covariance': 0.1}
    columns = {'range': np.ones(3), present: np.full(3, values[present])}
    R = observation_noise(columns, 0.01, 0.0004)
    assert R.shape == (3, 2, 2)
    expected = np.array([[0.01, 0.0], [0.0, 0.0004]])
    index = {'range_variance': [(0, 0)], 'bearing_variance': [(1, 1)],
             'range_bearing_covariance': [(0, 1), (1, 0)]}[present]
    for i, j in index:
        expected[i, j] = values[present]
    np.testing.assert_array_equal(R, np.broadcast_to(expected, (3, 2, 2)))


# --- row_problems --------------------------------------------------------------------------------

def _rows(count=6):
    ids = np.arange(count, dtype=np.int64) * 1000
    z = np.c_[np.linspace(1.0, 20.0, count), np.linspace(-3.0, 3.0, count)]
    R = np.repeat(np.array([[[0.01, 0.001], [0.001, 0.0004]]]), count, axis=0)
    return ids, z, R


def test_row_problems_all_valid(no_warnings):
    ids, z, R = _rows()
    for noise in (R, R[0]):
        valid, reasons = row_problems(ids, z, noise)
        assert valid.tolist() == [True] * 6 and reasons == Counter()
    # The limits themselves are valid.
    ids[:2] = [0, MAX_ID]
    z[2, 0] = MIN_RANGE
    valid, reasons = row_problems(ids, z, R)
    assert valid.all() and not reasons


@pytest.mark.parametrize('change, reason', [
    (lambda ids, z, R: z.__setitem__((1, 0), np.nan), 'observation_nonfinite'),
    (lambda ids, z, R: z.__setitem__((1, 1), np.inf), 'observation_nonfinite'),
    (lambda ids, z, R: z.__setitem__((1, 0), -np.inf), 'observation_nonfinite'),
    (lambda ids, z, R: z.__setitem__((1, 0), 0.0), 'range_not_positive'),
    (lambda ids, z, R: z.__setitem__((1, 0), -2.0), 'range_not_positive'),
    (lambda ids, z, R: z.__setitem__((1, 0), MIN_RANGE / 2), 'range_not_positive'),
    (lambda ids, z, R: ids.__setitem__(1, -1), 'invalid_id'),
    (lambda ids, z, R: ids.__setitem__(1, MAX_ID + 1), 'invalid_id'),
    (lambda ids, z, R: R.__setitem__((1, 0, 0), -0.01), 'negative_variance'),
    (lambda ids, z, R: R.__setitem__((1, 1, 1), -1e-9), 'negative_variance'),
    (lambda ids, z, R: R.__setitem__((1, 1, 1), np.nan), 'noise_covariance_nonfinite'),
    (lambda ids, z, R: R.__setitem__((1, 0, 1), 0.5), 'noise_covariance_asymmetric'),
    (lambda ids, z, R: R[1].__setitem__((slice(None), slice(None)), [[0.01, 0.1], [0.1, 0.01]]),
     'noise_covariance_not_psd'),
])
def test_row_problems_each_reason(change, reason, no_warnings):
    ids, z, R = _rows()
    change(ids, z, R)
    valid, reasons = row_problems(ids, z, R)
    assert valid.tolist() == [True, False, True, True, True, True]
    assert reasons == Counter({reason: 1})


def test_row_problems_precedence_and_counts(no_warnings):
    ids, z, R = _rows(8)
    z[0] = [np.nan, 0.0]
    ids[0] = -5                       # also invalid id: counted as nonfinite only
    z[1, 0] = 0.0
    ids[1] = MAX_ID + 7               # range first
    ids[2] = -1
    R[2, 0, 0] = -1.0                 # invalid id before the noise
    R[3, 0, 0] = -1.0                 # negative variance (also not PSD)
    R[4, 0, 1] = 1.0                  # asymmetric (and not PSD when symmetrised?)
    R[5] = [[1.0, 2.0], [2.0, 1.0]]   # not PSD
    valid, reasons = row_problems(ids, z, R)
    assert valid.tolist() == [False] * 6 + [True] * 2
    assert reasons == Counter(observation_nonfinite=1, range_not_positive=1, invalid_id=1,
                              negative_variance=1, noise_covariance_asymmetric=1,
                              noise_covariance_not_psd=1)
    assert sum(reasons.values()) + valid.sum() == len(ids)


def test_row_problems_shared_noise_is_not_checked_per_row():
    ids, z, _ = _rows()
    valid, reasons = row_problems(ids, z, np.array([[0.01, 0.0], [0.0, 0.0004]]))
    assert valid.all() and not reasons


# --- landmarks_from_rows -------------------------------------------------------------------------

@pytest.mark.parametrize('per_row_noise', [False, True])
@pytest.mark.parametrize('extras', [False, True])
def test_landmarks_from_rows_matches_the_core(per_row_noise, extras, rng, no_warnings):
    count = 40
    ids = rng.integers(0, MAX_ID, count)
    z = random_observations(rng, count)
    R = random_spd(rng, 2, count, scale=0.1) if per_row_noise else np.diag([0.01, 0.0004])
    pose, P_pose = random_poses(rng), random_spd(rng, 3, scale=0.1)
    sensor_pose = np.array([0.3, -0.1, 0.2]) if extras else None
    R_bias = np.diag([0.0025, 1e-4]) if extras else None
    kept, m, P_m, P_dep, reasons = landmarks_from_rows(ids, z, R, pose, P_pose,
                                                       sensor_pose, R_bias)
    ref = landmark_to_world_dependent(pose, P_pose, z, R, R_bias, sensor_pose)
    assert kept.dtype == bool and kept.tolist() == [True] * count
    for actual, expected in zip((m, P_m, P_dep), ref):
        np.testing.assert_array_equal(actual, expected)
    assert reasons == Counter()
    assert m.shape == (count, 2) and P_m.shape == P_dep.shape == (count, 2, 2)


def test_landmarks_from_rows_with_a_pose_per_row(rng, no_warnings):
    count = 12
    ids = np.arange(count)
    z = random_observations(rng, count)
    z[3, 0] = -1.0
    R = np.diag([0.01, 0.0004])
    pose, P_pose = random_poses(rng, count), random_spd(rng, 3, count, scale=0.1)
    kept, m, P_m, P_dep, reasons = landmarks_from_rows(ids, z, R, pose, P_pose)
    assert kept.tolist() == [k != 3 for k in range(count)]
    ref = landmark_to_world_dependent(pose[kept], P_pose[kept], z[kept], R)
    for actual, expected in zip((m, P_m, P_dep), ref):
        np.testing.assert_array_equal(actual, expected)
    assert reasons == Counter(range_not_positive=1)


def test_landmarks_from_rows_drops_invalid_rows(rng, no_warnings):
    count = 10
    ids = np.arange(count, dtype=np.int64)
    z = random_observations(rng, count)
    R = random_spd(rng, 2, count, scale=0.1)
    z[1, 0] = np.nan
    z[4, 0] = 0.0
    ids[6] = -1
    R[8, 1, 1] = -1.0
    pose, P_pose = random_poses(rng), random_spd(rng, 3, scale=0.1)
    kept, m, P_m, P_dep, reasons = landmarks_from_rows(ids, z, R, pose, P_pose)
    keep = np.array([0, 2, 3, 5, 7, 9])
    np.testing.assert_array_equal(np.flatnonzero(kept), keep)
    ref = landmark_to_world_dependent(pose, P_pose, z[keep], R[keep])
    for actual, expected in zip((m, P_m, P_dep), ref):
        np.testing.assert_array_equal(actual, expected)
    assert reasons == Counter(observation_nonfinite=1, range_not_positive=1, invalid_id=1,
                              negative_variance=1)
    assert kept.sum() + sum(reasons.values()) == count


def test_landmarks_from_rows_drops_nonfinite_results_without_warnings(rng, no_warnings):
    ids = np.array([1, 2, 3, 4, 5], np.int64)
    z = np.array([[5.0, 0.1], [1e200, 0.3], [1e300, -1.0], [7.0, 2.0], [-1.0, 0.0]])
    pose, P_pose = np.array([1.0, 2.0, 0.3]), random_spd(rng, 3, scale=0.1)
    R = np.diag([0.01, 0.0004])
    R_bias = np.diag([1e-4, 1e-6])
    kept, m, P_m, P_dep, reasons = landmarks_from_rows(ids, z, R, pose, P_pose,
                                                       R_bias=R_bias)
    assert kept.tolist() == [True, False, False, True, False]
    assert reasons == Counter(result_nonfinite=2, range_not_positive=1)
    assert np.all(np.isfinite(m)) and np.all(np.isfinite(P_m)) and np.all(np.isfinite(P_dep))
    ref = landmark_to_world_dependent(pose, P_pose, z[[0, 3]], R, R_bias)
    for actual, expected in zip((m, P_m, P_dep), ref):
        np.testing.assert_array_equal(actual, expected)
    # Every row dropped: empty outputs of the right shapes.
    kept, m, P_m, P_dep, reasons = landmarks_from_rows(ids[1:3], z[1:3], R, pose, P_pose)
    assert kept.tolist() == [False, False] and m.shape == (0, 2) and P_m.shape == (0, 2, 2)
    assert P_dep.shape == (0, 2, 2) and reasons == Counter(result_nonfinite=2)


@pytest.mark.parametrize('bad', ['landmark_out_of_range', 'covariance_too_small',
                                 'covariance_too_large', 'covariance_ill_conditioned'])
def test_landmarks_from_rows_result_checks_match_the_core(rng, no_warnings, bad):
    # One row that fails one result check among good rows, at a random place; the
    # expected rows come from the core's checks, not from the observer's fast path.
    count = 12
    pose = random_poses(rng, count)
    P_pose = np.stack([random_spd(rng, 3, scale=0.1) for _ in range(count)])
    z = np.column_stack([rng.uniform(1.0, 20.0, count), rng.uniform(-np.pi, np.pi, count)])
    R = np.tile(np.diag([0.01, 0.0004]), (count, 1, 1))
    i = rng.integers(count)
    if bad == 'landmark_out_of_range':
        pose[i], z[i] = [MAX_COORDINATE - 1.0, 0.0, 0.0], [5.0, 0.0]
    else:
        P_pose[i] = 0.0
        z[i], R[i] = {'covariance_too_small': ([5.0, 0.1], np.diag([1e-20, 1e-20])),
                      'covariance_too_large': ([5.0, 0.1], np.diag([1e13, 1e-4])),
                      'covariance_ill_conditioned': ([1.0, 0.2], np.diag([1e2, 1e-10]))}[bad]
    ids = np.arange(count, dtype=np.int64)
    kept, m, P_m, P_dep, reasons = landmarks_from_rows(ids, z, R, pose, P_pose)
    m_ref, P_ref, P_dep_ref = landmark_to_world_dependent(pose, P_pose, z, R)
    status = covariance_range_status(P_ref)
    far = np.any(np.abs(m_ref) > MAX_COORDINATE, axis=1)
    good = (status == 0) & ~far
    assert np.flatnonzero(~good).tolist() == [i]
    name = bad if far[i] else COVARIANCE_RANGE_PROBLEMS[int(status[i])]
    assert name == bad and reasons == Counter({f'result_{bad}': 1})
    np.testing.assert_array_equal(kept, good)
    for actual, reference in zip((m, P_m, P_dep), (m_ref, P_ref, P_dep_ref)):
        np.testing.assert_array_equal(actual, reference[good])


def test_landmarks_from_rows_dependent_part_is_the_pose_and_bias(rng, no_warnings):
    count = 20
    ids = np.arange(count)
    z = random_observations(rng, count)
    R = np.diag([0.01, 0.0004])
    pose = random_poses(rng)
    # Exact pose, no bias: nothing dependent.
    _, _, P_m, P_dep, _ = landmarks_from_rows(ids, z, R, pose, np.zeros((3, 3)))
    np.testing.assert_array_equal(P_dep, np.zeros((count, 2, 2)))
    # The dependent part grows with the pose covariance, the total by as much.
    P_pose = random_spd(rng, 3, scale=0.1)
    _, _, P_m2, P_dep2, _ = landmarks_from_rows(ids, z, R, pose, P_pose)
    np.testing.assert_allclose(P_m2 - P_m, P_dep2, rtol=0, atol=1e-12)
    # A bias adds the same to both.
    R_bias = np.diag([0.0025, 1e-4])
    _, _, P_m3, P_dep3, _ = landmarks_from_rows(ids, z, R, pose, P_pose, R_bias=R_bias)
    np.testing.assert_allclose(P_m3 - P_m2, P_dep3 - P_dep2, rtol=0, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(P_dep3 - P_dep2)[:, -1] > 0)


def test_bias_covariance_adds_the_scale_term_per_row():
    R_bias = np.diag([0.0004, 1e-5])
    r = np.array([1.0, 2.0, 4.0])
    assert bias_covariance(R_bias, 0.0, r) is R_bias
    assert bias_covariance(None, 0.0, r) is None
    out = bias_covariance(R_bias, 1e-4, r)
    assert out.shape == (3, 2, 2)
    np.testing.assert_allclose(out[:, 0, 0], 0.0004 + 1e-4 * r ** 2, rtol=1e-12)
    np.testing.assert_array_equal(out[:, 1, 1], 1e-5)
    np.testing.assert_array_equal(out[:, 0, 1], 0.0)
    np.testing.assert_allclose(bias_covariance(None, 1e-4, r)[:, 0, 0], 1e-4 * r ** 2)


def test_landmarks_from_rows_scale_bias_grows_with_the_range(rng, no_warnings):
    count = 30
    ids = np.arange(count)
    z = random_observations(rng, count)
    R = np.diag([0.01, 0.0004])
    pose, P_pose = random_poses(rng), random_spd(rng, 3, scale=0.01)
    R_bias = np.diag([0.0009, 1e-5])
    _, _, P_m, P_dep, _ = landmarks_from_rows(ids, z, R, pose, P_pose, None, R_bias)
    _, _, P_m2, P_dep2, _ = landmarks_from_rows(ids, z, R, pose, P_pose, None, R_bias, 1e-4)
    # Added to both, along the line of sight, with variance s^2 r^2.
    np.testing.assert_allclose(P_m2 - P_m, P_dep2 - P_dep, rtol=0, atol=1e-12)
    e = landmark_to_world_dependent(pose, P_pose, z, R)[0] - pose[:2]
    added = 1e-4 * np.einsum('ni,nj->nij', e, e)
    np.testing.assert_allclose(P_dep2 - P_dep, added, rtol=1e-9, atol=1e-15)
