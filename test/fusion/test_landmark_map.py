"""Tests of landmark_ros.fusion.landmark_map.LandmarkMap: fusion by ID, gating, confirmation."""

from collections import Counter
import json

from conftest import random_spd
from landmark_ros.core import gating, gaussian, landmarks, pose2, sensors
from landmark_ros.fusion.landmark_map import FUSION_METHODS, LandmarkMap
import numpy as np
import pytest
from scipy import stats

METHODS = pytest.mark.parametrize('fusion', FUSION_METHODS)
S = 1_000_000_000
"""One second [ns]."""

# The textbook example (chapter, case 5): one landmark seen by two robots.
R_TEXTBOOK = np.diag([0.25, 0.04])
M1 = np.array([2.44943102, 5.72815634])
P_M1 = np.array([[0.94677477, -0.23978943], [-0.23978943, 0.94322523]])
M2 = np.array([3.05042514, 6.70185272])
P_M2 = np.array([[0.84693794, 0.4333316], [0.4333316, 0.81306206]])
M_FUSED = np.array([2.58757252, 6.15534036])
P_FUSED = np.array([[0.37966125, 0.07773125], [0.07773125, 0.36999739]])


def textbook_observations():
    """Return the two robots' landmark estimates, computed with the core."""
    m1, P1 = landmarks.landmark_to_world([1.0, 2.0, 0.5], np.diag([0.08, 0.6, 0.02]),
                                         [4.0, 0.7], R_TEXTBOOK)
    m2, P2 = landmarks.landmark_to_world([6.0, 4.0, 2.1], np.diag([0.2, 0.09, 0.03]),
                                         [4.0, 0.3], R_TEXTBOOK)
    return m1, P1, m2, P2


def snapshots_equal(a, b):
    """Assert two ``snapshot()`` results are bitwise identical."""
    for x, y in zip(a.snapshot(), b.snapshot()):
        np.testing.assert_array_equal(x, y)


def one(m, P, P_dep=None):
    """Return single-row update arguments."""
    return (np.asarray(m)[None], np.asarray(P)[None],
            None if P_dep is None else np.asarray(P_dep)[None])


def reference_fuse(fusion, m, P_ind, P_dep, z, R_ind, R_dep):
    """One fusion step of ``fusion`` with the public gaussian functions."""
    if fusion == 'independent':
        m, P = gaussian.fuse(m, P_ind + P_dep, z, R_ind + R_dep)
        return m, P, np.zeros((2, 2))
    if fusion == 'covariance_intersection':
        m, P = gaussian.covariance_intersection(m, P_ind + P_dep, z, R_ind + R_dep)
        return m, np.zeros((2, 2)), P
    omega = gaussian.split_covariance_intersection_omega(P_ind, P_dep, R_ind, R_dep)
    return gaussian.split_covariance_intersection(m, P_ind, P_dep, z, R_ind, R_dep, omega)


def reference_sequence(fusion, zs, Rs, R_deps):
    """
    Fuse observations in order, from the first; return mean, total and dependent.

    With one source per observation, split CI folds the sources from the smallest
    covariance (determinant) up, whatever their order.
    """
    zs, Rs, R_deps = np.asarray(zs), np.asarray(Rs), np.asarray(R_deps)
    if fusion == 'split_covariance_intersection':
        order = np.argsort([np.linalg.det(R) for R in Rs], kind='stable')
        zs, Rs, R_deps = zs[order], Rs[order], R_deps[order]
    m, P_ind, P_dep = zs[0], Rs[0] - R_deps[0], R_deps[0]
    for z, R, R_dep in zip(zs[1:], Rs[1:], R_deps[1:]):
        m, P_ind, P_dep = reference_fuse(fusion, m, P_ind, P_dep, z, R - R_dep, R_dep)
    if fusion == 'independent':
        P_ind, P_dep = P_ind + P_dep, np.zeros((2, 2))
    elif fusion == 'covariance_intersection':
        P_ind, P_dep = np.zeros((2, 2)), P_ind + P_dep
    return m, P_ind + P_dep, P_dep


def noise_parts(rng, count, dependent=True):
    """Return ``R`` and its dependent part ``R_dep`` (PSD, not larger than ``R``)."""
    R_ind = random_spd(rng, 2, count, scale=0.2, eps=0.01)
    if not dependent:
        return R_ind, np.zeros_like(R_ind)
    weights = rng.uniform(0, 1, count)[:, None, None]
    R_dep = random_spd(rng, 2, count, scale=0.2, eps=0.0) * weights
    return R_ind + R_dep, R_dep


def draw(rng, mean, R, scale=1.0):
    """Return one sample per row of N(mean, scale^2 R)."""
    return mean + scale * (np.linalg.cholesky(R) @ rng.standard_normal(R.shape[:-1] + (1,))
                           )[..., 0]


# --- construction ------------------------------------------------------------------------------

def test_constructor_validates():
    with pytest.raises(ValueError, match='fusion'):
        LandmarkMap('product')
    with pytest.raises(ValueError):
        LandmarkMap(min_observations=0)
    with pytest.raises(ValueError):
        LandmarkMap(max_consecutive_rejections=0)
    with pytest.raises(ValueError):
        LandmarkMap(gate_probability=1.0)
    m = LandmarkMap()
    assert m.fusion == 'split_covariance_intersection' and len(m) == 0
    assert m.threshold == pytest.approx(stats.chi2.ppf(0.999, 2), rel=1e-9)
    ids, mean, P, P_dep, count = m.snapshot()
    assert ids.shape == (0,) and mean.shape == (0, 2) and P.shape == P_dep.shape == (0, 2, 2)
    result = m.update(np.empty(0, np.int64), np.empty((0, 2)), np.empty((0, 2, 2)))
    assert not result.changed and not result.accepted and not result.rejected


# --- the textbook case -------------------------------------------------------------------------

def test_textbook_inputs():
    m1, P1, m2, P2 = textbook_observations()
    for actual, expected in zip((m1, P1, m2, P2), (M1, P_M1, M2, P_M2)):
        np.testing.assert_allclose(actual, expected, rtol=0, atol=1e-8)


