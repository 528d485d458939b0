"""The per-source dependent parts of landmarks updated by bearing-only views."""

import math

from landmark_ros.core.partial import BEARING, RANGE, update, Views
from landmark_ros.fuser.fuser import Fuser
from landmark_ros.fuser.partial_sources import MIXED, SourceLedger
from landmark_ros.pipeline.config import FuserConfig
from landmark_ros.pipeline.partial_rows import PartialObservations
import numpy as np
import pytest
from scipy.stats import chi2

S = 1_000_000_000
VIEWS = ['/r1/partial_observations', '/r2/partial_observations', '/r3/partial_observations']


def _spd(rng, scale):
    A = rng.normal(size=(2, 2)) * scale
    return A @ A.T + np.eye(2) * scale ** 2 * 0.2


def test_the_ledger_splits_the_update_by_source():
    rng = np.random.default_rng(1)
    parts = {MIXED: _spd(rng, 0.05), 'a': _spd(rng, 0.08), 'b': _spd(rng, 0.06)}
    P_dep = sum(parts.values())
    P = P_dep + _spd(rng, 0.03)
    m = np.array([3.0, 1.0])
    ledger = SourceLedger()
    ledger.keep(7, dict(parts))
    shared = ledger.shared_part(7, 'a', P_dep)
    np.testing.assert_allclose(shared, parts[MIXED] + parts['a'])
    s = np.array([[0.0, 0.0, 0.2]])
    view = Views(BEARING, s, np.zeros((1, 3, 3)), [math.atan2(1.0, 3.0) - 0.2 + 0.01],
                 0.01 ** 2, 0.005 ** 2)
    result = update(m, P, view, shared, 'split_covariance_intersection')
    new_dep, new = ledger.book(7, 'a', P_dep, result)
    L, w = result.L[0], result.omega[0]
    np.testing.assert_allclose(new['b'], L @ parts['b'] @ L.T, atol=1e-15)
    np.testing.assert_allclose(new[MIXED], L @ parts[MIXED] @ L.T / w, atol=1e-15)
    np.testing.assert_allclose(new[MIXED] + new['a'], result.P_m_dep[0], atol=1e-15)
    np.testing.assert_allclose(new_dep, sum(new.values()), atol=1e-15)
    assert np.all(np.linalg.eigvalsh(result.P_m[0] - new_dep) > -1e-15)   # ind part PSD
    assert np.all(np.linalg.eigvalsh(new['a']) > -1e-15)
    # a map whose dependent part moved on (a range-bearing row): all of it mixed again
    np.testing.assert_allclose(ledger.shared_part(7, 'b', P_dep * 1.1), P_dep * 1.1)
    ledger.keep(7, new)
    np.testing.assert_allclose(ledger.shared_part(7, 'b', new_dep), new[MIXED] + new['b'])
    ledger.forget(7)
    np.testing.assert_allclose(ledger.shared_part(7, 'b', new_dep), new_dep)


def _run(rng, source_correlation, kind=BEARING):
    """
    Return the NEES and the covariance's trace of one landmark from three robots.

    Each robot has its own bearing bias (0.03 rad, constant: the dependent part) and
    looks from 20 poses around the landmark (white noise 0.01 rad, poses known to 1 cm).
    """
    m_true = np.array([2.0, 3.0])
    f = Fuser(FuserConfig(fusion='split_covariance_intersection',
                          source_correlation=source_correlation), [], partial_sources=VIEWS)
    P_s = np.diag([1e-4, 1e-4, 1e-6])
    bias = rng.normal(0.0, 0.03, len(VIEWS))
    for k in range(60):
        r = k % len(VIEWS)
        angle = rng.uniform(0, 2 * np.pi)
        s = np.array([*(m_true + rng.uniform(2, 5) * np.array([np.cos(angle), np.sin(angle)])),
                      rng.uniform(-np.pi, np.pi)])
        if kind == BEARING:
            y = math.atan2(*(m_true - s[:2])[::-1]) - s[2] + bias[r] + rng.normal(0, 0.01)
            R, R_bias = 0.01 ** 2, 0.03 ** 2
        else:
            y = np.hypot(*(m_true - s[:2])) * (1.0 + bias[r]) + rng.normal(0, 0.01)
            R, R_bias = 0.01 ** 2, (0.03 * 3.5) ** 2
        views = Views(kind, s[None] + rng.multivariate_normal(np.zeros(3), P_s)[None],
                      P_s[None], [y], R, R_bias)
        cols = PartialObservations(np.array([1]), views, np.array([k])).columns()
        f.add_partial_observations(VIEWS[r], (k + 1) * S, cols)
        f.fuse_queued()
    _, m, P, _, _ = f.snapshot()
    d = m[0] - m_true
    return d @ np.linalg.solve(P[0], d), np.trace(P[0])


def test_bearing_only_views_of_independent_robots_stay_conservative_and_tighter():
    """
    Monte Carlo: the ledger's ANEES is not above its interval, its covariance smaller.

    Split CI inside a source still bounds the views' shared bias for any correlation
    (both ANEES about 0.5 here); the ledger only stops inflating the other sources'.
    """
    out = {}
    for correlation in ('independent', 'unknown'):
        rng = np.random.default_rng(5)
        out[correlation] = np.array([_run(rng, correlation) for _ in range(60)])
    nees, trace = out['independent'].T
    high = chi2.ppf(0.9995, 2 * len(nees)) / len(nees)
    assert nees.mean() <= high, nees.mean()
    shared = out['unknown'][:, 1]
    assert np.mean(trace) < 0.8 * np.mean(shared), (trace.mean(), shared.mean())


def test_range_only_views_keep_every_dependent_part_shared():
    """Range-only views take the whole dependent part, whatever the source correlation."""
    a = [_run(np.random.default_rng(3), c, RANGE) for c in ('independent', 'unknown')]
    assert a[0] == pytest.approx(a[1], rel=1e-12)
