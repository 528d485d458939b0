"""Tests of pipeline.rows: the landmark row checks and the fast covariance range test."""

from collections import Counter

from conftest import random_spd
from landmark_ros.pipeline.rows import landmark_row_problems, MAX_ID
import numpy as np
import pytest


# --- landmark_row_problems -----------------------------------------------------------------------

def _landmark_rows(rng, count=6):
    ids = np.arange(count, dtype=np.int64) + 10
    m = rng.uniform(-10, 10, (count, 2))
    P = random_spd(rng, 2, count, eps=0.01)
    P_dep = 0.4 * P
    return ids, m, P, P_dep


def test_landmark_rows_valid(rng, no_warnings):
    ids, m, P, P_dep = _landmark_rows(rng)
    P_dep[0] = 0.0          # no dependent part
    P_dep[1] = P[1]         # all of it dependent
    valid, reasons = landmark_row_problems(ids, m, P, P_dep)
    assert valid.all() and reasons == Counter()


def _set(array, index, value):
    array[index] = value


@pytest.mark.parametrize('change, reason', [
    (lambda ids, m, P, D: _set(m, (2, 0), np.nan), 'landmark_nonfinite'),
    (lambda ids, m, P, D: _set(m, (2, 1), -np.inf), 'landmark_nonfinite'),
    (lambda ids, m, P, D: _set(P, (2, 1, 1), np.inf), 'landmark_nonfinite'),
    (lambda ids, m, P, D: _set(D, (2, 0, 1), np.nan), 'landmark_nonfinite'),
    (lambda ids, m, P, D: _set(ids, 2, -3), 'invalid_id'),
    (lambda ids, m, P, D: _set(ids, 2, MAX_ID + 1), 'invalid_id'),
    (lambda ids, m, P, D: _set(P, (2, 0, 1), P[2, 0, 1] + 0.5), 'covariance_asymmetric'),
    (lambda ids, m, P, D: _set(P, 2, [[1.0, 2.0], [2.0, 1.0]]), 'covariance_not_psd'),
    (lambda ids, m, P, D: _set(P, 2, -np.eye(2)), 'covariance_not_psd'),
    (lambda ids, m, P, D: (_set(P, 2, [[1.0, 1.0], [1.0, 1.0]]), _set(D, 2, 0.0)),
     'covariance_singular'),
    (lambda ids, m, P, D: (_set(P, 2, np.zeros((2, 2))), _set(D, 2, 0.0)),
     'covariance_singular'),
    (lambda ids, m, P, D: (_set(P, 2, np.diag([1.0, 1e-13])), _set(D, 2, 0.0)),
     'covariance_singular'),
    (lambda ids, m, P, D: _set(D, 2, -0.1 * np.eye(2)), 'dependent_part_invalid'),
    (lambda ids, m, P, D: _set(D, 2, 2.0 * P[2]), 'dependent_part_invalid'),
    (lambda ids, m, P, D: _set(D, 2, P[2] + np.diag([0.0, 1e-3])), 'dependent_part_invalid'),
    (lambda ids, m, P, D: _set(D, (2, 0, 1), D[2, 0, 1] + 0.1), 'dependent_part_invalid'),
])
def test_landmark_rows_each_reason(change, reason, rng, no_warnings):
    ids, m, P, P_dep = _landmark_rows(rng)
    change(ids, m, P, P_dep)
    valid, reasons = landmark_row_problems(ids, m, P, P_dep)
    assert valid.tolist() == [True, True, False, True, True, True]
    assert reasons == Counter({reason: 1})


def test_landmark_rows_small_but_regular_covariances_are_valid(no_warnings):
    # The singularity test is relative to the scale of the matrix; the accepted range
    # of variances is core.gaussian's [MIN_VARIANCE, MAX_VARIANCE].
    for s in (1e-11, 1e-8, 1.0, 1e8, 1e11):
        P = np.array([[[2.0, 0.5], [0.5, 1.0]]]) * s
        valid, reasons = landmark_row_problems(np.array([1]), np.zeros((1, 2)), P, 0.5 * P)
        assert valid.all() and not reasons, s
    for s, reason in ((1e-150, 'covariance_too_small'), (1e150, 'covariance_too_large')):
        P = np.array([[[2.0, 0.5], [0.5, 1.0]]]) * s
        valid, reasons = landmark_row_problems(np.array([1]), np.zeros((1, 2)), P, 0.5 * P)
        assert not valid.any() and reasons == Counter({reason: 1}), s


def test_landmark_rows_ill_conditioned_covariance_is_rejected(no_warnings):
    P = np.array([[[1.0, 1.0 - 1e-11], [1.0 - 1e-11, 1.0]]])
    valid, reasons = landmark_row_problems(np.array([1]), np.zeros((1, 2)), P, 0.0 * P)
    assert not valid.any() and reasons == Counter(covariance_ill_conditioned=1)


def test_landmark_rows_precedence(rng, no_warnings):
    ids, m, P, P_dep = _landmark_rows(rng, 7)
    m[0, 0] = np.nan
    ids[0] = -1                               # nonfinite first
    ids[1] = -1
    P[1] = -np.eye(2)                         # invalid id before the covariance
    P[2, 0, 1] += 5.0                         # asymmetric (and not PSD) -> asymmetric
    P[3] = [[1.0, 1.0], [1.0, 1.0]]           # singular; its dependent part now too large
    valid, reasons = landmark_row_problems(ids, m, P, P_dep)
    assert valid.tolist() == [False] * 4 + [True] * 3
    assert reasons == Counter(landmark_nonfinite=1, invalid_id=1, covariance_asymmetric=1,
                              covariance_singular=1)


def test_landmark_rows_huge_covariances_without_warnings(no_warnings):
    P = np.array([np.eye(2) * 1e200, np.eye(2) * 1e300, [[1e200, 1e199], [1e199, 1e200]]])
    valid, reasons = landmark_row_problems(np.arange(3), np.zeros((3, 2)), P, 0.5 * P)
    assert not valid.any() and reasons == Counter(covariance_too_large=3)


# --- range_status ----------------------------------------------------------------------------

def test_range_status_fast_path_agrees_with_the_core(rng):
    from landmark_ros.core.covariance import covariance_range_status
    from landmark_ros.pipeline.rows import range_status
    scale = 10.0 ** rng.uniform(-14, 14, (4000, 1, 1))
    P = random_spd(rng, 2, 4000, eps=10.0 ** rng.uniform(-12, 0, (4000, 1, 1))) * scale
    P[:50] = [[1.0, 1.0 - 1e-10], [1.0 - 1e-10, 1.0]]          # ill conditioned
    expected = np.atleast_1d(covariance_range_status(P))
    assert 0 < (expected == 0).sum() < len(P)                   # both kinds present
    np.testing.assert_array_equal(range_status(P, np.ones(len(P), bool)), expected)