@METHODS
@pytest.mark.parametrize('batched', [False, True])
def test_textbook_case(fusion, batched):
    m1, P1, m2, P2 = textbook_observations()
    lm = LandmarkMap(fusion, min_observations=2)
    if batched:
        result = lm.update([7, 7], [m1, m2], [P1, P2], source=['robot1', 'robot2'],
                           stamp_ns=[1 * S, 2 * S])
    else:
        first = lm.update([7], *one(m1, P1), source='robot1', stamp_ns=1 * S)
        assert len(lm) == 0 and not first.changed and first.confirmed == []
        result = lm.update([7], *one(m2, P2), source='robot2', stamp_ns=2 * S)
    assert result.confirmed == [7]
    assert result.accepted == Counter(robot1=1, robot2=1) and not result.rejected
    ids, m, P, P_dep, count = lm.snapshot()
    assert ids.tolist() == [7] and count.tolist() == [2] and len(lm) == 1
    if fusion == 'covariance_intersection':
        m_ref, P_ref = gaussian.covariance_intersection(m1, P1, m2, P2)
        np.testing.assert_allclose(m[0], m_ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(P[0], P_ref, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(P_dep[0], P[0])   # CI: everything is dependent
        assert np.linalg.det(P[0]) > np.linalg.det(P_FUSED) * 1.5
    else:
        np.testing.assert_allclose(m[0], M_FUSED, rtol=0, atol=1e-8)
        np.testing.assert_allclose(P[0], P_FUSED, rtol=0, atol=1e-8)
        np.testing.assert_allclose(P_dep[0], 0.0, rtol=0, atol=1e-15)
    assert lm.sources_of(7) == ['robot1', 'robot2']
    record, = lm.to_records()
    assert record['first_stamp_ns'] == 1 * S and record['last_stamp_ns'] == 2 * S


def test_textbook_case_with_dependent_parts_differs_by_method():
    # Declaring the pose terms dependent: split CI lies between the product and CI.
    m1, P1, m2, P2 = textbook_observations()
    P1_dep, P2_dep = 0.6 * P1, 0.6 * P2
    dets = {}
    for fusion in FUSION_METHODS:
        lm = LandmarkMap(fusion)
        lm.update([1, 1], [m1, m2], [P1, P2], [P1_dep, P2_dep], ['robot1', 'robot2'])
        _, m, P, P_dep, _ = lm.snapshot()
        m_ref, P_ref, P_dep_ref = reference_sequence(fusion, [m1, m2], [P1, P2],
                                                     [P1_dep, P2_dep])
        np.testing.assert_allclose(m[0], m_ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(P[0], P_ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(P_dep[0], P_dep_ref, rtol=0, atol=1e-12)
        dets[fusion] = np.linalg.det(P[0])
    assert dets['independent'] < dets['split_covariance_intersection'] < dets[
        'covariance_intersection']


# --- batches equal rows one by one -------------------------------------------------------------

def random_stream(rng, count=300, large_ids=False):
    """
    Return a stream of observations with outliers, late landmarks and a moved one.

    Rows: ids, z, R, R_dep, sources, stamps, and the ID that moves.
    """
    n_landmarks = 12
    base = 2 ** 21 if large_ids else 0
    ids_all = base + rng.choice(5000, n_landmarks, replace=False)
    truth = rng.uniform(-50, 50, (n_landmarks, 2))
    start = np.sort(rng.integers(0, count // 2, n_landmarks))   # late arrivals
    start[:3] = 0
    which = np.empty(count, np.int64)
    for i in range(count):
        which[i] = rng.choice(np.flatnonzero(start <= i))
    # Bursts: the same landmark several times in a row (repeated IDs within a batch).
    for i in rng.choice(count - 4, 30):
        which[i:i + 4] = which[i]
    R, R_dep = noise_parts(rng, count)
    positions = truth[which].copy()
    moved = 0       # there from the start (start[:3] = 0), so seen before it moves
    positions[(np.arange(count) > int(0.6 * count)) & (which == moved)] += [30.0, -20.0]
    z = draw(rng, positions, R)
    outliers = rng.uniform(size=count) < 0.05
    z[outliers] += rng.uniform(20.0, 60.0, (outliers.sum(), 1)) * np.array([1.0, 0.5])
    sources = rng.choice(['robot_a', 'robot_b', 'robot_c'], count)
    stamps = S + np.arange(count) * (S // 10)
    return ids_all[which], z, R, R_dep, sources, stamps, int(ids_all[moved])


def merged(results):
    """Add up UpdateResults."""
    accepted, rejected, confirmed, reinitialised = Counter(), Counter(), [], []
    for r in results:
        accepted += r.accepted
        rejected += r.rejected
        confirmed += r.confirmed
        reinitialised += r.reinitialised
    return accepted, rejected, sorted(confirmed), sorted(reinitialised)


@METHODS
@pytest.mark.parametrize('large_ids', [False, True])
def test_batch_equals_rows_one_by_one(fusion, large_ids, rng):
    ids, z, R, R_dep, sources, stamps, moved = random_stream(rng, large_ids=large_ids)
    count = len(ids)

    def feed(chunks):
        lm = LandmarkMap(fusion, min_observations=2, max_consecutive_rejections=4)
        results = [lm.update(ids[s], z[s], R[s], R_dep[s], sources[s].tolist(), stamps[s])
                   for s in chunks]
        return lm, merged(results)

    one_by_one = feed([slice(i, i + 1) for i in range(count)])
    cuts = np.sort(rng.choice(np.arange(1, count), 20, replace=False))
    bounds = [0, *cuts.tolist(), count]
    splits = [
        [slice(0, count)],
        [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])],
        # A per-row warm-up, then the rest in one batch (rows of confirmed landmarks
        # are fused in rounds, vectorised).
        [slice(i, i + 1) for i in range(60)] + [slice(60, count)],
    ]
    ref_map, ref_result = one_by_one
    accepted, rejected, confirmed, reinitialised = ref_result
    # The stream exercises what it should.
    assert moved in reinitialised
    assert sum(rejected.values()) >= 8 and sum(accepted.values()) >= 200
    assert len(confirmed) == 12 and len(ref_map) == 12
    assert set(accepted) == {'robot_a', 'robot_b', 'robot_c'}
    for chunks in splits:
        lm, result = feed(chunks)
        snapshots_equal(lm, ref_map)
        assert result == ref_result
        assert lm.to_records() == ref_map.to_records()


def test_batch_of_confirmed_landmark_rows_is_sequential(rng):
    # Several rows of one confirmed landmark in one batch: fused one after the other.
    # (One source per observation: split CI then fuses them one by one too.)
    for fusion in FUSION_METHODS:
        R, R_dep = noise_parts(rng, 6)
        z = draw(rng, np.array([3.0, -2.0]), R, 0.3)
        lm = LandmarkMap(fusion)
        lm.update([4, 4], z[:2], R[:2], R_dep[:2], ['s0', 's1'])
        lm.update([4, 9, 4, 4, 9], np.r_[z[2:3], [[50.0, 50.0]], z[3:5], [[50.1, 50.0]]],
                  np.r_[R[2:3], R[5:6], R[3:5], R[5:6]],
                  np.r_[R_dep[2:3], R_dep[5:6], R_dep[3:5], R_dep[5:6]],
                  ['s2', 'x', 's3', 's4', 'y'])
        _, m, P, P_dep, count = lm.snapshot()
        m_ref, P_ref, P_dep_ref = reference_sequence(fusion, z[:5], R[:5], R_dep[:5])
        np.testing.assert_allclose(m[0], m_ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(P[0], P_ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(P_dep[0], P_dep_ref, rtol=0, atol=1e-12)
        assert count.tolist() == [5, 2]


# --- independent fusion: order does not matter ------------------------------------------------

def test_independent_fusion_is_order_independent_and_equals_fuse_many(rng):
    n_landmarks, n_messages = 6, 12
    truth = rng.uniform(-20, 20, (n_landmarks, 2))
    messages = []
    for k in range(n_messages):
        ids = rng.choice(n_landmarks, rng.integers(2, n_landmarks + 1), replace=False)
        R, _ = noise_parts(rng, len(ids), dependent=False)
        # Small errors: every observation passes every gate in any order.
        messages.append((ids, draw(rng, truth[ids], R, 0.2), R, f'robot{k % 3}'))
    maps = []
    for trial in range(6):
        order = rng.permutation(n_messages) if trial else np.arange(n_messages)
        lm = LandmarkMap('independent', min_observations=2)
        results = [lm.update(*messages[k][:3], source=messages[k][3]) for k in order]
        assert not merged(results)[1]   # nothing rejected
        maps.append(lm)
    reference = maps[0].snapshot()
    for lm in maps[1:]:
        ids, m, P, P_dep, count = lm.snapshot()
        np.testing.assert_array_equal(ids, reference[0])
        np.testing.assert_array_equal(count, reference[4])
        np.testing.assert_allclose(m, reference[1], rtol=0, atol=1e-10)
        np.testing.assert_allclose(P, reference[2], rtol=0, atol=1e-10)
    ids, m, P, P_dep, count = reference
    for k, landmark in enumerate(ids):
        zs = [msg[1][msg[0] == landmark] for msg in messages]
        Rs = [msg[2][msg[0] == landmark] for msg in messages]
        zs, Rs = np.concatenate(zs), np.concatenate(Rs)
        if len(zs) < 2:
            continue
        assert count[k] == len(zs)
        m_ref, P_ref = gaussian.fuse_many(zs, Rs)
        np.testing.assert_allclose(m[k], m_ref, rtol=0, atol=1e-10)
        np.testing.assert_allclose(P[k], P_ref, rtol=0, atol=1e-10)
        np.testing.assert_array_equal(P_dep[k], np.zeros((2, 2)))
    assert len(ids) >= n_landmarks - 1


# --- gating ------------------------------------------------------------------------------------

@METHODS
def test_outlier_of_a_confirmed_landmark_is_rejected(fusion, rng):
    R, R_dep = noise_parts(rng, 8)
    truth = np.array([4.0, 1.0])
    z = draw(rng, truth, R, 0.3)
    with_outlier, without = LandmarkMap(fusion), LandmarkMap(fusion)
    for lm in (with_outlier, without):
        lm.update([3] * 4, z[:4], R[:4], R_dep[:4], source='good')
    before = with_outlier.snapshot()
    # 20 sigma away along the innovation covariance's largest axis.
    _, m, P, _, _ = before
    S = P[0] + R[4]
    values, vectors = np.linalg.eigh(S)
    outlier = m[0] + 20.0 * np.sqrt(values[-1]) * vectors[:, -1]
    assert gating.mahalanobis_sq(outlier, m[0], S) == pytest.approx(400.0)
    result = with_outlier.update([3], *one(outlier, R[4], R_dep[4]), source='bad')
    assert result.rejected == Counter(bad=1) and not result.accepted and not result.changed
    for x, y in zip(with_outlier.snapshot(), before):
        np.testing.assert_array_equal(x, y)
    record, = with_outlier.to_records()
    assert record['rejections'] == 1 and record['observations'] == 4
    assert with_outlier.sources_of(3) == ['good']
    # Later observations fuse as if the outlier never came.
    for lm in (with_outlier, without):
        result = lm.update([3] * 3, z[5:], R[5:], R_dep[5:], source='good')
        assert result.accepted == Counter(good=3)
    snapshots_equal(with_outlier, without)
    assert without.to_records()[0]['rejections'] == 0


@METHODS
def test_gate_threshold_is_the_chi_square_quantile(fusion):
    # Just inside the gate is fused, just outside is not.
    for probability in (0.99, 0.999):
        threshold = stats.chi2.ppf(probability, 2)
        for d2, accepted in ((threshold * (1 - 1e-6), True), (threshold * (1 + 1e-6), False)):
            lm = LandmarkMap(fusion, gate_probability=probability, min_observations=1)
            lm.update([1], *one([0.0, 0.0], np.eye(2)))
            _, m, P, _, _ = lm.snapshot()
            S = P[0] + np.eye(2)
            # Along x, with S diagonal: d2 = x^2 / S_xx.
            x = np.sqrt(d2 * S[0, 0])
            result = lm.update([1], *one([x, 0.0], np.eye(2)))
            assert bool(result.accepted) is accepted, (probability, d2)


# --- confirmation ------------------------------------------------------------------------------

@METHODS
def test_first_outlier_is_never_published(fusion, rng):
    R, R_dep = noise_parts(rng, 3)
    truth = np.array([-2.0, 5.0])
    outlier = truth + [40.0, 0.0]
    z = draw(rng, truth, R, 0.3)
    lm = LandmarkMap(fusion, min_observations=2)
    r0 = lm.update([11], *one(outlier, R[0], R_dep[0]), source='liar', stamp_ns=1 * S)
    r1 = lm.update([11], *one(z[1], R[1], R_dep[1]), source='robot1', stamp_ns=2 * S)
    for r in (r0, r1):
        assert not r.changed and not r.confirmed
        assert len(lm) == 0 and lm.snapshot()[0].size == 0
    r2 = lm.update([11], *one(z[2], R[2], R_dep[2]), source='robot2', stamp_ns=3 * S)
    assert r2.confirmed == [11]
    assert r2.accepted == Counter(robot1=1, robot2=1) and r2.rejected == Counter(liar=1)
    ids, m, P, P_dep, count = lm.snapshot()
    m_ref, P_ref, P_dep_ref = reference_sequence(fusion, z[1:], R[1:], R_dep[1:])
    np.testing.assert_allclose(m[0], m_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(P[0], P_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(P_dep[0], P_dep_ref, rtol=0, atol=1e-12)
    assert np.linalg.norm(m[0] - truth) < 2.0
    record, = lm.to_records()
    assert record['observations'] == 2 and record['rejections'] == 1
    assert record['sources'] == ['robot1', 'robot2']
    assert record['first_stamp_ns'] == 1 * S and record['last_stamp_ns'] == 3 * S


@METHODS
def test_single_observation_is_not_published_with_two_required(fusion, rng):
    R, R_dep = noise_parts(rng, 3)
    lm = LandmarkMap(fusion, min_observations=2)
    # Observations of different landmarks never confirm one another.
    for k in range(3):
        result = lm.update([100 + k], *one([k * 1.0, 0.0], R[k], R_dep[k]))
        assert not result.changed and len(lm) == 0
    assert lm.snapshot()[0].size == 0 and lm.to_records() == []
    # Two disagreeing observations of one landmark do not either.
    lm.update([100], *one([30.0, 0.0], R[1], R_dep[1]))
    assert len(lm) == 0


@METHODS
def test_min_observations_one_publishes_at_once(fusion, rng):
    R, R_dep = noise_parts(rng, 1)
    lm = LandmarkMap(fusion, min_observations=1)
    result = lm.update([5], *one([1.5, -2.5], R[0], R_dep[0]), source='r', stamp_ns=4 * S)
    assert result.confirmed == [5] and result.accepted == Counter(r=1) and len(lm) == 1
    ids, m, P, P_dep, count = lm.snapshot()
    np.testing.assert_allclose(m[0], [1.5, -2.5], rtol=1e-14, atol=0)
    np.testing.assert_allclose(P[0], R[0], rtol=0, atol=1e-10 * np.abs(R[0]).max())
    expected_dep = {'independent': np.zeros((2, 2)), 'covariance_intersection': R[0],
                    'split_covariance_intersection': R_dep[0]}[fusion]
    np.testing.assert_allclose(P_dep[0], expected_dep, rtol=0, atol=1e-10 * np.abs(R[0]).max())


def test_confirmation_needs_min_observations_agreeing(rng):
    R, R_dep = noise_parts(rng, 4)
    z = draw(rng, np.zeros(2), R, 0.2)
    lm = LandmarkMap('independent', min_observations=3)
    assert not lm.update([1, 1], z[:2], R[:2], R_dep[:2]).confirmed
    assert len(lm) == 0
    result = lm.update([1], *one(z[2], R[2], R_dep[2]))
    assert result.confirmed == [1] and sum(result.accepted.values()) == 3
    assert lm.snapshot()[4].tolist() == [3]


def test_every_tentative_observation_is_counted_once(rng):
    # Disagreeing observations overflow the tentative buffer (8 = 4 * min_observations):
    # the evicted one counts as rejected, the rest when the landmark is confirmed.
    lm = LandmarkMap('split_covariance_intersection', min_observations=2)
    R = 0.01 * np.eye(2)
    results = []
    for k in range(9):
        results.append(lm.update([1], [[100.0 * k, 0.0]], [R], source=f's{k}'))
    assert [sum(r.rejected.values()) for r in results] == [0] * 8 + [1]
    assert results[-1].rejected == Counter(s0=1)
    assert len(lm) == 0
    result = lm.update([1], [[800.0, 0.01]], [R], source='s9')
    assert result.confirmed == [1]
    assert result.accepted == Counter(s8=1, s9=1)
    assert result.rejected == Counter({f's{k}': 1 for k in range(1, 8)})
    record, = lm.to_records()
    assert record['rejections'] == 8 and record['observations'] == 2
    np.testing.assert_allclose(record['mean'], [800.0, 0.005], rtol=0, atol=1e-12)


@METHODS
def test_a_shared_error_is_never_averaged_away(fusion, rng):
    # One robot, one stop, many looks: the dependent part (its pose error) is the same
    # error in every observation, so no number of them may shrink the estimate below it.
    R_ind = random_spd(rng, 2, scale=0.1, eps=0.01)
    R_dep = random_spd(rng, 2, scale=0.3, eps=0.01)
    truth = np.array([1.0, 1.0])
    z = draw(rng, np.broadcast_to(truth, (40, 2)), np.broadcast_to(R_ind, (40, 2, 2)), 0.3)
    lm = LandmarkMap(fusion)
    for k in range(0, 40, 8):
        lm.update([1] * 8, z[k:k + 8], np.broadcast_to(R_ind + R_dep, (8, 2, 2)),
                  np.broadcast_to(R_dep, (8, 2, 2)), source='robot')
    _, m, P, _, count = lm.snapshot()
    assert count.tolist() == [40]
    smallest = np.linalg.eigvalsh(P[0] - R_dep)[0]
    if fusion == 'independent':
        assert smallest < -0.5 * np.linalg.eigvalsh(R_dep)[0]   # over-confident
    else:
        assert smallest >= -1e-9 * np.abs(R_dep).max()


# --- re-initialisation -------------------------------------------------------------------------

@METHODS
def test_moved_landmark_is_reinitialised(fusion, rng):
    R, R_dep = noise_parts(rng, 12)
    old, new = np.array([0.0, 0.0]), np.array([15.0, -10.0])
    lm = LandmarkMap(fusion, max_consecutive_rejections=5)
    lm.update([2] * 3, draw(rng, old, R[:3], 0.3), R[:3], R_dep[:3], source='r1')
    before = lm.snapshot()
    z_new = draw(rng, new, R[3:8], 0.3)
    for k in range(4):
        result = lm.update([2], *one(z_new[k], R[3 + k], R_dep[3 + k]), source=f'r2{k}')
        assert result.rejected == Counter({f'r2{k}': 1}) and not result.reinitialised
        for x, y in zip(lm.snapshot(), before):
            np.testing.assert_array_equal(x, y)
    result = lm.update([2], *one(z_new[4], R[7], R_dep[7]), source='r24')
    assert result.reinitialised == [2] and result.rejected == Counter(r24=1)
    assert result.changed
    ids, m, P, P_dep, count = lm.snapshot()
    assert count.tolist() == [5]
    # Rebuilt from the five new observations only, near the new place.
    m_ref, P_ref, P_dep_ref = reference_sequence(fusion, z_new, R[3:8], R_dep[3:8])
    np.testing.assert_allclose(m[0], m_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(P[0], P_ref, rtol=0, atol=1e-12)
    assert gating.mahalanobis_sq(new, m[0], P[0]) < stats.chi2.ppf(0.999, 2)
    assert lm.to_records()[0]['rejections'] == 5
    assert lm.sources_of(2) == ['r1', 'r20', 'r21', 'r22', 'r23', 'r24']
    # It now accepts observations at the new place.
    result = lm.update([2], *one(draw(rng, new, R[8], 0.3), R[8], R_dep[8]))
    assert result.accepted and not result.rejected


@METHODS
def test_non_agreeing_outliers_do_not_reinitialise(fusion, rng):
    R, R_dep = noise_parts(rng, 20)
    lm = LandmarkMap(fusion, max_consecutive_rejections=3)
    lm.update([2] * 3, draw(rng, np.zeros(2), R[:3], 0.3), R[:3], R_dep[:3])
    before = lm.snapshot()
    angles = np.arange(12) * (2 * np.pi / 12)
    outliers = 100.0 * np.c_[np.cos(angles), np.sin(angles)] * (1 + np.arange(12))[:, None]
    result = lm.update([2] * 12, outliers, R[3:15], R_dep[3:15], source='noise')
    assert not result.reinitialised and result.rejected == Counter(noise=12)
    for x, y in zip(lm.snapshot(), before):
        np.testing.assert_array_equal(x, y)
    assert lm.to_records()[0]['rejections'] == 12


def test_an_accepted_observation_resets_the_rejection_run(rng):
    R, R_dep = noise_parts(rng, 12)
    new = np.array([15.0, -10.0])
    lm = LandmarkMap('split_covariance_intersection', max_consecutive_rejections=3)
    lm.update([2] * 3, draw(rng, np.zeros(2), R[:3], 0.3), R[:3], R_dep[:3])
    _, m, _, _, _ = lm.snapshot()
    results = [lm.update([2, 2], draw(rng, new, R[3:5], 0.3), R[3:5], R_dep[3:5])]
    results.append(lm.update([2], *one(m[0], R[5], R_dep[5])))   # accepted
    results.append(lm.update([2, 2], draw(rng, new, R[6:8], 0.3), R[6:8], R_dep[6:8]))
    assert merged(results)[3] == [] and sum(merged(results)[1].values()) == 4
    # The third in a row now does it; only this run's observations are used.
    z_last = draw(rng, new, R[8], 0.3)
    result = lm.update([2], *one(z_last, R[8], R_dep[8]))
    assert result.reinitialised == [2] and lm.snapshot()[4].tolist() == [3]


def test_reinitialisation_prefers_the_latest_of_equal_clusters(rng):
    # Two places, two rejected observations each: the most recent place wins.
    lm = LandmarkMap('independent', min_observations=2, max_consecutive_rejections=4)
    R = 0.01 * np.eye(2)
    lm.update([6, 6], [[0.0, 0.0], [0.0, 0.01]], [R, R])
    result = lm.update([6] * 4, [[50.0, 0.0], [50.0, 0.01], [-50.0, 0.0], [-50.0, 0.01]],
                       [R] * 4)
    assert result.reinitialised == [6]
    np.testing.assert_allclose(lm.snapshot()[1][0], [-50.0, 0.005], rtol=0, atol=1e-12)
    result = lm.update([6] * 4, [[30.0, 0.0], [-80.0, 0.0], [30.0, 0.01], [-80.0, 0.01]],
                       [R] * 4)
    assert result.reinitialised == [6]
    np.testing.assert_allclose(lm.snapshot()[1][0], [-80.0, 0.005], rtol=0, atol=1e-12)


# --- records, reset ----------------------------------------------------------------------------

def populated_map(rng, fusion='split_covariance_intersection'):
    ids, z, R, R_dep, sources, stamps, _ = random_stream(rng, count=200)
    lm = LandmarkMap(fusion)
    lm.update(ids, z, R, R_dep, sources.tolist(), stamps)
    assert len(lm) >= 5
    return lm, (ids, z, R, R_dep, sources, stamps)


@METHODS
def test_records_round_trip(fusion, rng):
    lm, (ids, z, R, R_dep, sources, stamps) = populated_map(rng, fusion)
    records = lm.to_records()
    assert [r['id'] for r in records] == sorted(r['id'] for r in records)
    copy = LandmarkMap(fusion)
    copy.load_records(records)
    assert copy.to_records() == records
    assert len(copy) == len(lm)
    a, b = lm.snapshot(), copy.snapshot()
    for x, y in zip(a, b):
        np.testing.assert_allclose(x, y, rtol=1e-15, atol=0)
    for record in records:
        assert copy.sources_of(record['id']) == record['sources']
        assert isinstance(record['id'], int) and isinstance(record['observations'], int)
        assert isinstance(record['mean'][0], float)
    # Fusing more into both gives the same estimates.
    more = lm.snapshot()[0][:4]
    z_more = lm.snapshot()[1][:4] + 0.01
    R_more = np.repeat(0.1 * np.eye(2)[None], 4, axis=0)
    for m in (lm, copy):
        m.update(more, z_more, R_more, 0.5 * R_more, 'later', 99 * S)
    for x, y in zip(lm.snapshot(), copy.snapshot()):
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-15)


def _record():
    return {'id': 4, 'mean': [1.0, 2.0], 'covariance': [[1.0, 0.1], [0.1, 2.0]],
            'covariance_dependent': [[0.5, 0.0], [0.0, 0.5]], 'observations': 3,
            'rejections': 1, 'sources': ['a'], 'first_stamp_ns': 1 * S,
            'last_stamp_ns': 2 * S}


def _malformed():
    cases = []
    for key in ('id', 'mean', 'covariance', 'covariance_dependent', 'observations',
                'sources', 'first_stamp_ns', 'last_stamp_ns'):
        record = _record()
        del record[key]
        cases.append(('missing ' + key, [record]))
    for key, value in (('mean', [1.0, 2.0, 3.0]), ('mean', [1.0, float('nan')]),
                       ('mean', 'xy'), ('covariance', [[1.0, 0.0, 0.0]]),
                       ('covariance', [[1.0, float('inf')], [0.0, 1.0]]),
                       ('covariance_dependent', [[float('nan'), 0.0], [0.0, 1.0]]),
                       ('covariance_dependent', None), ('id', 'four'), ('id', None),
                       ('observations', 'many'), ('first_stamp_ns', 'now'),
                       ('first_stamp_ns', 1.5), ('last_stamp_ns', True), ('sources', 5)):
        record = _record()
        record[key] = value
        cases.append((f'{key}={value!r}', [record]))
    cases.append(('duplicate id', [_record(), _record()]))
    cases.append(('not a dict', [_record(), [1, 2, 3]]))
    cases.append(('none', None))
    return cases


@pytest.mark.parametrize('name, records', _malformed(), ids=[c[0] for c in _malformed()])
def test_malformed_records_raise_and_leave_the_map_empty(name, records, rng):
    lm = LandmarkMap('independent')
    lm.load_records([dict(_record(), id=9)])
    assert len(lm) == 1
    with pytest.raises(ValueError, match='malformed landmark record'):
        lm.load_records(records)
    assert len(lm) == 0 and lm.snapshot()[0].size == 0 and lm.to_records() == []
    # Still usable afterwards.
    lm.load_records([_record()])
    assert lm.snapshot()[0].tolist() == [4]


@pytest.mark.parametrize('fusion', ['independent', 'covariance_intersection'])
def test_load_records_accepts_a_valid_record(fusion):
    lm = LandmarkMap(fusion)
    lm.load_records([_record()])
    ids, m, P, P_dep, count = lm.snapshot()
    np.testing.assert_array_equal(m[0], [1.0, 2.0])
    np.testing.assert_array_equal(P[0], [[1.0, 0.1], [0.1, 2.0]])
    np.testing.assert_array_equal(P_dep[0], 0.5 * np.eye(2))
    assert count.tolist() == [3] and lm.sources_of(4) == ['a']
    assert lm.to_records() == [_record()]
    # 'rejections' is optional.
    record = _record()
    del record['rejections']
    lm.load_records([record])
    assert lm.to_records()[0]['rejections'] == 0


def test_reset_forgets_everything(rng):
    lm, stream = populated_map(rng)
    lm.reset()
    assert len(lm) == 0 and lm.snapshot()[0].size == 0 and lm.to_records() == []
    with pytest.raises(KeyError):
        lm.sources_of(int(stream[0][0]))
    ids, z, R, R_dep, sources, stamps = stream
    fresh = LandmarkMap()
    for m in (lm, fresh):
        m.update(ids, z, R, R_dep, sources.tolist(), stamps)
    snapshots_equal(lm, fresh)
    assert lm.to_records() == fresh.to_records()


# --- IDs, len, sources -------------------------------------------------------------------------

def test_large_ids_use_binary_search(rng):
    big = np.array([2 ** 20, 2 ** 20 + 1, 2 ** 31, 2 ** 32 - 1, 2 ** 40], np.int64)
    points = rng.uniform(-10, 10, (len(big), 2))
    R = np.repeat(0.01 * np.eye(2)[None], len(big), 0)
    lm = LandmarkMap('independent')
    lm.update(big[::-1], points[::-1], R)
    lm.update(big, points + 0.001, R)
    ids, m, P, _, count = lm.snapshot()
    np.testing.assert_array_equal(ids, big)
    np.testing.assert_allclose(m, points + 0.0005, rtol=0, atol=1e-12)
    np.testing.assert_allclose(P, R / 2, rtol=0, atol=1e-15)
    assert count.tolist() == [2] * len(big)
    # One at a time, in another order.
    for k in (3, 0, 4):
        lm.update(big[k:k + 1], points[k:k + 1], R[:1])
    assert lm.snapshot()[4].tolist() == [3, 2, 2, 3, 3]


def test_mixed_small_and_large_ids(rng):
    ids = np.array([5, 2 ** 33, 0, 2 ** 20 - 1, 2 ** 20, 77], np.int64)
    points = rng.uniform(-10, 10, (len(ids), 2))
    R = np.repeat(0.01 * np.eye(2)[None], len(ids), 0)
    lm = LandmarkMap('independent')
    lm.update(ids, points, R)
    for k in rng.permutation(len(ids)):
        lm.update(ids[k:k + 1], points[k:k + 1], R[:1])
    lm.update(ids[::-1], points[::-1], R)
    got, m, _, _, count = lm.snapshot()
    order = np.argsort(ids)
    np.testing.assert_array_equal(got, ids[order])
    np.testing.assert_allclose(m, points[order], rtol=0, atol=1e-12)
    assert count.tolist() == [3] * len(ids)


def test_small_id_first_seen_with_a_large_id_is_found_again():
    R = 0.1 * np.eye(2)[None]
    lm = LandmarkMap(min_observations=1)
    lm.update([5], [[0.0, 0.0]], R)                     # builds a table of size 6
    lm.update([3, 2 ** 21], [[1.0, 1.0], [2.0, 2.0]], np.repeat(R, 2, 0))
    lm.update([3], [[1.01, 1.0]], R)                   # table[3] is -1: treated as new
    ids, _, _, _, count = lm.snapshot()
    assert ids.tolist() == [3, 5, 2 ** 21]
    assert count.tolist() == [2, 1, 1]


def test_len_counts_confirmed_only_and_sources_of(rng):
    lm = LandmarkMap('covariance_intersection', min_observations=2)
    R = 0.05 * np.eye(2)
    lm.update([1, 2, 3], [[0, 0], [5, 5], [9, 9]], [R, R, R], source=['a', 'b', 'a'])
    assert len(lm) == 0 and lm._count == 3
    lm.update([1, 2], [[0.01, 0], [5, 5.01]], [R, R], source=['c', 'a'])
    assert len(lm) == 2 and lm.snapshot()[0].tolist() == [1, 2]
    assert lm.sources_of(1) == ['a', 'c'] and lm.sources_of(2) == ['a', 'b']
    assert lm.sources_of(3) == []                           # tentative: nothing fused yet
    lm.update([1], [[30.0, 0.0]], [R], source='z')         # rejected: not a source of 1
    assert lm.sources_of(1) == ['a', 'c']
    lm.update([1], [[0.0, 0.01]], [R], source='b')
    assert lm.sources_of(1) == ['a', 'b', 'c']
    with pytest.raises(KeyError):
        lm.sources_of(42)


def test_per_row_sources_and_stamps(rng):
    lm = LandmarkMap('split_covariance_intersection', min_observations=1)
    R = np.repeat(0.05 * np.eye(2)[None], 4, 0)
    result = lm.update([1, 1, 2, 1], [[0, 0], [0, 0.01], [3, 3], [0.01, 0]], R,
                       source=np.array(['x', 'y', 'x', 'z']),
                       stamp_ns=[1 * S, 2 * S, 3 * S, 4 * S])
    assert result.accepted == Counter(x=2, y=1, z=1) and sorted(result.confirmed) == [1, 2]
    records = {r['id']: r for r in lm.to_records()}
    assert records[1]['sources'] == ['x', 'y', 'z']
    assert records[1]['first_stamp_ns'] == 1 * S and records[1]['last_stamp_ns'] == 4 * S
    assert records[2]['first_stamp_ns'] == records[2]['last_stamp_ns'] == 3 * S


@pytest.mark.parametrize('fusion', ['independent', 'split_covariance_intersection'])
def test_sources_by_index_are_the_sources_by_name(rng, fusion):
    # source_index into a list of names: the same map, the same codes in the same
    # order of first appearance (a name listed but unused is not registered).
    count = 300
    ids = rng.integers(0, 20, count)
    z = rng.normal(0.0, 0.05, (count, 2)) + ids[:, None]
    R = np.repeat(0.02 * np.eye(2)[None], count, 0)
    names = ['c', 'a', 'unused', 'b']
    index = rng.choice([0, 1, 3], count)
    by_name, by_index = LandmarkMap(fusion), LandmarkMap(fusion)
    for part in (slice(0, 100), slice(100, 300)):
        a = by_name.update(ids[part], z[part], R[part], 0.3 * R[part],
                           np.array(names)[index[part]], S)
        b = by_index.update(ids[part], z[part], R[part], 0.3 * R[part], names, S,
                            source_index=index[part])
        assert a.accepted == b.accepted
    assert by_name.source_names == by_index.source_names
    assert 'unused' not in by_index.source_names
    assert by_name.to_records() == by_index.to_records()
    with pytest.raises(ValueError, match='source_index'):
        by_index.update(ids[:3], z[:3], R[:3], source=names, source_index=[0, 4, 1])
    with pytest.raises(ValueError, match='source_index'):
        by_index.update(ids[:3], z[:3], R[:3], source=names, source_index=[0, 1])


# --- Monte Carlo consistency through the map ---------------------------------------------------

def simulate_robots(rng, n_landmarks, n_robots=3, repeats=4):
    """
    Return world-frame observation batches of robots with shared pose errors.

    Every robot stops once near every landmark and observes it ``repeats`` times: the
    pose error of that stop is shared by those observations (dependent part), the
    sensor noise is not. Stops (and so landmark errors) are independent across
    landmarks, so the NEES of the landmarks are independent samples.
    """
    truth = rng.uniform(-100, 100, (n_landmarks, 2))
    P_pose = np.diag([0.15 ** 2, 0.15 ** 2, 0.03 ** 2])
    R = np.diag([0.05 ** 2, 0.01 ** 2])
    batches = []
    stops = []
    for robot in range(n_robots):
        r = rng.uniform(3.0, 8.0, n_landmarks)
        a = rng.uniform(-np.pi, np.pi, n_landmarks)
        heading = rng.uniform(-np.pi, np.pi, n_landmarks)
        pose_true = np.c_[truth - r[:, None] * np.c_[np.cos(a), np.sin(a)], heading]
        pose_est = pose_true + rng.standard_normal((n_landmarks, 3)) @ np.sqrt(P_pose)
        pose_est[:, 2] = pose2.wrap_angle(pose_est[:, 2])
        stops.append((pose_true, pose_est))
    for t in range(repeats):
        for robot, (pose_true, pose_est) in enumerate(stops):
            z = sensors.observe(pose_true, truth)
            z = z + rng.standard_normal((n_landmarks, 2)) @ np.sqrt(R)
            m, P_m, P_dep = landmarks.landmark_to_world_dependent(pose_est, P_pose, z, R)
            batches.append((m, P_m, P_dep, f'robot{robot}'))
    return truth, batches


def test_simulated_robots_helper_is_consistent_per_observation(rng):
    # One observation on its own has NEES ~ 2: the sim and the propagation agree.
    truth, batches = simulate_robots(rng, 4000, n_robots=1, repeats=1)
    m, P_m, _, _ = batches[0]
    d2 = gating.mahalanobis_sq(m, truth, P_m)
    assert abs(d2.mean() - 2.0) < 0.15


@pytest.fixture(scope='module')
def map_nees():
    rng = np.random.default_rng(7)
    n_landmarks = 1000
    truth, batches = simulate_robots(rng, n_landmarks)
    out = {}
    for fusion in FUSION_METHODS:
        lm = LandmarkMap(fusion)
        results = [lm.update(np.arange(n_landmarks), m, P, P_dep, source)
                   for m, P, P_dep, source in batches]
        ids, m, P, _, _ = lm.snapshot()
        np.testing.assert_array_equal(ids, np.arange(n_landmarks))
        d2 = gating.mahalanobis_sq(m, truth[ids], P)
        out[fusion] = (d2.mean(), merged(results), np.linalg.det(P))
    bound = stats.chi2.ppf(0.975, 2 * n_landmarks) / n_landmarks
    return out, bound, len(batches) * n_landmarks


@pytest.mark.parametrize('fusion', ['covariance_intersection', 'split_covariance_intersection'])
def test_map_is_consistent_with_shared_pose_errors(fusion, map_nees):
    out, bound, rows = map_nees
    anees, (accepted, rejected, _, _), _ = out[fusion]
    assert bound < 2.15
    assert anees <= bound, f'{fusion}: ANEES {anees:.3f} above the 97.5 % bound {bound:.3f}'
    assert sum(accepted.values()) >= 0.99 * rows


def test_independent_fusion_is_over_confident_in_the_map(map_nees):
    out, bound, _ = map_nees
    anees = out['independent'][0]
    assert anees > 2.0 * bound, f'independent ANEES {anees:.3f}'


def test_split_ci_is_tighter_than_ci_in_the_map(map_nees):
    out, _, _ = map_nees
    # Split CI uses the independence of the sensor noise: smaller, still consistent.
    ratio = out['split_covariance_intersection'][2] / out['covariance_intersection'][2]
    assert np.median(ratio) < 0.95 and np.quantile(ratio, 0.99) < 1.0
    assert out['split_covariance_intersection'][0] < out['covariance_intersection'][0]


# --- scale safety (issue 9) --------------------------------------------------------------------

def one_landmark_rows(count, R):
    """Return ``count`` agreeing rows of landmark 1 with covariance R, in units of its scale."""
    sigma = np.sqrt(R[0, 0])
    z = sigma * (np.array([3.0, 4.0]) + 0.1 * np.arange(count)[:, None])
    return [1] * count, z, np.repeat(np.asarray(R)[None], count, 0)


TINY = 1e-200 * np.eye(2)
HUGE = np.array([[1e200, 1e199], [1e199, 1e200]])


@METHODS
@pytest.mark.parametrize('R', [TINY, HUGE], ids=['1e-200 I', '1e200 correlated'])
def test_out_of_range_covariances_do_not_raise_and_stay_finite(fusion, R):
    # These raised IndexError in _agreeing (NaN d2 emptied the cluster): now two
    # agreeing rows confirm the landmark with the estimate of in-range inputs, scaled.
    lm = LandmarkMap(fusion)
    ids, z, Rs = one_landmark_rows(2, R)
    result = lm.update(ids, z, Rs)
    assert result.confirmed == [1]
    _, m, P, P_dep, count = lm.snapshot()
    assert np.all(np.isfinite(m)) and np.all(np.isfinite(P)) and np.all(np.isfinite(P_dep))
    assert count.tolist() == [2]
    unit = LandmarkMap(fusion)
    unit.update(ids, z / np.sqrt(R[0, 0]), Rs / R[0, 0])
    _, m_unit, P_unit, _, _ = unit.snapshot()
    np.testing.assert_allclose(m, m_unit * np.sqrt(R[0, 0]), rtol=1e-12, atol=0)
    np.testing.assert_allclose(P, P_unit * R[0, 0], rtol=1e-9, atol=0)
    # A row far away (in units of R) is gated out, a near one is fused.
    sigma = np.sqrt(R[0, 0])
    far = lm.update([1], [m[0] + [0.0, 1e3 * sigma]], R[None])
    assert far.rejected and not far.accepted
    near = lm.update([1], [m[0] + [0.0, 0.1 * sigma]], R[None])
    assert near.accepted and np.all(np.isfinite(lm.snapshot().P))


@METHODS
def test_three_rows_of_1e300_give_a_finite_map(fusion):
    # Three rows of one ID with 1e300 I made NaN means and covariances.
    R = 1e300 * np.eye(2)
    ids, z, Rs = one_landmark_rows(3, R)
    lm = LandmarkMap(fusion, min_observations=3)
    result = lm.update(ids, z, Rs)
    assert result.confirmed == [1] and sum(result.accepted.values()) == 3
    _, m, P, P_dep, count = lm.snapshot()
    for x in (m, P, P_dep):
        assert np.all(np.isfinite(x))
    unit = LandmarkMap(fusion, min_observations=3)
    unit.update(ids, z / 1e150, Rs / 1e300)
    _, m_unit, P_unit, _, _ = unit.snapshot()
    np.testing.assert_allclose(m, m_unit * 1e150, rtol=1e-12, atol=0)
    np.testing.assert_allclose(P, P_unit * 1e300, rtol=1e-9, atol=0)
    if fusion != 'covariance_intersection':
        np.testing.assert_allclose(P[0], R / 3.0, rtol=1e-9, atol=0)


def test_agreeing_never_empties_the_cluster():
    from landmark_ros.fusion import records
    nan = np.full((2, 2), np.nan)
    observations = [records.Observation(np.array([k, 0.0]), nan, np.zeros((2, 2)), 's', k)
                    for k in range(3)]
    cluster = records.agreeing(observations, 13.8, lambda *a: a[:3])
    assert cluster == [observations[-1]]   # the seed, alone
    lm = LandmarkMap('split_covariance_intersection')
    result = lm.update([1, 1], [[0.0, 0.0], [0.0, 0.0]], [nan, nan])
    assert not result.confirmed and len(lm) == 0


# --- the records of an update ------------------------------------------------------------------

def test_snapshot_is_a_named_tuple():
    lm = LandmarkMap('independent', min_observations=1)
    lm.update([4, 2], [[1.0, 2.0], [3.0, 4.0]], [np.eye(2), 2.0 * np.eye(2)])
    snapshot = lm.snapshot()
    assert snapshot.ids.tolist() == [2, 4] and snapshot.ids.dtype == np.int64
    np.testing.assert_array_equal(snapshot.m, [[3.0, 4.0], [1.0, 2.0]])
    np.testing.assert_array_equal(snapshot.P[0], 2.0 * np.eye(2))
    np.testing.assert_array_equal(snapshot.P_dep, np.zeros((2, 2, 2)))
    assert snapshot.observations.tolist() == [1, 1]
    ids, m, P, P_dep, count = snapshot
    assert ids is snapshot.ids and snapshot._fields == ('ids', 'm', 'P', 'P_dep',
                                                        'observations')


@METHODS
def test_changed_ids_lists_the_landmarks_whose_estimate_changed(fusion):
    lm = LandmarkMap(fusion, min_observations=2, max_consecutive_rejections=2)
    R = 0.01 * np.eye(2)
    result = lm.update([5, 9, 5], [[0.0, 0.0], [9.0, 9.0], [0.0, 0.01]], [R] * 3)
    assert result.changed_ids.tolist() == [5] and result.changed_ids.dtype == np.int64
    result = lm.update([9, 5, 5], [[9.0, 9.01], [0.01, 0.0], [50.0, 0.0]], [R] * 3)
    assert result.changed_ids.tolist() == [5, 9]   # 9 confirmed, 5 fused (one rejected)
    result = lm.update([5], [[50.0, 0.01]], [R])     # second rejection: moved
    assert result.reinitialised == [5] and result.changed_ids.tolist() == [5]
    result = lm.update([9, 7], [[80.0, 0.0], [1.0, 1.0]], [R] * 2)
    assert not result.changed and result.changed_ids.tolist() == []


def test_stamps_are_integer_nanoseconds():
    lm = LandmarkMap('independent', min_observations=1)
    big = 1_700_000_000_123_456_789   # beyond float64's integer precision
    lm.update([1, 1], [[0.0, 0.0], [0.0, 0.0]], [np.eye(2)] * 2, stamp_ns=[big, big + 1])
    record, = lm.to_records()
    assert record['first_stamp_ns'] == big and record['last_stamp_ns'] == big + 1
    assert isinstance(record['first_stamp_ns'], int)
    with pytest.raises(ValueError, match='integer nanoseconds'):
        lm.update([1], [[0.0, 0.0]], [np.eye(2)], stamp_ns=1.5)
    copy = LandmarkMap('independent')
    copy.load_records([record])
    assert copy.to_records() == [record]


def test_fusion_methods_share_one_interface():
    from landmark_ros.fusion import methods
    interface = {name for name in vars(methods.Independent) if not name.startswith('_')}
    assert {'fuse', 'held', 'absorb', 'settle', 'start', 'replace', 'merge', 'retire',
            'records', 'load', 'checkpoint', 'restore', 'reset'} <= interface
    for fusion in FUSION_METHODS:
        method = LandmarkMap(fusion)._method
        assert method.name == fusion and isinstance(method, methods.Independent)
        # Nothing beyond the interface (the map can call only that).
        extra = {name for name in dir(method) if not name.startswith('_')} - interface
        assert extra <= {'sums', 'stale', 'independent_sources'}   # state, a setting
    assert set(methods.METHODS) == set(FUSION_METHODS)


# --- all or nothing ------------------------------------------------------------------------

@pytest.mark.parametrize('fusion', FUSION_METHODS)
@pytest.mark.parametrize('fail_at', [1, 2, 3])
def test_an_update_that_fails_half_way_leaves_the_map_as_it_was(fusion, fail_at, rng):
    def batch(n, first_id, count):
        ids = rng.integers(first_id, first_id + count, n)
        z = np.column_stack([ids * 1.0, -ids * 1.0]) + rng.normal(0, 0.05, (n, 2))
        R = np.broadcast_to(np.diag([0.01, 0.02]), (n, 2, 2)).copy()
        sources = rng.choice(['a', 'b', 'c'], n)
        return ids, z, R, 0.3 * R, sources, np.arange(n, dtype=np.int64) + 10 ** 12

    def state(landmark_map):
        return json.dumps(landmark_map.to_records(), sort_keys=True), [
            a.tolist() for a in landmark_map.snapshot()]

    landmark_map, twin = LandmarkMap(fusion), LandmarkMap(fusion)
    first = batch(60, 0, 20)
    landmark_map.update(*first)
    twin.update(*first)
    before = state(landmark_map)
    # The failing batch has confirmed, tentative and new landmarks and a new source.
    failing = list(batch(40, 10, 25))
    failing[4] = np.where(failing[4] == 'c', 'd', failing[4])
    calls = []
    method_update = landmark_map._method.absorb

    def broken(*args):
        calls.append(1)
        result = method_update(*args)
        if len(calls) == fail_at:
            raise RuntimeError('injected fault')
        return result
    landmark_map._method.absorb = broken
    with pytest.raises(RuntimeError, match='injected'):
        landmark_map.update(*failing)
    del landmark_map._method.absorb
    assert calls and state(landmark_map) == before
    # And it goes on exactly as a map that never saw the failed batch.
    after = batch(50, 5, 30)
    landmark_map.update(*after)
    twin.update(*after)
    assert state(landmark_map) == state(twin)


def test_split_ci_source_dependent_part_is_a_covariance():
    # Two rows of one source whose dependent fractions differ in shape: the
    # information-weighted mean sym(Y^-1 Q) of their dependent parts is indefinite
    # (eigenvalue -12.4), so the map projects it onto the PSD matrices before split CI.
    R_ind = np.array([[[0.913, 2.074], [2.074, 4.777]], [[1.712, 1.701], [1.701, 1.739]]])
    R_dep = np.array([[[0.0, 0.0], [0.0, 0.0]], [[10.236, -4.074], [-4.074, 4.393]]])
    Y = np.linalg.inv(R_ind).sum(axis=0)
    D = np.linalg.solve(Y, np.einsum('kij,kjl->il', np.linalg.inv(R_ind), R_dep))
    assert np.linalg.eigvalsh(0.5 * (D + D.T))[0] < -10.0
    z = np.array([[1.0, 2.0], [1.2, 1.9]])
    other = (np.array([[1.1, 2.05]]), np.array([[[0.5, 0.1], [0.1, 0.4]]]),
             np.array([[[0.2, 0.0], [0.0, 0.1]]]))
    maps = []
    for batches in ([(0, 2)], [(0, 1), (1, 2)]):
        lm = LandmarkMap('split_covariance_intersection')
        for lo, hi in batches:
            lm.update([7] * (hi - lo), z[lo:hi], R_ind[lo:hi] + R_dep[lo:hi], R_dep[lo:hi],
                      source='a')
        lm.update([7], other[0], other[1] + other[2], other[2], source='b')
        maps.append(lm.snapshot())
    for snap in maps:
        assert snap.ids.tolist() == [7]
        assert np.linalg.eigvalsh(snap.P_dep[0])[0] >= -1e-12
        assert np.linalg.eigvalsh(snap.P[0] - snap.P_dep[0])[0] >= -1e-12
    np.testing.assert_array_equal(maps[0].m, maps[1].m)
    np.testing.assert_array_equal(maps[0].P, maps[1].P)
