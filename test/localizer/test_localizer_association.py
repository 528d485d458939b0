"""The localizer's association of rows without ID (``localizer.association``)."""

import math

from landmark_ros.core import sensors
from landmark_ros.localizer import motion
from landmark_ros.localizer.association import label_rows, MapAssociation
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.localizer.localizer import Estimate, Localizer, UNKNOWN_ID
from landmark_ros.localizer.update import RANGE, RANGE_BEARING
import numpy as np
import pytest

MS = 1_000_000
# Two pairs 1.5 m apart: close enough that a loose gate would confuse them.
LANDMARKS = np.array([[4.0, 1.0], [4.0, 2.5], [-3.0, 5.0], [2.0, -4.0], [3.5, -4.0],
                      [6.0, 6.0], [-5.0, -2.0]])


def _config(association):
    return LocalizerConfig(odometry_alphas=(0.5, 2.0, 0.5, 0.1), range_stddev=0.05,
                           range_stddev_per_m=0.0, bearing_stddev=0.02,
                           initial_stddev=(0.05, 0.05, 0.02), correlation='independent',
                           association=association)


def _simulate(seed, association, hide, steps=1500):
    """Drive a Localizer; return position errors, NEES samples and the localizer."""
    rng = np.random.default_rng(seed)
    cfg = _config(association)
    loc = Localizer(cfg)
    loc.set_map(np.arange(len(LANDMARKS)) + 10, LANDMARKS,
                np.tile(np.eye(2) * 1e-6, (len(LANDMARKS), 1, 1)))
    x = np.zeros(3)
    loc.initialize(0, x + rng.normal(0, cfg.initial_stddev),
                   np.diag(np.square(cfg.initial_stddev)))
    loc.add_odometry(0, twist=np.array([0.3, 0.0]))
    errors, nees = [], []
    for k in range(steps):
        v, w = 0.3, 0.4 * math.sin(k / 200)
        d = motion.delta_from_twist(v, w, 0.02)
        Q = motion.odometry_noise(d, cfg.odometry_alphas) + np.eye(3) * 1e-14
        x = motion.compose(x, d + rng.multivariate_normal(np.zeros(3), Q))
        loc.add_odometry((k + 1) * 20 * MS, twist=np.array([v, w]))
        if k % 10 == 3:
            seen = rng.permutation(len(LANDMARKS))[:4]
            z = sensors.observe(np.tile(x, (len(seen), 1)), LANDMARKS[seen])
            z += rng.normal(0, [0.05, 0.02], z.shape)
            ids = np.full(len(seen), UNKNOWN_ID, np.int64) if hide else seen + 10
            loc.add_observations((k + 1) * 20 * MS, ids, z)
        if k > 100 and k % 5 == 0:
            est = loc.estimate()
            e = est.x - x
            e[2] = motion.wrap(e[2])
            errors.append(np.hypot(e[0], e[1]))
            nees.append(e @ np.linalg.solve(est.P, e))
    return np.array(errors), np.array(nees), loc


@pytest.mark.parametrize('method', ['nn', 'jcbb'])
def test_hidden_ids_reach_nearly_the_result_with_ids(method):
    for seed in range(3):
        err_ids, nees_ids, with_ids = _simulate(seed, method, hide=False)
        err, nees, hidden = _simulate(seed, method, hide=True)
        rows = with_ids.counters['rows_used']
        assert hidden.counters['no_id'] > 0 and with_ids.counters['no_id'] == 0
        # nearly every row found its landmark, and the same landmark: the same estimate
        assert hidden.counters['associated'] >= 0.97 * hidden.counters['no_id']
        assert hidden.counters['rows_used'] >= 0.97 * rows
        assert np.sqrt(np.mean(err ** 2)) < 1.1 * np.sqrt(np.mean(err_ids ** 2)) + 0.005
        assert np.linalg.norm(hidden.estimate().x[:2] - with_ids.estimate().x[:2]) < 0.02
        assert 1.5 < np.mean(nees) < 4.5


