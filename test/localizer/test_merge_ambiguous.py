"""Rows without ID against their merged candidates (``association_merge_ambiguous``)."""

from landmark_ros.core import sensors
from landmark_ros.localizer.association import (association_probabilities, label_rows,
                                                MapAssociation)
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.localizer.localizer import Estimate, Localizer, UNKNOWN_ID
from landmark_ros.localizer.mixture import collapse
from landmark_ros.localizer.update import RANGE_BEARING
import numpy as np
import pytest


def test_association_probabilities_and_the_mixture_moments():
    S = np.array([np.eye(2) * 0.5, np.eye(2) * 0.6, np.diag([0.5, 0.9])])
    d2 = np.array([0.3, 1.2, 2.5])
    beta = association_probabilities(d2, S)
    w = np.exp(-0.5 * d2) / np.sqrt(np.linalg.det(S))
    np.testing.assert_allclose(beta, w / w.sum(), rtol=1e-12)
    # collapse: the moments of the mixture, by sampling; headings across +-pi wrap
    x_parts = np.array([[0.0, 0.0, 3.1], [2.0, 0.0, -3.1], [0.0, 1.0, 3.0]])
    P_parts = np.array([np.eye(3) * 0.01, np.eye(3) * 0.04, np.diag([0.01, 0.09, 0.02])])
    x, P = collapse(x_parts, P_parts, beta)
    rng = np.random.default_rng(3)
    k = rng.choice(3, size=400_000, p=beta)
    unwrapped = x_parts.copy()
    unwrapped[1, 2] += 2 * np.pi
    draws = unwrapped[k] + np.einsum('nij,nj->ni', np.linalg.cholesky(P_parts)[k],
                                     rng.standard_normal((len(k), 3)))
    expected = draws.mean(axis=0)
    expected[2] = (expected[2] + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(x, expected, atol=5e-3)
    np.testing.assert_allclose(P, np.cov(draws.T), atol=5e-3)
    assert np.all(np.linalg.eigvalsh(P) > 0)


def _label(m, merge):
    assoc = MapAssociation(m, np.tile(np.eye(2) * 1e-6, (len(m), 1, 1)), 'nn', 0.999,
                           take_ambiguous=True, merge_ambiguous=merge)
    z = sensors.observe(np.zeros((1, 3)), m[:1])
    return label_rows(assoc, Estimate(0, np.zeros(3), np.eye(3) * 0.25),
                      np.arange(1, len(m) + 1), np.array([UNKNOWN_ID]), z,
                      np.array([RANGE_BEARING]), np.tile(np.eye(2) * 1e-4, (1, 1, 1)))


def test_label_rows_reports_the_candidates():
    m = np.array([[3.0, 0.0], [3.0, 0.6]])
    ids, counts, merged = _label(m, True)
    assert counts['association_merged'] == 1 and ids[0] == 1  # the likeliest names it
    cand_ids, beta = merged[0]
    assert sorted(cand_ids.tolist()) == [1, 2] and beta.sum() == pytest.approx(1.0)
    assert beta[cand_ids.tolist().index(1)] > 0.5
    ids, counts, merged = _label(m, False)
    assert merged == {} and counts['association_merged'] == 0 and ids[0] == 1


def _wrong_pairing(merge):
    """Return the NEES after a robot 8 m from landmarks 0.25 rad apart sees one, 0.15 rad off."""
    cfg = LocalizerConfig(association='nn', association_take_ambiguous=True,
                          association_merge_ambiguous=merge, correlation='independent',
                          range_stddev=0.05, range_stddev_per_m=0.0, bearing_stddev=0.02)
    m = 8.0 * np.array([[1.0, 0.0], [np.cos(0.25), np.sin(0.25)]])
    loc = Localizer(cfg)
    loc.set_map(np.array([7, 9]), m, np.tile(np.eye(2) * 1e-4, (2, 1, 1)))
    truth = np.array([0.0, 0.0, 0.0])
    P0 = np.diag([0.05, 0.05, 0.17]) ** 2
    loc.initialize(0, truth + [0.0, 0.0, 0.15], P0)
    loc.add_odometry(0, twist=np.zeros(2))
    z = sensors.observe(truth[None], m[:1])  # landmark 7 seen, exactly
    loc.add_observations(1_000_000, [UNKNOWN_ID], z)
    loc.add_odometry(2_000_000, twist=np.zeros(2))
    est = loc.estimate()
    e = est.x - truth
    return float(e @ np.linalg.solve(est.P, e)), est


def test_a_pairing_the_heading_cannot_decide_does_not_make_the_pose_confident():
    nees_take, _ = _wrong_pairing(False)
    nees_merge, est = _wrong_pairing(True)
    assert nees_take > 16.0  # taken as landmark 9: the pose confident and wrong
    assert nees_merge < 7.8  # merged: inside the 95 % gate of 3 dof
    assert np.sqrt(est.P[2, 2]) > 0.05


def test_config_default_keeps_the_old_behaviour():
    assert LocalizerConfig().association_merge_ambiguous is False
    with pytest.raises((TypeError, ValueError)):
        LocalizerConfig(association_merge_ambiguous='maybe')


def test_simulated_pairs_without_ids_stay_consistent():
    from landmark_ros.eval.localization_montecarlo import run_seed
    nees, rows = run_seed(1, duration_s=30.0, hidden='merge')
    nees_ids, rows_ids = run_seed(1, duration_s=30.0)
    # every landmark has a partner 0.25 m away: twice the rows, nearly all associated
    assert rows > 1.8 * rows_ids
    assert 1.5 < nees < 4.5 and 1.5 < nees_ids < 4.5