def test_without_association_the_rows_are_skipped():
    _, _, loc = _simulate(0, 'none', hide=True, steps=300)
    assert loc.counters['no_id'] > 0 and loc.counters['rows_used'] == 0
    assert loc.counters['associated'] == 0


@pytest.mark.parametrize('method', ['nn', 'jcbb'])
def test_rows_take_the_ids_of_their_landmarks_and_strangers_none(method):
    rng = np.random.default_rng(5)
    assoc = MapAssociation(LANDMARKS, np.tile(np.eye(2) * 1e-4, (7, 1, 1)), method, 0.999)
    map_ids = np.arange(7) + 10
    for _ in range(50):
        x = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-math.pi, math.pi)])
        P = np.diag([0.02, 0.02, 0.005]) ** 2
        truth = np.append(rng.permutation(7)[:4], -1)
        m = np.vstack([LANDMARKS[truth[:4]], [[20.0, 20.0]]])  # the last: not in the map
        z = sensors.observe(np.tile(x, (5, 1)), m) + rng.normal(0, [0.01, 0.003], (5, 2))
        R = np.tile(np.diag([0.01, 0.003]) ** 2, (5, 1, 1))
        kind = np.array([RANGE_BEARING] * 4 + [RANGE_BEARING])
        ids = np.full(5, UNKNOWN_ID, np.int64)
        ids[0] = 99  # a row with an ID keeps it
        out, counts, _ = label_rows(assoc, Estimate(0, x, P), map_ids, ids, z, kind, R)
        assert out[0] == 99 and out[4] == UNKNOWN_ID
        np.testing.assert_array_equal(out[1:4], map_ids[truth[1:4]])
        assert counts['associated'] == 3 and counts['association_unmatched'] == 1
    # a partial row is not associated; a row seen from a badly wrong pose is not paired
    kind = np.array([RANGE, RANGE_BEARING])
    z = sensors.observe(np.zeros((2, 3)), LANDMARKS[:2])
    pose = Estimate(0, np.array([0.0, 0.0, 1.0]), np.eye(3) * 1e-6)
    out, counts, _ = label_rows(assoc, pose, map_ids, np.full(2, UNKNOWN_ID, np.int64), z,
                                kind, np.tile(np.eye(2) * 1e-6, (2, 1, 1)))
    assert counts == {'associated': 0, 'association_ambiguous': 0,
                      'association_unmatched': 1, 'association_partial': 1,
                      'association_merged': 0}
    assert np.all(out == UNKNOWN_ID)


def test_ambiguous_rows_are_skipped():
    # Two landmarks 5 cm apart, a pose known to 0.5 m: both pass the gate.
    m = np.array([[3.0, 0.0], [3.0, 0.05]])
    assoc = MapAssociation(m, np.tile(np.eye(2) * 1e-6, (2, 1, 1)), 'nn', 0.999)
    z = sensors.observe(np.zeros((1, 3)), m[:1])
    out, counts, _ = label_rows(assoc, Estimate(0, np.zeros(3), np.eye(3) * 0.25),
                                np.array([1, 2]), np.array([UNKNOWN_ID]), z,
                                np.array([RANGE_BEARING]),
                                np.tile(np.eye(2) * 1e-4, (1, 1, 1)))
    assert counts['association_ambiguous'] == 1 and out[0] == UNKNOWN_ID
    take = MapAssociation(m, np.tile(np.eye(2) * 1e-6, (2, 1, 1)), 'nn', 0.999, True)
    out, counts, _ = label_rows(take, Estimate(0, np.zeros(3), np.eye(3) * 0.25),
                                np.array([1, 2]), np.array([UNKNOWN_ID]), z,
                                np.array([RANGE_BEARING]),
                                np.tile(np.eye(2) * 1e-4, (1, 1, 1)))
    assert counts['association_ambiguous'] == 0 and out[0] == 1  # the nearest


def test_config_rejects_an_unknown_method():
    with pytest.raises(ValueError):
        LocalizerConfig(association='gnn_maybe')
